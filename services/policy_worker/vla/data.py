"""Demonstrations for the Zetta VLA: a teacher policy run in-process on the env families.

The teacher is any :class:`~services.policy_worker.models.base.PolicyModel` (the full scripted
"oracle" when it is registered, else "scripted-pick-place", which solves the six pick-and-place
tasks of LIBERO-Goal). Demos come from LIBERO's own suites (libero_goal by default; libero_90's
scenes show the same objects elsewhere), never from a LIBERO-PRO variant, which is what the policy
is evaluated on; only successful episodes are kept. Episodes run in worker processes (robosuite's
Python does not scale in threads).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from services.common.policies import BENCHMARK_INITS, SAMPLED_LAYOUTS
from services.common.progress import add_progress_option, progress
from services.policy_worker.vla.features import IMAGE_INPUTS, STATE_INPUTS, image_env_config, parse_cameras, state_vector
from services.policy_worker.vla.procs import still_running

#: The six pick-and-place tasks of libero_goal that "scripted-pick-place" solves.
PICK_PLACE_TASKS = (1, 2, 4, 6, 8, 9)


def default_teacher() -> str:
    from services.policy_worker.models.base import FACTORIES

    return "oracle" if "oracle" in FACTORIES else "scripted-pick-place"


@dataclass
class DataRecipe:
    """Everything needed to regenerate the demonstration set (stored next to the checkpoint)."""

    suite: str = "libero_goal"
    tasks: list[int] = field(default_factory=lambda: list(range(10)))
    teacher: str = ""
    seeds_per_task: int = 30
    seed_offset: int = 1000
    #: BENCHMARK_INITS or SAMPLED_LAYOUTS: sampled layouts come from the same placement regions as
    #: the benchmark's 50 fixed states without being any of them (those stay for evaluation).
    init_states: str = BENCHMARK_INITS
    processes: int = 2
    keep: str = "successful episodes only"
    image_size: int = 0
    #: Image recipes: the camera tensors recorded at each frame (the VLA's ``cameras``), stored
    #: as ``images`` uint8 [frames, cameras, H, W, 3].
    cameras: list[str] = field(default_factory=lambda: list(IMAGE_INPUTS))
    #: Image recipes render one camera frame every this many steps, the policy-call frequency
    #: of the served image VLA (it runs ``execute_steps`` actions of a chunk per call): the
    #: frames a policy is trained on are the ones it will be shown. States and actions are kept
    #: at every step (chunk targets need them).
    image_every: int = 2
    time_budget_s: float = 0.0
    #: DAgger rounds: a checkpoint whose policy drives the episode (each step: the teacher's action
    #: with probability ``beta``, else the policy's); every visited state is labelled with the
    #: teacher's action and kept, failed episodes included (the labels are the teacher's).
    dagger_checkpoint: str = ""
    beta: float = 0.5
    #: DART-style perturbation: Gaussian noise of this std is added to the executed arm action
    #: (not the gripper, not the recorded label), so demos cover the states just off the
    #: teacher's path that a learned policy drifts into, each labelled with the teacher's correction.
    action_noise: float = 0.0
    #: DAgger: the student's chunk runs this many actions before it is asked again (as in evaluation).
    execute_steps: int = 1
    #: Run only the first N episodes of :meth:`episodes` (0: all); a deterministic cut, unlike a time budget.
    max_episodes: int = 0
    #: DAgger student's flow start ("zero" or "gaussian", see ZettaVLAPolicy): "gaussian", as
    #: served, so the student visits the states it will visit when deployed.
    student_noise: str = "gaussian"
    #: Frames multisampled (MuJoCo's 4x offscreen buffer) or single-sampled, about 2x cheaper on
    #: the CPU rasterizer; served sessions of the checkpoint render the same way.
    antialias: bool = False

    def episodes(self) -> list[tuple[int, int, int]]:
        """(task, seed, init_state_index), interleaved over tasks so a time budget cuts evenly."""
        from services.env_worker.families import SAMPLED_LAYOUT

        check_training_suite(self.suite)
        if self.init_states not in (BENCHMARK_INITS, SAMPLED_LAYOUTS):
            raise ValueError(f"init_states {self.init_states!r}: use {BENCHMARK_INITS!r} or {SAMPLED_LAYOUTS!r}")
        sampled = self.init_states == SAMPLED_LAYOUTS
        eps = [(t, self.seed_offset + s, SAMPLED_LAYOUT if sampled else (self.seed_offset + s) % 50)
               for s in range(self.seeds_per_task) for t in self.tasks]
        return eps[: self.max_episodes] if self.max_episodes else eps


def check_training_suite(suite: str) -> None:
    """Refuse a LIBERO-PRO variant: its layouts and instructions are the evaluation's, and a
    policy that has seen them says nothing about generalising to them."""
    from services.env_worker.families import is_libero_pro_variant

    if is_libero_pro_variant(suite):
        raise ValueError(f"suite {suite!r} is a LIBERO-PRO variant, which the policy is evaluated on; "
                         "train on a LIBERO suite such as libero_goal or libero_90")


def _worker(recipe: dict, jobs, results) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from services.env_worker.families import ResetSpec, get_family
    from services.policy_worker.models.base import load_model

    cfg = {"suite": recipe["suite"]}
    if recipe["image_size"]:
        cfg.update(image_env_config(recipe["image_size"], antialias=recipe.get("antialias", True),
                                    cameras=tuple(recipe.get("cameras", IMAGE_INPUTS))))
    every = max(1, int(recipe.get("image_every", 1))) if recipe["image_size"] else 0
    family = get_family("libero")(get_family("libero").canonical_config(cfg))
    slot = family.init()
    teacher = load_model(recipe["teacher"])
    student = None
    if recipe.get("dagger_checkpoint"):
        import torch

        from services.policy_worker.vla.policy import ZettaVLAPolicy

        torch.set_num_threads(1)
        student = ZettaVLAPolicy(recipe["dagger_checkpoint"], noise=recipe["student_noise"])
    names = [n for n, _ in STATE_INPUTS]
    cameras = list(recipe.get("cameras", IMAGE_INPUTS))
    student_names = [sp.name for sp in student.input_specs()] if student is not None else []
    execute = max(1, int(recipe.get("execute_steps", 1)))
    while True:
        job = jobs.get()
        if job is None:
            break
        task, seed, init = job
        rng = np.random.default_rng(seed)  # per episode: the noise and the beta mixing replay
        try:
            obs, instruction = slot.reset(ResetSpec(task=str(task), seed=seed, init_state_index=init))
            states, actions, images, frame_steps = [], [], [], []
            success = False
            queued: list[np.ndarray] = []  # the rest of the student's chunk, as served policies run it
            teacher_turn = True
            while True:
                batch = {k: v[None] for k, v in obs.items()}
                action = teacher.infer(batch, [instruction])[0, 0]
                executed = action
                if student is not None:
                    if not queued:  # who drives is drawn once per chunk of ``execute`` steps
                        teacher_turn = rng.random() < recipe["beta"]
                        chunk = student.infer({n: obs[n][None] for n in student_names}, [instruction])[0]
                        queued = list(chunk[:execute])
                    student_action = queued.pop(0)
                    if not teacher_turn:
                        executed = student_action
                elif recipe.get("action_noise"):
                    executed = action.copy()
                    executed[:6] = np.clip(executed[:6] + rng.normal(0.0, recipe["action_noise"], 6), -1.0, 1.0)
                if every and len(states) % every == 0:
                    frame_steps.append(len(states))
                    images.append(np.stack([obs[c] for c in cameras]))
                states.append(state_vector({n: obs[n][None] for n in names})[0])
                actions.append(np.asarray(action, np.float32))
                out = slot.step(executed, render=bool(every) and len(states) % every == 0)
                obs = out.observation
                if out.success:
                    success = True
                if out.terminated or out.truncated:
                    break
            results.put((task, seed, init, instruction, success, np.stack(states), np.stack(actions),
                         np.stack(images) if images else None, np.asarray(frame_steps, np.int64)))
        except Exception as exc:  # noqa: BLE001 - a failed reset loses one demo, not the run
            results.put((task, seed, init, repr(exc), False, None, None, None, None))
    slot.close()
    family.close()


#: Recipe fields that say how many episodes run and how, not what one (task, seed) episode holds.
_COUNT_FIELDS = ("seeds_per_task", "max_episodes", "processes", "time_budget_s")


def episode_key(recipe: DataRecipe) -> dict:
    """What one stored episode depends on: a resumed run may ask for more or fewer episodes
    (or other processes) and keep the ones it has, never mix teachers, noise or image settings."""
    return {k: v for k, v in asdict(recipe).items() if k not in _COUNT_FIELDS}


def _shard_dir(out_path: str) -> str:
    return out_path + ".parts"


def _save_episode(shard_dir: str, r: tuple) -> None:
    """One finished episode as its own file, written atomically: a cut-off run resumes from these."""
    task, seed, init, instruction, success, states, actions, images, frames = r
    arrays: dict[str, np.ndarray] = {"meta": np.array([task, seed, init, int(success)], np.int64),
                                     "instruction": np.array(instruction)}
    if states is not None:
        arrays.update(states=states, actions=actions)
        if images is not None:
            arrays.update(images=images, frame_steps=frames)
    tmp = os.path.join(shard_dir, f".{task}_{seed}.tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, os.path.join(shard_dir, f"{task}_{seed}.npz"))


def _load_episode(path: str) -> tuple:
    with np.load(path, allow_pickle=False) as z:
        task, seed, init, success = (int(v) for v in z["meta"])
        get = lambda k: z[k] if k in z else None  # noqa: E731 - absent for failed resets
        return (task, seed, init, str(z["instruction"]), bool(success), get("states"), get("actions"),
                get("images"), get("frame_steps"))


def collect(recipe: DataRecipe, out_path: str, log=print) -> dict:
    """Run the recipe, save an .npz of successful demos, return a summary.

    Every finished episode is stored on its own under ``<out_path>.parts`` first, so a run that
    is cut off (a session ending, a crash) resumes with the episodes it has not run yet; the
    parts are removed once the assembled file is written.
    """
    if not recipe.teacher:
        recipe.teacher = default_teacher()
    if recipe.image_size and recipe.dagger_checkpoint and recipe.image_every != recipe.execute_steps:
        raise ValueError(f"DAgger with an image student needs image_every == execute_steps "
                         f"({recipe.image_every} != {recipe.execute_steps}): the student reads a frame per call")
    shard_dir = _shard_dir(out_path)
    os.makedirs(shard_dir, exist_ok=True)
    recipe_file = os.path.join(shard_dir, "recipe.json")
    key = episode_key(recipe)
    if os.path.exists(recipe_file) and json.loads(open(recipe_file).read()) != key:
        raise ValueError(f"{shard_dir} holds episodes of another recipe; remove it or choose another --out")
    with open(recipe_file, "w") as f:
        json.dump(key, f)
    episodes = recipe.episodes()
    results_by_key = {}
    for e in episodes:
        part = os.path.join(shard_dir, f"{e[0]}_{e[1]}.npz")
        if os.path.exists(part):
            results_by_key[(e[0], e[1])] = _load_episode(part)
    todo = [e for e in episodes if (e[0], e[1]) not in results_by_key]
    if results_by_key:
        log(f"resuming: {len(results_by_key)} of {len(episodes)} episodes already in {shard_dir}")
    start = time.monotonic()
    if todo:
        ctx = mp.get_context("spawn")
        results = ctx.Queue()
        # Each process runs its own share of the tasks: a family keeps one warm env (with its
        # renderer, about 0.5 GB) per task it has run, so sharing every task costs every process.
        queues = [ctx.Queue() for _ in range(recipe.processes)]
        for e in todo:
            queues[recipe.tasks.index(e[0]) % recipe.processes].put(e)
        for q in queues:
            q.put(None)
        procs = [ctx.Process(target=_worker, args=(asdict(recipe), q, results), daemon=True) for q in queues]
        for p in procs:
            p.start()
        done = 0
        bar = progress(total=len(episodes), desc="demos", initial=len(results_by_key))
        try:
            while done < len(todo):
                if recipe.time_budget_s and time.monotonic() - start > recipe.time_budget_s:
                    log(f"time budget {recipe.time_budget_s:.0f}s reached after {done} episodes")
                    break
                try:
                    r = results.get(timeout=5)
                except Exception:  # noqa: BLE001 - queue.Empty
                    if not still_running(procs, "a demo process", len(todo) - done,
                                         f"the finished ones stay in {shard_dir}: rerun the same command to continue"):
                        break
                    continue
                done += 1
                bar.update()
                _save_episode(shard_dir, r)
                results_by_key[(r[0], r[1])] = r
                if done % 20 == 0:
                    log(f"{len(results_by_key)}/{len(episodes)} episodes, {time.monotonic() - start:.0f}s")
        finally:
            bar.close()
            for p in procs:
                p.terminate()
                p.join(timeout=5)
    ordered = [results_by_key[(e[0], e[1])] for e in episodes if (e[0], e[1]) in results_by_key]
    per_task: dict[int, list[int]] = {}
    kept: list[tuple] = []
    for r in ordered:
        stats = per_task.setdefault(r[0], [0, 0])
        stats[1] += 1
        stats[0] += int(r[4])
        if r[4] or (recipe.dagger_checkpoint and r[5] is not None):
            kept.append(r)
    done = len(ordered)
    ep_len = np.array([len(k[6]) for k in kept], dtype=np.int64)
    arrays = {
        "states": np.concatenate([k[5] for k in kept]).astype(np.float32),
        "actions": np.concatenate([k[6] for k in kept]).astype(np.float32),
        "episode_lengths": ep_len,
        "episode_task": np.array([k[0] for k in kept], dtype=np.int64),
        "episode_seed": np.array([k[1] for k in kept], dtype=np.int64),
        "instructions": np.array([k[3] for k in kept]),
    }
    if recipe.image_size:
        offsets = np.concatenate([[0], np.cumsum(ep_len)[:-1]])
        arrays["images"] = np.concatenate([k[7] for k in kept])
        #: Global transition index of each image (frames are taken every ``image_every`` steps).
        arrays["image_steps"] = np.concatenate([k[8] + o for k, o in zip(kept, offsets)])
    os.makedirs(os.path.dirname(os.path.abspath(out_path)), exist_ok=True)
    np.savez_compressed(out_path, **arrays)
    summary = {
        "recipe": asdict(recipe),
        "episodes_run": done,
        "demos_kept": len(kept),
        "transitions": int(ep_len.sum()),
        "per_task_success": {str(t): f"{s}/{n}" for t, (s, n) in sorted(per_task.items())},
        "seconds": round(time.monotonic() - start, 1),
    }
    with open(out_path + ".json", "w") as f:
        json.dump(summary, f, indent=2)
    shutil.rmtree(shard_dir, ignore_errors=True)
    return summary


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="collect teacher demonstrations on a LIBERO suite")
    p.add_argument("--out", default="out/demos/libero_goal_state.npz")
    p.add_argument("--teacher", default="")
    p.add_argument("--suite", default=DataRecipe.suite,
                   help="LIBERO suite the demos come from (libero_goal, libero_90, ...; never a LIBERO-PRO variant)")
    p.add_argument("--tasks", default="", help="comma-separated task indices (default on libero_goal: all the "
                   "teacher solves; required on other suites)")
    p.add_argument("--seeds-per-task", type=int, default=30)
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--image-size", type=int, default=0)
    p.add_argument("--cameras", type=parse_cameras, default=",".join(IMAGE_INPUTS),
                   help="image recipes: the camera tensors recorded at each frame, comma-separated")
    p.add_argument("--image-every", type=int, default=DataRecipe.image_every,
                   help="render a frame every N steps (the served policy's execute_steps)")
    p.add_argument("--time-budget", type=float, default=0.0)
    p.add_argument("--dagger-checkpoint", default="")
    p.add_argument("--beta", type=float, default=0.5)
    p.add_argument("--seed-offset", type=int, default=1000)
    p.add_argument("--sampled-layouts", action="store_true",
                   help="start each episode from the layout sampled from its seed, not a benchmark init state")
    p.add_argument("--action-noise", type=float, default=0.0, help="DART noise std on the executed arm action")
    p.add_argument("--execute-steps", type=int, default=1, help="DAgger: student actions run per chunk")
    p.add_argument("--max-episodes", type=int, default=0, help="run only the first N episodes of the list")
    add_progress_option(p)
    p.add_argument("--student-noise", default=DataRecipe.student_noise, choices=("gaussian", "zero"),
                   help="DAgger: the student's flow start")
    a = p.parse_args(argv)
    try:
        check_training_suite(a.suite)
    except ValueError as exc:
        p.error(str(exc))
    if a.suite != DataRecipe.suite and not a.tasks:
        p.error(f"--tasks is required on {a.suite} (the default task list is libero_goal's)")
    teacher = a.teacher or default_teacher()
    tasks = [int(t) for t in a.tasks.split(",")] if a.tasks else (
        list(range(10)) if teacher != "scripted-pick-place" else list(PICK_PLACE_TASKS))
    recipe = DataRecipe(suite=a.suite, tasks=tasks, teacher=teacher, seeds_per_task=a.seeds_per_task, processes=a.processes,
                        image_size=a.image_size, cameras=list(a.cameras),
                        image_every=a.image_every, time_budget_s=a.time_budget,
                        dagger_checkpoint=a.dagger_checkpoint, beta=a.beta, seed_offset=a.seed_offset,
                        action_noise=a.action_noise, execute_steps=a.execute_steps,
                        max_episodes=a.max_episodes, student_noise=a.student_noise,
                        init_states=SAMPLED_LAYOUTS if a.sampled_layouts else BENCHMARK_INITS)
    print(json.dumps(collect(recipe, a.out), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
