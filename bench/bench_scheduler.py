"""What dynamic batching buys: scheduler throughput at several ``max_batch`` values, same load.

The model is synthetic, ``cost(n) = a + b * n`` seconds per batch of n, spent in ``time.sleep``
(which, like a GPU kernel wait, releases the GIL). ``a`` stands for the fixed per-call overhead
(kernel launches, Python, transfers) that batching amortises, ``b`` for the per-sample work it
cannot. Closed-loop submitters (each sends its next request as soon as the previous returns, like
env workers stepping episodes) keep the offered load identical across configurations, so the
only thing that changes between columns is the batch limit.

    python bench/bench_scheduler.py [--submitters 64] [--a 0.002] [--b 0.0001] [--duration 1.0]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Lets `python bench/bench_scheduler.py` run from a plain checkout, without installing the package.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.policy_worker.scheduler import BatchScheduler, InferItem, RunBatch, SchedulerConfig


@dataclass
class RunResult:
    items_per_s: float
    mean_batch: float
    p50_ms: float
    p99_ms: float


class _BatchSizes:
    """Observer that keeps only what the report needs."""

    def __init__(self) -> None:
        self.batches = 0
        self.items = 0

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        self.batches += 1
        self.items += size

    def on_queue_wait(self, model: str, seconds: float) -> None:
        pass

    def on_queue_depth(self, model: str, depth: int) -> None:
        pass

    def on_reject(self, model: str, reason: str) -> None:
        pass


def synthetic_model(a: float, b: float) -> RunBatch:
    def run_batch(model: str, inputs: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        time.sleep(a + b * len(instructions))
        return inputs["state"][:, :7] * 0.5

    return run_batch


async def one_run(max_batch: int, args: argparse.Namespace) -> RunResult:
    observer = _BatchSizes()
    config = SchedulerConfig(max_batch=max_batch, max_queue_delay=args.max_queue_delay)
    scheduler = BatchScheduler(synthetic_model(args.a, args.b), config, observer)
    state = np.zeros(32, dtype=np.float32)
    latencies: list[float] = []
    start = time.monotonic()
    stop = start + args.duration

    async def submitter(sid: int) -> None:
        k = 0
        while True:
            sent = time.monotonic()
            if sent >= stop:
                return
            await scheduler.submit(InferItem(f"{sid}-{k}", "synthetic", {"state": state}, "pick up the bowl"))
            done = time.monotonic()
            if done <= stop:
                latencies.append(done - sent)
            k += 1

    await asyncio.gather(*(submitter(i) for i in range(args.submitters)))
    await scheduler.drain()
    latencies.sort()
    return RunResult(
        items_per_s=len(latencies) / args.duration,
        mean_batch=observer.items / max(observer.batches, 1),
        p50_ms=1e3 * latencies[len(latencies) // 2],
        p99_ms=1e3 * latencies[min(len(latencies) - 1, int(len(latencies) * 0.99))],
    )


async def main(args: argparse.Namespace) -> None:
    print(
        f"synthetic model: {args.a * 1e3:.1f} ms + {args.b * 1e3:.2f} ms/item per batch; "
        f"{args.submitters} closed-loop submitters; max_queue_delay {args.max_queue_delay * 1e3:.1f} ms; "
        f"{args.duration:.1f} s per run, median of {args.repeats}"
    )
    rows = []
    for max_batch in args.max_batch:
        runs = [await one_run(max_batch, args) for _ in range(args.repeats)]
        median = sorted(runs, key=lambda run: run.items_per_s)[len(runs) // 2]
        ideal = max_batch / (args.a + args.b * max_batch)
        rows.append((max_batch, median, ideal, statistics.pstdev(run.items_per_s for run in runs)))
    base = rows[0][1].items_per_s
    print(
        f"{'max_batch':>9} {'items/s':>9} {'+-':>6} {'ideal':>7} {'speedup':>8} "
        f"{'mean batch':>11} {'p50 ms':>7} {'p99 ms':>7}"
    )
    for max_batch, run, ideal, spread in rows:
        print(
            f"{max_batch:>9} {run.items_per_s:>9.0f} {spread:>6.0f} {ideal:>7.0f} {run.items_per_s / base:>7.1f}x "
            f"{run.mean_batch:>11.1f} {run.p50_ms:>7.1f} {run.p99_ms:>7.1f}"
        )


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--submitters", type=int, default=64)
    parser.add_argument("--a", type=float, default=0.002, help="fixed seconds per batch")
    parser.add_argument("--b", type=float, default=0.0001, help="seconds per item in a batch")
    parser.add_argument("--max-queue-delay", type=float, default=0.002)
    parser.add_argument("--duration", type=float, default=1.0, help="seconds per run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-batch", type=int, nargs="+", default=[1, 4, 16, 32])
    return parser.parse_args()


if __name__ == "__main__":
    asyncio.run(main(parse_args()))
