"""The `zetta` command line.

  zetta up --demo              start Redis + gateway + 2 env workers + 1 policy worker + critic on
                               loopback; run the frozen policy on a LIBERO-PRO task bare, under a
                               shipped harness, and that harness around a do-nothing policy (the
                               control), on the same seeds; print the three rows; stop
  zetta up --demo throughput   the infrastructure demo: 16 concurrent LIBERO-Goal episodes, per-hop latency
  zetta up                     start the same stack and keep it up until Ctrl-C
  zetta demo [mission|throughput] --gateway ADDR
                               run a demo against a stack that is already up
  zetta workers|sessions --gateway ADDR
                               (demo, workers, sessions and harness take --token-file, --tls-ca,
                               --tls-cert, --tls-key, or ZETTA_TOKEN, ZETTA_TLS_CA, ZETTA_TLS_CERT,
                               ZETTA_TLS_KEY, for a stack with auth or TLS on: docs/security.md)
  zetta train [--variant state|image] [--data DEMOS.npz ...]
                               oracle demos (clean + DART) on LIBERO-Goal, train the Zetta VLA, DAgger
  zetta eval-policy [--model zetta-vla-image] [--suites ...] [--seeds N]
                               closed-loop success per task with Wilson 95% intervals
  zetta bench rollout [--concurrency 1,8,16,32,64] [--episodes N] [--max-steps N] [--write-docs]
                               throughput sweep vs a naive loop, the stack without batching and
                               sharing, and this machine's limit (docs/throughput.md)
  zetta harness publish DIR | list | get REF [--out DIR] | diff A B | pin TASK [REF]
                               versioned harness packages in the critic service's registry
  zetta evolve --suite SUITE --tasks 6,9 --rounds N [--dev-seeds 20] [--heldout-seeds 10] [--test-seeds 20]
                               profile, diagnose, repair, gate; resumable; Markdown report
  zetta eval --harness NAME@VERSION --suite SUITE --tasks ...
                               zero-shot transfer of an evolved harness, bare policy vs harness
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS, policy_env_config
from services.common.progress import add_progress_option, progress
from zetta.client import Gateway, SessionGroup, ZettaError
from zetta.credentials import ClientCredentials, add_credential_flags, credentials_from_args
from services.ops.hops import histograms, scrape
from zetta_wire.stats import wilson
from zetta_wire.v1 import types_pb2

DEFAULT_TASK = "put_the_cream_cheese_in_the_bowl"


@dataclass
class DemoResult:
    """What the demo measured."""

    episodes: int
    successes: int
    steps: int
    create_s: float
    rollout_s: float

    @property
    def success_rate(self) -> float:
        """Fraction of successful episodes."""
        return self.successes / self.episodes if self.episodes else 0.0

    @property
    def episodes_per_min(self) -> float:
        """Episodes per minute over the rollout phase (reset to last episode end)."""
        return 60.0 * self.episodes / self.rollout_s if self.rollout_s > 0 else 0.0


async def run_demo(address: str, episodes: int, suite: str, task: str, mode: str, max_steps: int,
                   model: str = DEFAULT_POLICY, execute_steps: int = EXECUTE_STEPS,
                   credentials: ClientCredentials | None = None) -> DemoResult:
    """Create ``episodes`` sessions, run one episode in each concurrently, close them.

    The sessions render what ``model`` reads (the shipped image VLA: its camera, at its size)."""
    async with Gateway(address, **(credentials or ClientCredentials()).gateway_kwargs()) as gw:
        t0 = time.perf_counter()
        sessions = await gw.create_sessions(
            env_family="libero", n=episodes, env_config={"suite": suite, "task": task, **policy_env_config(model)}
        )
        create_s = time.perf_counter() - t0
        try:
            t1 = time.perf_counter()
            inits = [i % 50 for i in range(episodes)]
            if mode == "run_episode":
                summaries = await sessions.run_episode(task=task, seed=list(range(episodes)), init_state_index=inits,
                                                       max_steps=max_steps, model=model, execute_steps=execute_steps)
                successes = sum(s.success for s in summaries)
                steps = sum(s.steps for s in summaries)
            else:
                successes, steps = await _policy_step_loop(sessions, task, inits, max_steps, model, execute_steps)
            rollout_s = time.perf_counter() - t1
        finally:
            await sessions.close()
    return DemoResult(episodes, successes, steps, create_s, rollout_s)


async def _policy_step_loop(sessions: SessionGroup, task: str, inits: Sequence[int], max_steps: int, model: str,
                            execute_steps: int) -> tuple[int, int]:
    """The paper's listing: reset, then policy_step on every running session until all end."""
    resets = await sessions.reset(task=task, seed=list(range(len(sessions))), init_state_index=list(inits))
    budget = max_steps or resets[0].max_steps
    running = list(sessions.ids)
    successes = 0
    steps = 0
    with progress(total=len(running), desc="episodes") as bar:
        while running:
            results = await sessions.subset(running).policy_step(model=model, execute_steps=execute_steps)
            still = []
            for r in results:
                if r.done or r.episode_step >= budget:
                    successes += r.success
                    steps += r.episode_step
                    bar.update()
                else:
                    still.append(r.session_id)
            running = still
    return successes, steps


def print_hops(metrics_urls: Sequence[str]) -> None:
    """Per-hop latency from the services' own histograms."""
    texts = []
    for url in metrics_urls:
        try:
            texts.append(scrape(url))
        except OSError as exc:
            print(f"  (could not scrape {url}: {exc})")
    hops = histograms(texts, "zetta_hop_latency_seconds", ("service", "method"))
    steps = histograms(texts, "zetta_env_step_duration_seconds", ("family",))
    print(f"  {'hop':<40} {'calls':>8} {'mean ms':>9} {'p50 ms':>9} {'p99 ms':>9}")
    for h in hops + [type(s)(f"env_step/{s.name}", s.count, s.mean_ms, s.p50_ms, s.p99_ms) for s in steps]:
        if h.name.endswith(("OpenSlots", "CreateSessions", "ListWorkers", "ListSessions", "CloseSlots", "CloseSessions")):
            continue
        print(f"  {h.name:<40} {h.count:>8} {h.mean_ms:>9.2f} {h.p50_ms:>9.2f} {h.p99_ms:>9.2f}")


def report(res: DemoResult, metrics_urls: Sequence[str]) -> None:
    """Print the demo's summary."""
    lo, hi = wilson(res.successes, res.episodes)
    print()
    print(f"episodes            {res.episodes} concurrent")
    print(f"success rate        {res.success_rate:.1%} ({res.successes}/{res.episodes}, Wilson 95% {lo:.0%}-{hi:.0%})")
    print(f"episodes/min        {res.episodes_per_min:.1f} (rollout {res.rollout_s:.1f} s, {res.steps} env steps, "
          f"{res.steps / max(res.rollout_s, 1e-9):.0f} steps/s)")
    print(f"session creation    {res.create_s:.1f} s (environments built once per worker and config)")
    print("per-hop latency (from /metrics):")
    print_hops(metrics_urls)


def run_chosen_demo(args: argparse.Namespace, address: str, metrics_urls: Sequence[str],
                    credentials: ClientCredentials) -> None:
    """The mission demo (default) or the throughput demo, against the gateway at ``address``."""
    if args.demo == "throughput":
        res = asyncio.run(run_demo(address, args.episodes or 16, args.suite or "libero_goal", args.task or DEFAULT_TASK,
                                   args.mode, args.max_steps, args.model, args.execute_steps, credentials))
        report(res, metrics_urls)
        return
    from services.ops.mission_demo import MissionSpec, run_mission, summary

    spec = MissionSpec(model=args.model, execute_steps=args.execute_steps, seeds=tuple(range(30, 30 + (args.episodes or 10))))
    spec.suite, spec.task = args.suite or spec.suite, args.task or spec.task
    if args.harness:
        spec.harness_dir = Path(args.harness)
    print(f"mission demo: {len(spec.seeds)} seeds x 3 conditions (bare, harness, do-nothing control) ...", flush=True)
    print()
    res = asyncio.run(run_mission(address, spec, credentials=credentials))
    assert res.report_path is not None
    print(summary(json.loads(res.report_path.read_text()), res.report_path))


def cmd_up(args: argparse.Namespace) -> int:
    from services.ops.local_stack import LocalStack

    models: tuple[str, ...] = (args.model,)
    extra_env: dict[str, str] = {}
    if args.demo == "mission":
        models += ("do-nothing",)
        videos = Path("out/demo/videos").resolve()
        videos.mkdir(parents=True, exist_ok=True)
        extra_env["ZETTA_VIDEO_DIR"] = str(videos)
    stack = LocalStack(env_workers=args.env_workers, slots=args.slots, policy_workers=1, models=models,
                       extra_env=extra_env)
    print(f"starting redis, gateway, {args.env_workers} env workers x {args.slots} slots, 1 policy worker ...",
          flush=True)
    t = time.perf_counter()
    with stack:
        print(f"stack up in {time.perf_counter() - t:.1f} s; gateway at {stack.gateway_address}; logs in {stack.workdir}")
        print("security: loopback only, no TLS, no tokens: any local process may use every session "
              "(fine on a workstation; for a shared network see docs/security.md)")
        for svc in stack.services.values():
            print(f"  {svc.name:<10} grpc {svc.address:<18} metrics {svc.metrics_url}")
        if args.demo:
            # The stack's services read ZETTA_TLS_* from this environment; so does the demo client.
            run_chosen_demo(args, stack.gateway_address, [s.metrics_url for s in stack.services.values()],
                            ClientCredentials.from_env())
        else:
            print("Ctrl-C to stop")
            # sigwait needs the signals blocked: an unblocked SIGTERM (kill, docker stop) would
            # take its default action and end this process without stopping the children.
            stop_signals = {signal.SIGINT, signal.SIGTERM}
            signal.pthread_sigmask(signal.SIG_BLOCK, stop_signals)
            try:
                signal.sigwait(stop_signals)
            except KeyboardInterrupt:
                pass
            finally:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, stop_signals)
        print("stopping ...", flush=True)
    print("stopped; no process left behind")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    run_chosen_demo(args, args.gateway, args.metrics or [], credentials_from_args(args))
    return 0


def cmd_workers(args: argparse.Namespace) -> int:
    async def go() -> None:
        async with Gateway(args.gateway, **credentials_from_args(args).gateway_kwargs()) as gw:
            for w in await gw.list_workers():
                state = "alive" if w.alive else "DEAD"
                print(f"{w.worker_id:<24} {w.address:<22} {state:<6} {w.free_slots}/{w.slots} free  {','.join(w.env_families)}")

    asyncio.run(go())
    return 0


def cmd_sessions(args: argparse.Namespace) -> int:
    async def go() -> None:
        async with Gateway(args.gateway, **credentials_from_args(args).gateway_kwargs()) as gw:
            for s in await gw.list_sessions():
                state = types_pb2.SessionState.Name(s.state).removeprefix("SESSION_STATE_")
                print(f"{s.session_id}  {s.env_family:<10} {state:<11} {s.worker_id:<16} {s.reason}")

    asyncio.run(go())
    return 0


def _demo_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", type=int, default=0,
                   help="mission: seeds per condition (default 10); throughput: concurrent episodes (default 16)")
    p.add_argument("--suite", default="", help="LIBERO suite (mission: libero_goal_lan; throughput: libero_goal)")
    p.add_argument("--task", default="", help=f"task name or index (default {DEFAULT_TASK})")
    p.add_argument("--harness", default="", help="mission: harness package directory "
                   "(default examples/harnesses/libero-goal-pick-place)")
    p.add_argument("--mode", choices=("policy_step", "run_episode"), default="policy_step",
                   help="client-driven policy_step loop (default) or whole episodes inside the workers")
    p.add_argument("--max-steps", type=int, default=0, help="step budget per episode (default: the suite's)")
    p.add_argument("--model", default=DEFAULT_POLICY, help=f"the policy (default {DEFAULT_POLICY})")
    p.add_argument("--execute-steps", type=int, default=EXECUTE_STEPS,
                   help=f"actions of each chunk run per policy call (default {EXECUTE_STEPS})")
    add_progress_option(p)


#: Subcommands that hand their arguments to another module's own parser (their --help is theirs).
_FORWARDED = {
    "train": "services.policy_worker.vla.train",
    "eval-policy": "services.policy_worker.vla.evaluate",
    # Versioned harness packages in the registry (docs/harness.md).
    "harness": "services.ops.harness",
    # The throughput sweep against its baselines and the machine's limit (docs/throughput.md).
    "bench": "bench.bench_sweep",
    # The evolution loops and zero-shot transfer of evolved harnesses (docs/evolution.md).
    "evolve": "services.evolver.cmd_evolve",
    "eval": "services.evolver.cmd_eval",
}


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `zetta` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in _FORWARDED:
        import importlib

        return int(importlib.import_module(_FORWARDED[argv[0]]).main(argv[1:]))
    parser = argparse.ArgumentParser(
        prog="zetta",
        description="Zetta rollout infrastructure",
        epilog="also: " + ", ".join(f"zetta {name}" for name in _FORWARDED) + " (each has its own --help)",
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    up = sub.add_parser("up", help="run the whole stack on this machine")
    up.add_argument("--demo", nargs="?", const="mission", choices=("mission", "throughput"),
                    help="run a demo, print its summary and stop (default: mission)")
    up.add_argument("--env-workers", type=int, default=2)
    up.add_argument("--slots", type=int, default=8, help="slots per env worker")
    _demo_args(up)
    up.set_defaults(func=cmd_up)
    demo = sub.add_parser("demo", help="run a demo against a running gateway (it must serve do-nothing too)")
    demo.add_argument("demo", nargs="?", default="mission", choices=("mission", "throughput"))
    demo.add_argument("--gateway", default="127.0.0.1:50051")
    demo.add_argument("--metrics", nargs="*", help="/metrics URLs to read hop latency from")
    _demo_args(demo)
    add_credential_flags(demo)
    demo.set_defaults(func=cmd_demo)
    for name, fn in (("workers", cmd_workers), ("sessions", cmd_sessions)):
        p = sub.add_parser(name, help=f"list {name}")
        p.add_argument("--gateway", default="127.0.0.1:50051")
        add_credential_flags(p)
        p.set_defaults(func=fn)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (ZettaError, OSError, ValueError) as exc:  # a refused call, an unreadable certificate
        print(f"zetta {args.cmd}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
