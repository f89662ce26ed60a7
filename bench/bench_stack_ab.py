"""Two stack configurations side by side: which settings step faster, measured so drift cancels.

Settings of the services (``ZETTA_*`` variables, or any environment variable such as
``MALLOC_ARENA_MAX``) change the stack's speed by a few percent, while this kind of shared machine
drifts by a quarter between measurements minutes apart. Both stacks (A and B) are started and
their sessions created and warmed first; then each round runs the same number of episodes on A
and on B one right after the other (the order alternating), and the report gives the medians of
the per-round ratios B/A, so that load which drifts weighs on both alike. The stacks share the
machine but only one steps at a time.

    python bench/bench_stack_ab.py --a ZETTA_STEP_CONCURRENCY=0 --b ZETTA_STEP_CONCURRENCY=1
    python bench/bench_stack_ab.py --b MALLOC_ARENA_MAX=1 --rounds 8 --concurrency 16
    python bench/bench_stack_ab.py --a-rev HEAD~1     # the services of the previous commit against this tree's

``--a-rev``/``--b-rev`` run a stack's services from another git revision (exported with ``git
archive``, its stubs built from its own protos; the working tree is not touched), so a code change
is measured the same way as a setting.

Episodes are those of ``zetta bench rollout`` (LIBERO-Goal, state only, fixed step budget, the
shipped policy); CPU is every process of the stack and the client, from /proc.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python"), str(ROOT / "bench")]

import trees  # noqa: E402
from bench import bench_sweep as bs  # noqa: E402
from zetta.client import Gateway  # noqa: E402
from services.ops.local_stack import LocalStack  # noqa: E402


@dataclass
class Window:
    """One measured window of one stack."""

    steps_per_s: float
    cpu_ms_per_step: float
    own_cpu_pct: float


def settings(pairs: list[str]) -> dict[str, str]:
    """NAME=VALUE arguments as an environment."""
    out = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise SystemExit(f"bench_stack_ab: {pair!r} is not NAME=VALUE")
        out[name] = value
    return out


def stack_envs(args: argparse.Namespace, scratch: Path) -> dict[str, dict[str, str]]:
    """Each stack's extra environment: its settings, and the import path of its revision if it has one."""
    envs = {"A": settings(args.a), "B": settings(args.b)}
    for name, rev in (("A", args.a_rev), ("B", args.b_rev)):
        if rev:
            envs[name].update(trees.import_env(trees.export(rev, scratch / name)))
    return envs


async def measure(args: argparse.Namespace, envs: dict[str, dict[str, str]]) -> dict[str, list[Window]]:
    """Start both stacks, then alternate windows of 4 episodes a lane on each (the sweep's
    ``MIN_EPISODES_PER_LANE``)."""
    slots = -(-args.concurrency // args.env_workers)
    stacks: dict[str, LocalStack] = {}
    windows: dict[str, list[Window]] = {"A": [], "B": []}
    try:
        for name, extra in envs.items():
            stacks[name] = LocalStack(env_workers=args.env_workers, slots=slots, policy_workers=1,
                                      families=("libero",), models=(args.model,),
                                      workdir=Path(tempfile.mkdtemp(prefix=f"zetta-ab-{name}-")),
                                      extra_env={"ZETTA_LOG_LEVEL": "WARNING", **extra},
                                      heartbeat_timeout_ms=30_000)
            stacks[name].start()
        async with Gateway(stacks["A"].gateway_address) as gw_a, Gateway(stacks["B"].gateway_address) as gw_b:
            gateways = {"A": gw_a, "B": gw_b}
            config = bs.env_config(args.task, args.max_steps)
            sessions = {n: await bs.create_sessions(g, args.concurrency, config, 2 * args.env_workers, print)
                        for n, g in gateways.items()}
            first = 0
            episodes = bs.MIN_EPISODES_PER_LANE * args.concurrency
            for r in range(args.rounds):
                for name in ("A", "B") if r % 2 == 0 else ("B", "A"):
                    stack = stacks[name]
                    meter = bs.ResourceMeter(lambda stack=stack: bs.stack_pids(stack))
                    meter.start()
                    done, wall = await bs.run_lanes(gateways[name], bs.balanced(sessions[name].infos, args.concurrency),
                                                    episodes, args.task, args.max_steps, first)
                    usage = meter.stop()
                    steps = sum(e.steps for e in done)
                    w = Window(steps / wall, 1000.0 * usage.cpu_s / steps, usage.own_cpu_pct)
                    windows[name].append(w)
                    print(f"round {r + 1} {name}: {w.steps_per_s:.0f} steps/s, {w.cpu_ms_per_step:.2f} CPU ms per step, "
                          f"CPU own {w.own_cpu_pct:.0f}%", flush=True)
                first += episodes  # both stacks run the same episodes in a round
            for s in sessions.values():
                await s.close()
    finally:
        for stack in stacks.values():
            stack.stop()
    return windows


def report(args: argparse.Namespace, windows: dict[str, list[Window]]) -> str:
    """Medians of each stack and of the per-round ratios."""
    a, b = windows["A"], windows["B"]
    lines = [f"bench_stack_ab: concurrency {args.concurrency}, {args.env_workers} env workers, {len(a)} rounds "
             f"of {bs.MIN_EPISODES_PER_LANE * args.concurrency} episodes; load average {os.getloadavg()[0]:.1f} at the end"]
    for name, ws, env, rev in (("A", a, args.a, args.a_rev), ("B", b, args.b, args.b_rev)):
        label = " ".join([*([f"revision {rev}"] if rev else []), *env]) or "defaults"
        lines.append(f"  {name} ({label}): median {statistics.median(w.steps_per_s for w in ws):.0f} "
                     f"steps/s, {statistics.median(w.cpu_ms_per_step for w in ws):.2f} CPU ms per step")
    steps = statistics.median(y.steps_per_s / x.steps_per_s for x, y in zip(a, b))
    cpu = statistics.median(y.cpu_ms_per_step / x.cpu_ms_per_step for x, y in zip(a, b))
    wins = sum(y.cpu_ms_per_step < x.cpu_ms_per_step for x, y in zip(a, b))
    lines.append(f"  B/A, median of the rounds' ratios: steps/s x{steps:.3f}, CPU per step x{cpu:.3f} "
                 f"(B cheaper in {wins} of {len(a)} rounds)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--a", nargs="*", default=[], metavar="NAME=VALUE", help="settings of stack A (default: none)")
    p.add_argument("--b", nargs="*", default=[], metavar="NAME=VALUE", help="settings of stack B")
    p.add_argument("--a-rev", default="", metavar="REV", help="run stack A's services from this git revision")
    p.add_argument("--b-rev", default="", metavar="REV", help="run stack B's services from this git revision")
    p.add_argument("--rounds", type=int, default=6, help="windows per stack (default 6)")
    p.add_argument("--concurrency", type=int, default=32, help="concurrent episodes per stack (default 32)")
    p.add_argument("--env-workers", type=int, default=2, help="env workers per stack (default 2)")
    p.add_argument("--max-steps", type=int, default=120, help="fixed step budget of every episode (default 120)")
    p.add_argument("--model", default=bs.DEFAULT_MODEL, help=f"served policy (default {bs.DEFAULT_MODEL})")
    p.add_argument("--task", default=bs.DEFAULT_TASK, help=f"LIBERO-Goal task (default {bs.DEFAULT_TASK})")
    args = p.parse_args(argv)
    if args.rounds < 1 or args.concurrency < 1 or args.env_workers < 1:
        p.error("--rounds, --concurrency and --env-workers must be at least 1")
    os.environ.setdefault("ZETTA_TORCH_THREADS", "1")
    with tempfile.TemporaryDirectory(prefix="zetta-ab-trees-") as scratch:
        envs = stack_envs(args, Path(scratch))
        print(report(args, asyncio.run(measure(args, envs))))


if __name__ == "__main__":
    main()
