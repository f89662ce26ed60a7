"""The Zetta VLA served three ways, side by side in one run.

1. throughput of the monolithic policy at batch 1/4/16/32, float vs W8A8 (prefix MLP int8), and
   the served (TorchScript-traced) action expert vs the eager module, CPU time per call, interleaved;
2. split (VLM and action expert in two processes, prefix through shared memory) vs monolithic
   (one process, one scheduler): latency and goodput under a 200 ms SLO at several open-loop
   Poisson loads (requests/s); goodput = answers within the SLO per second;
3. the scheduler's max_queue_delay and max_batch at the highest load (how the defaults were chosen).

Every section runs on the same inputs (the checkpoint's declared tensors: camera frames and
proprioception for the image VLA), so the ratios printed side by side are measured in one run.

    python bench/bench_policy.py [--duration 3] [--loads 50,200,400,800] [--checkpoint DIR]
    python bench/bench_policy.py --only trace       # traced vs eager stage 2 alone (20 s)
    python bench/bench_policy.py --write-docs       # also docs/results/policy-bench.json and .md
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.common.provenance import page_header, publish, weights_sha256
from services.common.specs import TensorSpec
from services.policy_worker.scheduler import DeadlineExceededError, InferItem, SchedulerConfig

SLO = 0.2
TOPIC = "policy-bench"
TITLE = "The Zetta VLA served: batching, W8A8, the traced action expert, split vs monolithic"
BATCHES = (1, 4, 16, 32)
#: The served checkpoint's inputs (set in main): camera frames and proprioception for the image VLA.
SPECS: list[TensorSpec] = []


def sample_inputs(n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    """``n`` requests shaped as the checkpoint declares: random frames, small proprioception values."""
    rng = np.random.default_rng(seed)

    def one(spec: TensorSpec) -> np.ndarray:
        if spec.dtype == "uint8":
            return rng.integers(0, 256, spec.shape, dtype=np.uint8)
        return rng.standard_normal(spec.shape).astype(spec.dtype) * 0.1

    return [{s.name: one(s) for s in SPECS} for _ in range(n)]


def stack(rows: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    return {s.name: np.stack([r[s.name] for r in rows]) for s in SPECS}


def throughput(policy, instruction: str, batches=BATCHES, seconds: float = 1.0) -> dict[str, dict[str, float]]:
    """Wall ms per monolithic call and rows/s at each batch size (one policy, back-to-back calls)."""
    out = {}
    for b in batches:
        batch = stack(sample_inputs(b))
        policy.infer(batch, [instruction] * b)
        calls, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            policy.infer(batch, [instruction] * b)
            calls += 1
        dt = (time.perf_counter() - t0) / calls
        out[str(b)] = {"ms": dt * 1000, "rows_s": b / dt}
    return out


def traced_vs_eager(checkpoint: str | None, instruction: str, batches=BATCHES, calls: int = 200) -> dict:
    """Median thread CPU ms of one full inference (both stages), the served traced action expert
    against the eager one, calls interleaved so both see the same machine; the outputs must match."""
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    kw = {"checkpoint": checkpoint} if checkpoint else {}
    pols = {"eager": ZettaVLAPolicy(trace=False, **kw), "traced": ZettaVLAPolicy(**kw)}
    out = {}
    for b in batches:
        batch = stack(sample_inputs(b, seed=b))
        texts = [instruction] * b
        answers = {k: p.infer(batch, texts) for k, p in pols.items()}
        assert np.array_equal(answers["eager"], answers["traced"]), "the trace changed the actions"
        cpu: dict[str, list[float]] = {k: [] for k in pols}
        for _ in range(calls):
            for k, p in pols.items():
                t = time.thread_time()
                p.infer(batch, texts)
                cpu[k].append(time.thread_time() - t)
        out[str(b)] = {k: float(np.median(v)) * 1000 for k, v in cpu.items()}
    return out


def stage1_ms(policy, instruction: str, rows: int = 32, seconds: float = 1.0) -> float:
    """Wall ms of stage 1 (the VLM prefix) alone at ``rows``: what W8A8 changes."""
    batch = stack(sample_inputs(rows))
    policy.encode(batch, [instruction] * rows)
    t0, k = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        policy.encode(batch, [instruction] * rows)
        k += 1
    return (time.perf_counter() - t0) / k * 1000


async def open_loop(server, instruction: str, rate: float, duration: float, seed: int = 1,
                    inputs: list[dict[str, np.ndarray]] | None = None) -> dict:
    """Poisson arrivals at ``rate``/s for ``duration`` s; ``inputs`` (default: 64 state samples) in turn."""
    rng = np.random.default_rng(seed)
    inputs = inputs or sample_inputs(64)
    lat, tasks, rejected, errors = [], [], [0], {}

    async def one(i: int) -> None:
        t = time.monotonic()
        item = InferItem(f"r{seed}-{i}", "m", inputs[i % len(inputs)], instruction, deadline=t + SLO, arrival=t)
        try:
            await server.submit(item)
            lat.append(time.monotonic() - t)
        except DeadlineExceededError:
            rejected[0] += 1
        except Exception as exc:  # noqa: BLE001 - RESOURCE_EXHAUSTED etc. count as misses
            rejected[0] += 1
            errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1

    start = time.monotonic()
    next_t, i = start, 0
    while next_t - start < duration:
        now = time.monotonic()
        if next_t > now:
            await asyncio.sleep(next_t - now)
        tasks.append(asyncio.ensure_future(one(i)))
        i += 1
        next_t += rng.exponential(1.0 / rate)
    await asyncio.gather(*tasks)
    lat_ms = np.array(lat) * 1000 if lat else np.array([np.nan])
    good = int((np.array(lat) <= SLO).sum()) if lat else 0
    return {"sent": i, "mean_ms": float(np.mean(lat_ms)), "p50_ms": float(np.percentile(lat_ms, 50)),
            "p99_ms": float(np.percentile(lat_ms, 99)), "goodput": good / duration, "rejected": rejected[0],
            "errors": errors}


async def serving(args: argparse.Namespace, instruction: str) -> dict[str, Any]:
    """Split vs monolithic at each open-loop load, then the monolithic scheduler's knobs at the top load."""
    from services.policy_worker.vla.split import MonolithicVLA, SplitVLA

    cfg = SchedulerConfig(max_batch=args.max_batch, max_queue_delay=args.delay_ms / 1000)
    loads = [float(x) for x in args.loads.split(",")]
    modes: dict[str, dict[str, Any]] = {"monolithic": {}, "split": {}}
    delay_sweep: dict[str, Any] = {}
    batch_sweep: dict[str, Any] = {}
    for mode in modes:
        server = (MonolithicVLA(args.checkpoint, config=cfg) if mode == "monolithic"
                  else SplitVLA(args.checkpoint, vlm=cfg, ae=cfg))
        await open_loop(server, instruction, 50, 0.5, seed=99)  # warm-up
        for rate in loads:
            modes[mode][f"{rate:g}"] = await open_loop(server, instruction, rate, args.duration)
        await server.drain()
        server.close()
    for delay in (0.0, 0.002, 0.005, 0.010):
        s2 = MonolithicVLA(args.checkpoint, config=SchedulerConfig(max_batch=args.max_batch, max_queue_delay=delay))
        delay_sweep[f"{delay * 1000:g}"] = await open_loop(s2, instruction, loads[-1], args.duration)
        await s2.drain()
    for mb in (1, 4, 8, 16, 32, 64):
        s2 = MonolithicVLA(args.checkpoint, config=SchedulerConfig(
            max_batch=mb, max_queue_delay=args.delay_ms / 1000, max_queue=max(1024, mb)))
        batch_sweep[str(mb)] = await open_loop(s2, instruction, loads[-1], args.duration)
        await s2.drain()
    return {"slo_ms": SLO * 1000, "max_batch": args.max_batch, "max_queue_delay_ms": args.delay_ms,
            "duration_s": args.duration, "loads": [f"{r:g}" for r in loads], "modes": modes,
            "delay_sweep": delay_sweep, "batch_sweep": batch_sweep}


def measure(args: argparse.Namespace) -> dict[str, Any]:
    """Every section asked for, on one checkpoint, in one run: the results file's measurements."""
    import torch

    torch.set_num_threads(args.threads)
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    kw = {"checkpoint": args.checkpoint} if args.checkpoint else {}
    flt, q = ZettaVLAPolicy(**kw), ZettaVLAPolicy(quantize="w8a8", **kw)
    instruction = sorted(flt.text.cache)[0]
    SPECS[:] = flt.input_specs()
    only = set(args.only.split(","))
    doc: dict[str, Any] = {
        "policy": {"model": Path(flt.checkpoint).name, "checkpoint_sha256": weights_sha256(flt.checkpoint)},
        "inputs": [[sp.name, list(sp.shape), sp.dtype] for sp in SPECS], "config": flt.cfg.to_dict(),
        "torch_threads": torch.get_num_threads(), "cores": os.cpu_count(), "quantized": q.quantized,
        "load_before": os.getloadavg()[0]}
    if "trace" in only:
        doc["trace"] = traced_vs_eager(args.checkpoint, instruction)
    if "throughput" in only:
        doc["throughput"] = {"float": throughput(flt, instruction), "w8a8": throughput(q, instruction)}
        doc["stage1_batch32_ms"] = {"float": stage1_ms(flt, instruction), "w8a8": stage1_ms(q, instruction)}
    if "serving" in only:
        doc["serving"] = asyncio.run(serving(args, instruction))
    doc["load_after"] = os.getloadavg()[0]
    return doc


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}x" if b else "n/a"


def report(doc: Mapping[str, Any]) -> list[str]:
    """The run's tables, then the three comparisons the issue asks for on one line each."""
    out = [f"checkpoint: {doc['policy']['model']} (model.pt sha256 {doc['policy']['checkpoint_sha256'][:12]}), "
           f"inputs {[(n, s) for n, s, _ in doc['inputs']]}",
           f"torch threads {doc['torch_threads']} of {doc['cores']} cores, load {doc['load_before']:.1f} before, "
           f"{doc['load_after']:.1f} after; W8A8 plug-in: {doc['quantized']}"]
    summary = []
    if "trace" in doc:
        out += ["", "== action expert: traced (served) vs eager, one inference, median thread CPU ms, interleaved ==",
                f"{'batch':>5} | {'eager ms':>9} {'traced ms':>9} | {'speedup':>7}"]
        for b, r in doc["trace"].items():
            out.append(f"{b:>5} | {r['eager']:>9.2f} {r['traced']:>9.2f} | {_ratio(r['eager'], r['traced']):>7}")
    if "throughput" in doc:
        tf, tq = doc["throughput"]["float"], doc["throughput"]["w8a8"]
        out += ["", "== throughput, monolithic, float vs W8A8 (prefix MLP) ==",
                f"{'batch':>5} | {'float ms':>9} {'float rows/s':>12} | {'w8a8 ms':>9} {'w8a8 rows/s':>12} | "
                f"{'speedup':>7} | {'float rows/s vs batch 1':>23}"]
        for b in tf:
            out.append(f"{b:>5} | {tf[b]['ms']:>9.2f} {tf[b]['rows_s']:>12.0f} | {tq[b]['ms']:>9.2f} "
                       f"{tq[b]['rows_s']:>12.0f} | {_ratio(tf[b]['ms'], tq[b]['ms']):>7} | "
                       f"{_ratio(tf[b]['rows_s'], tf['1']['rows_s']):>23}")
        s1 = doc["stage1_batch32_ms"]
        out.append(f"stage 1 (VLM) only, batch 32: float {s1['float']:.2f} ms, w8a8 {s1['w8a8']:.2f} ms "
                   f"({_ratio(s1['float'], s1['w8a8'])})")
        if "16" in tf:
            summary.append(f"batch 16 vs batch 1 (float): {_ratio(tf['16']['rows_s'], tf['1']['rows_s'])} rows/s")
            summary.append(f"W8A8 vs float at batch 16: {_ratio(tq['16']['rows_s'], tf['16']['rows_s'])} rows/s; "
                           f"at batch 1: {_ratio(tq['1']['rows_s'], tf['1']['rows_s'])}")
    if "serving" in doc:
        sv = doc["serving"]
        out += ["", f"== split vs monolithic, open-loop Poisson load, SLO {sv['slo_ms']:.0f} ms (max_batch "
                f"{sv['max_batch']}, max_queue_delay {sv['max_queue_delay_ms']:g} ms, {sv['duration_s']:g} s per load) ==",
                f"{'load/s':>7} | {'mode':<10} {'sent':>6} {'mean ms':>8} {'p50 ms':>8} {'p99 ms':>8} "
                f"{'goodput/s':>10} {'missed':>7}"]
        for rate in sv["loads"]:
            for mode in ("monolithic", "split"):
                r = sv["modes"][mode][rate]
                out.append(f"{rate:>7} | {mode:<10} {r['sent']:>6} {r['mean_ms']:>8.1f} {r['p50_ms']:>8.1f} "
                           f"{r['p99_ms']:>8.1f} {r['goodput']:>10.1f} {r['rejected']:>7} {r['errors'] or ''}")
        top = sv["loads"][-1]
        out += ["", f"== monolithic max_queue_delay sweep at {top} req/s ==",
                f"{'delay ms':>8} {'mean ms':>8} {'p99 ms':>8} {'goodput/s':>10}"]
        for d, r in sv["delay_sweep"].items():
            out.append(f"{d:>8} {r['mean_ms']:>8.1f} {r['p99_ms']:>8.1f} {r['goodput']:>10.1f}")
        out += ["", f"== monolithic max_batch sweep at {top} req/s (max_queue_delay {sv['max_queue_delay_ms']:g} ms) ==",
                f"{'max_batch':>9} {'mean ms':>8} {'p99 ms':>8} {'goodput/s':>10} {'missed':>7}"]
        for mb, r in sv["batch_sweep"].items():
            out.append(f"{mb:>9} {r['mean_ms']:>8.1f} {r['p99_ms']:>8.1f} {r['goodput']:>10.1f} {r['rejected']:>7}")
        split, mono = sv["modes"]["split"][top], sv["modes"]["monolithic"][top]
        summary.append(f"split vs monolithic at {top} req/s: goodput {_ratio(split['goodput'], mono['goodput'])}, "
                       f"p99 {split['p99_ms']:.0f} vs {mono['p99_ms']:.0f} ms")
    if summary:
        out += ["", "== side by side =="] + summary
    return out


def page(doc: Mapping[str, Any]) -> str:
    """docs/results/policy-bench.md from its results file."""
    return page_header(TOPIC, TITLE, doc) + (
        "\nWhat each section measures and how the serving defaults follow from it: "
        "[docs/policies.md](../policies.md) and [docs/configuration.md](../configuration.md).\n\n```\n"
        + "\n".join(report(doc)) + "\n```\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--duration", type=float, default=3.0)
    p.add_argument("--loads", default="50,200,400,800")
    p.add_argument("--max-batch", type=int, default=32)
    p.add_argument("--delay-ms", type=float, default=5.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--only", default="throughput,trace,serving", help="comma-separated sections to run")
    p.add_argument("--write-docs", action="store_true", help=f"also write docs/results/{TOPIC}.json and .md")
    a = p.parse_args(argv)
    doc = measure(a)
    print("\n".join(report(doc)))
    if a.write_docs:
        args = list(argv if argv is not None else sys.argv[1:])
        for path in publish(TOPIC, TITLE, "bench/bench_policy.py", args, doc, page, Path(__file__).resolve().parents[1]):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
