"""Run the same episode keys several times through one local stack and report which keys diverge.

  python scripts/check_replays.py                                   # libero_goal tasks 0-9, seeds 48-49, 3 passes
  python scripts/check_replays.py --env-workers 1 --slots 4 --passes 3
  python scripts/check_replays.py --suite libero_goal_task --tasks 8 --seeds 31,32,33
  python scripts/check_replays.py --passes 1 --against /tmp/zetta-replays-XXXX/pass0   # across two stacks

Each pass runs every key as the evolver does (services/evolver/rollout.py: step-recorded rollouts,
`--concurrency` in flight), into a store of its own. A key whose end-effector trajectory differs
from the first pass's is printed with both lengths and the first env step where they part. The
evolver relies on a key giving the same episode (docs/evolution.md, "Replays"); this script checks it.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS  # noqa: E402 - after the path set-up above
from services.evolver.evolve import env_config  # noqa: E402
from services.evolver.rollout import RunConfig, Runner  # noqa: E402
from services.evolver.stack import endpoints  # noqa: E402
from services.evolver.store import DEV, EpisodeKey, RolloutStore  # noqa: E402
from services.evolver.trace import Trace  # noqa: E402


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x.strip()]


def first_divergence(a: Trace, b: Trace) -> int | None:
    """The first env step where two traces' end-effector positions differ, or None when identical."""
    ea, eb = a.step_obs["robot0_eef_pos"], b.step_obs["robot0_eef_pos"]
    n = min(len(ea), len(eb))
    differs = np.flatnonzero(np.abs(ea[:n] - eb[:n]).max(axis=1) > 0)
    if len(differs):
        return int(differs[0])
    return None if len(ea) == len(eb) else n


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--suite", default="libero_goal")
    p.add_argument("--tasks", default="0,1,2,3,4,5,6,7,8,9", help="comma-separated task indices")
    p.add_argument("--seeds", default="49,48", help="comma-separated seeds (init state = seed %% 50)")
    p.add_argument("--passes", type=int, default=3)
    p.add_argument("--model", default=DEFAULT_POLICY)
    p.add_argument("--env-workers", type=int, default=2)
    p.add_argument("--slots", type=int, default=4)
    p.add_argument("--concurrency", type=int, default=4)
    p.add_argument("--against", default="", metavar="STORE",
                   help="also compare with a rollout store an earlier run wrote (another stack, other processes), "
                        "e.g. the pass0 folder of an earlier invocation")
    a = p.parse_args(argv)
    keys = [EpisodeKey(a.suite, str(t), s, "", "replay") for t in _ints(a.tasks) for s in _ints(a.seeds)]
    earlier: dict[tuple[str, int], tuple[int, bool, Trace]] = {}
    if a.against:  # read before the stack starts: a wrong folder fails at once
        if not (Path(a.against) / "index.sqlite").is_file():
            p.error(f"{a.against} is not a rollout store (no index.sqlite in it)")
        store = RolloutStore(a.against)
        found = {(k.task, k.seed): store.get(k) for k in keys}
        missing = sorted(key for key, r in found.items() if r is None)
        if missing:
            p.error(f"{a.against} holds no rollout of {len(missing)} of these keys, e.g. task/seed {missing[0]}")
        earlier = {key: (r.steps, r.success, store.trace(r)) for key, r in found.items() if r is not None}
    work = Path(tempfile.mkdtemp(prefix="zetta-replays-"))
    passes: list[dict[tuple[str, int], tuple[int, bool, Trace]]] = []
    with endpoints(None, None, a.model, a.env_workers, a.slots, work / "stack", False) as ep:
        run = RunConfig(gateway=ep.gateway, model=a.model, execute_steps=EXECUTE_STEPS, concurrency=a.concurrency)
        for i in range(a.passes):
            store = RolloutStore(work / f"pass{i}")
            for k in keys:
                store.assign_seeds(k.suite, k.task, DEV, [k.seed])
            rows = asyncio.run(Runner(store, run, env_config(a.suite, run)).run(keys))
            passes.append({(r.task, r.seed): (r.steps, r.success, store.trace(r)) for r in rows})
            print(f"pass {i}: {sum(v[1] for v in passes[-1].values())}/{len(keys)} succeeded", flush=True)
    if earlier:
        passes.insert(0, earlier)
        print(f"earlier run {a.against}: {sum(v[1] for v in earlier.values())}/{len(keys)} succeeded "
              "(compared as pass 0; the passes of this run follow it)", flush=True)
    diverged = 0
    for key in sorted(passes[0]):
        for i, other in enumerate(passes[1:], start=1):
            step = first_divergence(passes[0][key][2], other[key][2])
            if step is not None:
                diverged += 1
                print(f"{a.suite}/{key[0]}/{key[1]}: pass 0 {passes[0][key][0]} steps, pass {i} {other[key][0]}; "
                      f"first differing env step {step}")
    print(f"{diverged} divergent replays of {len(keys) * (len(passes) - 1)} (stores under {work})")
    return 1 if diverged else 0


if __name__ == "__main__":
    sys.exit(main())
