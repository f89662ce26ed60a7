"""zetta.gym.ZettaEnv over a real stack: a gateway session as a gymnasium.Env."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import zetta.gym  # registers zetta/Session-v0
from tests.conftest import LIBERO_CREAM
from zetta import SyncGateway, ZettaError
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import types_pb2


def test_session_env_passes_the_checker_and_replays_keys(stack: LocalStack) -> None:
    env = gymnasium.make("zetta/Session-v0", gateway=stack.gateway_address, env_family="libero",
                         env_config=LIBERO_CREAM)
    inner = env.unwrapped
    try:
        check_env(inner, skip_render_check=True)
        assert inner.action_space.shape == (7,) and np.all(inner.action_space.high == 1.0), "bounds from the wire"
        obs, info = env.reset(seed=4, options={"init_state_index": 7})
        assert inner.observation_space.contains(obs) and info["instruction"] == "put the cream cheese in the bowl"
        actions = np.random.default_rng(1).uniform(-1, 1, (4, 7)).astype(np.float32)
        first = [env.step(a)[0] for a in actions]
        env.reset(seed=4, options={"init_state_index": 7})
        again = [env.step(a)[0] for a in actions]
        for a, b in zip(first, again, strict=True):
            for name in a:
                np.testing.assert_array_equal(a[name], b[name], err_msg=name)
        _, _, _, _, info = env.step(np.zeros(7, np.float32))
        assert info["episode_step"] == 5 and info["executed_actions"].shape[-1] == 7
        with pytest.raises(ZettaError) as err:
            env.step(np.zeros(3, np.float32))  # wrong shape: the worker answers INVALID_ARGUMENT
        assert "INVALID_ARGUMENT" in str(err.value.code)
        session_id = inner.session_id
    finally:
        env.close()
    with SyncGateway(stack.gateway_address) as gw:
        state = {s.session_id: s.state for s in gw.list_sessions()}
    assert state.get(session_id, types_pb2.SESSION_STATE_TERMINATED) == types_pb2.SESSION_STATE_TERMINATED


def test_session_env_refuses_rgb_array_without_cameras_and_closes_its_session(stack: LocalStack) -> None:
    with SyncGateway(stack.gateway_address) as gw:
        before = {s.session_id for s in gw.list_sessions() if s.state == types_pb2.SESSION_STATE_RUNNING}
        with pytest.raises(ValueError, match="needs a camera"):
            zetta.gym.ZettaEnv(gw, "libero", LIBERO_CREAM, render_mode="rgb_array")
        after = {s.session_id for s in gw.list_sessions() if s.state == types_pb2.SESSION_STATE_RUNNING}
    assert after == before, "the refused env's session was closed"
