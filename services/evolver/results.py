"""The machine-readable results of `zetta evolve experiment`, and the tables rendered from them.

`results.json` holds everything a reader needs to trust a number and rerun it: the command, the
commit (and whether the tree was dirty), the policy and the hash of its checkpoint, the do-nothing
control's model, every task's splits (dev, gate, test seeds), and per task the test arms (bare
policy, evolved harness, the harness around the do-nothing policy) with Wilson 95 % intervals,
the recoveries' share of actions over successful episodes and the share of successes with the
policy in control at the success step; the means, the transfer rows and the wall time per phase.
Published as docs/results/evolution.json, it renders docs/results/evolution.md (:func:`page`;
``python scripts/gen_results.py evolution --from runs/experiment/results.json``), never typed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from services.common.provenance import page_header, weights_sha256
from services.evolver.store import RolloutStore

SCHEMA = 1
ARMS = ("bare", "final", "control")


def policy_provenance(model: str) -> dict[str, Any]:
    """The served policy: its name, checkpoint directory and hash (none for scripted models)."""
    from services.common.policies import checkpoint_dir

    path = checkpoint_dir(model)
    return {"model": model, "checkpoint": str(path or ""), "checkpoint_sha256": weights_sha256(path)}


def _mean(rows: Sequence[Mapping[str, Any]], arm: str, key: str = "rate") -> float:
    values = [float(r["arms"][arm][key]) for r in rows if arm in r.get("arms", {})]
    return sum(values) / len(values) if values else 0.0


def collect(out: Path, suites: Sequence[str], transfer_suite: str, meta: Mapping[str, Any]) -> dict[str, Any]:
    """The results of an experiment directory, from what its stores recorded."""
    data: dict[str, Any] = {"schema": SCHEMA, **meta, "suites": {}, "transfer": [], "wall_s": {}}
    for suite in suites:
        store = RolloutStore(out / suite)
        finals = sorted((f for f in store.events("final") if f["suite"] == suite and "arms" in f),
                        key=lambda f: (len(f["task"]), f["task"]))
        tasks = [{"task": f["task"], "harness": f["harness"], "arms": f["arms"], "split": f.get("split", {}),
                  "rollouts": len(store.query(task=f["task"]))} for f in finals]
        data["suites"][suite] = {"tasks": tasks, "mean": {arm: _mean(tasks, arm) for arm in ARMS},
                                 "rollouts": len(store.query())}
        data["wall_s"][suite] = sum(float(e["wall_s"]) for e in store.events("wall"))
        store.close()
    tdir = out / f"transfer-{transfer_suite}"
    if transfer_suite and (tdir / "index.sqlite").exists():
        tstore = RolloutStore(tdir)
        data["transfer"] = [{"suite": f["suite"], "task": f["task"], "harness": f["harness"], "source": f["source"],
                             "arms": f["arms"]} for f in tstore.events("transfer_source") if "arms" in f]
        data["wall_s"]["transfer"] = sum(float(e["wall_s"]) for e in tstore.events("wall"))
        tstore.close()
    return data


def write(path: Path, data: Mapping[str, Any]) -> Path:
    """Write the results file (sorted keys: a rerun that reproduces gives the same bytes but times)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    return path


def _cell(a: Mapping[str, Any]) -> str:
    lo, hi = a["wilson95"]
    return f"{a['successes']}/{a['episodes']} = {a['rate']:.0%} [{lo:.0%}, {hi:.0%}]" if a["episodes"] else "-"


def _arm_cells(arms: Mapping[str, Any]) -> str:
    """The cells bare | harness | delta | harness + nothing of one row."""
    b, f, c = (arms[k] for k in ARMS)
    return f"{_cell(b)} | {_cell(f)} | {f['rate'] - b['rate']:+.0%} | {_cell(c)}"


def render(data: Mapping[str, Any]) -> str:
    """The Markdown tables of a results file."""
    pol = data.get("policy", {})
    src = data.get("source", {})
    lines = [f"Generated from `{data.get('results_path', 'results.json')}` (schema {data.get('schema')}): commit "
             f"`{src.get('commit', '')[:12] or 'unknown'}`{' (dirty tree)' if src.get('dirty') else ''}, policy "
             f"`{pol.get('model', '')}` (checkpoint sha256 `{pol.get('checkpoint_sha256', '')[:16] or 'none'}`), "
             f"control `{data.get('control_model', '')}`, command `{data.get('command', '')}`.", "",
             "Test seeds only (no decision read them). *harness + nothing*: the same harness around a policy "
             "that outputs zero actions. *recoveries*: share of actions taken by recoveries over the successful "
             "harness episodes; *policy at success*: share of those successes with the policy in control at the "
             "success step.", ""]
    for suite, body in data.get("suites", {}).items():
        lines += [f"#### {suite}", "",
                  "| task | bare | harness | delta | harness + nothing | recoveries | policy at success | harness version |",
                  "|---|---|---|---|---|---|---|---|"]
        for t in body["tasks"]:
            f = t["arms"]["final"]
            lines.append(f"| {t['task']} | {_arm_cells(t['arms'])} | "
                         f"{f['recovery_share']:.0%} | {f['policy_in_control_at_success']:.0%} | {t['harness']} |")
        m = body["mean"]
        lines += [f"| **mean** | {m['bare']:.1%} | {m['final']:.1%} | {m['final'] - m['bare']:+.1%} | "
                  f"{m['control']:.1%} | | | |", "",
                  f"Rollouts: {body['rollouts']}; wall time {data.get('wall_s', {}).get(suite, 0.0):.0f} s.", ""]
    if data.get("transfer"):
        lines += ["#### Zero-shot transfer", "",
                  "| suite | task | harness (evolved on) | bare | harness | delta | harness + nothing |",
                  "|---|---|---|---|---|---|---|"]
        for t in data["transfer"]:
            lines.append(f"| {t['suite']} | {t['task']} | {t['harness']} ({t['source']}) | {_arm_cells(t['arms'])} |")
        lines += ["", f"Transfer wall time {data.get('wall_s', {}).get('transfer', 0.0):.0f} s.", ""]
    return "\n".join(lines).rstrip() + "\n"


def page(data: Mapping[str, Any]) -> str:
    """docs/results/evolution.md: the generated page of a published results file."""
    return page_header("evolution", "Evolution: bare policy, evolved harness, do-nothing control", data) + "\n" + render(data)
