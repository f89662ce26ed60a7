"""Any env family as a gymnasium.Env (services/ops/gym_env.py, zetta/gym.py).

The in-process env runs a real LIBERO slot; Gymnasium's own checker validates the API, and the
tests check what the wrapper promises on top: spaces from the family's schema, episode keys
through reset options, privileged signals left out on request, milestones in info.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env

from services.ops.gym_env import LocalFamilyEnv
from zetta.gym import space_for

CONFIG = {"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl", "max_steps": 40}


@pytest.fixture(scope="module")
def env():
    e = LocalFamilyEnv("libero", CONFIG)
    yield e
    e.close()


def test_space_for_each_kind_of_tensor() -> None:
    assert space_for("bool", (3,)) == spaces.MultiBinary((3,))
    box = space_for("uint8", (8, 8, 3))
    assert isinstance(box, spaces.Box) and box.low.min() == 0 and box.high.max() == 255
    action = space_for("float32", (7,), -1.0, 1.0)
    assert action.dtype == np.float32 and np.all(action.low == -1) and np.all(action.high == 1)
    assert np.isinf(space_for("float64", (2,)).high).all()
    with pytest.raises(ValueError, match="free dimension"):
        space_for("float32", (-1, 7))


def test_gymnasium_env_checker_passes(env) -> None:
    check_env(env, skip_render_check=True)


def test_spaces_follow_the_family_schema_and_observations_lie_in_them(env) -> None:
    schema = env._family.obs_schema()
    assert set(env.observation_space.spaces) == set(schema)
    assert env.action_space.shape == (7,) and np.all(env.action_space.low == -1.0)
    obs, first = env.reset(seed=3, options={"init_state_index": 5})
    assert env.observation_space.contains(obs)
    assert first["instruction"] == "put the cream cheese in the bowl"
    assert first["milestone_names"][0] == "reached(cream_cheese_1)"
    obs, reward, terminated, truncated, info = env.step(np.zeros(7, np.float32))
    assert env.observation_space.contains(obs) and info["episode_step"] == 1
    assert not terminated and not truncated and not info["success"]
    assert info["milestones_reached"] == [] and info["first_missing_milestone"] == first["milestone_names"][0]


def test_a_reset_key_replays_bit_for_bit(env) -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (5, 7)).astype(np.float32)

    def run() -> list[dict[str, np.ndarray]]:
        out = [env.reset(seed=11, options={"init_state_index": 2})[0]]
        out += [env.step(a)[0] for a in actions]
        return out

    first, second = run(), run()
    for a, b in zip(first, second, strict=True):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_episode_ends_by_the_step_budget(env) -> None:
    env.reset(seed=0)
    for _ in range(CONFIG["max_steps"]):
        _, _, terminated, truncated, _ = env.step(np.zeros(7, np.float32))
        if terminated or truncated:
            break
    assert truncated and env._slot.episode_step == CONFIG["max_steps"]


def test_privileged_signals_left_out_on_request_and_bad_options_refused() -> None:
    e = gymnasium.make("zetta/Local-v0", env_family="libero", env_config=CONFIG, include_privileged=False)
    try:
        names = set(e.observation_space.spaces)
        assert "robot0_eef_pos" in names
        assert not names & {"task_object_pos", "object_state", "phi_grasp"}
        obs, _ = e.reset(seed=0)
        assert set(obs) == names
        with pytest.raises(ValueError, match="unknown reset options"):
            e.reset(options={"init_state": 1})
    finally:
        e.close()
    with pytest.raises(ValueError, match="needs a camera"):
        LocalFamilyEnv("libero", CONFIG, render_mode="rgb_array")
