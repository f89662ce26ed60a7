"""The fast step path produces the physics, observations and rewards of robosuite's own env.step.

Two slots of one sharing group are reset with the same episode key (so they start from the same
state, checked); one is stepped with stock ``env.step``, the other with ``FastStepper``; qpos and
qvel are compared after every one of 200 random actions (gripper toggling), on LIBERO-Goal and on
Lift. The contract is 1e-6; the implementation reproduces robosuite's arithmetic operation by
operation, so the differences are in fact exactly zero, and the tests say so when they are.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.env_worker.families import ResetSpec, get_family

CREAM_CHEESE = "put_the_cream_cheese_in_the_bowl"
TOLERANCE = 1e-6


def _actions(n: int, seed: int = 1) -> np.ndarray:
    actions = np.random.default_rng(seed).uniform(-1, 1, size=(n, 7))
    actions[:, 6] = np.where(np.arange(n) % 60 < 30, -1.0, 1.0)  # open, then close, so grasps happen
    return actions


def _compare(stock_env, fast, actions: np.ndarray) -> dict[str, float]:
    """Step both envs through ``actions``; max abs differences and the count of differing observations."""
    fast_env = fast.env
    assert np.array_equal(stock_env.sim.data.qpos, fast_env.sim.data.qpos)
    assert np.array_equal(stock_env.sim.data.qvel, fast_env.sim.data.qvel)
    worst = {"qpos": 0.0, "qvel": 0.0, "obs": 0.0, "reward": 0.0}
    for action in actions:
        obs_a, reward_a, _, _ = stock_env.step(action.copy())
        obs_b, reward_b, _, _ = fast.step(action.copy())
        worst["qpos"] = max(worst["qpos"], float(np.abs(stock_env.sim.data.qpos - fast_env.sim.data.qpos).max()))
        worst["qvel"] = max(worst["qvel"], float(np.abs(stock_env.sim.data.qvel - fast_env.sim.data.qvel).max()))
        assert obs_a.keys() == obs_b.keys()
        for name in obs_a:
            diff = np.abs(np.asarray(obs_a[name], dtype=np.float64) - np.asarray(obs_b[name], dtype=np.float64))
            worst["obs"] = max(worst["obs"], float(diff.max()) if diff.size else 0.0)
        worst["reward"] = max(worst["reward"], abs(float(reward_a) - float(reward_b)))
    return worst


def _pair(family, spec: ResetSpec):
    from services.env_worker.fast_step import FastStepper

    a, b = family.init(), family.init()
    a.reset(spec)
    b.reset(spec)
    return a, b, FastStepper(b._env)


@pytest.fixture(scope="module")
def libero():
    family = get_family("libero")({"suite": "libero_goal", "task": CREAM_CHEESE})
    yield family
    family.close()


@pytest.fixture(scope="module")
def lift():
    family = get_family("robosuite")({"env_name": "Lift"})
    yield family
    family.close()


def test_libero_goal_fast_step_matches_stock(libero) -> None:
    a, b, fast = _pair(libero, ResetSpec(task="", seed=3))
    assert fast.fast and fast._kernel is not None, fast.reason
    worst = _compare(a._env, fast, _actions(200))
    print(f"LIBERO-Goal, 200 actions: max |dqpos| {worst['qpos']:.3g}, max |dqvel| {worst['qvel']:.3g}")
    assert worst["qpos"] <= TOLERANCE and worst["qvel"] <= TOLERANCE
    assert worst["obs"] <= TOLERANCE and worst["reward"] == 0.0
    assert worst["qpos"] == worst["qvel"] == worst["obs"] == 0.0, "bit-for-bit equality regressed"
    a.close()
    b.close()


def test_lift_fast_step_matches_stock(lift) -> None:
    a, b, fast = _pair(lift, ResetSpec(task="", seed=11))
    worst = _compare(a._env, fast, _actions(200, seed=2))
    print(f"Lift, 200 actions: max |dqpos| {worst['qpos']:.3g}, max |dqvel| {worst['qvel']:.3g}")
    assert worst["qpos"] == worst["qvel"] == worst["obs"] == worst["reward"] == 0.0
    a.close()
    b.close()


def test_python_substeps_match_stock_too(lift) -> None:
    """Without the compiled kernel (numba missing) the Python substeps are exact as well."""
    from services.env_worker.fast_step import FastStepper

    a, b = lift.init(), lift.init()
    spec = ResetSpec(task="", seed=5)
    a.reset(spec)
    b.reset(spec)
    fast = FastStepper(b._env, compiled=False)
    assert fast._kernel is None
    worst = _compare(a._env, fast, _actions(40, seed=3))
    assert worst["qpos"] == worst["qvel"] == worst["obs"] == 0.0
    a.close()
    b.close()


def test_family_steps_equal_with_and_without_fast_step(lift) -> None:
    """Through the slot API: fast_step true (the default) and false give the same outcomes."""
    stock_family = get_family("robosuite")({"env_name": "Lift", "fast_step": False})
    try:
        assert lift.config["fast_step"] is True
        fast_slot, stock_slot = lift.init(), stock_family.init()
        spec = ResetSpec(task="", seed=7, init_state_index=2)
        first_fast, _ = fast_slot.reset(spec)
        first_stock, _ = stock_slot.reset(spec)
        for name in first_fast:
            assert np.array_equal(first_fast[name], first_stock[name]), name
        for t, action in enumerate(_actions(30, seed=4).astype(np.float32)):
            x, y = fast_slot.step(action), stock_slot.step(action)
            assert (x.reward, x.success, x.terminated, x.truncated) == (y.reward, y.success, y.terminated, y.truncated)
            for name in x.observation:
                assert np.array_equal(x.observation[name], y.observation[name]), f"{name} at step {t}"
        from services.env_worker.fast_step import FastStepper, StockStepper

        assert isinstance(fast_slot._env._zetta_stepper, FastStepper)
        assert isinstance(stock_slot._env._zetta_stepper, StockStepper)
        fast_slot.close()
        stock_slot.close()
    finally:
        stock_family.close()


def test_check_contact_has_stocks_truth_table(lift) -> None:
    """The vectorized check_contact agrees with robosuite's loop for names, lists, models and None."""
    from robosuite.environments.base import MujocoEnv

    slot = lift.init()
    slot.reset(ResetSpec(task="", seed=1))
    env = slot._env
    gripper = env.robots[0].gripper
    queries = [
        (gripper.important_geoms["left_finger"], env.cube.contact_geoms),
        (gripper, env.cube),
        ("cube_g0", None),
        (env.cube, None),
        (gripper.important_geoms["right_fingerpad"], "cube_g0"),
        (["no_such_geom"], None),
        ("table_collision", env.cube),
    ]
    seen = set()
    for action in _actions(60, seed=5):
        action[2] = -1.0  # push down so the fingers and the cube touch the table and each other
        slot.step(action.astype(np.float32))
        for g1, g2 in queries:
            fast = env.check_contact(g1, g2)
            assert fast == MujocoEnv.check_contact(env, g1, g2), (g1, g2)
            seen.add(fast)
    assert seen == {True, False}
    slot.close()


def test_unsupported_env_falls_back_to_env_step() -> None:
    from services.env_worker.fast_step import StockStepper, make_stepper

    class Custom:  # an environment whose step the fast path does not know
        robots: list = []

        def step(self, action):
            return {}, 0.0, False, {}

        def _pre_action(self, action, policy_step=False):
            pass

    env = Custom()
    stepper = make_stepper(env, fast=True)
    assert isinstance(stepper, StockStepper) and "overrides" in stepper.reason
    assert make_stepper(env, fast=True) is stepper  # built once per env
    assert stepper.step(np.zeros(7)) == ({}, 0.0, False, {})
