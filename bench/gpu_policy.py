"""The policy parts of bench/gpu_check.py: inference by batch size and precision, and split against
monolithic serving, on one device (``cpu`` or ``cuda``), each written to a JSON file as it goes.

batch     ms per call and rows/s at each batch size, the variants interleaved per batch size so
          drifting load weighs on all alike. On CUDA: fp32 (as served) and bf16 (autocast) on the
          GPU, plus fp32 and W8A8 on the CPU (the W8A8 plug-in's int8 kernels are CPU kernels,
          services/policy_worker/vla/quant.py). On CPU: fp32 and W8A8. Each variant's actions on
          the same inputs are compared with fp32's (arm dimensions: max absolute difference;
          gripper: share of equal commands, it snaps to -1/0/1).
serving   open-loop Poisson load against MonolithicVLA and SplitVLA (two processes; the prefix
          through CUDA IPC on a GPU, shared memory on CPU), mean/p50/p99 latency and goodput under
          the 200 ms SLO (bench/bench_policy.py's open_loop), the two modes alternating per load.

    python bench/gpu_policy.py batch --device cuda --json out/batch.json
    python bench/gpu_policy.py serving --device cuda --loads 200,800,2000 --json out/serving.json
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from bench_policy import SLO, open_loop  # noqa: E402

#: Untimed calls per batch size and variant: TorchScript's profiling executor optimizes the traced
#: action expert after its first calls, CUDA loads its kernels and autocast fills its cast cache.
WARMUP_CALLS = 3


def sample_inputs(specs: list[Any], n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """``n`` requests' inputs for a model's input specs (state and image variants alike)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        row = {}
        for s in specs:
            if s.dtype == "uint8":
                row[s.name] = rng.integers(0, 256, tuple(s.shape), dtype=np.uint8)
            else:
                row[s.name] = (rng.standard_normal(tuple(s.shape)) * 0.1).astype(np.float32)
        out.append(row)
    return out


def stacked(rows: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {k: np.stack([r[k] for r in rows]) for k in rows[0]}


def write(path: str, doc: dict[str, Any]) -> None:
    """Write the section's JSON now, so a step stopped at its time limit keeps what it measured."""
    if path:
        Path(path).write_text(json.dumps(doc, indent=1))


def _bf16(device: str) -> Callable[[], contextlib.AbstractContextManager]:
    import torch

    return lambda: torch.autocast(device_type=device.split(":")[0], dtype=torch.bfloat16)


def agreement(ref: np.ndarray, other: np.ndarray) -> dict[str, float]:
    """How far a variant's actions are from fp32's on the same inputs."""
    return {"arm_max_abs_diff": float(np.abs(ref[..., :6] - other[..., :6]).max()),
            "arm_mean_abs_diff": float(np.abs(ref[..., :6] - other[..., :6]).mean()),
            "gripper_equal_share": float(np.mean(ref[..., 6] == other[..., 6]))}


def batch_section(checkpoint: str, device: str, batches: list[int], seconds: float, path: str) -> dict[str, Any]:
    """ms per inference call by batch size and variant (see the module docstring)."""
    import torch

    from services.policy_worker.vla.policy import ZettaVLAPolicy

    torch.set_num_threads(1)
    variants: dict[str, tuple[Any, Callable[[], contextlib.AbstractContextManager]]] = {}
    if device.startswith("cuda"):
        gpu = ZettaVLAPolicy(checkpoint, device=device)
        variants["fp32 (gpu)"] = (gpu, contextlib.nullcontext)
        variants["bf16 autocast (gpu)"] = (gpu, _bf16(device))
    variants["fp32 (cpu)"] = (ZettaVLAPolicy(checkpoint), contextlib.nullcontext)
    variants["w8a8 (cpu)"] = (ZettaVLAPolicy(checkpoint, quantize="w8a8"), contextlib.nullcontext)
    ref_name = next(iter(variants))
    first = variants[ref_name][0]
    instruction = sorted(first.text.cache)[0]
    doc: dict[str, Any] = {"device": device, "checkpoint": checkpoint, "torch_threads": 1, "seconds": seconds,
                           "ms": {k: {} for k in variants}, "rows_per_s": {k: {} for k in variants},
                           "agreement": {}, "reference": ref_name}
    specs = first.input_specs()
    for b in batches:
        batch = stacked(sample_inputs(specs, b, seed=b))
        texts = [instruction] * b
        answers = {}
        for name, (pol, ctx) in variants.items():
            with ctx():
                for _ in range(WARMUP_CALLS):
                    answers[name] = pol.infer(batch, texts)
        for name, (pol, ctx) in variants.items():
            calls, t0 = 0, time.perf_counter()
            with ctx():
                while time.perf_counter() - t0 < seconds:
                    pol.infer(batch, texts)
                    calls += 1
            ms = (time.perf_counter() - t0) / calls * 1000
            doc["ms"][name][b] = ms
            doc["rows_per_s"][name][b] = b * 1000 / ms
        for name in variants:
            if name != ref_name:
                cpu_ref = "fp32 (cpu)" if name.endswith("(cpu)") else ref_name
                doc["agreement"].setdefault(f"{name} vs {cpu_ref}", {})[b] = agreement(answers[cpu_ref], answers[name])
        write(path, doc)
    return doc


@contextlib.contextmanager
def _servers(checkpoint: str, device: str, max_batch: int, delay_ms: float) -> Iterator[dict[str, Any]]:
    from services.policy_worker.scheduler import SchedulerConfig
    from services.policy_worker.vla.split import MonolithicVLA, SplitVLA

    cfg = SchedulerConfig(max_batch=max_batch, max_queue_delay=delay_ms / 1000)
    servers: dict[str, Any] = {"monolithic": MonolithicVLA(checkpoint, device=device, config=cfg)}
    try:
        servers["split"] = SplitVLA(checkpoint, device=device, vlm=cfg, ae=cfg)
        yield servers
    finally:
        for s in servers.values():
            s.close()


async def warm_up(server: Any, instruction: str, inputs: list, max_batch: int, rounds: int = 2) -> None:
    """Bursts of every size up to ``max_batch``, without deadlines, ``rounds`` times.

    A batch size the model has not run yet is slow (TorchScript's profiling executor specializes
    the traced action expert per shape; CUDA picks kernels per shape), and each scheduler's compute
    estimate is a moving average of its batches: warmed at one size only, the first load's new sizes
    would push the estimate above the SLO and the scheduler would reject requests until it expired.
    """
    from services.policy_worker.scheduler import InferItem

    for r in range(rounds):
        for k in range(1, max_batch + 1):
            await asyncio.gather(*(server.submit(InferItem(f"w{r}-{k}-{i}", "m", inputs[i % len(inputs)], instruction))
                                   for i in range(k)))


async def _serve(servers: dict[str, Any], instruction: str, inputs: list, loads: list[float], duration: float,
                 max_batch: int, doc: dict[str, Any], path: str) -> None:
    for server in servers.values():
        await warm_up(server, instruction, inputs, max_batch)
    for rate in loads:
        for mode, server in servers.items():
            r = await open_loop(server, instruction, rate, duration, inputs=inputs)
            doc["rows"].append({"mode": mode, "load": rate, **r})
            write(path, doc)
    for server in servers.values():
        await server.drain()


def serving_section(checkpoint: str, device: str, loads: list[float], duration: float, max_batch: int,
                    delay_ms: float, path: str) -> dict[str, Any]:
    """Split against monolithic serving at each offered load (see the module docstring)."""
    import torch

    torch.set_num_threads(1)
    doc: dict[str, Any] = {"device": device, "checkpoint": checkpoint, "slo_ms": SLO * 1000, "duration_s": duration,
                           "max_batch": max_batch, "max_queue_delay_ms": delay_ms, "rows": []}
    with _servers(checkpoint, device, max_batch, delay_ms) as servers:
        policy = servers["monolithic"].policy
        instruction = sorted(policy.text.cache)[0]
        inputs = sample_inputs(policy.input_specs(), 64, seed=1)
        asyncio.run(_serve(servers, instruction, inputs, loads, duration, max_batch, doc, path))
    return doc


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("section", choices=("batch", "serving"))
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--device", default="cpu")
    p.add_argument("--batches", default="1,8,32,64")
    p.add_argument("--seconds", type=float, default=1.0, help="timed seconds per batch size and variant")
    p.add_argument("--loads", default="50,200,400", help="offered loads, requests/s")
    p.add_argument("--duration", type=float, default=3.0, help="seconds per load and mode")
    p.add_argument("--max-batch", type=int, default=32)
    p.add_argument("--delay-ms", type=float, default=5.0)
    p.add_argument("--json", default="")
    args = p.parse_args(argv)
    if args.section == "batch":
        doc = batch_section(args.checkpoint, args.device, [int(x) for x in args.batches.split(",")], args.seconds,
                            args.json)
    else:
        doc = serving_section(args.checkpoint, args.device, [float(x) for x in args.loads.split(",")], args.duration,
                              args.max_batch, args.delay_ms, args.json)
    print(json.dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
