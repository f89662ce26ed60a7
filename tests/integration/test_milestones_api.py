"""Milestones and physical signals through the whole stack (gateway -> env worker -> client).

ResetResult names the episode's milestones M, every StepResult carries the first missing milestone
so far, EpisodeSummary ends with M, the milestones observed and m*; the observation carries mu_t
and phi_t tensors declared (privileged) in the session's schema.
"""

from __future__ import annotations

import numpy as np

from tests.conftest import LIFT
from zetta import Gateway

LIFT_MILESTONES = ["reached(cube)", "grasped(cube)", "lifted(cube)", "up(cube)"]


async def test_milestones_and_signals_over_grpc(gw: Gateway) -> None:
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 5})
    schema = {s.name: s for s in group.infos[0].observation_schema}
    for name in ("milestones", "milestones_reached", "task_stage", "phi_grasp", "phi_contact_force", "phi_eef_motion"):
        assert schema[name].privileged, name
    reset = (await group.reset(task="", seed=1))[0]
    assert reset.milestone_names == LIFT_MILESTONES
    step = (await group.action_step([np.array([0, 0, 0.5, 0, 0, 0, -1], np.float32)]))[0]
    assert step.first_missing_milestone == "reached(cube)" and step.milestones_reached == []
    assert step.observation["phi_eef_motion"][2] > 0, "commanded upward motion"
    # An episode too short to reach the cube: m* is the first milestone.
    summary = (await group.run_episode(task="", seed=2, max_steps=3))[0]
    assert summary.milestone_names == LIFT_MILESTONES
    assert not summary.success and summary.first_missing_milestone == "reached(cube)"
    await group.close()
