"""Demonstrations for the Zetta VLA: a teacher policy run in-process on the env families.

The teacher is any :class:`~services.policy_worker.models.base.PolicyModel` (the full scripted
"oracle" when it is registered, else "scripted-pick-place", which solves the six pick-and-place
tasks of LIBERO-Goal). Only the original LIBERO-Goal tasks are used, never a LIBERO-PRO variant;
only successful episodes are kept. Episodes run in worker processes (robosuite's Python does not
scale in threads).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from services.policy_worker.vla.features import IMAGE_INPUTS, STATE_INPUTS, state_vector

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
    init_states: str = "init_state_index = seed % 50"
    processes: int = 2
    keep: str = "successful episodes only"
    image_size: int = 0
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

    def episodes(self) -> list[tuple[int, int, int]]:
        """(task, seed, init_state_index), interleaved over tasks so a time budget cuts evenly."""
        eps = [(t, self.seed_offset + s, (self.seed_offset + s) % 50)
               for s in range(self.seeds_per_task) for t in self.tasks]
        return eps[: self.max_episodes] if self.max_episodes else eps


def _worker(recipe: dict, jobs, results) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from services.env_worker.families import ResetSpec, get_family
    from services.policy_worker.models.base import load_model

    cfg = {"suite": recipe["suite"]}
    if recipe["image_size"]:
        cfg.update(cameras=["agentview"], camera_size=recipe["image_size"])
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
            states, actions, images = [], [], []
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
                states.append(state_vector({n: obs[n][None] for n in names})[0])
                if recipe["image_size"]:
                    images.append(obs[IMAGE_INPUTS[0]])
                actions.append(np.asarray(action, np.float32))
                out = slot.step(executed)
                obs = out.observation
                if out.success:
                    success = True
                if out.terminated or out.truncated:
                    break
            results.put((task, seed, init, instruction, success, np.stack(states), np.stack(actions),
                         np.stack(images) if images else None))
        except Exception as exc:  # noqa: BLE001 - a failed reset loses one demo, not the run
            results.put((task, seed, init, repr(exc), False, None, None, None))
    slot.close()
    family.close()


def collect(recipe: DataRecipe, out_path: str, log=print) -> dict:
    """Run the recipe, save an .npz of successful demos, return a summary."""
    if not recipe.teacher:
        recipe.teacher = default_teacher()
    ctx = mp.get_context("spawn")
    jobs, results = ctx.Queue(), ctx.Queue()
    episodes = recipe.episodes()
    for e in episodes:
        jobs.put(e)
    for _ in range(recipe.processes):
        jobs.put(None)
    procs = [ctx.Process(target=_worker, args=(asdict(recipe), jobs, results), daemon=True)
             for _ in range(recipe.processes)]
    for p in procs:
        p.start()
    start = time.monotonic()
    kept: list[tuple] = []
    per_task: dict[int, list[int]] = {}
    done = 0
    try:
        while done < len(episodes):
            if recipe.time_budget_s and time.monotonic() - start > recipe.time_budget_s:
                log(f"time budget {recipe.time_budget_s:.0f}s reached after {done} episodes")
                break
            try:
                r = results.get(timeout=5)
            except Exception:  # noqa: BLE001 - queue.Empty
                if not any(p.is_alive() for p in procs):
                    break
                continue
            done += 1
            task, seed, init, instruction, success, states, actions, images = r
            stats = per_task.setdefault(task, [0, 0])
            stats[1] += 1
            if success:
                stats[0] += 1
            if success or (recipe.dagger_checkpoint and r[5] is not None):
                kept.append(r)
            if done % 20 == 0:
                log(f"{done}/{len(episodes)} episodes, {len(kept)} kept, {time.monotonic() - start:.0f}s")
    finally:
        for p in procs:
            p.terminate()
            p.join(timeout=5)
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
        arrays["images"] = np.concatenate([k[7] for k in kept])
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
    return summary


def main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(description="collect teacher demonstrations on LIBERO-Goal")
    p.add_argument("--out", default="out/demos/libero_goal_state.npz")
    p.add_argument("--teacher", default="")
    p.add_argument("--tasks", default="", help="comma-separated task indices (default: all the teacher solves)")
    p.add_argument("--seeds-per-task", type=int, default=30)
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--image-size", type=int, default=0)
    p.add_argument("--time-budget", type=float, default=0.0)
    p.add_argument("--dagger-checkpoint", default="")
    p.add_argument("--beta", type=float, default=0.5)
    p.add_argument("--seed-offset", type=int, default=1000)
    p.add_argument("--action-noise", type=float, default=0.0, help="DART noise std on the executed arm action")
    p.add_argument("--execute-steps", type=int, default=1, help="DAgger: student actions run per chunk")
    p.add_argument("--max-episodes", type=int, default=0, help="run only the first N episodes of the list")
    p.add_argument("--student-noise", default=DataRecipe.student_noise, choices=("gaussian", "zero"),
                   help="DAgger: the student's flow start")
    a = p.parse_args(argv)
    teacher = a.teacher or default_teacher()
    tasks = [int(t) for t in a.tasks.split(",")] if a.tasks else (
        list(range(10)) if teacher != "scripted-pick-place" else list(PICK_PLACE_TASKS))
    recipe = DataRecipe(tasks=tasks, teacher=teacher, seeds_per_task=a.seeds_per_task, processes=a.processes,
                        image_size=a.image_size, time_budget_s=a.time_budget,
                        dagger_checkpoint=a.dagger_checkpoint, beta=a.beta, seed_offset=a.seed_offset,
                        action_noise=a.action_noise, execute_steps=a.execute_steps,
                        max_episodes=a.max_episodes, student_noise=a.student_noise)
    print(json.dumps(collect(recipe, a.out), indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
