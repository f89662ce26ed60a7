"""What dynamic batching buys: scheduler throughput at several ``max_batch`` values, same load.

The model is synthetic, ``cost(n) = a + b * n`` seconds per batch of n, spent in ``time.sleep``
(which, like a GPU kernel wait, releases the GIL). ``a`` stands for the fixed per-call overhead
(kernel launches, Python, transfers) that batching amortises, ``b`` for the per-sample work it
cannot. Closed-loop submitters (each sends its next request ``--think`` seconds after the
previous one returns, like env workers that step an action chunk between requests) keep the
offered load identical across configurations, so the only things that change between rows are
the batch limit and, with ``--early-dispatch both``, whether a partial batch goes out at once when
every submitter seen lately is waiting (the scheduler's early dispatch) or waits out
``max_queue_delay``. Both settings run in the same invocation, interleaved, medians of
``--repeats``.

    python bench/bench_scheduler.py [--submitters 64] [--a 0.002] [--b 0.0001] [--duration 1.0]
    python bench/bench_scheduler.py --submitters 1 --think 0.02 --max-queue-delay 0.005 --max-batch 32
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

from services.policy_worker.scheduler import BatchScheduler, InferItem, NullObserver, RunBatch, SchedulerConfig


@dataclass
class RunResult:
    items_per_s: float
    mean_batch: float
    p50_ms: float
    p99_ms: float


class _BatchSizes(NullObserver):
    """Observer that keeps only what the report needs."""

    def __init__(self) -> None:
        self.batches = 0
        self.items = 0

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        self.batches += 1
        self.items += size


def synthetic_model(a: float, b: float) -> RunBatch:
    def run_batch(model: str, inputs: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        time.sleep(a + b * len(instructions))
        return inputs["state"][:, :7] * 0.5

    return run_batch


async def one_run(max_batch: int, early_dispatch: bool, args: argparse.Namespace) -> RunResult:
    observer = _BatchSizes()
    config = SchedulerConfig(max_batch=max_batch, max_queue_delay=args.max_queue_delay, early_dispatch=early_dispatch)
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
            if args.think:
                await asyncio.sleep(args.think)

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
        f"{args.submitters} closed-loop submitters, think {args.think * 1e3:.1f} ms; max_queue_delay "
        f"{args.max_queue_delay * 1e3:.1f} ms; {args.duration:.1f} s per run, median of {args.repeats}"
    )
    settings = {"on": [True], "off": [False], "both": [True, False]}[args.early_dispatch]
    rows = []
    for max_batch in args.max_batch:
        runs: dict[bool, list[RunResult]] = {e: [] for e in settings}
        for _ in range(args.repeats):  # the settings interleaved, so drifting load weighs on both
            for early in settings:
                runs[early].append(await one_run(max_batch, early, args))
        ideal = max_batch / (args.a + args.b * max_batch)
        for early in settings:
            median = sorted(runs[early], key=lambda run: run.items_per_s)[len(runs[early]) // 2]
            rows.append((max_batch, early, median, ideal, statistics.pstdev(run.items_per_s for run in runs[early])))
    base = rows[0][2].items_per_s
    print(
        f"{'max_batch':>9} {'early':>5} {'items/s':>9} {'+-':>6} {'ideal':>7} {'speedup':>8} "
        f"{'mean batch':>11} {'p50 ms':>7} {'p99 ms':>7}"
    )
    for max_batch, early, run, ideal, spread in rows:
        print(
            f"{max_batch:>9} {'on' if early else 'off':>5} {run.items_per_s:>9.0f} {spread:>6.0f} {ideal:>7.0f} "
            f"{run.items_per_s / base:>7.1f}x {run.mean_batch:>11.1f} {run.p50_ms:>7.1f} {run.p99_ms:>7.1f}"
        )


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--submitters", type=int, default=64)
    parser.add_argument("--a", type=float, default=0.002, help="fixed seconds per batch")
    parser.add_argument("--b", type=float, default=0.0001, help="seconds per item in a batch")
    parser.add_argument("--max-queue-delay", type=float, default=0.002)
    parser.add_argument("--think", type=float, default=0.0,
                        help="seconds a submitter waits after an answer before its next request")
    parser.add_argument("--early-dispatch", choices=("on", "off", "both"), default="both",
                        help="the scheduler's early dispatch (default: both, side by side)")
    parser.add_argument("--duration", type=float, default=1.0, help="seconds per run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-batch", type=int, nargs="+", default=[1, 4, 16, 32])
    return parser.parse_args()


if __name__ == "__main__":
    asyncio.run(main(parse_args()))
