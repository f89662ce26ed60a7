"""Success of the scripted oracle per suite, task and init state: docs/results/oracle.json and .md.

Runs the oracle (services/policy_worker/models/oracle.py) in-process on the libero family, one
episode per (suite, task, init state), spread over worker processes (each process keeps one slot
per suite, so a task switch only swaps warm envs). Every episode is judged by the environment's own
success predicate; failures are reported with their first missing milestone m*.

    python scripts/oracle_report.py --suites libero_goal libero_goal_swap libero_goal_task \
        --inits 50 --processes 2

Per-episode results are appended to a JSONL file as they finish (``--jsonl``), so a long run that
is cut short still leaves its data; ``--resume`` skips episodes already in that file. The results
file (``--results``, default docs/results/oracle.json) and its page are written every 20 episodes
and at the end; docs/oracle.md says what the oracle does and how to read the page.
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

from services.common.progress import add_progress_option, progress  # noqa: E402 - after the path set-up above
from services.common.provenance import RESULTS_DIR, page_header, provenance, write_results  # noqa: E402
from zetta_wire.stats import wilson  # noqa: E402


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


def page(doc: dict) -> str:
    """docs/results/oracle.md from a results file: per task and per suite, with Wilson 95 % intervals."""
    records = doc["episodes"]
    by_task: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for r in records:
        by_task[(r["suite"], r["task"])].append(r)
    lines = [
        page_header("oracle", "Scripted oracle: success per task", doc),
        f"Episodes run: {len(records)} of {doc['planned']} planned; seed {doc['seed']}, one episode per init state, "
        "LIBERO's step budget. What the oracle does: [docs/oracle.md](../oracle.md).",
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
    return "\n".join(lines) + "\n"


def write_report(records: list[dict], results: Path, command: str, planned: int, seed: int) -> None:
    """The results file (every episode, sorted by key) and its page beside it."""
    doc = {**provenance(command, ROOT), "planned": planned, "seed": seed, "episodes": sorted(records, key=_key)}
    write_results("oracle", doc, page(doc), results.parent)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=["libero_goal", "libero_goal_swap", "libero_goal_task"])
    parser.add_argument("--tasks", nargs="+", type=int, default=list(range(10)))
    parser.add_argument("--inits", type=int, default=50, help="init states 0..N-1 per task")
    parser.add_argument("--first-init", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--results", type=Path, default=RESULTS_DIR / "oracle.json",
                        help="the results file; its page oracle.md is written beside it")
    parser.add_argument("--jsonl", type=Path, default=ROOT / "out" / "oracle" / "episodes.jsonl",
                        help="per-episode results as they finish (what --resume reads)")
    parser.add_argument("--resume", action="store_true", help="skip episodes already in the JSONL file")
    parser.add_argument("--quiet", action="store_true", help="no line per episode")
    add_progress_option(parser)
    args = parser.parse_args(argv)
    jsonl = args.jsonl
    jsonl.parent.mkdir(parents=True, exist_ok=True)
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
    command = "python scripts/oracle_report.py " + " ".join(
        a if " " not in a else repr(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    records = [done[j] for j in jobs if j in done]
    start = time.time()
    os.environ.setdefault("MUJOCO_GL", "egl")
    ctx = mp.get_context("spawn")
    with ctx.Pool(args.processes, maxtasksperchild=None) as pool, jsonl.open("a") as sink:
        for r in progress(pool.imap_unordered(run_one, todo, chunksize=1), total=len(todo), desc="oracle"):
            records.append(r)
            sink.write(json.dumps(r) + "\n")
            sink.flush()
            if not args.quiet:
                print(f"[{len(records)}/{len(jobs)} {time.time() - start:.0f}s] {r['suite']} task {r['task']} "
                      f"init {r['init']}: {'ok' if r['success'] else 'FAIL ' + r['first_missing']} "
                      f"({r['steps']} steps)", flush=True)
            if len(records) % 20 == 0:
                write_report(records, args.results, command, len(jobs), args.seed)
    write_report(records, args.results, command, len(jobs), args.seed)
    k = sum(r["success"] for r in records)
    print(f"{k}/{len(records)} successes; results in {args.results} and {args.results.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
