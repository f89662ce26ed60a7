"""`zetta evolve`: the three loops on a suite's tasks, resumable, with a Markdown report.

  zetta evolve --suite libero_goal_task --tasks 6,9 --rounds 2 --dev-seeds 20 --heldout-seeds 10 --test-seeds 20
  zetta evolve export --store DIR --out DATASET     (a LeRobot v3.0 dataset of the stored rollouts)
  zetta evolve experiment [--suites ...] [--tasks 0-9] (every task of several suites + transfer, one summary)

Without --gateway a local stack is started (Redis, gateway, critic service, a policy worker
serving --model, env workers). Everything is filed in --store first: stop it (Ctrl-C) and run the
same command again to resume without losing finished rollouts.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from services.common.progress import PhaseBars, add_progress_option
from services.evolver.cluster import ClusterParams
from services.evolver.cmd_common import add_run_args, llm_from_env, run_config, tasks_of
from services.evolver.eod import EODParams
from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.gate import GateParams
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.repair import SearchParams
from services.evolver.stack import endpoints, stop_on_sigterm
from services.evolver.store import RolloutStore, StoreError


def _export(argv: Sequence[str]) -> int:
    from services.evolver.instructions import libero_instructions
    from services.evolver.lerobot_export import export_lerobot

    p = argparse.ArgumentParser(prog="zetta evolve export", description="export stored rollouts as a LeRobot v3.0 dataset")
    p.add_argument("--store", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--task", default=None)
    p.add_argument("--harness", default=None, help="only rollouts of this harness reference ('' for the bare policy)")
    add_progress_option(p)
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
    p.add_argument("--dev-seeds", type=int, default=EvolveConfig.dev_seeds, help="repair seeds per task")
    p.add_argument("--heldout-seeds", type=int, default=EvolveConfig.heldout_seeds,
                   help="gate (admission) seeds per task")
    p.add_argument("--test-seeds", type=int, default=EvolveConfig.test_seeds,
                   help="seeds of the reported number per task (dev + held-out + test <= 50 initial states)")
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
                       heldout_seeds=a.heldout_seeds, test_seeds=a.test_seeds, name=a.name, max_clusters=a.max_clusters,
                       eod=EODParams(epsilon=a.eod_epsilon), cluster=ClusterParams(radius=a.cluster_radius, max_size=a.cluster_max_size),
                       search=SearchParams(max_candidates=a.max_candidates), gate=GateParams(a.regression_min),
                       llm=llm_from_env(), max_depth=a.max_depth)
    store = RolloutStore(store_dir)
    bars = PhaseBars()
    t0 = time.time()
    try:
        with stop_on_sigterm(), endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency,
                                          store_dir / "stack", a.video) as ep:
            registry = RegistryClient(ep.registry)
            try:
                Evolution(cfg, store, run_config(a, ep.gateway), registry, bars).run()
            except StoreError as exc:
                raise SystemExit(f"zetta evolve: {exc}") from None
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
