"""The machine-readable results of `zetta evolve experiment`, and the page rendered from them.

`results.json` holds everything a reader needs to trust a number and rerun it: the command, the
commit (and whether the tree was dirty), the policy and the hash of its checkpoint, the do-nothing
control's model, the budgets, every task's splits (dev, gate, test seeds with their initial states
and the recorded gate -> dev moves), and per task the test arms (bare policy, evolved harness, the
harness around the do-nothing policy) with Wilson 95 % intervals, the recoveries' share of actions
over successful episodes and the share of successes with the policy in control at the success
step; the means, the transfer rows, the issue's goals with their gaps, the evolution history per
task and round, the internal-version curves of every cluster, the rollouts by purpose and the wall
time per phase. Published as docs/results/evolution.json (where an optional free-text ``limits``
says what limits a missed goal), it renders docs/results/evolution.md (:func:`page`;
``python scripts/gen_results.py evolution --from runs/experiment/results.json``), never typed.

Schema 2 added the goals, the initial states, the history, the curves, the rollouts by purpose and
the wall time per phase; a schema 1 file still renders (its goals are computed from its tables).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from services.common.provenance import page_header, weights_sha256
from services.evolver import history
from services.evolver.store import INIT_STATES, SPLITS, RolloutStore

SCHEMA = 2
ARMS = ("bare", "final", "control")
#: The issue's goals: harness mean test success per variant, the do-nothing control of every admitted
#: harness, the recoveries' share of actions over successful test episodes, zero-shot transfer gain.
MIN_SUCCESS, MAX_CONTROL, MAX_RECOVERY_SHARE, MIN_TRANSFER_GAIN = 0.90, 0.05, 0.30, 0.20
#: The paper's LIBERO-PRO means (frozen pi0.5 -> with its harness) per variant.
PAPER = {"libero_goal_task": ("Goal-T", 0.310, 0.925), "libero_goal_swap": ("Goal-S", 0.380, 0.890)}
PAPER_TRANSFER = "paper: +16 to +20 points"
_SPARK = "▁▂▃▄▅▆▇█"


def policy_provenance(model: str) -> dict[str, Any]:
    """The served policy: its name, checkpoint directory and hash (none for scripted models)."""
    from services.common.policies import checkpoint_dir

    path = checkpoint_dir(model)
    return {"model": model, "checkpoint": str(path or ""), "checkpoint_sha256": weights_sha256(path)}


def _mean(rows: Sequence[Mapping[str, Any]], arm: str, key: str = "rate") -> float:
    values = [float(r["arms"][arm][key]) for r in rows if arm in r.get("arms", {})]
    return sum(values) / len(values) if values else 0.0


def _task_row(store: RolloutStore, final: Mapping[str, Any]) -> dict[str, Any]:
    """One task's test arms, its splits with their initial states, rollouts and final wall time."""
    split = final.get("split", {})
    return {"task": final["task"], "harness": final["harness"], "arms": final["arms"], "split": split,
            "init_states": {k: [s % INIT_STATES for s in split.get(k, [])] for k in SPLITS},
            "rollouts": len(store.query(suite=final["suite"], task=final["task"])), "wall_s": final.get("wall_s")}


def _suite(store: RolloutStore, suite: str) -> dict[str, Any]:
    """One evolved suite: its tasks' test arms, means, history, curves and wall time per phase."""
    finals = sorted((f for f in store.events("final") if f["suite"] == suite and "arms" in f),
                    key=lambda f: history.task_order(f["task"]))
    tasks = [_task_row(store, f) for f in finals]
    return {"tasks": tasks, "mean": {arm: _mean(tasks, arm) for arm in ARMS}, "rollouts": len(store.query()),
            "history": history.round_rows(store, suite), "curves": history.curves(store, suite),
            "phases_s": history.phase_walls(store, suite),
            "nominal": next((e for e in store.events("nominal") if e.get("for_suite") == suite), None)}


def _walls(store: RolloutStore) -> float:
    return sum(float(e["wall_s"]) for e in store.events("wall"))


def collect(out: Path, suites: Sequence[str], transfer_suites: Sequence[str], meta: Mapping[str, Any]) -> dict[str, Any]:
    """The results of an experiment directory, from what its stores recorded (the transfer rows of
    every transfer suite in one list; their wall times summed)."""
    data: dict[str, Any] = {"schema": SCHEMA, **meta, "suites": {}, "transfer": [], "wall_s": {},
                            "rollouts_by_purpose": {}}
    for suite in suites:
        store = RolloutStore(out / suite)
        data["suites"][suite] = _suite(store, suite)
        data["wall_s"][suite] = _walls(store)
        data["rollouts_by_purpose"][suite] = history.rollout_counts(store)
        store.close()
    for transfer_suite in transfer_suites:
        tdir = out / f"transfer-{transfer_suite}"
        if not (tdir / "index.sqlite").exists():
            continue
        tstore = RolloutStore(tdir)
        data["transfer"] += [{"suite": f["suite"], "task": f["task"], "harness": f["harness"], "source": f["source"],
                              "arms": f["arms"]} for f in tstore.events("transfer_source") if "arms" in f]
        data["wall_s"]["transfer"] = data["wall_s"].get("transfer", 0.0) + _walls(tstore)
        data["rollouts_by_purpose"][f"transfer-{transfer_suite}"] = history.rollout_counts(tstore)
        tstore.close()
    data["goals"] = goals(data)
    return data


def write(path: Path, data: Mapping[str, Any]) -> Path:
    """Write the results file (sorted keys: a rerun that reproduces gives the same bytes but times)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    return path


# ---- goals ------------------------------------------------------------------------------------------


def _goal(goal: str, target: float, at_least: bool, value: float | None, detail: str, reference: str = "",
          unit: str = "%") -> dict[str, Any]:
    """A goal with its measured value and the gap (positive: met with that margin; negative: missed)."""
    gap = None if value is None else (value - target if at_least else target - value)
    return {"goal": goal, "target": target, "at_least": at_least, "value": value, "gap": gap,
            "met": None if gap is None else gap >= -1e-9, "detail": detail, "reference": reference, "unit": unit}


def _success_goal(suite: str, body: Mapping[str, Any]) -> dict[str, Any]:
    """Harness mean test success of one variant >= 90 %."""
    tasks = body.get("tasks", [])
    name, bare, harness = PAPER.get(suite, ("", 0.0, 0.0))
    evolved = sum(t["harness"] != "bare" for t in tasks)
    detail = (f"{evolved} of {len(tasks)} tasks with an admitted harness; bare mean {body['mean']['bare']:.1%}"
              if tasks else "no task measured")
    reference = f"paper ({name}, frozen pi0.5): {bare:.1%} -> {harness:.1%}" if name else ""
    return _goal(f"harness mean test success, {suite}" + (f" ({name})" if name else ""), MIN_SUCCESS, True,
                 body["mean"]["final"] if tasks else None, detail, reference)


def _admitted(data: Mapping[str, Any]) -> list[tuple[str, Mapping[str, Any]]]:
    """(label, arms) of every row run with an admitted harness: evolved tasks and transfer rows."""
    rows = [(f"{suite}/{t['task']}", t["arms"]) for suite, body in data.get("suites", {}).items()
            for t in body.get("tasks", []) if t["harness"] != "bare"]
    return rows + [(f"{t['suite']}/{t['task']} (transfer)", t["arms"]) for t in data.get("transfer", [])]


def _worst(rows: Sequence[tuple[str, Mapping[str, Any]]], arm: str, key: str) -> tuple[float, str] | None:
    """The largest ``key`` of ``arm`` over the rows, with the row's label."""
    return max(((float(a[arm][key]), label) for label, a in rows), default=None)


def _control_goal(data: Mapping[str, Any]) -> dict[str, Any]:
    """The do-nothing control of every admitted harness <= 5 % on the test seeds."""
    worst = _worst(_admitted(data), "control", "rate")
    detail = f"highest: {worst[1]}" if worst else "no harness was admitted"
    return _goal("do-nothing control of every admitted harness", MAX_CONTROL, False, worst[0] if worst else None,
                 detail)


def _recovery_goal(data: Mapping[str, Any]) -> dict[str, Any]:
    """The recoveries' share of actions over successful test episodes <= 30 % on every task with an
    admitted harness (a bare row has no recoveries: it says nothing about the goal)."""
    evolved = [(s, t) for s, body in data.get("suites", {}).items() for t in body.get("tasks", [])
               if t["harness"] != "bare"]
    rows = [(f"{s}/{t['task']}", t["arms"]) for s, t in evolved if t["arms"]["final"]["successes"]]
    worst = _worst(rows, "final", "recovery_share")
    detail = (f"largest: {worst[1]}" if worst else
              "no successful test episode of an admitted harness" if evolved else "no harness was admitted")
    return _goal("recoveries' share of actions over successful test episodes", MAX_RECOVERY_SHARE, False,
                 worst[0] if worst else None, detail)


def _transfer_goal(data: Mapping[str, Any]) -> dict[str, Any]:
    """Zero-shot transfer: the harness's mean success >= 20 points over the bare policy's."""
    rows = data.get("transfer", [])
    gain = _mean(rows, "final") - _mean(rows, "bare") if rows else None
    detail = (f"transfer tasks: {len(rows)}; bare {_mean(rows, 'bare'):.1%}, harness {_mean(rows, 'final'):.1%}"
              if rows else "no admitted harness was run zero-shot")
    return _goal("zero-shot transfer gain over the bare policy", MIN_TRANSFER_GAIN, True, gain, detail,
                 PAPER_TRANSFER, "points")


def goals(data: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The issue's goals, each with the measured value and by how much it is met or missed."""
    return [*(_success_goal(s, b) for s, b in data.get("suites", {}).items()), _control_goal(data),
            _recovery_goal(data), _transfer_goal(data)]


# ---- rendering --------------------------------------------------------------------------------------


def _cell(a: Mapping[str, Any]) -> str:
    lo, hi = a["wilson95"]
    return f"{a['successes']}/{a['episodes']} = {a['rate']:.0%} [{lo:.0%}, {hi:.0%}]" if a["episodes"] else "-"


def _arm_cells(arms: Mapping[str, Any]) -> str:
    """The cells bare | harness | delta | harness + nothing of one row."""
    b, f, c = (arms[k] for k in ARMS)
    return f"{_cell(b)} | {_cell(f)} | {f['rate'] - b['rate']:+.0%} | {_cell(c)}"


def _amount(value: float, unit: str) -> str:
    """A rate as '31.0%', a difference as '+12.0 points'."""
    return f"{value:.1%}" if unit == "%" else f"{100 * value:+.1f} points"


def _status(g: Mapping[str, Any]) -> str:
    """'met (by 2.0 points)', 'missed by 58.0 points' or 'not measured'."""
    if g["gap"] is None:
        return "not measured"
    points = f"{100 * abs(g['gap']):.1f} points"
    return f"met (margin {points})" if g["met"] else f"**missed by {points}**"


def render_goals(data: Mapping[str, Any]) -> list[str]:
    """The goals table, the paper's reference figures and the publisher's note on what limits them."""
    lines = ["#### Goals and gaps", "",
             "| goal | target | measured | status | from the data | reference |", "|---|---|---|---|---|---|"]
    for g in data.get("goals") or goals(data):
        target = ("≥ " if g["at_least"] else "≤ ") + _amount(g["target"], g["unit"])
        value = "-" if g["value"] is None else _amount(g["value"], g["unit"])
        lines.append(f"| {g['goal']} | {target} | {value} | {_status(g)} | {g['detail']} | {g['reference']} |")
    lines.append("")
    if data.get("limits"):
        lines += [f"**What limits it** (the publisher's note): {data['limits']}", ""]
    return lines


def _suite_tables(data: Mapping[str, Any]) -> list[str]:
    """Per suite, a row per task: the three test arms, the recoveries' share, policy at success."""
    lines: list[str] = []
    for suite, body in data.get("suites", {}).items():
        lines += [f"#### {suite}", "",
                  "| task | bare | harness | delta | harness + nothing | recoveries | policy at success | harness version |",
                  "|---|---|---|---|---|---|---|---|"]
        for t in body["tasks"]:
            f = t["arms"]["final"]
            recoveries = f"{f['recovery_share']:.0%}"
            if f.get("redirected_share"):
                recoveries += f" ({f['redirected_share']:.0%} redirected)"
            lines.append(f"| {t['task']} | {_arm_cells(t['arms'])} | "
                         f"{recoveries} | {f['policy_in_control_at_success']:.0%} | {t['harness']} |")
        m = body["mean"]
        lines += [f"| **mean** | {m['bare']:.1%} | {m['final']:.1%} | {m['final'] - m['bare']:+.1%} | "
                  f"{m['control']:.1%} | | | |", "",
                  f"Rollouts: {body['rollouts']}; wall time {data.get('wall_s', {}).get(suite, 0.0):.0f} s.", ""]
        if nominal := body.get("nominal"):
            lines += [f"False-positive reference: {nominal['successes']} of {nominal['episodes']} bare-policy "
                      f"episodes on {nominal['suite']} (tasks {_ranges([int(t) for t in nominal['tasks']])}, seeds "
                      f"{_ranges(nominal['seeds'])}) succeeded; a critic that fires on one counts a false positive "
                      "as on the task's own successes.", ""]
    return lines


def _transfer_table(data: Mapping[str, Any]) -> list[str]:
    """The zero-shot transfer rows."""
    if not data.get("transfer"):
        return []
    lines = ["#### Zero-shot transfer", "",
             "| suite | task | harness (evolved on) | bare | harness | delta | harness + nothing |",
             "|---|---|---|---|---|---|---|"]
    for t in data["transfer"]:
        lines.append(f"| {t['suite']} | {t['task']} | {t['harness']} ({t['source']}) | {_arm_cells(t['arms'])} |")
    return lines + ["", f"Transfer wall time {data.get('wall_s', {}).get('transfer', 0.0):.0f} s.", ""]


def _ranges(xs: Sequence[int]) -> str:
    """[1, 2, 3, 7] -> '1-3, 7' ('-' when empty)."""
    runs: list[list[int]] = []
    for x in sorted(xs):
        if runs and runs[-1][1] == x - 1:
            runs[-1][1] = x
        else:
            runs.append([x, x])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs) or "-"


def _split_cell(t: Mapping[str, Any], split: str) -> str:
    """Seeds of one split with their initial states (when the file records them)."""
    seeds = _ranges(t["split"].get(split, []))
    states = t.get("init_states", {}).get(split)
    return f"{seeds} (init {_ranges(states)})" if states else seeds


def _test_disjoint(t: Mapping[str, Any]) -> bool:
    """Whether no dev or gate seed shares an initial state (or a seed) with a test seed."""
    split = t.get("init_states") or t["split"]
    return not set(split.get("test", [])) & (set(split.get("dev", [])) | set(split.get("heldout", [])))


def render_splits(data: Mapping[str, Any]) -> list[str]:
    """The budgets, and per task the seeds and initial states of each split and the recorded moves."""
    lines = ["#### Budgets and splits", ""]
    if data.get("budgets"):
        lines += ["Budgets: " + ", ".join(f"`{k}` {v}" for k, v in sorted(data["budgets"].items())) + ".", ""]
    lines += ["| suite | task | dev seeds | gate (held-out) seeds | test seeds | moved gate -> dev | test disjoint |",
              "|---|---|---|---|---|---|---|"]
    moves = []
    for suite, body in data.get("suites", {}).items():
        for t in body["tasks"]:
            moved = t["split"].get("moves", [])
            moves += [f"- {suite}/{t['task']} seed {m['seed']}: {m['reason']}" for m in moved]
            lines.append(f"| {suite} | {t['task']} | {_split_cell(t, 'dev')} | {_split_cell(t, 'heldout')} | "
                         f"{_split_cell(t, 'test')} | {_ranges([m['seed'] for m in moved])} | "
                         f"{'yes' if _test_disjoint(t) else '**no**'} |")
    return lines + ["", *(["Recorded moves:", "", *moves, ""] if moves else [])]


def _pair(x: Sequence[int]) -> str:
    return f"{x[0]}/{x[1]}"


def _candidates_cell(c: Mapping[str, Any]) -> str:
    """'4 run: 1 validated; refused: validation 2, held-out 1'."""
    refused = ", ".join(f"{k} {n}" for k, n in sorted(c["refused"].items()))
    return f"{c['run']} run: {c['validated']} validated" + (f"; refused: {refused}" if refused else "")


def _gate_cell(g: Mapping[str, Any] | None) -> str:
    """The gate's numbers of the round's candidate, or '-' when none reached the gate."""
    if g is None:
        return "-"
    verdict = "admitted" if g["admitted"] else f"refused ({g['refusal']})"
    return (f"regression {_pair(g['regression'])}, control (dev) {_pair(g['control'])}, held-out "
            f"{_pair(g['heldout'])} vs current {_pair(g['current'])} (bare {_pair(g['bare'])}): {verdict}")


def _seconds(x: float | None) -> str:
    return "-" if x is None else f"{x:.0f}"


def _wall_cell(r: Mapping[str, Any]) -> str:
    """'120 (40 / 70 / 10)': the round's wall time, then profile / repair / gate."""
    p = r.get("phases_s") or {}
    parts = " / ".join(_seconds(p.get(k)) for k in ("profile", "repair", "gate"))
    return _seconds(r.get("wall_s")) + (f" ({parts})" if p else "")


def _clusters_cell(r: Mapping[str, Any]) -> str:
    """'2 (+3 small)': the clusters repaired, then those left below the gate's minimum size."""
    return f"{r['clusters']}" + (f" (+{r['small']} small)" if r.get("small") else "")


def render_history(data: Mapping[str, Any]) -> list[str]:
    """One row per suite, task and round: what each loop did and what the gate measured."""
    if not any("history" in body for body in data.get("suites", {}).values()):
        return []  # a schema 1 file
    rows = [(suite, r) for suite, body in data.get("suites", {}).items() for r in body.get("history", [])]
    lines = ["#### Evolution history per task and round", "",
             "| suite | task | round | harness | dev profile | clusters | repaired / solved | candidates | gate | "
             "admitted | wall s (profile / repair / gate) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for suite, r in rows:
        lines.append(f"| {suite} | {r['task']} | {r['round']} | {r['harness']} | {_pair(r['profile'])} | "
                     f"{_clusters_cell(r)} | {r['repaired']} / {r['solved']} | {_candidates_cell(r['candidates'])} | "
                     f"{_gate_cell(r['gate'])} | {r['admitted'] or '-'} | {_wall_cell(r)} |")
    return lines + ([] if rows else ["| (no round recorded) | | | | | | | | | | |"]) + [""]


def _spark(versions: Sequence[Mapping[str, Any]]) -> str:
    """A text sparkline of the versions' success on the cluster's seeds."""
    return "".join(_SPARK[round(v["successes"] / v["episodes"] * (len(_SPARK) - 1)) if v["episodes"] else 0]
                   for v in versions)


def render_curves(data: Mapping[str, Any]) -> list[str]:
    """The internal versions of every cluster (the 'aha' curves) with their success on its seeds."""
    rows = [(suite, c) for suite, body in data.get("suites", {}).items() for c in body.get("curves", [])]
    if not rows:
        return []
    lines = ["#### Internal versions per cluster (the aha curves)", "",
             "| suite | task | round | cluster | seeds | versions (success on the cluster's seeds; ✓ validated) | "
             "curve | candidates proposed |", "|---|---|---|---|---|---|---|---|"]
    for suite, c in rows:
        steps = " → ".join(f"{v['version']} {v['successes']}/{v['episodes']}{' ✓' if v['validated'] else ''}"
                           for v in c["versions"])
        lines.append(f"| {suite} | {c['task']} | {c['round']} | {c['cluster']} | {_ranges(c['seeds'])} | {steps} | "
                     f"{_spark(c['versions'])} | {c['proposed']} |")
    return lines + [""]


def render_rollouts(data: Mapping[str, Any]) -> list[str]:
    """Rollouts by purpose with their summed episode time per store, and the wall time per phase."""
    stores = data.get("rollouts_by_purpose", {})
    if not stores:
        return []
    purposes = list(dict.fromkeys(p for s in stores.values() for p in s["purposes"]))
    lines = ["#### Rollouts and wall time", "",
             "| store | " + " | ".join(purposes) + " | invalid attempts |", "|---" * (len(purposes) + 2) + "|"]
    for label, s in stores.items():
        cells = [f"{s['purposes'][p]['rollouts']} ({s['purposes'][p]['episode_s']:.0f} s)" if p in s["purposes"]
                 else "-" for p in purposes]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {s['invalid']} |")
    lines += ["", "| suite | profile | repair | gate | final measurement | total |", "|---|---|---|---|---|---|"]
    for suite, body in data.get("suites", {}).items():
        p = body.get("phases_s", {})
        phases = " | ".join(_seconds(p.get(k)) for k in ("profile", "repair", "gate", "final"))
        lines.append(f"| {suite} | {phases} | {_seconds(data.get('wall_s', {}).get(suite))} |")
    if "transfer" in data.get("wall_s", {}):
        lines.append(f"| transfer | - | - | - | - | {_seconds(data['wall_s']['transfer'])} |")
    return lines + [""]


def render(data: Mapping[str, Any]) -> str:
    """The Markdown sections of a results file."""
    pol = data.get("policy", {})
    src = data.get("source", {})
    lines = [f"Generated from `{data.get('results_path', 'results.json')}` (schema {data.get('schema')}): commit "
             f"`{src.get('commit', '')[:12] or 'unknown'}`{' (dirty tree)' if src.get('dirty') else ''}, policy "
             f"`{pol.get('model', '')}` (checkpoint sha256 `{pol.get('checkpoint_sha256', '')[:16] or 'none'}`), "
             f"control `{data.get('control_model', '')}`, command `{data.get('command', '')}`.", "",
             *render_goals(data),
             "Test seeds only (no decision read them). *harness + nothing*: the same harness around a policy "
             "that outputs zero actions. *recoveries*: share of actions taken by recoveries over the successful "
             "harness episodes, the policy's actions under a redirected instruction included (their share in "
             "parentheses); *policy at success*: share of those successes with the policy in control at the "
             "success step.", ""]
    lines += [*_suite_tables(data), *_transfer_table(data), *render_splits(data), *render_history(data),
              *render_curves(data), *render_rollouts(data)]
    return "\n".join(lines).rstrip() + "\n"


def page(data: Mapping[str, Any]) -> str:
    """docs/results/evolution.md: the generated page of a published results file."""
    return page_header("evolution", "Evolution: bare policy, evolved harness, do-nothing control", data) + "\n" + render(data)


def page_own_suite(data: Mapping[str, Any]) -> str:
    """docs/results/evolution-goal.md: the same loops on the suite the policy was made for, where it
    succeeds alone most of the time, so the page shows what the loops do for a competent policy."""
    return (page_header("evolution-goal", "Evolution on the policy's own suite: bare policy, evolved harness, "
                        "do-nothing control", data) + "\n" + render(data))
