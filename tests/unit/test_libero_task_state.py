"""LIBERO task state on the real simulator: episode keys, milestones from BDDL goals, m*, success.

* every LIBERO-Goal task of every PRO variant (_task, _swap, _lan, _object) yields a non-empty
  milestone sequence whose predicates resolve to real bodies, sites and joints;
* constructed failures (the oracle with its gripper forced open; the oracle stopped after the lift)
  end with the expected first missing milestone m*;
* success is the environment's own ``_check_success`` and nothing else;
* an episode key replays bit for bit, also on another slot and after other episodes;
* a sampled layout (``SAMPLED_LAYOUT``) is keyed by the seed and is none of the benchmark's states.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.env_worker.families import SAMPLED_LAYOUT, ConfigError, ResetSpec, canonical_config_key, get_family
from services.common.milestone_kinds import MAX_MILESTONES, STAGE_KINDS
from services.policy_worker.models.oracle import OraclePolicy

GOAL_SUITES = ["libero_goal", "libero_goal_task", "libero_goal_swap", "libero_goal_lan", "libero_goal_object"]
CREAM_CHEESE = "put_the_cream_cheese_in_the_bowl"


def _check_plan(slot, obs: dict[str, np.ndarray]) -> None:
    state = slot._state
    names = slot.milestone_names()
    assert names and len(names) == len(set(names)) <= MAX_MILESTONES
    model = slot._env.sim.model._model
    for stage in state.plan.stages:
        goal = [m.name for m in state.plan.milestones if m.kind == "goal" and state.plan.stages[m.stage] is stage]
        assert goal == [f"{stage.predicate[0]}({','.join(stage.predicate[1:])})"], "the goal milestone is the predicate"
        for arg in stage.predicate[1:]:
            part = state.parts[arg]
            assert (part.body_id is not None and part.body_id > 0) or (part.site_id is not None and part.site_id >= 0), arg
        if stage.template == "articulate":
            art = state.articulations[stage.subject]
            assert art.handle_geom in art.moving_geoms and model.jnt_type[art.joint] in (2, 3)
            assert stage.predicate[0] in art.targets
    assert obs["milestones"].shape == (MAX_MILESTONES,) and not obs["milestones"][len(names):].any()
    assert obs["task_stage"].sum() == 1.0
    assert obs["task_object_bbox"].any(), "the stage names something to move"
    assert slot.first_missing_milestone() in names


def _check_goal(state, model) -> None:  # type: ignore[no-untyped-def]
    assert state.plan.names and len(set(state.plan.names)) == len(state.plan.names) <= MAX_MILESTONES
    for stage in state.plan.stages:
        for arg in stage.predicate[1:]:
            part = state.parts[arg]
            assert (part.body_id is not None and part.body_id > 0) or (part.site_id is not None and part.site_id >= 0), arg
        if stage.template == "articulate":
            art = state.articulations[stage.subject]
            assert art.handle_geom in art.moving_geoms and model.jnt_type[art.joint] in (2, 3)
            assert stage.predicate[0] in art.targets


def test_milestones_of_every_goal_task_and_variant_resolve() -> None:
    """Each suite's ten BDDL goals, expanded and resolved against the live scene; libero_goal itself
    through a real reset of every task, the variants in the first task's scene where it holds the
    goal's objects (else after a reset of that task)."""
    from libero.libero.envs import bddl_utils

    from services.env_worker.families import task_state
    from services.env_worker.families.libero import _bddl_path, _suite

    for suite in GOAL_SUITES:
        family = get_family("libero")({"suite": suite})
        slot = family.init()
        try:
            if suite == "libero_goal":
                for task in range(10):
                    obs, _ = slot.reset(ResetSpec(str(task), seed=0, init_state_index=0))
                    _check_plan(slot, obs)
                continue
            slot.reset(ResetSpec("0"))
            for task in range(10):
                goal = bddl_utils.robosuite_parse_problem(_bddl_path(_suite(suite).get_task(task)))["goal_state"]
                env = slot._env
                names = {n for predicate in goal for n in predicate[1:]}
                if not names <= set(env.objects_dict) | set(env.fixtures_dict) | set(env.object_sites_dict):
                    obs, _ = slot.reset(ResetSpec(str(task)))  # this task has other objects
                    _check_plan(slot, obs)
                    env = slot._env
                _check_goal(task_state.for_libero(env, goal), env.sim.model._model)
        finally:
            slot.close()
            family.close()


@pytest.mark.slow
@pytest.mark.parametrize("suite", GOAL_SUITES[1:])
def test_milestones_of_every_variant_task_after_reset(suite: str) -> None:
    family = get_family("libero")({"suite": suite})
    slot = family.init()
    try:
        for task in range(10):
            obs, _ = slot.reset(ResetSpec(str(task), seed=0, init_state_index=0))
            _check_plan(slot, obs)
    finally:
        slot.close()
        family.close()


@pytest.mark.slow
@pytest.mark.parametrize("suite", ["libero_10", "libero_10_task", "libero_10_swap", "libero_10_lan", "libero_10_object"])
def test_milestones_of_every_long_task_resolve(suite: str) -> None:
    family = get_family("libero")({"suite": suite})
    slot = family.init()
    try:
        for task in range(10):
            obs, _ = slot.reset(ResetSpec(str(task), seed=0, init_state_index=0))
            _check_plan(slot, obs)
    finally:
        slot.close()
        family.close()


@pytest.fixture(scope="module")
def cheese():
    family = get_family("libero")({"suite": "libero_goal", "task": CREAM_CHEESE, "max_steps": 120})
    slot = family.init()
    yield slot
    slot.close()
    family.close()


def _run(slot, spec: ResetSpec, control) -> tuple[bool, list[str]]:  # type: ignore[no-untyped-def]
    """Run an episode with ``control(obs, action) -> action`` wrapped around the oracle."""
    policy = OraclePolicy()
    obs, _ = slot.reset(spec)
    while True:
        action = policy.act({k: np.asarray(v, dtype=np.float64) for k, v in obs.items()})
        outcome = slot.step(control(slot, action).astype(np.float32))
        obs = outcome.observation
        if outcome.terminated or outcome.truncated:
            return outcome.success, slot.milestones_reached()


def test_oracle_succeeds_and_m_star_is_empty(cheese) -> None:
    success, reached = _run(cheese, ResetSpec("", seed=0, init_state_index=0), lambda slot, a: a)
    assert success and cheese.first_missing_milestone() == ""
    assert reached[:5] == cheese.milestone_names()[:5]


def test_m_star_gripper_forced_open(cheese) -> None:
    def never_close(slot, action):  # type: ignore[no-untyped-def]
        action[6] = -1.0
        return action

    success, reached = _run(cheese, ResetSpec("", seed=0, init_state_index=1), never_close)
    assert not success
    assert "reached(cream_cheese_1)" in reached
    assert cheese.first_missing_milestone() == "grasped(cream_cheese_1)"


def test_m_star_stopped_after_lifting(cheese) -> None:
    def freeze_once_lifted(slot, action):  # type: ignore[no-untyped-def]
        if "lifted(cream_cheese_1)" in slot.milestones_reached():
            return np.array([0, 0, 0, 0, 0, 0, 1.0])  # hold it where it is
        return action

    success, _ = _run(cheese, ResetSpec("", seed=0, init_state_index=2), freeze_once_lifted)
    assert not success
    assert cheese.first_missing_milestone() == "above(cream_cheese_1,akita_black_bowl_1)"


def test_success_is_only_the_environment_predicate(cheese) -> None:
    cheese.reset(ResetSpec("", seed=0, init_state_index=0))
    env = cheese._env
    try:
        env._check_success = lambda: True
        assert cheese.step(np.zeros(7, np.float32)).success, "the env says success: it is a success"
        cheese.reset(ResetSpec("", seed=0, init_state_index=0))
        env._check_success = lambda: False
        env._eval_predicate = lambda predicate: True  # every goal predicate "holds"
        outcome = cheese.step(np.zeros(7, np.float32))
        assert not outcome.success and not outcome.terminated
        assert outcome.info["goal_predicates_met"] == outcome.info["goal_predicates"] == 1.0
    finally:
        del env._check_success, env._eval_predicate  # back to the class methods


def test_observing_only_after_each_chunk_changes_nothing_observed(cheese) -> None:
    """Steps taken with observe=False (inside an action chunk) keep milestones, success, reward and
    the signals' state as observing every step does: each observation built afterwards, after a
    chunk or when the episode ends inside one, is the same bit for bit, through a grasp and lift."""
    spec = ResetSpec("", seed=0, init_state_index=3)
    policy = OraclePolicy()
    obs, _ = cheese.reset(spec)
    actions, full = [], []
    while True:
        action = policy.act({k: np.asarray(v, dtype=np.float64) for k, v in obs.items()}).astype(np.float32)
        outcome = cheese.step(action)
        obs = outcome.observation
        actions.append(action)
        full.append((outcome, cheese.milestones_reached(), cheese.first_missing_milestone()))
        if outcome.terminated or outcome.truncated:
            break
    assert outcome.success and max(o.observation["phi_grasp"][0] for o, _, _ in full) == 1.0
    cheese.reset(spec)
    chunk = 8
    for t, action in enumerate(actions):
        observed = t % chunk == chunk - 1
        outcome = cheese.step(action, observe=observed)
        expected, reached, missing = full[t]
        assert (outcome.reward, outcome.success, outcome.terminated, outcome.info) == (
            expected.reward, expected.success, expected.terminated, expected.info), t
        assert (cheese.milestones_reached(), cheese.first_missing_milestone()) == (reached, missing), t
        if not observed:
            assert outcome.observation is None
        got = outcome.observation if observed else (cheese.observe() if t == len(actions) - 1 else None)
        for name, value in (got or {}).items():
            assert np.array_equal(value, expected.observation[name]), f"{name} differs at step {t}"


# ---- episode keys ---------------------------------------------------------------------------------


def test_variant_is_part_of_the_suite() -> None:
    spelled = canonical_config_key("libero", {"suite": "libero_goal", "variant": "swap"})
    assert spelled == canonical_config_key("libero", {"suite": "libero_goal_swap"})
    with pytest.raises(ConfigError, match="valid variants"):
        get_family("libero")({"suite": "libero_goal", "variant": "mirror"})
    with pytest.raises(ConfigError, match="base suite"):
        get_family("libero")({"suite": "libero_goal_swap", "variant": "task"})


def _trajectory(slot, spec: ResetSpec, steps: int) -> list[tuple[dict[str, np.ndarray], np.ndarray]]:
    actions = np.random.default_rng(5).uniform(-1, 1, size=(steps, 7)).astype(np.float32)
    obs, _ = slot.reset(spec)
    out = [(obs, np.array(slot._env.sim.data.qpos))]
    for a in actions:
        out.append((slot.step(a).observation, np.array(slot._env.sim.data.qpos)))
    return out


def test_episode_key_replays_bit_for_bit() -> None:
    """(family, suite+variant, task, init state, seed) + actions -> identical obs and qpos, anywhere."""
    family = get_family("libero")({"suite": "libero_goal", "variant": "swap"})
    first_slot, second_slot = family.init(), family.init()
    key = ResetSpec("put_the_bowl_on_the_plate", seed=11, init_state_index=7)
    try:
        reference = _trajectory(first_slot, key, 30)
        _trajectory(first_slot, ResetSpec("7", seed=3, init_state_index=2), 10)  # another task in between
        _trajectory(second_slot, ResetSpec("put_the_bowl_on_the_plate", seed=12, init_state_index=7), 5)
        for replay in (_trajectory(first_slot, key, 30), _trajectory(second_slot, key, 30)):
            for t, ((obs_a, qpos_a), (obs_b, qpos_b)) in enumerate(zip(reference, replay, strict=True)):
                assert np.array_equal(qpos_a, qpos_b), f"qpos differs at step {t}"
                for name in obs_a:
                    assert np.array_equal(obs_a[name], obs_b[name]), f"{name} differs at step {t}"
        assert reference[0][0]["task_stage"][STAGE_KINDS.index("on")] == 1.0
    finally:
        first_slot.close()
        second_slot.close()
        family.close()


def test_sampled_layout_is_keyed_by_the_seed_and_is_no_benchmark_state() -> None:
    """Training data on sampled layouts: the same seed gives the same layout, another seed another,
    and none is one of the task's 50 benchmark init states (those are kept for evaluation)."""
    family = get_family("libero")({"suite": "libero_goal", "cameras": []})
    slot = family.init()

    def layout(seed: int, init: int) -> np.ndarray:
        slot.reset(ResetSpec("put_the_wine_bottle_on_top_of_the_cabinet", seed=seed, init_state_index=init))
        return slot._env.sim.data.qpos.copy()

    try:
        a, b = layout(11, SAMPLED_LAYOUT), layout(12, SAMPLED_LAYOUT)
        assert np.array_equal(a, layout(11, SAMPLED_LAYOUT))
        assert not np.allclose(a, b, atol=1e-4)
        benchmark = [layout(11, k) for k in range(50)]
        assert min(float(np.abs(a - q).max()) for q in benchmark) > 1e-4
        with pytest.raises(Exception, match="out of range"):
            slot.reset(ResetSpec("0", seed=1, init_state_index=-2))
    finally:
        slot.close()
        family.close()


def test_geoms_box_is_the_box_around_every_rotated_corner() -> None:
    """The compiled box equals, bit for bit, numpy's arithmetic in the same order (each corner
    coordinate (x + z) + y), over random geoms, rotations and subsets; and is the box of the corners."""
    import mujoco

    from services.env_worker.families.task_state import _BOX_CORNERS, geoms_box

    rng = np.random.default_rng(7)
    n = 50
    for _ in range(300):
        aabb = rng.normal(size=(n, 6)) * rng.choice([1e-3, 1.0, 10.0])
        xmat = np.zeros((n, 9))
        for k in range(n):
            q = rng.normal(size=4)
            mujoco.mju_quat2Mat(xmat[k], q / np.linalg.norm(q))
        xpos = rng.normal(size=(n, 3))
        ids = rng.choice(n, size=int(rng.integers(1, 41)), replace=False)
        local = aabb[ids]
        corners = local[:, None, :3] + local[:, None, 3:] * _BOX_CORNERS  # [k, 8, 3]
        m = xmat[ids].reshape(-1, 3, 3)
        p = [m[:, None, :, j] * corners[:, :, None, j] for j in range(3)]
        world = ((p[0] + p[2]) + p[1]) + xpos[ids][:, None]
        want = np.concatenate([world.min(axis=(0, 1)), world.max(axis=(0, 1))])
        model = type("M", (), {"geom_aabb": aabb})()
        data = type("D", (), {"geom_xmat": xmat, "geom_xpos": xpos})()
        got = geoms_box(model, data, ids)
        assert got.tobytes() == want.tobytes()
