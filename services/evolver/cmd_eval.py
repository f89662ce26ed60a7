"""`zetta eval`: zero-shot transfer of an evolved harness to tasks, bare policy vs harness, same report.

  zetta eval --harness evolved-6@2 --suite libero_goal_swap --tasks 3,4 --seeds 20

The bare policy, the harness and the harness around the do-nothing policy (the control) run on
the same test seeds of each task (the store keeps them apart from any dev or gate seed), with the
same policy and budget; results are filed in --store and reported with Wilson intervals.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from services.common.progress import PhaseBars
from services.evolver.cmd_common import add_run_args, publish_dir, run_config, tasks_of
from services.evolver.evolve import evaluate_transfer
from services.evolver.report import write_report
from services.evolver.stack import endpoints, stop_on_sigterm
from services.evolver.store import RolloutStore


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `zetta eval`."""
    p = argparse.ArgumentParser(prog="zetta eval", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    add_run_args(p)
    p.add_argument("--harness", required=True, help="harness reference NAME@VERSION in the critic registry")
    p.add_argument("--harness-dir", type=Path, default=None,
                   help="publish this package directory to the (local) registry first and evaluate it")
    p.add_argument("--seeds", type=int, default=20, help="held-out seeds per task")
    a = p.parse_args(list(sys.argv[1:] if argv is None else argv))
    store_dir = a.store or Path("runs") / f"eval-{a.suite}"
    store = RolloutStore(store_dir)
    bars = PhaseBars()
    t0 = time.time()
    try:
        with stop_on_sigterm():
            rows, harness = _run(a, store, bars)
    except KeyboardInterrupt:
        bars.close()
        print(f"\nstopped; finished rollouts are in {store_dir}: run the same command to resume", file=sys.stderr)
        return 130
    bars.close()
    for r in rows:
        print(f"{r['suite']} task {r['task']}: bare {r['bare'][0]}/{r['bare'][1]}, {harness} {r['final'][0]}/{r['final'][1]}")
    path = write_report(store, a.report or store_dir / "report", f"Transfer of {harness} to {a.suite} tasks {a.tasks}",
                        time.time() - t0)
    print(f"report: {path}")
    return 0


def _run(a: argparse.Namespace, store: RolloutStore, bars: PhaseBars) -> tuple[list[dict[str, Any]], str]:
    """Both arms on every task, on the stack named by the arguments (or a local one)."""
    store_dir = store.root
    with endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency, store_dir / "stack", a.video) as ep:
        harness = a.harness
        if a.harness_dir is not None:
            harness = publish_dir(ep.registry, a.harness_dir)
        rows = evaluate_transfer(store, run_config(a, ep.gateway), a.suite, list(tasks_of(a.tasks)), harness, a.seeds,
                                 bars)
    return rows, harness


if __name__ == "__main__":
    sys.exit(main())
