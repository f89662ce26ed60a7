"""The evolution report: Markdown plus PNG plots, built only from what the store recorded.

Sections: dev success per round and test before/after with the do-nothing control (Wilson 95 % intervals), the internal
versions of each cluster (the paper's v0/v1/v2 curves), the share of actions taken by recoveries
vs the policy with the interventions by kind, and the lineage of every admitted change.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from services.evolver.store import RolloutStore
from zetta_wire.stats import wilson


def _rate(s: int, n: int) -> str:
    lo, hi = wilson(s, n)
    return f"{s}/{n} = {s / n:.0%} [{lo:.0%}, {hi:.0%}]" if n else "0/0"


def _plot_rounds(profiles: list[dict[str, Any]], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for i, task in enumerate(sorted({p["task"] for p in profiles})):
        pts = sorted((p["round"], p["successes"], p["episodes"]) for p in profiles if p["task"] == task)
        xs = [r + 0.04 * i for r, _, _ in pts]  # side by side where intervals overlap
        ys = [s / n if n else 0 for _, s, n in pts]
        lo = [y - wilson(s, n)[0] for y, (_, s, n) in zip(ys, pts)]
        hi = [wilson(s, n)[1] - y for y, (_, s, n) in zip(ys, pts)]
        ax.errorbar(xs, ys, yerr=[lo, hi], marker="o", capsize=3, label=f"task {task}")
    ax.set_xticks(sorted({p["round"] for p in profiles}))
    ax.set_xlabel("round")
    ax.set_ylabel("dev success (Wilson 95%)")
    ax.set_ylim(0, 1)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_versions(curves: list[dict[str, Any]], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for c in curves:
        ys = [v["successes"] / v["episodes"] if v["episodes"] else 0 for v in c["versions"]]
        ax.plot([v["version"] for v in c["versions"]], ys, marker="o", label=c["cluster"])
    ax.set_ylabel("success on cluster seeds")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _plot_final(finals: list[dict[str, Any]], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    labels = [f"{f['task']}{' (T)' if f.get('transfer') else ''}" for f in finals]
    for off, key, name in ((-0.2, "bare", "bare policy"), (0.2, "final", "with harness")):
        ys = [f[key][0] / f[key][1] if f[key][1] else 0 for f in finals]
        ax.bar([i + off for i in range(len(finals))], ys, width=0.4, label=name)
    ax.set_xticks(range(len(finals)), labels)
    ax.set_ylabel("test success")
    ax.set_ylim(0, 1)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _version_note(v: dict[str, Any]) -> str:
    """" (seed 12 reached 4 milestones; validated)" for an internal version, "" when nothing was recorded."""
    if "medoid_milestones" not in v:
        return ""
    who = f"seed {v['seed']}" if "seed" in v else "medoid"
    return f" ({who} reached {v['medoid_milestones']} milestones{'; validated' if v.get('validated') else ''})"


def interventions(store: RolloutStore, harnesses: set[str]) -> tuple[dict[str, tuple[int, int]], Counter[str]]:
    """For the given harness versions: (policy actions, recovery actions) each, and their
    interventions by kind, over every rollout they ran."""
    shares: dict[str, tuple[int, int]] = {}
    kinds: Counter[str] = Counter()
    for r in store.query():
        if r.harness not in harnesses:
            continue
        p, q = shares.get(r.harness, (0, 0))
        shares[r.harness] = (p + r.policy_steps, q + r.recovery_steps)
        if r.interventions:
            for iv in store.trace(r).interventions:
                kinds[str(iv.get("recovery") or iv.get("kind") or "intervention")] += 1
    return shares, kinds


def write_report(store: RolloutStore, out: Path, title: str, wall_s: float | None = None) -> Path:
    """Write ``out``/report.md and its plots; returns the Markdown path."""
    out.mkdir(parents=True, exist_ok=True)
    profiles = store.events("profile")
    curves = store.events("cluster_versions")
    finals = store.events("final")
    admitted = store.events("admitted")
    gates = store.events("gate")
    lines = [f"# {title}", ""]
    rollouts = store.query()
    lines += [f"Rollouts in the store: {len(rollouts)} valid, {len(store.invalid_attempts())} invalid attempts "
              f"(rerun on the same episode key)." + (f" Wall time: {wall_s:.0f} s." if wall_s is not None else ""), ""]
    if finals:
        _plot_final(finals, out / "test.png")
        lines += ["## Test success (seeds no decision read), bare policy vs harness", "",
                  "*harness + nothing*: the same harness around a do-nothing policy; *recoveries*: their share of "
                  "the actions of the harness's successful episodes; *policy at success*: share of those successes "
                  "with the policy in control at the success step.", "",
                  "| suite | task | harness | bare | with harness | delta | harness + nothing | recoveries | "
                  "policy at success |", "|---|---|---|---|---|---|---|---|---|"]
        for f in finals:
            b, h = f["bare"], f["final"]
            delta = (h[0] / h[1] if h[1] else 0) - (b[0] / b[1] if b[1] else 0)
            kind = " (zero-shot transfer)" if f.get("transfer") else ""
            arms = f.get("arms", {})
            control = arms.get("control")
            final = arms.get("final", {})
            extra = (f"{_rate(control['successes'], control['episodes'])} | {final['recovery_share']:.0%} | "
                     f"{final['policy_in_control_at_success']:.0%}" if control and final else "- | - | -")
            lines.append(f"| {f['suite']} | {f['task']}{kind} | {f['harness']} | {_rate(*b)} | {_rate(*h)} | "
                         f"{delta:+.0%} | {extra} |")
        tb, th = [sum(f[k][0] for f in finals) for k in ("bare", "final")], sum(f["bare"][1] for f in finals)
        lines += [f"| **all** | | | {_rate(tb[0], th)} | {_rate(tb[1], sum(f['final'][1] for f in finals))} | | | | |",
                  "", "![test](test.png)", ""]
    if profiles:
        _plot_rounds(profiles, out / "rounds.png")
        lines += ["## Dev success per round (Loop 1 profile with the round's current harness)", "",
                  "| task | round | harness | success |", "|---|---|---|---|"]
        for p in profiles:
            lines.append(f"| {p['task']} | {p['round']} | {p['harness']} | {_rate(p['successes'], p['episodes'])} |")
        lines += ["", "![rounds](rounds.png)", ""]
    clusters = store.events("cluster")
    if clusters:
        lines += ["## Clusters and diagnoses", "", "| cluster | size | m* | medoid seed | t_EOD | L* | consistency |",
                  "|---|---|---|---|---|---|---|"]
        for c in clusters:
            s = c["spec"]
            lines.append(f"| {c['cluster']} | {c['size']} | {s['m_star']} | {c['medoid_seed']} | {s['t_eod']} | "
                         f"{s['layer']} | {s['consistency']:.0%} |")
        lines.append("")
    if curves:
        _plot_versions(curves, out / "versions.png")
        lines += ["## Internal versions per cluster", "",
                  "v0 is the harness before the repair; each later version stacks the candidate that got the "
                  "seed under repair furthest (or succeeded on it: validated) and is measured on every seed of "
                  "the cluster. The seed under repair is the medoid, then a member the last validated version "
                  "still failed.", ""]
        for c in curves:
            pts = ", ".join(f"{v['version']} {v['successes']}/{v['episodes']}{_version_note(v)}" for v in c["versions"])
            tried = f"; {c['tried']} candidates tried" if "tried" in c else ""
            lines.append(f"- {c['cluster']}: {pts}{tried}")
        lines += ["", "![versions](versions.png)", ""]
    final_refs = {a["ref"] for a in admitted} | {f["harness"] for f in finals if f["harness"] != "bare"}
    shares, kinds = interventions(store, final_refs)
    candidates = {r.harness for r in store.query() if r.harness and r.harness not in final_refs}
    if shares or candidates:
        lines += ["## Intervention shares", "",
                  "Actions taken by the policy vs by recoveries with each admitted or evaluated harness, over all "
                  "its rollouts (a success that recoveries carried shows here).", "",
                  "| harness | policy actions | recovery actions | recovery share |", "|---|---|---|---|"]
        for h, (p, q) in sorted(shares.items()):
            lines.append(f"| {h} | {p} | {q} | {q / max(p + q, 1):.1%} |")
        lines += ["", "Interventions by kind: " + (", ".join(f"{k} {n}" for k, n in kinds.most_common()) or "none"),
                  "", f"Candidate harnesses run during validation and gating: {len(candidates)}.", ""]
    joins = store.events("consolidation")
    if joins:
        lines += ["## Consolidation across clusters", "",
                  "Largest cluster first; a further cluster's stack joins only if the merged harness still solves "
                  "every seed of the clusters joined so far.", ""]
        for j in joins:
            lines.append(f"- {j['task']} round {j['round']} {j['cluster']} via {j['candidate']}: regression "
                         f"{j['regression'][0]}/{j['regression'][1]}, " + ("joined" if j["joined"] else f"not joined ({j['reason']})"))
        lines.append("")
    if gates:
        lines += ["## Gate decisions", ""]
        for g in gates:
            v = g["verdict"]
            lines.append(f"- {g['task']} round {g['round']} {g['candidate']}: "
                         f"{'ADMITTED' if v['admitted'] else 'rejected'} ({v['reason']})")
        lines.append("")
    lines += ["## Lineage of admitted changes", ""]
    if not admitted:
        lines.append("No candidate passed both gates: the harness stayed as it was.")
    for a in admitted:
        lines.append(f"- {a['ref']} (parent {a['parent']}, round {a['round']}): " + "; ".join(
            f"{p['critic']}({p['template']} {json.dumps(p['params'])}) -> {p.get('playbook') or p['recovery']}"
            for p in a["patches"])
            + f"; delta over bare {a['verdict']['delta_over_bare']:+.0%}")
    moves = store.split_moves()
    lines += ["", f"Split moves (held-out -> dev): {len(moves)}", ""]
    for m in moves:
        lines.append(f"- {m['suite']}/{m['task']} seed {m['seed']}: {m['reason']}")
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
