"""What an evolution did, per task and round, read back from its rollout store for the results file.

Everything here comes from the store's events (services/evolver/evolve.py records them): the Loop 1
profile of each round (``profile``), its failure clusters (``cluster``) and their internal
versions (``cluster_versions``: the v0/v1/v2 curves), the candidates' closed-loop validations
(``validation``), the merges of clusters (``consolidation``), the gate's verdict (``gate``), the
admitted version (``admitted``) and the round's wall time (``round_done``); and from the index: the
rollouts by purpose and the invalid attempts.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from services.evolver.store import RolloutStore

#: Rollout purposes in the order the loops use them (store keys; others follow, sorted).
PURPOSES = ("nominal", "profile", "validate", "regress", "control", "heldout", "test", "control-test")
#: A refusal's kind, by the words the gate's reasons start with (services/evolver/gate.py).
_REFUSALS = (("historical regression", "regression"), ("do-nothing", "control"), ("held-out", "held-out"))


def task_order(task: str) -> tuple[int, str]:
    """Sort key of task names: numeric indices in numeric order."""
    return len(task), task


def refusal_kind(reason: str) -> str:
    """The gate a refusal's reason names: regression, control, held-out (or other)."""
    return next((kind for words, kind in _REFUSALS if words in reason), "other")


def _of(events: Sequence[dict[str, Any]], suite: str, task: str, round_: int) -> list[dict[str, Any]]:
    """The events of one task and round (events recorded without a suite belong to the store's)."""
    return [e for e in events if e.get("suite", suite) == suite and e.get("task") == task and e.get("round") == round_]


def _pair(block: Mapping[str, Any] | None) -> list[int]:
    """[successes, episodes] of a verdict block."""
    return [int(block.get("successes", 0)), int(block.get("episodes", 0))] if block else [0, 0]


def gate_numbers(gate: Mapping[str, Any]) -> dict[str, Any]:
    """The gate's numbers of one candidate: regression on the clusters' seeds, the do-nothing control
    on the dev seeds, held-out success vs the current harness and the bare policy, and the verdict."""
    v = gate["verdict"]
    return {"candidate": gate.get("candidate", ""), "admitted": bool(v["admitted"]), "reason": v.get("reason", ""),
            "refusal": "" if v["admitted"] else refusal_kind(v.get("reason", "")),
            **{k: _pair(v.get(k)) for k in ("regression", "control", "heldout", "current", "bare")},
            "delta_over_bare": float(v.get("delta_over_bare", 0.0))}


def _candidates(validations: Sequence[dict[str, Any]], merges: Sequence[dict[str, Any]],
                gate: Mapping[str, Any] | None) -> dict[str, Any]:
    """Candidates run closed-loop in a round, those validated on their seed, and the refusals by kind."""
    refused: Counter[str] = Counter()
    for v in validations:
        if "skipped" in v:
            refused["no registry"] += len(v.get("candidates", []))
        elif not v.get("medoid_success"):
            refused["validation"] += 1
        elif not _validated(v):
            refused["no hand-back"] += 1
    refused["consolidation"] += sum(not m.get("joined") for m in merges)
    if gate is not None and not gate["admitted"]:
        refused[gate["refusal"]] += 1
    return {"run": sum(len(v.get("candidates", [])) if "skipped" in v else 1 for v in validations),
            "validated": sum(_validated(v) for v in validations), "refused": dict(+refused)}


def _validated(v: Mapping[str, Any]) -> bool:
    """A candidate's medoid rollout succeeded and the evolver counted it (a run that required a
    hand-back did not count a success an intervention finished; records before that knob say
    nothing, and every success of theirs counted)."""
    return bool(v.get("validated", v.get("medoid_success")))


def _curve_state(curves: Sequence[dict[str, Any]]) -> tuple[int, int]:
    """(clusters with a validated version, clusters a validated version solved on every seed)."""
    validated = [[v for v in c["versions"] if v.get("validated")] for c in curves]
    solved = sum(any(v["episodes"] and v["successes"] == v["episodes"] for v in vs) for vs in validated)
    return sum(bool(vs) for vs in validated), solved


def round_rows(store: RolloutStore, suite: str) -> list[dict[str, Any]]:
    """One row per task and round with a recorded profile: dev success, clusters repaired (and those
    left for being below the gate's minimum size), candidates, the gate's numbers when a candidate
    reached it, the admitted version and the wall time."""
    ev = {k: store.events(k) for k in ("cluster", "cluster_versions", "validation", "consolidation", "gate",
                                       "admitted", "round_done")}
    rows = []
    for p in (e for e in store.events("profile") if e.get("suite", suite) == suite):
        task, round_ = p["task"], p["round"]
        ids = {c["cluster"] for c in _of(ev["cluster"], suite, task, round_)}
        gates = _of(ev["gate"], suite, task, round_)
        gate = gate_numbers(gates[-1]) if gates else None
        repaired, solved = _curve_state(_of(ev["cluster_versions"], suite, task, round_))
        done = _of(ev["round_done"], suite, task, round_)
        admitted = _of(ev["admitted"], suite, task, round_)
        rows.append({"task": task, "round": round_, "harness": p["harness"], "profile": [p["successes"], p["episodes"]],
                     "clusters": len(ids), "small": len(done[-1].get("skipped_clusters", [])) if done else 0,
                     "repaired": repaired, "solved": solved,
                     "candidates": _candidates([v for v in ev["validation"] if v["cluster"] in ids],
                                               _of(ev["consolidation"], suite, task, round_), gate),
                     "gate": gate, "admitted": admitted[-1]["ref"] if admitted else "",
                     "wall_s": done[-1].get("wall_s") if done else None,
                     "phases_s": done[-1].get("phases_s", {}) if done else {}})
    return sorted(rows, key=lambda r: (r["round"], task_order(r["task"])))


def curves(store: RolloutStore, suite: str) -> list[dict[str, Any]]:
    """Every cluster's internal versions (v0 = the harness before the repair) with their success on
    the cluster's seeds, whether each was validated on its seed, and the candidates the search proposed."""
    seeds = {c["cluster"]: c.get("seeds", []) for c in store.events("cluster")}
    return [{"task": c["task"], "round": c["round"], "cluster": c["cluster"], "seeds": seeds.get(c["cluster"], []),
             "proposed": c.get("tried", 0),
             "versions": [{"version": v["version"], "harness": v.get("harness", ""), "successes": v["successes"],
                           "episodes": v["episodes"], "validated": bool(v.get("validated"))} for v in c["versions"]]}
            for c in store.events("cluster_versions") if c.get("suite", suite) == suite]


def rollout_counts(store: RolloutStore) -> dict[str, Any]:
    """Valid rollouts by purpose with their summed episode time, and the invalid attempts."""
    count: Counter[str] = Counter()
    seconds: dict[str, float] = {}
    for r in store.query():
        count[r.purpose] += 1
        seconds[r.purpose] = seconds.get(r.purpose, 0.0) + r.wall_s
    order = [p for p in PURPOSES if p in count] + sorted(set(count) - set(PURPOSES))
    return {"purposes": {p: {"rollouts": count[p], "episode_s": seconds[p]} for p in order},
            "invalid": len(store.invalid_attempts())}


def phase_walls(store: RolloutStore, suite: str) -> dict[str, float]:
    """Wall time per phase summed over tasks and rounds (profile, repair, gate), and of the final
    measurement; a phase a store never timed is left out."""
    total: dict[str, float] = {}
    for done in (d for d in store.events("round_done") if d.get("suite", suite) == suite):
        for k, v in done.get("phases_s", {}).items():
            total[k] = total.get(k, 0.0) + float(v)
    finals = [float(f["wall_s"]) for f in store.events("final") if f.get("suite") == suite and "wall_s" in f]
    return {**total, "final": sum(finals)} if finals else total
