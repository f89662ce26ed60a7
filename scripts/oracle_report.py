"""Success of the scripted oracle per suite, task and init state, written as docs/oracle.md.

Runs the oracle (services/policy_worker/models/oracle.py) in-process on the libero family, one
episode per (suite, task, init state), spread over worker processes (each process keeps one slot
per suite, so a task switch only swaps warm envs). Every episode is judged by the environment's own
success predicate; failures are reported with their first missing milestone m*.

    .venv/bin/python scripts/oracle_report.py --suites libero_goal libero_goal_swap libero_goal_task \
        --inits 50 --processes 1 --out docs/oracle.md

Per-episode results are appended to a JSONL file as they finish (``--jsonl``), so a long run that
is cut short still leaves its data; ``--resume`` skips episodes already in that file.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

from zetta_wire.stats import wilson  # noqa: E402 - after the path set-up above


_SLOTS: dict[str, object] = {}


def run_one(job: tuple[str, int, int, int]) -> dict:
    """One episode: (suite, task index, init state index, seed) -> result record."""
    suite, task, init, seed = job
    import numpy as np

    from services.env_worker.families import ResetSpec, get_family
    from services.policy_worker.models.oracle import OraclePolicy

    slot = _SLOTS.get(suite)
    if slot is None:
        slot = _SLOTS[suite] = get_family("libero")({"suite": suite}).init()
    policy = OraclePolicy()
    start = time.perf_counter()
    obs, instruction = slot.reset(ResetSpec(str(task), seed=seed, init_state_index=init))
    outcome = None
    while True:
        action = policy.infer({k: v[None] for k, v in obs.items()}, [instruction])[0, 0]
        outcome = slot.step(np.asarray(action, dtype=np.float32), render=False)
        obs = outcome.observation
        if outcome.terminated or outcome.truncated:
            break
    return {
        "suite": suite, "task": task, "init": init, "seed": seed, "instruction": instruction,
        "success": bool(outcome.success), "steps": slot.episode_step,
        "first_missing": slot.first_missing_milestone(), "wall_s": round(time.perf_counter() - start, 2),
    }


def _key(r: dict) -> tuple:
    return (r["suite"], r["task"], r["init"], r["seed"])


def write_report(records: list[dict], out: Path, command: str, planned: int) -> None:
    by_task: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for r in records:
        by_task[(r["suite"], r["task"])].append(r)
    lines = [
        "# Scripted oracle: success per task",
        "",
        "The oracle (`services/policy_worker/models/oracle.py`, model name `oracle`) runs one generic skill",
        "per goal predicate of the task's BDDL goal (pick-and-place for on/in, push for on a table region,",
        "finger push of the lever for turnon/turnoff, grasp-and-pull of the handle bar for open/close), reading",
        "only privileged state; no task names or per-task constants. Pick-and-place slides an object out from",
        "under its target first (an opened drawer over the bowl it must receive), lowers an object into a",
        "deep dish it fits in (a bottle into a bowl), and carries around the obstacles the scene reports",
        "(`task_obstacle_bbox`), letting go where nothing hangs over the target; the hand pitches toward the",
        "base when the elbow nears its limit; a drawer bar too low to grip from the front is hooked from",
        "above. Success is the environment's own `_check_success()`. Episodes use LIBERO's step budget (300",
        "for LIBERO-Goal) and seed 0.",
        "",
        f"Episodes run: {len(records)} of {planned} planned.",
        "",
        "Command:",
        "",
        "```",
        command,
        "```",
        "",
        "| suite | task | instruction | successes | Wilson 95% | mean steps (successes) | most common m* of failures |",
        "|---|---|---|---|---|---|---|",
    ]
    totals: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for (suite, task), rs in sorted(by_task.items()):
        n, k = len(rs), sum(r["success"] for r in rs)
        lo, hi = wilson(k, n)
        steps = [r["steps"] for r in rs if r["success"]]
        mean_steps = f"{sum(steps) / len(steps):.0f}" if steps else "-"
        misses = Counter(r["first_missing"] for r in rs if not r["success"])
        common = ", ".join(f"`{m}` ({c})" for m, c in misses.most_common(2)) or "-"
        lines.append(
            f"| {suite} | {task} | {rs[0]['instruction']} | {k}/{n} | {lo:.2f}-{hi:.2f} | {mean_steps} | {common} |"
        )
        totals[suite][0] += k
        totals[suite][1] += n
    lines += ["", "| suite | successes | rate | Wilson 95% |", "|---|---|---|---|"]
    for suite, (k, n) in sorted(totals.items()):
        lo, hi = wilson(k, n)
        lines.append(f"| {suite} | {k}/{n} | {k / n:.1%} | {lo:.2f}-{hi:.2f} |")
    notes = ""
    if out.exists():  # a hand-written "## Notes" section at the end survives a rerun
        previous = out.read_text()
        if "\n## Notes" in previous:
            notes = previous[previous.index("\n## Notes"):]
    out.write_text("\n".join(lines) + "\n" + notes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=["libero_goal", "libero_goal_swap", "libero_goal_task"])
    parser.add_argument("--tasks", nargs="+", type=int, default=list(range(10)))
    parser.add_argument("--inits", type=int, default=50, help="init states 0..N-1 per task")
    parser.add_argument("--first-init", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "oracle.md")
    parser.add_argument("--jsonl", type=Path, default=None, help="per-episode results (default: OUT with .jsonl)")
    parser.add_argument("--resume", action="store_true", help="skip episodes already in the JSONL file")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    jsonl = args.jsonl or args.out.with_suffix(".jsonl")
    jobs = [
        (suite, task, init, args.seed)
        for init in range(args.first_init, args.first_init + args.inits)
        for suite in args.suites
        for task in args.tasks
    ]
    done: dict[tuple, dict] = {}
    if args.resume and jsonl.exists():
        for line in jsonl.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[_key(r)] = r
    todo = [j for j in jobs if j not in done]
    if not args.resume and jsonl.exists():
        jsonl.unlink()
    command = ".venv/bin/python scripts/oracle_report.py " + " ".join(
        a if " " not in a else repr(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    records = [done[j] for j in jobs if j in done]
    start = time.time()
    os.environ.setdefault("MUJOCO_GL", "egl")
    ctx = mp.get_context("spawn")
    with ctx.Pool(args.processes, maxtasksperchild=None) as pool, jsonl.open("a") as sink:
        for r in pool.imap_unordered(run_one, todo, chunksize=1):
            records.append(r)
            sink.write(json.dumps(r) + "\n")
            sink.flush()
            if not args.quiet:
                print(f"[{len(records)}/{len(jobs)} {time.time() - start:.0f}s] {r['suite']} task {r['task']} "
                      f"init {r['init']}: {'ok' if r['success'] else 'FAIL ' + r['first_missing']} "
                      f"({r['steps']} steps)", flush=True)
            if len(records) % 20 == 0:
                write_report(records, args.out, command, len(jobs))
    write_report(records, args.out, command, len(jobs))
    k = sum(r["success"] for r in records)
    print(f"{k}/{len(records)} successes; report in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
