"""`zetta evolve`: the three loops on a suite's tasks, resumable, with a Markdown report.

  zetta evolve --suite libero_goal_task --tasks 6,9 --rounds 2 --dev-seeds 50 --heldout-seeds 20
  zetta evolve export --store DIR --out DATASET     (a LeRobot v3.0 dataset of the stored rollouts)
  zetta evolve experiment [--suites ...] [--tasks 0-9] (every task of several suites + transfer, one summary)

Without --gateway a local stack is started (Redis, gateway, critic service, a policy worker
serving --model, env workers). Everything is filed in --store first: stop it (Ctrl-C) and run the
same command again to resume without losing finished rollouts.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from services.evolver.cluster import ClusterParams
from services.evolver.eod import EODParams
from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.gate import GateParams
from services.evolver.llm import LLMConfig
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.repair import SearchParams
from services.evolver.rollout import RunConfig
from services.evolver.stack import Bars, endpoints, stop_on_sigterm
from services.evolver.store import RolloutStore


def add_run_args(p: argparse.ArgumentParser) -> None:
    """Options shared by `zetta evolve` and `zetta eval`: the stack, the policy and the store."""
    p.add_argument("--suite", required=True, help="LIBERO suite, e.g. libero_goal_task or libero_goal_swap")
    p.add_argument("--tasks", required=True, help="comma-separated task indices or names, e.g. 6,9")
    p.add_argument("--store", type=Path, default=None, help="rollout store directory (default runs/<command>-<suite>)")
    p.add_argument("--report", type=Path, default=None, help="report directory (default <store>/report)")
    p.add_argument("--gateway", default=None, help="use a running stack's gateway (with --registry)")
    p.add_argument("--registry", default=None, help="critic service address of that stack")
    p.add_argument("--model", default="zetta-vla-state", help="the frozen policy (default zetta-vla-state)")
    p.add_argument("--execute-steps", type=int, default=2, help="actions of each chunk executed per policy call")
    p.add_argument("--max-steps", type=int, default=0, help="episode budget (default: the suite's)")
    p.add_argument("--concurrency", type=int, default=2, help="episodes in flight")
    p.add_argument("--env-workers", type=int, default=2, help="env workers of the local stack")
    p.add_argument("--video", action="store_true", help="record every rollout's video (slower: renders each step)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def tasks_of(text: str) -> tuple[str, ...]:
    """'6,9' -> ('6', '9')."""
    out = tuple(t.strip() for t in text.split(",") if t.strip())
    if not out:
        raise SystemExit("--tasks: give at least one task")
    return out


def run_config(args: argparse.Namespace, gateway: str) -> RunConfig:
    """The rollout settings of the parsed arguments."""
    return RunConfig(gateway=gateway, model=args.model, execute_steps=args.execute_steps, max_steps=args.max_steps,
                     record_video=args.video, concurrency=args.concurrency)


def llm_from_env() -> LLMConfig | None:
    """The optional LLM backend: ZETTA_EVOLVER_LLM_URL (+ _MODEL, _API_KEY); unset means offline only."""
    url = os.environ.get("ZETTA_EVOLVER_LLM_URL", "")
    if not url:
        return None
    model = os.environ.get("ZETTA_EVOLVER_LLM_MODEL", "")
    if not model:
        raise SystemExit("ZETTA_EVOLVER_LLM_URL is set but ZETTA_EVOLVER_LLM_MODEL is not: name the model")
    return LLMConfig(url, model, os.environ.get("ZETTA_EVOLVER_LLM_API_KEY", ""))


def _export(argv: Sequence[str]) -> int:
    from services.evolver.instructions import libero_instructions
    from services.evolver.lerobot_export import export_lerobot

    p = argparse.ArgumentParser(prog="zetta evolve export", description="export stored rollouts as a LeRobot v3.0 dataset")
    p.add_argument("--store", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--task", default=None)
    p.add_argument("--harness", default=None, help="only rollouts of this harness reference ('' for the bare policy)")
    a = p.parse_args(argv)
    store = RolloutStore(a.store)
    rows = store.query(task=a.task, harness=a.harness)
    info = export_lerobot(store, rows, a.out, libero_instructions((r.suite, r.task) for r in rows))
    print(f"exported {info['total_episodes']} episodes, {info['total_frames']} frames to {a.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `zetta evolve`."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "export":
        return _export(argv[1:])
    if argv and argv[0] == "experiment":
        from services.evolver.cmd_experiment import main as experiment

        return experiment(argv[1:])
    p = argparse.ArgumentParser(prog="zetta evolve", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    add_run_args(p)
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--dev-seeds", type=int, default=50)
    p.add_argument("--heldout-seeds", type=int, default=20)
    p.add_argument("--name", default="evolved", help="harness name prefix (versions are <name>-<task>@N)")
    p.add_argument("--max-clusters", type=int, default=EvolveConfig.max_clusters,
                   help="clusters repaired per task and round, largest first")
    p.add_argument("--max-candidates", type=int, default=SearchParams.max_candidates,
                   help="candidate patches validated per cluster and depth")
    p.add_argument("--max-depth", type=int, default=EvolveConfig.max_depth,
                   help="internal versions stacked per cluster until one solves every cluster seed")
    p.add_argument("--regression-min", type=float, default=1.0,
                   help="share of a cluster's seeds a candidate must solve (the paper: 1.0)")
    p.add_argument("--eod-epsilon", type=float, default=EODParams().epsilon)
    p.add_argument("--cluster-radius", type=float, default=ClusterParams().radius)
    p.add_argument("--cluster-max-size", type=int, default=ClusterParams().max_size,
                   help="most failures per cluster (0: no limit)")
    a = p.parse_args(argv)
    store_dir = a.store or Path("runs") / f"evolve-{a.suite}"
    cfg = EvolveConfig(suite=a.suite, tasks=tasks_of(a.tasks), rounds=a.rounds, dev_seeds=a.dev_seeds,
                       heldout_seeds=a.heldout_seeds, name=a.name, max_clusters=a.max_clusters,
                       eod=EODParams(epsilon=a.eod_epsilon), cluster=ClusterParams(radius=a.cluster_radius, max_size=a.cluster_max_size),
                       search=SearchParams(max_candidates=a.max_candidates), gate=GateParams(a.regression_min),
                       llm=llm_from_env(), max_depth=a.max_depth)
    store = RolloutStore(store_dir)
    bars = Bars(a.no_progress)
    t0 = time.time()
    try:
        with stop_on_sigterm(), endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency,
                                          store_dir / "stack", a.video) as ep:
            registry = RegistryClient(ep.registry)
            try:
                Evolution(cfg, store, run_config(a, ep.gateway), registry, bars).run()
            finally:
                registry.close()
    except KeyboardInterrupt:
        bars.close()
        print(f"\nstopped; finished rollouts are in {store_dir}: run the same command to resume", file=sys.stderr)
        return 130
    bars.close()
    wall = time.time() - t0
    store.record("wall", {"command": "evolve", "wall_s": wall})
    path = write_report(store, a.report or store_dir / "report", f"Evolution on {a.suite} tasks {a.tasks}", wall)
    print(f"report: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
