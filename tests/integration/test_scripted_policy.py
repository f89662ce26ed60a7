"""The scripted privileged-state policy solves real episodes through the family interface.

This is the end-to-end check that the privileged task state (object, target, grasp) is wired
correctly: if any of it is wrong, a pick-and-place driven only by it fails.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.env_worker.families import ResetSpec, get_family
from services.policy_worker.models.scripted import ScriptedPickPlacePolicy


def _run_episode(slot, policy: ScriptedPickPlacePolicy, spec: ResetSpec) -> bool:
    obs, instruction = slot.reset(spec)
    while True:
        action = policy.infer({k: v[None] for k, v in obs.items()}, [instruction])[0, 0]
        outcome = slot.step(action)
        obs = outcome.observation
        if outcome.terminated or outcome.truncated:
            return outcome.success


@pytest.mark.slow
def test_scripted_policy_puts_cream_cheese_in_bowl() -> None:
    family = get_family("libero")({"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"})
    slot = family.init()
    policy = ScriptedPickPlacePolicy()
    try:
        successes = [_run_episode(slot, policy, ResetSpec("", seed=0, init_state_index=k)) for k in range(3)]
    finally:
        slot.close()
        family.close()
    assert sum(successes) >= 2, f"successes per init state: {successes}"


@pytest.mark.slow
def test_scripted_policy_lifts_cube() -> None:
    family = get_family("robosuite")({"env_name": "Lift", "max_steps": 200})
    slot = family.init()
    try:
        assert _run_episode(slot, ScriptedPickPlacePolicy(), ResetSpec("Lift", seed=0))
    finally:
        slot.close()
        family.close()


def test_infer_is_batched_and_chunked() -> None:
    """One call serves many sessions; a chunk repeats the action, since the policy is stateless."""
    policy = ScriptedPickPlacePolicy(chunk_size=4)
    batch = {spec.name: np.zeros((5, *spec.shape), dtype=spec.dtype) for spec in policy.input_specs()}
    batch["task_object_bbox"][:] = [-0.02, 0.08, 0.9, 0.02, 0.12, 0.94]
    batch["task_target_bbox"][:] = [0.05, -0.05, 0.9, 0.15, 0.05, 0.92]
    batch["robot0_eef_pos"][:] = [0.0, 0.0, 1.1]
    batch["robot0_gripper_qpos"][:] = [0.04, -0.04]
    actions = policy.infer(batch, [""] * 5)
    assert actions.shape == (5, 4, 7) and actions.dtype == np.float32
    assert np.all(actions == actions[:1, :1]) and np.all(np.abs(actions) <= 1.0)
