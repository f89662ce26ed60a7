"""The VLA's published success figures: a results file made by one command, a page made from it.

``zetta eval-policy ... --results docs/results/vla.json`` writes what a reader needs to trust and
rerun a number (the command, the commit, the checkpoint's hash, the seeds and init states, which
init states the checkpoint was trained on, wall time, per-task Wilson intervals); ``python -m
services.policy_worker.vla.results docs/results/vla.json`` renders docs/results/vla.md from it.
The page is never edited by hand.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from services.common.policies import training_init_states
from services.common.provenance import machine, weights_sha256
from zetta_wire.stats import wilson


def git_commit() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10,
                             cwd=Path(__file__).resolve().parent)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, timeout=10, cwd=Path(__file__).resolve().parent).stdout.strip()
        return out.stdout.strip() + ("+local-changes" if dirty else "") if out.returncode == 0 else "unknown"
    except OSError:
        return "unknown"


def summarize(rows: list[dict]) -> dict[str, dict[str, Any]]:
    """Per suite: per task successes/episodes with Wilson 95 %, and the suite's total."""
    suites: dict[str, dict[str, Any]] = {}
    for r in rows:
        if "error" in r:
            continue
        s = suites.setdefault(r["suite"], {"tasks": {}, "seeds": set(), "init_states": set()})
        t = s["tasks"].setdefault(str(r["task"]), {"instruction": r.get("instruction", ""), "successes": 0,
                                                   "episodes": 0})
        t["successes"] += int(r["success"])
        t["episodes"] += 1
        s["seeds"].add(r["seed"])
        s["init_states"].add(r["init_state_index"])
    for s in suites.values():
        for t in s["tasks"].values():
            t["wilson95"] = [round(x, 4) for x in wilson(t["successes"], t["episodes"])]
        k = sum(t["successes"] for t in s["tasks"].values())
        n = sum(t["episodes"] for t in s["tasks"].values())
        s["total"] = {"successes": k, "episodes": n, "wilson95": [round(x, 4) for x in wilson(k, n)]}
        s["seeds"], s["init_states"] = sorted(s["seeds"]), sorted(s["init_states"])
    return suites


def write_results(path: str | Path, rows: list[dict], *, model: str, checkpoint: str | Path, execute_steps: int,
                  command: list[str], wall_s: float) -> dict:
    """Write the results file; refuses when an evaluated init state is one the checkpoint trained on.

    Suites this run did not evaluate are kept from the existing file when it measured the same
    weights (checkpoint sha256), model and execute_steps, each with the run that measured it, so one
    page can grow suite by suite; figures of other weights are dropped, never mixed in.
    """
    trained = training_init_states(checkpoint)
    suites = summarize(rows)
    for name, s in suites.items():
        base = "_".join(name.split("_")[:2])  # libero_goal_swap -> libero_goal: same init states
        overlap = sorted(set(s["init_states"]) & set(trained.get(base, [])))
        if overlap:
            raise ValueError(f"{name}: init states {overlap} were in the checkpoint's training data; "
                             f"evaluate on others (--seed-offset)")
    sha = weights_sha256(checkpoint)
    run = {"command": " ".join(command), "commit": git_commit(),
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "machine": machine(), "wall_s": round(wall_s, 1),
           "episode_s": round(sum(float(r.get("seconds", 0.0)) for r in rows), 1), "suites": sorted(suites)}
    runs = [run]
    merged = dict(suites)
    old = _previous(Path(path))
    if old and (old.get("checkpoint_sha256"), old.get("model"), old.get("execute_steps")) == (sha, model, execute_steps):
        for old_run in _runs(old):
            kept = [n for n in old_run["suites"] if n not in suites and n in old["suites"]]
            if kept:
                runs.append({**old_run, "suites": kept})
                merged.update({n: old["suites"][n] for n in kept})
    merged = {n: merged[n] for n in sorted(merged, key=lambda n: (n.count("_"), n))}  # libero_goal first
    doc = {
        "model": model, "checkpoint": str(checkpoint), "checkpoint_sha256": sha, **{k: run[k] for k in run if k != "suites"},
        "execute_steps": execute_steps, "training_init_states": trained, "runs": runs, "suites": merged,
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")
    return doc


def _previous(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _runs(doc: dict[str, Any]) -> list[dict[str, Any]]:
    """The runs behind a results file (a file written before runs were listed is one run)."""
    if "runs" in doc:
        return list(doc["runs"])
    keys = ("command", "commit", "date", "machine", "wall_s", "episode_s")
    return [{**{k: doc[k] for k in keys if k in doc}, "suites": sorted(doc.get("suites", {}))}]


def _pct(lo_hi: list[float]) -> str:
    return f"{lo_hi[0]:.0%}-{lo_hi[1]:.0%}"


def render(doc: dict) -> str:
    """docs/results/vla.md from a results file."""
    lines = [
        "# Zetta VLA: closed-loop success (generated)",
        "",
        f"Generated from `{doc.get('source', 'docs/results/vla.json')}` by "
        "`python -m services.policy_worker.vla.results`; do not edit by hand.",
        "",
        f"- model `{doc['model']}`, checkpoint `{doc['checkpoint']}` (model.pt sha256 `{doc['checkpoint_sha256'][:16]}...`)",
    ]
    for run in _runs(doc):
        lines += [
            f"- {', '.join(run['suites'])}: `{run['command']}`",
            f"  (commit `{run['commit']}`, {run['date']}, {run.get('machine', '')}, "
            + (f"episodes ran {run['episode_s'] / 60:.0f} process-minutes in all)" if "episode_s" in run
               else f"evaluation time about {run['wall_s'] / 60:.0f} min)"),
        ]
    lines += [
        f"- {doc['execute_steps']} actions of each 8-action chunk run per policy call",
        f"- the checkpoint was trained on init states {_ranges(doc['training_init_states'].get('libero_goal', []))} "
        "of libero_goal (original tasks only); every episode below starts from another",
        "",
        "| suite | successes / episodes | rate | Wilson 95% | seeds | init states |",
        "|---|---|---|---|---|---|",
    ]
    for name, s in doc["suites"].items():
        t = s["total"]
        lines.append(f"| {name} | {t['successes']}/{t['episodes']} | {t['successes'] / max(t['episodes'], 1):.0%} | "
                     f"{_pct(t['wilson95'])} | {_ranges(s['seeds'])} | {_ranges(s['init_states'])} |")
    for name, s in doc["suites"].items():
        lines += ["", f"## {name}", "", "| task | instruction | successes / episodes | rate | Wilson 95% |",
                  "|---|---|---|---|---|"]
        for task, t in sorted(s["tasks"].items(), key=lambda kv: int(kv[0])):
            lines.append(f"| {task} | {t['instruction']} | {t['successes']}/{t['episodes']} | "
                         f"{t['successes'] / max(t['episodes'], 1):.0%} | {_pct(t['wilson95'])} |")
    return "\n".join(lines) + "\n"


def _ranges(values: list[int]) -> str:
    """[0, 1, 2, 5] -> "0-2, 5"."""
    out, start = [], None
    for i, v in enumerate(values):
        if start is None:
            start = v
        if i + 1 == len(values) or values[i + 1] != v + 1:
            out.append(f"{start}-{v}" if v != start else f"{v}")
            start = None
    return ", ".join(out) or "none"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    src = Path(args[0] if args else "docs/results/vla.json")
    doc = {**json.loads(src.read_text()), "source": str(src)}
    out = src.with_suffix(".md")
    out.write_text(render(doc))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
