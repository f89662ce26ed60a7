"""Held-out success of a frozen policy alone vs the same policy under a harness, on the same seeds.

Everything goes through the real stack (LocalStack: Redis, gateway, env worker, policy worker on
loopback gRPC): for each (suite, task, seed) one session runs the bare policy and a second one the
policy plus the harness (ResetSpec.harness_dir), side by side, with identical episode keys. Per
episode it records success, m*, and the harness report: how many actions the policy and the
recoveries took and the interventions by kind, so a success that recoveries did all the work for
shows as such. The harness's package code runs only in the env worker's sandbox children
(services/harness/sandbox/, docs/security.md); this script checks the package and hashes it, it
never imports its tools. Results: one JSON row per episode appended to --out, the table on stdout and, with
--results, a results file (every row, the command, the commit) and its page beside it
(docs/results/harness.json and .md; docs/harness-results.md explains them).

    python scripts/eval_harness.py --harness examples/harnesses/libero-goal-pick-place \\
        --suites libero_goal_swap,libero_goal_task --tasks 6,9 --seeds 130-139 --out out/harness/eval.jsonl \\
        --results docs/results/harness.json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "clients" / "python"))

from services.common.policies import DEFAULT_POLICY, checkpoint_dir  # noqa: E402
from services.common.provenance import page_header, provenance, weights_sha256, write_results  # noqa: E402
from services.harness.package.loader import load_package  # noqa: E402
from zetta.client import EpisodeSummary, Gateway, ZettaError  # noqa: E402
from services.ops.local_stack import LocalStack  # noqa: E402
from zetta_wire.stats import wilson  # noqa: E402


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-", 1)
        return list(range(int(lo), int(hi) + 1))
    return [int(s) for s in text.split(",") if s]


def _row(suite: str, task: int, seed: int, condition: str, s: EpisodeSummary) -> dict:
    row = {"suite": suite, "task": task, "seed": seed, "init_state_index": seed % 50, "condition": condition,
           "success": s.success, "steps": s.steps, "policy_calls": s.policy_calls,
           "first_missing_milestone": s.first_missing_milestone, "wall_s": round(s.wall_ms / 1000, 2)}
    r = s.harness_report
    if r is not None:
        row.update(harness=f"{r.harness}@{r.version or 'dir'}", content_hash=r.content_hash,
                   policy_actions=r.policy_actions, recovery_actions=r.recovery_actions,
                   interventions_by_kind=r.interventions_by_kind,
                   kinds=[iv["kind"] for iv in r.interventions],
                   outcomes=[iv["outcome"] for iv in r.interventions],
                   disabled_critics=[d["name"] for d in r.disabled_critics])
    else:
        row.update(policy_actions=s.steps, recovery_actions=0)
    return row


#: Infrastructure failures (not the policy's or the harness's): the pair is rerun on the same seed.
_INVALID = {"DEADLINE_EXCEEDED", "UNAVAILABLE"}


async def _pair(group, task: int, seed: int, args: argparse.Namespace, harness_dir: str,
                tries: int = 3) -> tuple[EpisodeSummary, EpisodeSummary]:
    """Both conditions of one episode key; an infrastructure-invalid pair is rerun (Loop 1's rule)."""
    for attempt in range(tries):
        try:
            return await asyncio.gather(
                group[0].run_episode(task, seed, seed % 50, args.model, execute_steps=args.execute_steps),
                group[1].run_episode(task, seed, seed % 50, args.model, execute_steps=args.execute_steps,
                                     harness_dir=harness_dir),
            )
        except ZettaError as exc:
            if exc.code.name not in _INVALID or attempt == tries - 1:
                raise
            print(f"task {task} seed {seed}: invalid rollout ({exc.code.name}), rerun", flush=True)
    raise AssertionError("unreachable")


async def _run(args: argparse.Namespace, address: str, out: Path) -> list[dict]:
    rows: list[dict] = []
    harness_dir = str(Path(args.harness).resolve())
    async with Gateway(address) as gw:
        for suite in args.suites.split(","):
            group = await gw.create_sessions("libero", 2, {"suite": suite})
            try:
                for task in [int(t) for t in args.tasks.split(",")]:
                    for seed in _seeds(args.seeds):
                        bare, harnessed = await _pair(group, task, seed, args, harness_dir)
                        for cond, s in (("bare", bare), ("harness", harnessed)):
                            row = _row(suite, task, seed, cond, s)
                            row["checkpoint"] = args.checkpoint
                            rows.append(row)
                            with out.open("a") as fh:
                                fh.write(json.dumps(row) + "\n")
                        print(f"{suite} task {task} seed {seed}: bare {bare.success}, harness {harnessed.success} "
                              f"(policy share {rows[-1]['policy_actions']}/{harnessed.steps})", flush=True)
            finally:
                await group.close()
    return rows


def table(rows: list[dict]) -> str:
    """Markdown: per suite and task, bare vs harness successes with Wilson 95% intervals, action shares
    and interventions by kind."""
    lines = [
        "| suite | task | condition | successes | rate | Wilson 95% | policy share of actions | "
        "successes with policy share < 50% | interventions by kind |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    keys = sorted({(r["suite"], r["task"]) for r in rows}) + [("all", -1)]
    for suite, task in keys:
        for cond in ("bare", "harness"):
            rs = [r for r in rows if r["condition"] == cond and (suite == "all" or (r["suite"], r["task"]) == (suite, task))]
            if not rs:
                continue
            k, n = sum(r["success"] for r in rs), len(rs)
            lo, hi = wilson(k, n)
            pol = sum(r["policy_actions"] for r in rs)
            tot = pol + sum(r["recovery_actions"] for r in rs)
            mostly = sum(1 for r in rs if r["success"] and r["policy_actions"] < r["recovery_actions"])
            kinds: Counter[str] = Counter()
            for r in rs:
                kinds.update(r.get("interventions_by_kind", {}))
            label = "**all**" if suite == "all" else str(task)
            lines.append(
                f"| {suite} | {label} | {cond} | {k}/{n} | {k / n:.0%} | {lo:.0%}-{hi:.0%} | "
                f"{pol / tot if tot else 1.0:.0%} | {mostly if cond == 'harness' else '-'} | "
                f"{', '.join(f'{a}: {b}' for a, b in sorted(kinds.items())) or '-'} |"
            )
    return "\n".join(lines)


def checkpoint_id(model: str) -> str:
    """The weights' sha256 (the hash every results file reports) and when the checkpoint was written."""
    ckpt = checkpoint_dir(model)
    digest = weights_sha256(ckpt)
    if not digest or ckpt is None:
        return "no checkpoint file (not a checkpoint model)"
    stamp = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime((ckpt / "model.pt").stat().st_mtime))
    return f"model.pt sha256 {digest[:12]}..., written {stamp}"


def page(doc: dict) -> str:
    """docs/results/harness.md from a results file: the table, then every episode pair."""
    rows = doc["rows"]
    lines = [
        page_header("harness", "Harness evaluation: frozen policy alone vs policy + harness", doc),
        f"Harness `{doc['harness']}` (content hash `{doc['content_hash'][:16]}...`); policy `{doc['model']}` "
        f"({doc['checkpoint']}), {doc['execute_steps']} actions of each chunk executed per policy call; seeds "
        f"`{doc['seeds']}`, init state = seed % 50; {len(rows) // 2} episode pairs in {doc['wall_s'] / 60:.0f} min. "
        "How to read it: [docs/harness-results.md](../harness-results.md).",
        "",
        table(rows),
        "",
        "## Every episode",
        "",
        "| suite | task | seed | bare | m* (bare) | harness | m* (harness) | policy / all actions | interventions (kind: outcome) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    by_key: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        by_key.setdefault((r["suite"], r["task"], r["seed"]), {})[r["condition"]] = r
    for (suite, task, seed), pair in sorted(by_key.items()):
        b, h = pair.get("bare", {}), pair.get("harness", {})
        ivs = ", ".join(f"{k}: {o.split(':')[0]}" for k, o in zip(h.get("kinds", []), h.get("outcomes", []))) or "-"
        lines.append(
            f"| {suite} | {task} | {seed} | {'yes' if b.get('success') else 'no'} | {b.get('first_missing_milestone') or '-'} "
            f"| {'yes' if h.get('success') else 'no'} | {h.get('first_missing_milestone') or '-'} | "
            f"{h.get('policy_actions', 0)}/{h.get('policy_actions', 0) + h.get('recovery_actions', 0)} | {ivs} |"
        )
    return "\n".join(lines) + "\n"


def write_doc(results: Path, rows: list[dict], a: argparse.Namespace, seconds: float) -> None:
    """The results file (every row, what ran, the command, the commit) and its page beside it."""
    cmd = (f"python scripts/eval_harness.py --harness {a.harness_rel} --model {a.model} "
           f"--suites {a.suites} --tasks {a.tasks} --seeds {a.seeds} --execute-steps {a.execute_steps} "
           f"--out {a.out} --results {a.results}")
    doc = {**provenance(cmd, ROOT), "harness": a.harness_rel,
           "content_hash": next((r["content_hash"] for r in rows if "content_hash" in r), a.content_hash),
           "model": a.model, "checkpoint": next((r["checkpoint"] for r in rows if "checkpoint" in r), a.checkpoint),
           "execute_steps": a.execute_steps, "seeds": a.seeds, "wall_s": round(seconds, 1), "rows": rows}
    write_results("harness", doc, page(doc), results.parent)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--harness", default=str(ROOT / "examples" / "harnesses" / "libero-goal-pick-place"))
    p.add_argument("--model", default=DEFAULT_POLICY)
    p.add_argument("--suites", default="libero_goal_swap,libero_goal_task")
    p.add_argument("--tasks", default="6,9")
    p.add_argument("--seeds", default="130-139", help="held-out seeds: 'a-b' or a comma list; init state = seed %% 50")
    p.add_argument("--execute-steps", type=int, default=4)
    p.add_argument("--out", default="out/harness/eval.jsonl")
    p.add_argument("--results", default="", help="also write the results file (e.g. docs/results/harness.json) and "
                                                  "its page beside it")
    p.add_argument("--rebuild", action="store_true", help="run nothing: rebuild the table (and --results) from --out")
    a = p.parse_args(argv)
    a.harness_rel = os.path.relpath(Path(a.harness).resolve(), ROOT)
    # The static checks and the content hash only: the package's code runs in the env worker's
    # sandbox children (services/harness/sandbox/), never in this process.
    a.content_hash = load_package(a.harness, import_tools=False).content_hash
    a.checkpoint = checkpoint_id(a.model)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    start = time.time()
    if a.rebuild:
        rows = [json.loads(line) for line in out.read_text().splitlines() if line.strip()]
        print(table(rows))
        if a.results:
            write_doc(Path(a.results), rows, a, 0.0)
        return 0
    # A long heartbeat timeout: on a loaded 2-core machine a busy env worker can miss the default
    # 3 s, and the gateway would declare it dead in the middle of an episode.
    stack = LocalStack(env_workers=1, slots=2, policy_workers=1, families=("libero",), models=(a.model,), critic=False,
                       heartbeat_timeout_ms=30_000,
                       extra_env={"ZETTA_TORCH_THREADS": "1", "ZETTA_POLICY_TIMEOUT_MS": "120000"})
    with stack:
        rows = asyncio.run(_run(a, stack.gateway_address, out))
    print(table(rows))
    print(f"{len(rows)} episodes in {time.time() - start:.0f} s")
    if a.results:
        write_doc(Path(a.results), rows, a, time.time() - start)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
