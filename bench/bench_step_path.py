"""Where an env worker's CPU per step goes on the slot path, and what a change saves, side by side.

Three nested paths run the same recorded actions from the same reset states (LIBERO-Goal
"put_the_cream_cheese_in_the_bowl", state only, fast step), a fourth runs random actions for
comparison, and each is timed in thread CPU time per executed action (resets not counted: the
stack and the bench's `limit` rows pay the same ones):

stepper  ``FastStepper.step`` alone: the physics kernel plus robosuite's own per-step Python (what
         `zetta bench rollout`'s `limit` row runs)
slot     ``slot.step(action, render=False)``: the stepper plus the canonical observation, milestones,
         physical signals and the success check, every step
lazy     ``slot.step(action, observe=...)`` observing only after every 8th action: milestones, success
         and the signals' state every step, the observation where a chunked policy reads it (the
         `limit-obs` row)
chunk    ``EnvWorkerServicer._execute`` on chunks of 8 actions: the lazy slot steps plus what the env
         worker adds on a slot thread (metrics, the StepResult of the chunk)
random   ``FastStepper.step`` on fixed random actions (what the `limit` rows stepped before they
         replayed the policy's), as many per episode as the policy took

The actions are the shipped policy's own (``privileged-state-baseline`` run in-process on each episode key
once, then replayed), because a policy that grasps makes contact-rich, costlier physics than random
actions do. ``--against REV`` also measures another revision of the code (exported with
``git archive`` to a temporary directory; the working tree is not touched) in the same run: child
processes alternate between the two trees, each figure is the median over ``--repeats`` children,
so load that drifts on a shared machine weighs on both alike. Every child also hashes each replayed
step's observation, reward, success and info (untimed): the report says whether all runs of both
trees agree bit for bit, so a speed-up that changes behaviour shows. It also checks, on this
tree, that the observations the chunk path returns and every step's reward, success, info and
milestones are those of the slot path that observes every step.

    python bench/bench_step_path.py                    # this tree, 3 repeats (about 1 minute)
    python bench/bench_step_path.py --against HEAD~1   # this tree against the previous commit
    python bench/bench_step_path.py --parts            # also time the parts of a slot step (this tree)
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from trees import export  # this folder (bench/) is the script's first import path

ROOT = Path(__file__).resolve().parents[1]
TASK = "put_the_cream_cheese_in_the_bowl"
PATHS = ("stepper", "slot", "lazy", "chunk", "random")
CHUNK = 8


def _import_root(root: Path) -> None:
    """Import ``services`` and ``zetta`` from ``root`` (this tree or an exported revision), and the
    bench's own helpers (``bench.bench_sweep``) from this tree in either case."""
    sys.path[:0] = [str(root), str(root / "clients" / "python")]
    sys.path.append(str(ROOT))


def _families() -> Any:
    """The env families' API of the tree imported: their public module, or ``families.base`` in a
    revision from before the API had one (measured with ``--against``)."""
    import services.env_worker.families as api

    if hasattr(api, "ResetSpec"):
        return api
    return importlib.import_module("services.env_worker.families.base")


def _decode_observation() -> Callable[..., Any]:
    """The codec's observation decoder: ``zetta.codec`` in older revisions, ``zetta_wire`` since."""
    try:
        return importlib.import_module("zetta.codec").decode_observation
    except ImportError:
        return importlib.import_module("zetta_wire.codec").decode_observation


def _slot(max_steps: int) -> tuple[Any, Any]:
    from bench.bench_sweep import env_config, quiet_fds

    with quiet_fds():
        from services.env_worker.fast_step import warm_up

        families = _families()
        families.select_gl_backend()
        warm_up()
        family = families.get_family("libero")(env_config(TASK, max_steps))
        return family, family.init()


def record(out: Path, episodes: int, max_steps: int) -> None:
    """Run the state baseline policy in-process on episode keys (seed 0, init state k) and save its actions."""
    os.environ.setdefault("ZETTA_TORCH_THREADS", "1")
    from bench.bench_sweep import quiet_fds, random_replays
    from services.common.policies import PRIVILEGED_BASELINE
    from services.policy_worker.models.base import load_model

    ResetSpec = _families().ResetSpec
    family, slot = _slot(max_steps)
    with quiet_fds():  # a state policy: these slots render no camera, and its actions are deterministic
        policy = load_model(PRIVILEGED_BASELINE)

    actions = {"random": random_replays(1, max_steps, 1)[0][1]}
    for k in range(episodes):
        obs, instruction = slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=k))
        done: list[np.ndarray] = []
        while slot.episode_step < max_steps:
            outcome = None
            for action in policy.infer({n: v[None] for n, v in obs.items()}, [instruction])[0]:
                outcome = slot.step(action, render=False)
                done.append(action)
                if outcome.terminated or outcome.truncated:
                    break
            assert outcome is not None
            obs = outcome.observation
            if outcome.terminated or outcome.truncated:
                break
        actions[str(k)] = np.stack(done)
    np.savez(out, **actions)
    slot.close()
    family.close()


def measure(actions_file: Path, max_steps: int, parts: bool) -> dict[str, Any]:
    """CPU ms per action of each path over every recorded episode (and, with ``parts``, of the parts
    of a slot step, timed by wrappers that add a little of their own)."""
    from concurrent.futures import ThreadPoolExecutor

    ResetSpec = _families().ResetSpec
    from services.env_worker.fast_step import make_stepper
    from services.env_worker.servicer import EnvWorkerServicer
    from services.env_worker.slots import BoundSlot, Episode

    family, slot = _slot(max_steps)
    recorded = np.load(actions_file)
    bound = BoundSlot("bench", 0, family, "libero", ThreadPoolExecutor(max_workers=1))
    bound.env = slot

    def run(path: str, actions: np.ndarray) -> float:
        if path in ("stepper", "random"):
            stepper = make_stepper(slot._env, True)
            wide = (actions if path == "stepper" else recorded["random"][:len(actions)]).astype(np.float64)
            t = time.thread_time()
            for a in wide:
                stepper.step(a)
        elif path == "slot":
            t = time.thread_time()
            for a in actions:
                slot.step(a, render=False)
        elif path == "lazy":
            lazy = "observe" in inspect.signature(slot.step).parameters  # a tree before it observes every step
            t = time.thread_time()
            for i, a in enumerate(actions):
                slot.step(a, observe=i % CHUNK == CHUNK - 1) if lazy else slot.step(a, render=False)
        else:
            bound.episode = Episode("bench", TASK, max_steps)
            t = time.thread_time()
            for i in range(0, len(actions), CHUNK):
                EnvWorkerServicer._execute(bound, actions[i:i + CHUNK])
        return time.thread_time() - t

    cpu: Counter[str] = Counter()
    steps = 0
    keys = sorted((k for k in recorded.files if k != "random"), key=int)
    for key in keys:  # every key settled once, so the measured resets all restore the same snapshot
        slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
    for r, key in enumerate(keys):
        actions = recorded[key]
        for path in PATHS[r % len(PATHS):] + PATHS[:r % len(PATHS)]:  # rotating order
            slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
            cpu[path] += run(path, actions)
        steps += len(actions)
    out: dict[str, Any] = {p: 1000.0 * cpu[p] / steps for p in PATHS}
    out["digest"] = _digest(slot, recorded, keys)
    out["chunk_matches_slot"] = _chunk_matches_slot(slot, bound, recorded, keys)
    if parts:
        out["parts"] = _parts(slot, recorded, keys)
    return out


def _digest(slot: Any, recorded: Any, keys: list[str]) -> str:
    """A hash of every observation tensor, reward, success and info of the replayed episodes: two
    trees that agree on it behave the same on these steps, bit for bit."""
    import hashlib

    ResetSpec = _families().ResetSpec

    h = hashlib.blake2b(digest_size=16)
    for key in keys:
        obs, _ = slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
        for a in recorded[key]:
            for name in sorted(obs):
                h.update(name.encode())
                h.update(np.ascontiguousarray(obs[name]).tobytes())
            outcome = slot.step(a, render=False)
            obs = outcome.observation
            h.update(repr((outcome.reward, outcome.success, outcome.terminated, sorted(outcome.info.items()))).encode())
    return h.hexdigest()


def _chunk_matches_slot(slot: Any, bound: Any, recorded: Any, keys: list[str]) -> bool:
    """Whether the env worker's chunk path (observation built only after a chunk's last action)
    returns the observation, reward, success, info and milestones of the path that observes every
    step, on every chunk of the replayed episodes."""
    ResetSpec = _families().ResetSpec
    from services.env_worker.servicer import EnvWorkerServicer
    from services.env_worker.slots import Episode
    decode_observation = _decode_observation()

    for key in keys:
        actions = recorded[key]
        slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
        full = []
        for i in range(0, len(actions), CHUNK):
            outcomes = [slot.step(a, render=False) for a in actions[i:i + CHUNK]]
            full.append((outcomes[-1].observation, sum(o.reward for o in outcomes), outcomes[-1].success,
                         outcomes[-1].info, slot.milestones_reached()))
        slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
        bound.episode = Episode("bench", TASK, len(actions) + 1)
        for i, (obs, reward, success, info, reached) in zip(range(0, len(actions), CHUNK), full):
            result = EnvWorkerServicer._execute(bound, actions[i:i + CHUNK])
            got = decode_observation(result.observation)
            if (sorted(got) != sorted(obs) or any(not np.array_equal(got[n], obs[n]) for n in obs)
                    or result.reward != reward or result.success != success or dict(result.info) != info
                    or list(result.milestones_reached) != reached):
                return False
    return True


def _parts(slot: Any, recorded: Any, keys: list[str]) -> dict[str, float]:
    """Thread CPU microseconds per step of the named parts of a slot step (wrapped functions), the
    observation built after every chunk's last action as the env worker does."""
    from services.env_worker import signals
    from services.env_worker.families import episode, libero, task_state
    ResetSpec = _families().ResetSpec
    from services.env_worker.fast_step import FastStepper
    from services.env_worker.milestones import MilestoneTracker

    spent: Counter[str] = Counter()
    labels: list[str] = []

    def wrap(owner: Any, name: str, label: str) -> None:
        fn = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            t = time.thread_time_ns()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[label] += time.thread_time_ns() - t

        setattr(owner, name, timed)

    env_cls = type(slot._env)
    for owner, name, label in (
        (episode.EpisodeSlot, "step", "slot.step"),
        (FastStepper, "step", "  FastStepper.step"),
        (FastStepper, "_compiled_substeps", "    substeps (kernel, observables)"),
        (env_cls, "_post_action", "    _post_action (reward)"),
        (env_cls, "_get_observations", "    _get_observations"),
        (task_state.TaskState, "advance", "  TaskState.advance (every step)"),
        (signals, "read_contacts", "    read_contacts (both)"),
        (MilestoneTracker, "update", "    MilestoneTracker.update"),
        (task_state.TaskState, "holds", "      TaskState.holds (goal predicates)"),
        (task_state.TaskState, "bbox", "      TaskState.bbox"),
        (signals, "touches", "    signals.touches (all callers)"),
        (signals.SignalTracker, "track", "    SignalTracker.track"),
        (libero._LiberoSlot, "_canonical", "  _canonical (observed steps)"),
        (task_state.TaskState, "observation", "    TaskState.observation"),
        (task_state.TaskState, "_stage_tensors", "      _stage_tensors"),
        (task_state.TaskState, "_signals", "      _signals"),
        (env_cls, "_check_success", "  _check_success (every call)"),
        (episode, "normalize_observation", "  normalize_observation"),
    ):
        if hasattr(owner, name):
            wrap(owner, name, label)
            labels.append(label)
    steps = 0
    for key in keys:
        slot.reset(ResetSpec(task=TASK, seed=0, init_state_index=int(key)))
        for i, a in enumerate(recorded[key]):
            slot.step(a, observe=i % CHUNK == CHUNK - 1)  # as the env worker steps a chunk
            steps += 1
    return {label: spent[label] / steps / 1000.0 for label in labels}


def child(args: argparse.Namespace) -> None:
    _import_root(Path(args.child))
    print(json.dumps(measure(Path(args.actions), args.max_steps, args.parts)))


def run_child(root: Path, actions: Path, max_steps: int, parts: bool) -> dict[str, Any]:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(root), "--actions", str(actions),
           "--max-steps", str(max_steps)] + (["--parts"] if parts else [])
    done = subprocess.run(cmd, cwd=root, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--against", default="", metavar="REV", help="also measure this git revision, interleaved")
    p.add_argument("--repeats", type=int, default=3, help="child processes per tree (default 3); medians")
    p.add_argument("--episodes", type=int, default=4, help="recorded episode keys (default 4)")
    p.add_argument("--max-steps", type=int, default=120, help="step budget of an episode (default 120)")
    p.add_argument("--parts", action="store_true", help="also time the parts of a slot step (this tree)")
    p.add_argument("--child", default="", help=argparse.SUPPRESS)
    p.add_argument("--actions", default="", help=argparse.SUPPRESS)
    p.add_argument("--record", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        return child(args)
    if args.record:
        _import_root(ROOT)
        return record(Path(args.record), args.episodes, args.max_steps)
    log: Callable[[str], None] = lambda msg: print(msg, flush=True)  # noqa: E731
    with tempfile.TemporaryDirectory(prefix="zetta-step-path-") as tmp:
        actions = Path(tmp) / "actions.npz"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--record", str(actions), "--episodes",
                        str(args.episodes), "--max-steps", str(args.max_steps)], cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL)
        recorded = np.load(actions)
        lengths = [len(recorded[k]) for k in recorded.files if k != "random"]
        log(f"recorded the policy's actions on {len(lengths)} keys ({sum(lengths)} steps) in "
            f"{time.perf_counter() - t0:.0f} s; load average {os.getloadavg()[0]:.1f}")
        trees = {"this tree": ROOT}
        if args.against:
            trees[args.against] = export(args.against, Path(tmp))
        results: dict[str, list[dict[str, Any]]] = {name: [] for name in trees}
        for r in range(args.repeats):
            for name in (list(trees) if r % 2 == 0 else list(trees)[::-1]):
                results[name].append(run_child(trees[name], actions, args.max_steps, args.parts and name == "this tree"))
                log(f"  repeat {r + 1}/{args.repeats} {name}: " + ", ".join(
                    f"{k} {v:.3f}" for k, v in results[name][-1].items() if k in PATHS) + " CPU ms/step")
    medians = {name: {k: statistics.median(run[k] for run in runs) for k in PATHS} for name, runs in results.items()}
    names = list(trees)
    digests = {run["digest"] for runs in results.values() for run in runs}
    print("\nobservations, rewards and success of every replayed step: "
          + ("identical in every run" + (" of both trees" if len(names) == 2 else "") if len(digests) == 1
             else f"DIFFER ({len(digests)} distinct digests: {', '.join(sorted(digests))})"))
    chunked = [run.get("chunk_matches_slot") for run in results["this tree"]]
    print("chunk path (observation after each chunk's last action) against observing every step: "
          + ("the same observations, rewards, success, info and milestones" if all(chunked) else "DIFFERENT"))
    print(f"CPU ms per action (thread time, resets excluded), median of {args.repeats}; load average "
          f"{os.getloadavg()[0]:.1f} at the end")
    header = f"{'path':<28}" + "".join(f"{n:>14}" for n in names) + (f"{'change':>10}" if len(names) == 2 else "")
    print(header)
    rows = [(p, {n: medians[n][p] for n in names}) for p in PATHS]
    rows += [("slot - stepper (obs)", {n: medians[n]["slot"] - medians[n]["stepper"] for n in names}),
             ("lazy - stepper (obs/chunk)", {n: medians[n]["lazy"] - medians[n]["stepper"] for n in names}),
             ("chunk - lazy (env worker)", {n: medians[n]["chunk"] - medians[n]["lazy"] for n in names}),
             ("stepper / chunk", {n: medians[n]["stepper"] / medians[n]["chunk"] for n in names}),
             ("random / stepper", {n: medians[n]["random"] / medians[n]["stepper"] for n in names})]
    for label, values in rows:
        line = f"{label:<28}" + "".join(f"{values[n]:>14.3f}" for n in names)
        if len(names) == 2 and values[names[1]]:
            line += f"{100 * (values[names[0]] / values[names[1]] - 1):>+9.1f}%"
        print(line)
    if args.parts:
        parts = [run["parts"] for run in results["this tree"]]
        print("\nparts of a slot step observed after every chunk of 8, this tree (us per step, median; wrappers "
              "add ~1 us each):")
        for label in parts[0]:
            print(f"  {label:<40}{statistics.median(p[label] for p in parts):>9.1f}")


if __name__ == "__main__":
    main()
