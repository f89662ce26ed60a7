"""The evolver's rollout over the real stack records every env step of its trace (ResetSpec.record_steps):
what its critic replays read, step by step as the runtime's critics did."""

from __future__ import annotations

import numpy as np

from services.evolver.replay import frames
from services.evolver.rollout import RunConfig, run_one
from services.evolver.store import EpisodeKey
from services.evolver.trace import Trace
from tests.conftest import LIFT
from zetta import Gateway


async def test_a_rollout_trace_holds_every_step_and_its_call_rate_frames(gw: Gateway) -> None:
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 30})
    key = EpisodeKey(suite="robosuite", task="", seed=0, harness="", purpose="profile")
    out = await run_one(gw, group.ids[0], key, RunConfig(gateway="", model="scripted-pick-place", execute_steps=4))
    await group.close()
    trace = Trace.from_bytes(out.trace.to_bytes())
    assert out.steps == 30 and trace.steps == 31 and len(trace.actions) == 30
    assert trace.frame_step[0] == 0 and trace.frame_step[-1] == 30 and np.all(np.diff(trace.frame_step) > 0)
    assert not any(k.endswith("_image") for k in trace.step_obs)
    for k, step in enumerate(trace.frame_step):  # a call-rate frame is the step it was taken at
        np.testing.assert_array_equal(trace.obs["robot0_eef_pos"][k], trace.step_obs["robot0_eef_pos"][step])
    eef = trace.step_obs["robot0_eef_pos"]
    assert np.all(np.linalg.norm(np.diff(eef, axis=0), axis=1) > 0), "a step repeated its predecessor's observation"
    assert [f.step for f in frames(trace)] == list(range(31))
