"""The Zetta VLA served three ways, side by side in one run.

1. throughput of the monolithic policy at batch 1/4/16/32, float vs W8A8 (prefix MLP int8), and
   the served (TorchScript-traced) action expert vs the eager module, CPU time per call, interleaved;
2. split (VLM and action expert in two processes, prefix through shared memory) vs monolithic
   (one process, one scheduler): latency and goodput under a 200 ms SLO at several open-loop
   Poisson loads (requests/s); goodput = answers within the SLO per second;
3. the scheduler's max_queue_delay and max_batch at the highest load (how the defaults were chosen).

    python bench/bench_policy.py [--duration 3] [--loads 50,200,400,800] [--checkpoint DIR]
    python bench/bench_policy.py --only trace       # traced vs eager stage 2 alone (20 s)
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.common.specs import TensorSpec
from services.policy_worker.scheduler import DeadlineExceededError, InferItem, SchedulerConfig

SLO = 0.2
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


def throughput(policy, instruction: str, batches=(1, 4, 16, 32), seconds: float = 1.0) -> dict[int, tuple[float, float]]:
    out = {}
    for b in batches:
        batch = stack(sample_inputs(b))
        policy.infer(batch, [instruction] * b)
        calls, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            policy.infer(batch, [instruction] * b)
            calls += 1
        dt = (time.perf_counter() - t0) / calls
        out[b] = (dt * 1000, b / dt)
    return out


def traced_vs_eager(checkpoint: str | None, instruction: str, batches=(1, 4, 16, 32), calls: int = 200) -> dict:
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
        out[b] = {k: float(np.median(v)) * 1000 for k, v in cpu.items()}
    return out


def print_traced(res: dict) -> None:
    print("\n== action expert: traced (served) vs eager, one inference, median thread CPU ms, interleaved ==")
    print(f"{'batch':>5} | {'eager ms':>9} {'traced ms':>9} | {'speedup':>7}")
    for b, r in res.items():
        print(f"{b:>5} | {r['eager']:>9.2f} {r['traced']:>9.2f} | {r['eager'] / r['traced']:>6.2f}x")


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


async def serving(args, instruction: str) -> None:
    from services.policy_worker.vla.split import MonolithicVLA, SplitVLA

    cfg = SchedulerConfig(max_batch=args.max_batch, max_queue_delay=args.delay_ms / 1000)
    loads = [float(x) for x in args.loads.split(",")]
    results = {}
    for mode in ("monolithic", "split"):
        server = (MonolithicVLA(args.checkpoint, config=cfg) if mode == "monolithic"
                  else SplitVLA(args.checkpoint, vlm=cfg, ae=cfg))
        await open_loop(server, instruction, 50, 0.5, seed=99)  # warm-up
        for rate in loads:
            results[(mode, rate)] = await open_loop(server, instruction, rate, args.duration)
        if mode == "monolithic":
            sweep = {}
            for delay in (0.0, 0.002, 0.005, 0.010):
                s2 = MonolithicVLA(args.checkpoint, config=SchedulerConfig(max_batch=args.max_batch,
                                                                            max_queue_delay=delay))
                sweep[delay] = await open_loop(s2, instruction, loads[-1], args.duration)
                await s2.drain()
            batch_sweep = {}
            for mb in (1, 4, 8, 16, 32, 64):
                s2 = MonolithicVLA(args.checkpoint, config=SchedulerConfig(
                    max_batch=mb, max_queue_delay=args.delay_ms / 1000, max_queue=max(1024, mb)))
                batch_sweep[mb] = await open_loop(s2, instruction, loads[-1], args.duration)
                await s2.drain()
        await server.drain()
        server.close()
    print(f"\n== split vs monolithic, open-loop Poisson load, SLO {SLO * 1000:.0f} ms "
          f"(max_batch {args.max_batch}, max_queue_delay {args.delay_ms} ms, {args.duration:.0f} s per load) ==")
    print(f"{'load/s':>7} | {'mode':<10} {'sent':>6} {'mean ms':>8} {'p50 ms':>8} {'p99 ms':>8} {'goodput/s':>10} {'missed':>7}")
    for rate in loads:
        for mode in ("monolithic", "split"):
            r = results[(mode, rate)]
            print(f"{rate:>7.0f} | {mode:<10} {r['sent']:>6} {r['mean_ms']:>8.1f} {r['p50_ms']:>8.1f} "
                  f"{r['p99_ms']:>8.1f} {r['goodput']:>10.1f} {r['rejected']:>7} {r['errors'] or ''}")
    print(f"\n== monolithic max_queue_delay sweep at {loads[-1]:.0f} req/s ==")
    print(f"{'delay ms':>8} {'mean ms':>8} {'p99 ms':>8} {'goodput/s':>10}")
    for d, r in sweep.items():
        print(f"{d * 1000:>8.1f} {r['mean_ms']:>8.1f} {r['p99_ms']:>8.1f} {r['goodput']:>10.1f}")
    print(f"\n== monolithic max_batch sweep at {loads[-1]:.0f} req/s (max_queue_delay {args.delay_ms} ms) ==")
    print(f"{'max_batch':>9} {'mean ms':>8} {'p99 ms':>8} {'goodput/s':>10} {'missed':>7}")
    for mb, r in batch_sweep.items():
        print(f"{mb:>9} {r['mean_ms']:>8.1f} {r['p99_ms']:>8.1f} {r['goodput']:>10.1f} {r['rejected']:>7}")


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--duration", type=float, default=3.0)
    p.add_argument("--loads", default="50,200,400,800")
    p.add_argument("--max-batch", type=int, default=32)
    p.add_argument("--delay-ms", type=float, default=5.0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--only", default="throughput,trace,serving", help="comma-separated sections to run")
    args = p.parse_args()
    only = set(args.only.split(","))
    import torch

    torch.set_num_threads(args.threads)
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    flt = ZettaVLAPolicy(args.checkpoint) if args.checkpoint else ZettaVLAPolicy()
    q = ZettaVLAPolicy(args.checkpoint, quantize="w8a8") if args.checkpoint else ZettaVLAPolicy(quantize="w8a8")
    instruction = sorted(flt.text.cache)[0]
    SPECS[:] = flt.input_specs()
    print(f"checkpoint: {flt.checkpoint} inputs {[(sp.name, list(sp.shape)) for sp in SPECS]}")
    print(f"config: {flt.cfg.to_dict()}  torch threads {torch.get_num_threads()}  quantized: {q.quantized}")
    if "trace" in only:
        print_traced(traced_vs_eager(args.checkpoint, instruction))
    if "throughput" not in only:
        if "serving" in only:
            asyncio.run(serving(args, instruction))
        return
    tf, tq = throughput(flt, instruction), throughput(q, instruction)
    print("\n== throughput, monolithic, float vs W8A8 (prefix MLP) ==")
    print(f"{'batch':>5} | {'float ms':>9} {'float rows/s':>12} | {'w8a8 ms':>9} {'w8a8 rows/s':>12} | {'speedup':>7}")
    for b in tf:
        print(f"{b:>5} | {tf[b][0]:>9.2f} {tf[b][1]:>12.0f} | {tq[b][0]:>9.2f} {tq[b][1]:>12.0f} | "
              f"{tf[b][0] / tq[b][0]:>6.2f}x")
    # Stage-1-only timing: what the plug-in actually changes.
    import torch as _t

    batch = stack(sample_inputs(32))
    for name, pol in (("float", flt), ("w8a8", q)):
        pol.encode(batch, [instruction] * 32)
        t0, k = time.perf_counter(), 0
        while time.perf_counter() - t0 < 1.0:
            pol.encode(batch, [instruction] * 32)
            k += 1
        print(f"stage 1 (VLM) only, batch 32, {name}: {(time.perf_counter() - t0) / k * 1000:.2f} ms")
    del _t
    if "serving" in only:
        asyncio.run(serving(args, instruction))


if __name__ == "__main__":
    main()
