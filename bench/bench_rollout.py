"""Rollout throughput: our stack against a naive loop, side by side, in one run.

Both sides run the same episodes of LIBERO-Goal "put_the_cream_cheese_in_the_bowl" (episode i
uses init state i % 50 and seed i) with the same policy, the scripted pick-and-place controller
(``services/policy_worker/models/scripted.py``), and the same step budget (``--max-steps``).

naive        one process, episodes one after another, and for every episode a LIBERO environment
             built from scratch (a new family instance, so the MuJoCo scene is compiled again, as
             a script that calls LIBERO's env constructor per episode does; ``hard_reset=False``
             as everywhere), the policy called in-process on a batch of one. Half of its episodes
             run before the stack starts and half after it stops, so a load that drifts during
             the run (the machine is shared) weighs on both sides alike.
run_episode  ``services.ops.local_stack.LocalStack``: Redis, the gateway, 2 env workers x 8 slots and one
             policy worker, each its own process on loopback. Sessions are created once (the
             creation time is printed on its own and is not part of episodes/min); then
             ``concurrency`` lanes each drive one session and run episodes back to back with
             ``SessionGroup.run_episode`` (whole episode inside the env worker, inference batched
             across sessions by the policy worker) until the point's episodes are done.
policy_step  the same lanes, but the client drives every step: ``reset`` then ``policy_step``
             over the gateway until the episode ends (the paper's listing; calls made in the same
             event-loop turn leave as one RPC).

episodes/min counts the point's episodes over the wall time from its first reset to its last
episode's end; latency is the client-side wall time of one episode (reset included). With
``--repeats R`` every point runs R times and the table shows medians (episodes/min, and the
latency percentiles of each repeat); success counts all repeats.

    python bench/bench_rollout.py             # default: about 7 minutes on 2 cores
    python bench/bench_rollout.py --quick     # about 2 minutes
    python bench/bench_rollout.py --write-docs  # also docs/results/bench-rollout.json and .md
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# Lets `python bench/bench_rollout.py` run from a plain checkout, without installing the package.
ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

from bench import bench_sweep  # noqa: E402
from bench.bench_report import aligned  # noqa: E402
from bench.bench_sweep import Episode, balanced, quiet_fds  # noqa: E402
from services.common.progress import add_progress_option, progress  # noqa: E402
from services.common.provenance import page_header, provenance, write_results  # noqa: E402

SUITE = "libero_goal"
TASK = "put_the_cream_cheese_in_the_bowl"
ENV_WORKERS = 2
SLOTS_PER_WORKER = 8


@dataclass
class Run:
    """One repeat of one point."""

    episodes: list[Episode]
    wall_s: float

    @property
    def episodes_per_min(self) -> float:
        return 60.0 * len(self.episodes) / self.wall_s if self.wall_s > 0 else 0.0

    def latency_pct(self, q: float) -> float:
        return float(np.percentile([e.latency_s for e in self.episodes], q)) if self.episodes else 0.0


@dataclass
class Point:
    """A row of the table: one mode at one concurrency, possibly repeated."""

    mode: str
    concurrency: int
    runs: list[Run] = field(default_factory=list)

    @property
    def episodes(self) -> int:
        return sum(len(r.episodes) for r in self.runs)

    @property
    def successes(self) -> int:
        return sum(e.success for r in self.runs for e in r.episodes)

    @property
    def steps(self) -> int:
        return sum(e.steps for r in self.runs for e in r.episodes)

    @property
    def episodes_per_min(self) -> float:
        return statistics.median(r.episodes_per_min for r in self.runs)

    @property
    def steps_per_s(self) -> float:
        return statistics.median(sum(e.steps for e in r.episodes) / r.wall_s for r in self.runs)

    def latency(self, q: float) -> float:
        return statistics.median(r.latency_pct(q) for r in self.runs)


# ---------------------------------------------------------------------------------------------
# naive baseline


def env_config(max_steps: int) -> dict[str, object]:
    return bench_sweep.env_config(TASK, max_steps)


def naive_episode(index: int, max_steps: int) -> Episode:
    """Build a LIBERO env from scratch, run one episode with the in-process policy, drop the env
    (the loop of `zetta bench rollout`'s naive rows, on this page's episode key: seed i, init i % 50)."""
    from services.policy_worker.models.scripted import ScriptedPickPlacePolicy

    episode, _ = bench_sweep.naive_episode(ScriptedPickPlacePolicy(), index, TASK, max_steps, fast_step=True,
                                           key=(index, index % 50))
    return episode


def naive_warmup(max_steps: int, log: Callable[[str], None]) -> None:
    t = time.perf_counter()
    with quiet_fds():
        naive_episode(10_000, min(max_steps, 10))  # imports, lazy caches: a once-per-process cost
    log(f"naive: process warm-up (imports + one 10-step episode) {time.perf_counter() - t:.1f} s, not counted")


def run_naive_half(point: Point, indices: Sequence[int], max_steps: int, repeats: int, label: str,
                   log: Callable[[str], None]) -> None:
    """Run the naive episodes ``indices`` ``repeats`` times, adding them to the point's runs.

    The naive loop runs half of its episodes before the stack and half after it, so that a load
    that drifts over the run (the machine is shared) weighs on both sides alike; run ``r`` of the
    point is the sum of both halves of repeat ``r``.
    """
    if not indices:
        return
    for r in range(repeats):
        t0 = time.perf_counter()
        done = [naive_episode(i, max_steps) for i in progress(indices, desc=f"naive {r + 1}/{repeats}", leave=False)]
        wall = time.perf_counter() - t0
        if len(point.runs) <= r:
            point.runs.append(Run([], 0.0))
        run = point.runs[r]
        run.episodes += done
        run.wall_s += wall
        log(f"naive {label}: repeat {r + 1}/{repeats}: {len(done)} episodes in {wall:.1f} s "
            f"({60 * len(done) / wall:.1f}/min, {sum(e.success for e in done)} successes; env build "
            f"{statistics.mean(e.build_s for e in done):.2f} s of {statistics.mean(e.latency_s for e in done):.2f} s "
            f"per episode)")


# ---------------------------------------------------------------------------------------------
# our stack


async def run_lanes(sessions: object, ids: Sequence[str], episodes: int, mode: str, max_steps: int) -> Run:
    """``len(ids)`` lanes, each running episodes back to back on its own session."""
    from zetta.client import Session, SessionGroup

    assert isinstance(sessions, SessionGroup)
    counter = iter(range(episodes))
    done: list[Episode] = []

    async def lane(sid: str) -> None:
        group = sessions.subset([sid])
        session = Session(sessions.gateway, sid)
        for i in counter:
            t = time.perf_counter()
            if mode == "run_episode":
                (s,) = await group.run_episode(task=TASK, seed=i, init_state_index=i % 50, max_steps=max_steps)
                success, steps = s.success, s.steps
            else:
                await session.reset(task=TASK, seed=i, init_state_index=i % 50)
                while True:
                    r = await session.policy_step()
                    if r.done or r.episode_step >= max_steps:
                        break
                success, steps = r.success, r.episode_step
            done.append(Episode(i, success, steps, time.perf_counter() - t))
            bar.update()

    t0 = time.perf_counter()
    with progress(total=episodes, desc=f"{mode} c={len(ids)}", leave=False) as bar:
        await asyncio.gather(*(lane(sid) for sid in ids))
    return Run(sorted(done, key=lambda e: e.index), time.perf_counter() - t0)


async def create_sessions(gw: object, n: int, max_steps: int, setup: dict[str, float],
                          log: Callable[[str], None], attempts: int = 3) -> object:
    """Create ``n`` sessions once and warm them up with one short episode each.

    They are created a few at a time (as many as ``ENV_WORKERS`` x 2 per call) rather than all at
    once: building many LIBERO envs in parallel in one worker process can starve its heartbeats
    for seconds on a loaded 2-core machine, and the gateway then declares the worker dead and its
    sessions LOST. When that happens anyway, the sessions are closed and created again.
    """
    from zetta.client import Gateway, SessionGroup, ZettaError

    assert isinstance(gw, Gateway)
    batch = ENV_WORKERS * 2
    for attempt in range(1, attempts + 1):
        t = time.perf_counter()
        infos: list[object] = []
        sessions: SessionGroup | None = None
        try:
            for k in range(0, n, batch):
                group = await gw.create_sessions(env_family="libero", n=min(batch, n - k),
                                                 env_config=env_config(max_steps), keepalive=False)
                infos += group.infos
            setup["create_s"] = time.perf_counter() - t
            sessions = SessionGroup(gw, infos)  # type: ignore[arg-type]
            sessions.start_keepalive()
            per_worker: dict[str, int] = {}
            for info in sessions.infos:
                per_worker[info.worker_id] = per_worker.get(info.worker_id, 0) + 1
            log(f"stack: created {n} sessions in {setup['create_s']:.1f} s "
                f"({', '.join(f'{w}: {k}' for w, k in sorted(per_worker.items()))}), not counted")
            t = time.perf_counter()
            await sessions.run_episode(task=TASK, seed=10_000, init_state_index=0, max_steps=min(max_steps, 10))
            setup["warmup_s"] = time.perf_counter() - t
            log(f"stack: warm-up (one 10-step episode per session) {setup['warmup_s']:.1f} s, not counted")
            return sessions
        except ZettaError as err:
            try:
                await (sessions or SessionGroup(gw, infos)).close()  # type: ignore[arg-type]
            except ZettaError:
                pass
            if attempt == attempts:
                raise
            log(f"stack: session set-up failed ({err}); closing them and creating them again")
    raise AssertionError("unreachable")


async def run_stack_points(
    address: str, modes: Sequence[str], concurrency: Sequence[int], episodes: int, max_steps: int, repeats: int,
    log: Callable[[str], None],
) -> tuple[list[Point], dict[str, float]]:
    from zetta.client import Gateway

    setup: dict[str, float] = {}
    n = max(concurrency)
    async with Gateway(address) as gw:
        sessions = await create_sessions(gw, n, max_steps, setup, log)
        try:
            points = []
            for mode in modes:
                for c in concurrency:
                    point = Point(mode, c)
                    ids = balanced(sessions.infos, c)
                    for r in range(repeats):
                        run = await run_lanes(sessions, ids, episodes, mode, max_steps)
                        point.runs.append(run)
                        log(f"stack: {mode} c={c} repeat {r + 1}/{repeats}: {len(run.episodes)} episodes in "
                            f"{run.wall_s:.1f} s ({run.episodes_per_min:.1f}/min, "
                            f"{sum(e.success for e in run.episodes)} successes)")
                    points.append(point)
        finally:
            await sessions.close()
    return points, setup


# ---------------------------------------------------------------------------------------------
# report

HEADER = ("mode", "concurrency", "episodes", "success rate", "episodes/min", "vs naive", "p50 latency s",
          "p99 latency s", "env steps/s")


def rows(points: Sequence[Point]) -> list[tuple[str, ...]]:
    naive = next((p.episodes_per_min for p in points if p.mode == "naive"), 0.0)
    out = []
    for p in points:
        out.append((
            p.mode,
            str(p.concurrency),
            str(p.episodes),
            f"{p.successes / p.episodes:.0%} ({p.successes}/{p.episodes})" if p.episodes else "-",
            f"{p.episodes_per_min:.1f}",
            f"{p.episodes_per_min / naive:.2f}x" if naive else "-",
            f"{p.latency(50):.2f}",
            f"{p.latency(99):.2f}",
            f"{p.steps_per_s:.0f}",
        ))
    return out


def text_table(points: Sequence[Point]) -> str:
    return aligned([HEADER, *rows(points)])


def markdown_table(points: Sequence[Point]) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "|".join(["---"] + ["---:"] * (len(HEADER) - 1)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows(points)]
    return "\n".join(lines)


def results_doc(points: Sequence[Point], setup: dict[str, float], args: argparse.Namespace, command: str,
                load: tuple[float, float]) -> dict[str, Any]:
    """The results file: every episode of every point, what ran, the command and the commit."""
    return {**provenance(command, ROOT), "machine": bench_sweep.machine(), "load": list(load), "setup": setup,
            "max_steps": args.max_steps, "episodes_per_point": args.episodes_per_point,
            "naive_episodes": args.naive_episodes, "repeats": args.repeats,
            "points": [{"mode": p.mode, "concurrency": p.concurrency,
                        "runs": [{"wall_s": r.wall_s, "episodes": [asdict(e) for e in r.episodes]} for r in p.runs]}
                       for p in points]}


def page(doc: Mapping[str, Any]) -> str:
    """docs/results/bench-rollout.md from its results file."""
    points = [Point(p["mode"], p["concurrency"], [Run([Episode(**e) for e in r["episodes"]], r["wall_s"])
                                                     for r in p["runs"]]) for p in doc["points"]]
    setup, load = doc["setup"], doc["load"]
    sessions = max((p.concurrency for p in points if p.mode != "naive"), default=0)
    repeats = f", median of {doc['repeats']} repeats" if doc["repeats"] > 1 else ""
    return page_header("bench-rollout", "Rollout throughput: the stack vs a naive loop, scripted policy", doc) + f"""
Machine: {doc['machine']}; load average {load[0]:.1f} at the start and {load[1]:.1f} at the end of the run.
Task: LIBERO-Goal `{TASK}`, state only; episode i uses init state i % 50 and seed i; step budget
{doc['max_steps']}; {doc['episodes_per_point']} episodes per stack point and {doc['naive_episodes']} for the naive
loop{repeats}. What the rows and columns are: [docs/bench-rollout.md](../bench-rollout.md).

{markdown_table(points)}

Not counted: stack start-up ({setup.get('stack_up_s', 0):.1f} s), creating {sessions} sessions once
({setup.get('create_s', 0):.1f} s) and one 10-step warm-up episode per session ({setup.get('warmup_s', 0):.1f} s).
Counted: the naive loop's per-episode env build (mean {setup.get('naive_build_s', 0):.2f} s of its
{setup.get('naive_episode_s', 0):.2f} s per episode).
"""


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="about 2 minutes: 16 episodes per point, 6 naive episodes, run_episode only")
    p.add_argument("--max-steps", type=int, default=None, help="step budget per episode (default 300, the suite's)")
    p.add_argument("--episodes-per-point", type=int, default=None, help="episodes per stack point (default 32; --quick: 16)")
    p.add_argument("--naive-episodes", type=int, default=None, help="episodes of the naive loop (default 16; --quick: 6)")
    p.add_argument("--concurrency", default="1,4,16", help="comma-separated concurrency levels (default 1,4,16)")
    p.add_argument("--modes", default=None,
                   help="comma-separated stack modes out of run_episode,policy_step (default both; --quick: run_episode)")
    p.add_argument("--repeats", type=int, default=1, help="repeat every point and report medians (default 1)")
    p.add_argument("--write-docs", action="store_true",
                   help="write docs/results/bench-rollout.json (every episode) and its page bench-rollout.md")
    add_progress_option(p)
    args = p.parse_args(argv)
    quick = args.quick
    if args.max_steps is None:
        args.max_steps = 300
    if args.episodes_per_point is None:
        args.episodes_per_point = 16 if quick else 32
    if args.naive_episodes is None:
        args.naive_episodes = 6 if quick else 16
    if args.modes is None:
        args.modes = "run_episode" if quick else "run_episode,policy_step"
    args.concurrency = [int(c) for c in str(args.concurrency).split(",") if c.strip()]
    args.modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    for m in args.modes:
        if m not in ("run_episode", "policy_step"):
            p.error(f"unknown mode {m!r}: choose run_episode and/or policy_step")
    if max(args.concurrency) > ENV_WORKERS * SLOTS_PER_WORKER or min(args.concurrency) < 1:
        p.error(f"concurrency must be within 1..{ENV_WORKERS * SLOTS_PER_WORKER}")
    if args.episodes_per_point < max(args.concurrency):
        p.error("--episodes-per-point must be at least the largest concurrency")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    command = " ".join(["python bench/bench_rollout.py", *(sys.argv[1:] if argv is None else argv)])
    from services.ops.local_stack import LocalStack

    t_all = time.perf_counter()
    load0 = os.getloadavg()[0]

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t_all:6.1f} s] {msg}", flush=True)

    log(f"{bench_sweep.machine()}; load average {load0:.2f}")
    log(f"task {SUITE}/{TASK}, budget {args.max_steps} steps, {args.episodes_per_point} episodes per stack point, "
        f"{args.naive_episodes} naive episodes, concurrency {args.concurrency}, modes {args.modes}, "
        f"repeats {args.repeats}")
    naive = Point("naive", 1)
    half = (args.naive_episodes + 1) // 2
    naive_warmup(args.max_steps, log)
    run_naive_half(naive, range(half), args.max_steps, args.repeats, "(before the stack)", log)

    workdir = Path(tempfile.mkdtemp(prefix="zetta-bench-"))
    stack = LocalStack(env_workers=ENV_WORKERS, slots=SLOTS_PER_WORKER, policy_workers=1, families=("libero",),
                       workdir=workdir, extra_env={"ZETTA_LOG_LEVEL": "WARNING"})
    t = time.perf_counter()
    ok = False
    with stack:
        setup = {"stack_up_s": time.perf_counter() - t}
        log(f"stack: redis + gateway + {ENV_WORKERS} env workers x {SLOTS_PER_WORKER} slots + 1 policy worker up in "
            f"{setup['stack_up_s']:.1f} s, not counted")
        stack_points, more = asyncio.run(run_stack_points(
            stack.gateway_address, args.modes, args.concurrency, args.episodes_per_point, args.max_steps,
            args.repeats, log))
        setup.update(more)
        ok = True
    if ok:
        shutil.rmtree(workdir, ignore_errors=True)
    run_naive_half(naive, range(half, args.naive_episodes), args.max_steps, args.repeats, "(after the stack)", log)
    for run in naive.runs:
        run.episodes.sort(key=lambda e: e.index)
    points = [naive, *stack_points]
    load1 = os.getloadavg()[0]
    naive_eps = [e for r in points[0].runs for e in r.episodes]
    setup["naive_build_s"] = statistics.mean(e.build_s for e in naive_eps)
    setup["naive_episode_s"] = statistics.mean(e.latency_s for e in naive_eps)

    print()
    print(f"LIBERO-Goal {TASK}, budget {args.max_steps} steps, scripted policy; "
          f"{'median of %d repeats; ' % args.repeats if args.repeats > 1 else ''}load average {load0:.1f} -> {load1:.1f}")
    print(text_table(points))
    print(f"not counted: stack start-up {setup['stack_up_s']:.1f} s, creating {max(args.concurrency)} sessions "
          f"{setup['create_s']:.1f} s, warm-up {setup['warmup_s']:.1f} s; counted: naive env build "
          f"{setup['naive_build_s']:.2f} s of its {setup['naive_episode_s']:.2f} s per episode; "
          f"total run {time.perf_counter() - t_all:.0f} s")
    if args.write_docs:
        doc = json.loads(json.dumps(results_doc(points, setup, args, command, (load0, load1)), default=float))
        for path in write_results("bench-rollout", doc, page(doc)):
            print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
