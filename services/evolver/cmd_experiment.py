"""`zetta evolve experiment`: the full experiment in one command: evolve every task of several suites,
then zero-shot transfer of every admitted harness to suites it never saw, with one results file.

  zetta evolve experiment --suites libero_goal_task,libero_goal_swap --tasks 0-9 --dev-seeds 20 \\
      --heldout-seeds 10 --test-seeds 20 --rounds 2 --transfer-suites libero_goal_lan,libero_goal_object \\
      --transfer-seeds 20 --out runs/experiment

One local stack (or --gateway/--registry) serves everything, the frozen policy and the do-nothing
control. Each suite has its own store (<out>/<suite>, the usual `zetta evolve` store and report);
each transfer suite has one too (<out>/transfer-<suite>): the harness admitted for task t of an
evolved suite runs, beside the bare policy and the do-nothing control, on test seeds of task t of
every transfer suite (adding a transfer suite to a finished run's command runs only that arm).
<out>/results.json is the machine-readable result (services/evolver/results.py:
commit, policy checkpoint hash, budgets, splits, test arms with Wilson intervals, control, recoveries'
share, the goals and their gaps, the history per task and round, the internal-version curves,
rollouts by purpose, wall time per phase); <out>/summary.md is rendered from it; `python scripts/gen_results.py evolution
--from <out>/results.json` publishes it as docs/results/evolution.{json,md}. Stop it and run the same command again: finished rollouts,
rounds and admitted versions are kept (see `zetta evolve`).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS
from services.common.progress import PhaseBars, add_progress_option
from services.common.provenance import git_source
from services.evolver import results
from services.evolver.cmd_common import (add_policy_worker_arg, add_search_args, evolve_config, publish_dir,
                                         trained_instructions, with_policy_instructions)
from services.evolver.evolve import EvolveConfig, Evolution, evaluate_transfer
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.rollout import RunConfig
from services.evolver.stack import endpoints, stop_on_sigterm
from services.evolver.store import INIT_STATES, RolloutStore, StoreError

ROOT = Path(__file__).resolve().parents[2]


def task_list(text: str) -> tuple[str, ...]:
    """'0-9' or '1,6,9' (ranges and lists mix: '0-2,6') -> task indices as strings."""
    out: list[str] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        if "-" in part and all(x.isdigit() for x in part.split("-", 1)):
            lo, hi = (int(x) for x in part.split("-", 1))
            out += [str(i) for i in range(lo, hi + 1)]
        else:
            out.append(part)
    if not out:
        raise SystemExit("--tasks: give at least one task")
    return tuple(dict.fromkeys(out))


def _walls(store: RolloutStore) -> float:
    return sum(float(e["wall_s"]) for e in store.events("wall"))


def _admitted(out: Path, suites: Sequence[str], registry: str) -> list[tuple[str, str, str]]:
    """(suite, task, reference) of every suite's last admitted harness per task, published to
    ``registry`` once for all transfer suites."""
    rows = []
    for suite in suites:
        store = RolloutStore(out / suite)
        latest = {a["task"]: a["ref"] for a in store.events("admitted") if a["suite"] == suite}
        rows += [(suite, task, publish_dir(registry, store.root / "harness" / ref)) for task, ref in sorted(latest.items())]
        store.close()
    return rows


def _transfer(out: Path, harnesses: Sequence[tuple[str, str, str]], transfer_suite: str, seeds: int, run: RunConfig,
              bars: PhaseBars) -> None:
    """Each admitted harness (:func:`_admitted`) on the transfer suite's task of the same index."""
    tstore = RolloutStore(out / f"transfer-{transfer_suite}")
    t0 = time.time()
    for suite, task, published in harnesses:
        for rec in evaluate_transfer(tstore, run, transfer_suite, [task], published, seeds, bars):
            tstore.record("transfer_source", {**rec, "source": f"{suite}/{task}"},
                          ident=f"{transfer_suite}/{task}/{published}")
    tstore.record("wall", {"command": "experiment transfer", "wall_s": time.time() - t0})
    tstore.close()


def main(argv: Sequence[str]) -> int:
    """Entry point of `zetta evolve experiment`."""
    p = argparse.ArgumentParser(prog="zetta evolve experiment", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--suites", default="libero_goal_task,libero_goal_swap", help="suites to evolve on, comma-separated")
    p.add_argument("--tasks", default="0-9", help="task indices per suite, e.g. 0-9 or 1,6,9")
    add_search_args(p)
    p.set_defaults(rounds=2)
    p.add_argument("--transfer-suites", "--transfer-suite", dest="transfer_suites",
                   default="libero_goal_lan,libero_goal_object",
                   help="suites for zero-shot transfer, comma-separated ('' for none)")
    p.add_argument("--transfer-seeds", type=int, default=20, help="test seeds per transfer task")
    p.add_argument("--out", type=Path, default=Path("runs") / "experiment")
    p.add_argument("--gateway", default=None, help="use a running stack's gateway (with --registry)")
    p.add_argument("--registry", default=None, help="critic service address of that stack")
    add_policy_worker_arg(p)
    p.add_argument("--model", default=DEFAULT_POLICY)
    p.add_argument("--execute-steps", type=int, default=EXECUTE_STEPS,
                   help=f"actions of each chunk executed per policy call (default {EXECUTE_STEPS}, the VLA's own)")
    p.add_argument("--max-steps", type=int, default=0)
    p.add_argument("--concurrency", type=int, default=2)
    p.add_argument("--env-workers", type=int, default=1)
    add_progress_option(p)
    a = p.parse_args(list(argv))
    suites = [s.strip() for s in a.suites.split(",") if s.strip()]
    transfer_suites = [s.strip() for s in a.transfer_suites.split(",") if s.strip()]
    if overlap := sorted(set(suites) & set(transfer_suites)):
        raise SystemExit(f"zetta evolve experiment: {', '.join(overlap)} is both evolved on and a transfer suite; "
                         "transfer measures suites the harness never saw")
    if a.nominal_seeds + max(a.test_seeds, a.transfer_seeds) > INIT_STATES:
        raise SystemExit(f"zetta evolve experiment: --nominal-seeds {a.nominal_seeds} + test or transfer seeds "
                         f"{max(a.test_seeds, a.transfer_seeds)} exceed LIBERO's {INIT_STATES} initial states: a "
                         "reported episode would share its layout with a nominal one; lower one of them")
    tasks = task_list(a.tasks)
    bars = PhaseBars()
    meta = {"command": "zetta evolve experiment " + " ".join(argv), "source": git_source(ROOT),
            "policy": results.policy_provenance(a.model), "control_model": EvolveConfig.control_model,
            "budgets": {"rounds": a.rounds, "dev_seeds": a.dev_seeds, "heldout_seeds": a.heldout_seeds,
                        "test_seeds": a.test_seeds, "transfer_seeds": a.transfer_seeds,
                        "execute_steps": a.execute_steps, "max_steps": a.max_steps,
                        **{k: getattr(a, k) for k in ("max_clusters", "max_candidates", "max_depth", "regression_min", "require_hand_back",
                                                      "eod_epsilon", "cluster_radius", "cluster_max_size",
                                                      "nominal_seeds")}}}
    try:
        with stop_on_sigterm(), endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency,
                                          a.out / "stack", False, a.policy_worker) as ep:
            run = RunConfig(gateway=ep.gateway, model=a.model, execute_steps=a.execute_steps, max_steps=a.max_steps,
                            concurrency=a.concurrency)
            registry = RegistryClient(ep.registry)
            known = trained_instructions(ep.policy, a.model)
            try:
                for suite in suites:
                    store = RolloutStore(a.out / suite)
                    t0 = time.time()
                    # One registry serves every suite: the suite in the name keeps each task's versions apart.
                    cfg = with_policy_instructions(evolve_config(a, suite, tasks, f"evolved-{suite}"), known)
                    try:
                        Evolution(cfg, store, run, registry, bars).run()
                    except StoreError as exc:
                        raise SystemExit(f"zetta evolve experiment: {exc}") from None
                    store.record("wall", {"command": "experiment", "wall_s": time.time() - t0})
                    write_report(store, a.out / suite / "report", f"Evolution on {suite} tasks {a.tasks}",
                                 _walls(store))
            finally:
                registry.close()
            harnesses = _admitted(a.out, suites, ep.registry) if transfer_suites else []
            for transfer_suite in transfer_suites:
                _transfer(a.out, harnesses, transfer_suite, a.transfer_seeds, run, bars)
    except KeyboardInterrupt:
        bars.close()
        print(f"\nstopped; finished rollouts are in {a.out}: run the same command to resume", file=sys.stderr)
        return 130
    bars.close()
    data = results.collect(a.out, suites, transfer_suites, {**meta, "results_path": str(a.out / "results.json")})
    path = results.write(a.out / "results.json", data)
    (a.out / "summary.md").write_text("# Evolution experiment\n\n" + results.render(data))
    print(f"results: {path}\nsummary: {a.out / 'summary.md'}\n"
          f"publish: python scripts/gen_results.py evolution --from {path} (docs/results/evolution.json and .md)")
    return 0
