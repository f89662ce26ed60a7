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
from services.evolver.cmd_common import (add_policy_worker_arg, add_run_args, add_search_args, evolve_config,
                                         run_config, tasks_of, trained_instructions,
                                         with_policy_instructions)
from services.evolver.evolve import Evolution
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
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
    add_policy_worker_arg(p)
    add_search_args(p)
    p.add_argument("--name", default="evolved", help="harness name prefix (versions are <name>-<task>@N)")
    a = p.parse_args(argv)
    store_dir = a.store or Path("runs") / f"evolve-{a.suite}"
    cfg = evolve_config(a, a.suite, tasks_of(a.tasks), a.name)
    store = RolloutStore(store_dir)
    bars = PhaseBars()
    t0 = time.time()
    try:
        with stop_on_sigterm(), endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency,
                                          store_dir / "stack", a.video, a.policy_worker) as ep:
            cfg = with_policy_instructions(cfg, trained_instructions(ep.policy, a.model))
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
