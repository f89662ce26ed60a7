"""`zetta evolve experiment`: the full experiment in one command: evolve every task of several suites,
then zero-shot transfer of every admitted harness to a suite it never saw, with one summary.

  zetta evolve experiment --suites libero_goal_task,libero_goal_swap --tasks 0-9 --dev-seeds 20 \\
      --heldout-seeds 20 --rounds 1 --transfer-suite libero_goal --transfer-seeds 10 --out runs/experiment

One local stack (or --gateway/--registry) serves everything. Each suite has its own store
(<out>/<suite>, the usual `zetta evolve` store and report); the transfer arm has one too
(<out>/transfer-<suite>): the harness admitted for task t of an evolved suite runs, beside the bare
policy, on held-out seeds of task t of the transfer suite. <out>/summary.md holds held-out success
before and after evolution per task with Wilson intervals, the averages, the rollouts and the wall
time, and the transfer table. Stop it and run the same command again: finished rollouts, rounds
and admitted versions are kept (see `zetta evolve`).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from services.common.policies import DEFAULT_POLICY
from services.evolver.cmd_common import llm_from_env, publish_dir
from services.evolver.evolve import EvolveConfig, Evolution, evaluate_transfer
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.rollout import RunConfig
from services.evolver.stack import Bars, endpoints, stop_on_sigterm
from services.evolver.store import RolloutStore
from zetta_wire.stats import wilson


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


def _rate(s: int, n: int) -> str:
    lo, hi = wilson(s, n)
    return f"{s}/{n} = {s / n:.0%} [{lo:.0%}, {hi:.0%}]" if n else "-"


def _walls(store: RolloutStore) -> float:
    return sum(float(e["wall_s"]) for e in store.events("wall"))


def summary(out: Path, suites: Sequence[str], transfer_suite: str) -> str:
    """The experiment's Markdown summary, built from what the stores recorded."""
    lines = ["# Evolution experiment", "", "Held-out success of the frozen policy alone (bare) and with the harness "
             "evolved for the task (final), on the same held-out seeds; Wilson 95 % intervals. Rollouts: every "
             "valid rollout the task's evolution ran (profiles, validations, regressions, held-out arms).", ""]
    total = {"bare": [0, 0], "final": [0, 0]}
    rates: dict[str, list[float]] = {"bare": [], "final": []}
    for suite in suites:
        store = RolloutStore(out / suite)
        finals = {f["task"]: f for f in store.events("final") if f["suite"] == suite}
        lines += [f"## {suite}", "", "| task | bare | final | delta | harness | rollouts |", "|---|---|---|---|---|---|"]
        suite_total = {"bare": [0, 0], "final": [0, 0]}
        for task, f in sorted(finals.items(), key=lambda kv: (len(kv[0]), kv[0])):
            b, h = f["bare"], f["final"]
            delta = (h[0] / h[1] if h[1] else 0) - (b[0] / b[1] if b[1] else 0)
            lines.append(f"| {task} | {_rate(*b)} | {_rate(*h)} | {delta:+.0%} | {f['harness']} | "
                         f"{len(store.query(task=task))} |")
            for arm, x in (("bare", b), ("final", h)):
                suite_total[arm][0] += x[0]
                suite_total[arm][1] += x[1]
                total[arm][0] += x[0]
                total[arm][1] += x[1]
                rates[arm].append(x[0] / x[1] if x[1] else 0.0)
        lines += [f"| **all** | {_rate(*suite_total['bare'])} | {_rate(*suite_total['final'])} | | | "
                  f"{len(store.query())} |", "",
                  f"Wall time: {_walls(store):.0f} s; invalid attempts rerun: {len(store.invalid_attempts())}; "
                  f"report: {suite}/report/report.md", ""]
    if rates["bare"]:
        lines += ["## Average over every task", "",
                  f"bare {sum(rates['bare']) / len(rates['bare']):.1%} -> final "
                  f"{sum(rates['final']) / len(rates['final']):.1%} (mean of per-task rates over "
                  f"{len(rates['bare'])} tasks); pooled: bare {_rate(*total['bare'])}, final {_rate(*total['final'])}.", ""]
    tstore_dir = out / f"transfer-{transfer_suite}"
    if (tstore_dir / "index.sqlite").exists():
        tstore = RolloutStore(tstore_dir)
        lines += [f"## Zero-shot transfer to {transfer_suite}", "",
                  "Each admitted harness on the same task index of a suite it was never evolved on; bare and "
                  "harness arms on the same held-out seeds.", "",
                  "| task | harness (evolved on) | bare | harness | delta |", "|---|---|---|---|---|"]
        for f in tstore.events("transfer_source"):
            b, h = f["bare"], f["final"]
            delta = (h[0] / h[1] if h[1] else 0) - (b[0] / b[1] if b[1] else 0)
            lines.append(f"| {f['task']} | {f['harness']} ({f['source']}) | {_rate(*b)} | {_rate(*h)} | "
                         f"{delta:+.0%} |")
        lines += ["", f"Transfer rollouts: {len(tstore.query())}, wall time {_walls(tstore):.0f} s.", ""]
    return "\n".join(lines) + "\n"


def _transfer(out: Path, suites: Sequence[str], transfer_suite: str, seeds: int, run: RunConfig, registry: str,
              bars: Bars) -> None:
    """Every suite's last admitted harness per task, on the transfer suite's task of the same index."""
    tstore = RolloutStore(out / f"transfer-{transfer_suite}")
    t0 = time.time()
    for suite in suites:
        store = RolloutStore(out / suite)
        latest = {a["task"]: a["ref"] for a in store.events("admitted") if a["suite"] == suite}
        for task, ref in sorted(latest.items()):
            published = publish_dir(registry, store.root / "harness" / ref)
            for rec in evaluate_transfer(tstore, run, transfer_suite, [task], published, seeds, bars):
                tstore.record("transfer_source", {**rec, "source": f"{suite}/{task}"},
                              ident=f"{transfer_suite}/{task}/{published}")
    tstore.record("wall", {"command": "experiment transfer", "wall_s": time.time() - t0})


def main(argv: Sequence[str]) -> int:
    """Entry point of `zetta evolve experiment`."""
    p = argparse.ArgumentParser(prog="zetta evolve experiment", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--suites", default="libero_goal_task,libero_goal_swap", help="suites to evolve on, comma-separated")
    p.add_argument("--tasks", default="0-9", help="task indices per suite, e.g. 0-9 or 1,6,9")
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--dev-seeds", type=int, default=20)
    p.add_argument("--heldout-seeds", type=int, default=20)
    p.add_argument("--transfer-suite", default="libero_goal", help="suite for zero-shot transfer ('' for none)")
    p.add_argument("--transfer-seeds", type=int, default=10, help="held-out seeds per transfer task")
    p.add_argument("--out", type=Path, default=Path("runs") / "experiment")
    p.add_argument("--gateway", default=None, help="use a running stack's gateway (with --registry)")
    p.add_argument("--registry", default=None, help="critic service address of that stack")
    p.add_argument("--model", default=DEFAULT_POLICY)
    p.add_argument("--execute-steps", type=int, default=2)
    p.add_argument("--max-steps", type=int, default=0)
    p.add_argument("--concurrency", type=int, default=2)
    p.add_argument("--env-workers", type=int, default=1)
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(list(argv))
    suites = [s.strip() for s in a.suites.split(",") if s.strip()]
    tasks = task_list(a.tasks)
    bars = Bars(a.no_progress)
    try:
        with stop_on_sigterm(), endpoints(a.gateway, a.registry, a.model, a.env_workers, a.concurrency,
                                          a.out / "stack", False) as ep:
            run = RunConfig(gateway=ep.gateway, model=a.model, execute_steps=a.execute_steps, max_steps=a.max_steps,
                            concurrency=a.concurrency)
            registry = RegistryClient(ep.registry)
            try:
                for suite in suites:
                    store = RolloutStore(a.out / suite)
                    t0 = time.time()
                    # One registry serves every suite: the suite in the name keeps each task's versions apart.
                    cfg = EvolveConfig(suite=suite, tasks=tasks, rounds=a.rounds, dev_seeds=a.dev_seeds,
                                       heldout_seeds=a.heldout_seeds, name=f"evolved-{suite}", llm=llm_from_env())
                    Evolution(cfg, store, run, registry, bars).run()
                    store.record("wall", {"command": "experiment", "wall_s": time.time() - t0})
                    write_report(store, a.out / suite / "report", f"Evolution on {suite} tasks {a.tasks}",
                                 _walls(store))
            finally:
                registry.close()
            if a.transfer_suite:
                _transfer(a.out, suites, a.transfer_suite, a.transfer_seeds, run, ep.registry, bars)
    except KeyboardInterrupt:
        bars.close()
        print(f"\nstopped; finished rollouts are in {a.out}: run the same command to resume", file=sys.stderr)
        return 130
    bars.close()
    path = a.out / "summary.md"
    path.write_text(summary(a.out, suites, a.transfer_suite))
    print(f"summary: {path}")
    return 0
