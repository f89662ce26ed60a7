"""Closed-loop evaluation of a served policy on LIBERO suites, in-process, in worker processes.

Each worker builds the family once and runs (task, seed, init state) episodes with the policy
loaded in the same process (no gRPC: this measures the policy, not the stack). The policy acts
on the observation, its chunk's first ``execute_steps`` actions run, then it is asked again.
Results are one JSON row per episode; :func:`table` renders per-task rates with Wilson 95 %
intervals.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS, checkpoint_dir, policy_env_config
from services.common.progress import add_progress_option, progress
from services.policy_worker.vla.procs import still_running
from zetta_wire.stats import wilson


def _worker(model: str, env: dict, suite: str, execute_steps: int, jobs, results) -> None:
    os.environ.update(env)
    import numpy as np
    import torch

    torch.set_num_threads(1)
    from services.common.specs import render_config
    from services.env_worker.families import ResetSpec, get_family
    from services.policy_worker.models.base import load_model

    policy = load_model(model)
    specs = policy.input_specs()
    names = [s.name for s in specs]
    # An image policy: the cameras it reads, rendered as its training frames were.
    config = {"suite": suite, **(policy_env_config(model) or render_config(specs))}
    fam_cls = get_family("libero")
    family = fam_cls(fam_cls.canonical_config(config))
    slot = family.init()
    while True:
        job = jobs.get()
        if job is None:
            break
        task, seed, init = job
        t0 = time.monotonic()
        try:
            obs, instruction = slot.reset(ResetSpec(task=str(task), seed=seed, init_state_index=init))
            success, steps, done = False, 0, False
            while not done:
                chunk = policy.infer({n: obs[n][None] for n in names}, [instruction])[0]
                actions = chunk[: max(1, execute_steps)]
                for i, action in enumerate(actions):  # frames only for the next policy call
                    out = slot.step(np.asarray(action, np.float32), render=i == len(actions) - 1)
                    obs, steps = out.observation, steps + 1
                    if out.success or out.terminated or out.truncated:
                        success, done = out.success, True
                        break
            results.put({"suite": suite, "task": task, "seed": seed, "init_state_index": init,
                         "instruction": instruction, "success": bool(success), "steps": steps,
                         "first_missing_milestone": "" if success else slot.first_missing_milestone(),
                         "seconds": round(time.monotonic() - t0, 2)})
        except Exception as exc:  # noqa: BLE001 - reported as an invalid episode, not a failure
            results.put({"suite": suite, "task": task, "seed": seed, "init_state_index": init, "error": repr(exc)})
    slot.close()


def evaluate(model: str, suite: str, tasks: list[int], seeds: list[int], out_path: str, processes: int = 2,
             execute_steps: int = 4, env: dict | None = None, log=print, sampled: bool = False) -> list[dict]:
    """Run the episodes in ``processes`` workers, appending one JSON row each to ``out_path``.

    Seed s starts from benchmark init state s % 50, or with ``sampled`` from the layout LIBERO's
    placement sampler draws from s: none of the 50 fixed states, so a policy can be compared on
    them without spending the states a published split holds.

    Rows already in ``out_path`` for this model, suite, execute_steps, env and init state count as
    done, so an evaluation that was cut off continues where it stopped. Raises when a worker
    process dies with episodes left (killed for memory, say), instead of moving on with a partial suite."""
    from services.env_worker.families import SAMPLED_LAYOUT

    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    # Each process runs its own share of the tasks: a family keeps a warm env (with its renderer,
    # about 0.5 GB) per task it has run, so every process running every task costs ~5 GB each.
    queues = [ctx.Queue() for _ in range(processes)]
    episodes = [(t, s, SAMPLED_LAYOUT if sampled else s % 50) for s in seeds for t in tasks]
    done = done_rows(out_path, model, suite, execute_steps, env or {})
    rows = [done[e] for e in episodes if e in done]
    if rows:
        log(f"{suite}: {len(rows)} of {len(episodes)} episodes already in {out_path}")
    for e in episodes:
        if e not in done:
            queues[tasks.index(e[0]) % processes].put(e)
    for q in queues:
        q.put(None)
    procs = [ctx.Process(target=_worker, args=(model, env or {}, suite, execute_steps, q, results), daemon=True)
             for q in queues]
    for p in procs:
        p.start()
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    with open(out_path, "a") as f, progress(total=len(episodes), desc=suite, initial=len(rows)) as bar:
        while len(rows) < len(episodes):
            try:
                r = results.get(timeout=10)
            except Exception:  # noqa: BLE001 - queue.Empty
                if not still_running(procs, f"{suite}: an evaluation process", len(episodes) - len(rows),
                                     "rerun the same command to continue"):
                    break
                continue
            r.update(model=model, execute_steps=execute_steps, env=env or {})
            rows.append(r)
            bar.update()
            f.write(json.dumps(r) + "\n")
            f.flush()
            if len(rows) % 10 == 0:
                ok = sum(x.get("success", False) for x in rows)
                log(f"{suite}: {len(rows)}/{len(episodes)} episodes, {ok} successes")
    for p in procs:
        p.join(timeout=10)
        if p.is_alive():
            p.terminate()
    return rows


def done_rows(path: str, model: str, suite: str, execute_steps: int, env: dict) -> dict[tuple[int, int, int], dict]:
    """Valid rows of an earlier run with the same settings, by (task, seed, init state index)."""
    if not Path(path).exists():
        return {}
    out = {}
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        r = json.loads(line)
        if ("error" not in r and r.get("model") == model and r.get("suite") == suite
                and r.get("execute_steps") == execute_steps and r.get("env", {}) == env):
            out[(r["task"], r["seed"], r.get("init_state_index", r["seed"] % 50))] = r
    return out


def table(rows: list[dict], task_names: dict[str, list[str]] | None = None) -> str:
    """Markdown: per suite and task, successes/episodes, rate, Wilson 95 % interval, seeds."""
    lines = ["| suite | task | successes / episodes | rate | Wilson 95% | seeds |", "|---|---|---|---|---|---|"]
    by: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        if "error" in r:
            continue
        by.setdefault((r["suite"], r["task"]), []).append(r)
    suites = sorted({k[0] for k in by})
    for suite in suites:
        total_s = total_n = 0
        for (s, t), rs in sorted(by.items()):
            if s != suite:
                continue
            k, n = sum(r["success"] for r in rs), len(rs)
            total_s, total_n = total_s + k, total_n + n
            lo, hi = wilson(k, n)
            seeds = sorted(r["seed"] for r in rs)
            name = (task_names or {}).get(suite, [])
            label = f"{t} {name[t]}" if t < len(name) else f"{t} {rs[0].get('instruction', '')}".strip()
            lines.append(f"| {suite} | {label} | {k}/{n} | {k / n:.0%} | {lo:.0%}-{hi:.0%} | {seeds[0]}-{seeds[-1]} |")
        lo, hi = wilson(total_s, total_n)
        lines.append(f"| **{suite}** | **all** | **{total_s}/{total_n}** | **{total_s / max(total_n, 1):.0%}** | "
                     f"**{lo:.0%}-{hi:.0%}** | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="evaluate a policy on LIBERO suites")
    p.add_argument("--model", default=DEFAULT_POLICY)
    p.add_argument("--suites", default="libero_goal,libero_goal_task,libero_goal_swap")
    p.add_argument("--tasks", default="0,1,2,3,4,5,6,7,8,9")
    p.add_argument("--seeds", type=int, default=10, help="episodes per task: seeds offset..offset+N-1, init state = seed %% 50 (or sampled, --sampled-layouts)")
    p.add_argument("--seed-offset", type=int, default=0)
    p.add_argument("--sampled-layouts", action="store_true",
                   help="start each episode from the layout sampled from its seed, none of the benchmark's "
                        "50 init states (a comparison that spends no published split)")
    p.add_argument("--execute-steps", type=int, default=EXECUTE_STEPS,
                   help=f"actions of each chunk run per policy call (default {EXECUTE_STEPS})")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--quantize", default="", help="ZETTA_VLA_QUANTIZE for the policy (e.g. w8a8)")
    p.add_argument("--checkpoint", default="")
    p.add_argument("--out", default="out/eval/episodes.jsonl")
    add_progress_option(p)
    p.add_argument("--report", default="", help="print the table of an existing episodes .jsonl and stop")
    p.add_argument("--results", default="", help="also write the results file (e.g. docs/results/vla.json) "
                   "and its page (docs/results/vla.md); VLA models only")
    a = p.parse_args(argv)
    if a.results and a.sampled_layouts:
        p.error("--results publishes the benchmark's init states; --sampled-layouts is for comparisons that "
                "publish nothing")
    if a.report:
        print(table([json.loads(line) for line in Path(a.report).read_text().splitlines() if line.strip()]))
        return 0
    env = {}
    if a.quantize:
        env["ZETTA_VLA_QUANTIZE"] = a.quantize
    if a.checkpoint:
        env["ZETTA_VLA_CHECKPOINT" if a.model == DEFAULT_POLICY else "ZETTA_STATE_BASELINE_CHECKPOINT"] = a.checkpoint
    tasks = [int(t) for t in a.tasks.split(",")]
    seeds = list(range(a.seed_offset, a.seed_offset + a.seeds))
    rows = []
    start = time.monotonic()
    for suite in a.suites.split(","):
        rows += evaluate(a.model, suite, tasks, seeds, a.out, a.processes, a.execute_steps, env,
                         sampled=a.sampled_layouts)
    print(table(rows))
    if a.results:
        from services.policy_worker.vla.results import main as render_page
        from services.policy_worker.vla.results import write_results

        checkpoint = a.checkpoint or str(checkpoint_dir(a.model))
        if Path(checkpoint).resolve().is_relative_to(Path.cwd().resolve()):
            checkpoint = str(Path(checkpoint).resolve().relative_to(Path.cwd().resolve()))
        write_results(a.results, rows, model=a.model, checkpoint=checkpoint, execute_steps=a.execute_steps,
                      command=["zetta", "eval-policy", *(argv if argv is not None else sys.argv[1:])],
                      wall_s=time.monotonic() - start)
        render_page([a.results])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
