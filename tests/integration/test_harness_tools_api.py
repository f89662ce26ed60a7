"""The harness's tools through the gateway: Perceive (noisy estimates, grasp proposals) and Move
(a bounded closed-loop motion), batched across sessions, with bad input refused by name."""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from tests.conftest import LIFT
from zetta.client import ZettaError
from zetta_wire.v1 import gateway_pb2, types_pb2


def _centre(box: np.ndarray) -> np.ndarray:
    return (np.asarray(box[:3]) + np.asarray(box[3:])) / 2


async def test_perceive_estimates_the_cube_near_but_not_at_its_true_pose(gw) -> None:
    group = await gw.create_sessions(env_family="robosuite", n=2, env_config=LIFT)
    await group.reset(seed=[1, 2])
    exact = [_centre(o["task_object_bbox"]) for o in await group.observe()]
    found = 0
    for _ in range(5):  # the detector misses now and then (its dropout): count what it found
        for res, truth in zip(await group.perceive(grasps=True), exact):
            obj = res.first("object")
            if obj is None:
                continue
            found += 1
            error = float(np.linalg.norm(obj.position - truth))
            assert 0.0 < error < 0.05, error  # an estimate: close, never the simulator's exact pose
            assert obj.box.shape == (6,) and np.all(obj.box[3:] > obj.box[:3])
            assert obj.grasps and obj.grasps[0].grip_point.shape == (3,) and obj.grasps[0].finger_axis in (0, 1)
            assert res.episode_step == 0
    assert found >= 6


async def test_move_servos_the_grip_site_above_the_cube_in_bounded_steps(gw) -> None:
    group = await gw.create_sessions(env_family="robosuite", n=2, env_config=LIFT)
    await group.reset(seed=[3, 4])
    cubes = [_centre(o["task_object_bbox"]) for o in await group.observe()]
    goals = [c + np.array([0.0, 0.0, 0.08]) for c in cubes]
    results = await group.move(goals, gripper=-1.0, max_steps=60, tolerance_m=0.01)
    for res, goal in zip(results, goals):
        n = res.executed_actions.shape[0]
        assert 1 <= n <= 60 and res.episode_step == n
        assert np.all(res.executed_actions[:, 6] == -1.0)
        assert np.linalg.norm(res.observation["robot0_eef_pos"] - goal) < 0.02
    held = await group[0].move(None, gripper=1.0, max_steps=3)
    # Holding: all three steps run, the gripper closes, the servo only corrects drift.
    assert held.executed_actions.shape == (3, 7) and np.all(held.executed_actions[:, 6] == 1.0)
    assert np.abs(held.executed_actions[:, :3]).max() < 0.2


def _turned_about_z(q: np.ndarray, angle: float) -> np.ndarray:
    """The xyzw quaternion of q's rotation followed by ``angle`` about the world z axis."""
    x, y, z, w = q
    c, s = np.cos(angle / 2), np.sin(angle / 2)  # (0, 0, s, c) * (x, y, z, w), Hamilton product
    return np.array([c * x - s * y, c * y + s * x, c * z + s * w, c * w - s * z])


async def test_move_reaches_a_pose_position_and_orientation(gw) -> None:
    """A motion to a pose turns the hand 0.4 rad about the vertical while the grip site holds its
    position, and stops once both are within tolerance, before its step bound."""
    from services.common.rotations import quat_to_mat, rotvec

    group = await gw.create_sessions(env_family="robosuite", n=1, env_config=LIFT)
    await group.reset(seed=5)
    start = (await group.observe())[0]
    here = np.asarray(start["robot0_eef_pos"], np.float64)
    goal = _turned_about_z(np.asarray(start["robot0_eef_quat"], np.float64), 0.4)
    res = await group[0].move(here, max_steps=80, tolerance_m=0.01, orientation=goal, angle_tolerance_rad=0.05)
    reached = quat_to_mat(res.observation["robot0_eef_quat"])
    assert np.linalg.norm(rotvec(quat_to_mat(goal) @ reached.T)) <= 0.05
    assert np.linalg.norm(res.observation["robot0_eef_pos"] - here) <= 0.01
    assert 1 <= res.executed_actions.shape[0] < 80
    assert np.abs(res.executed_actions[:, 5]).max() > 0.1, "it turned the hand about z"


async def test_bad_tool_requests_are_refused_by_name(gw) -> None:
    group = await gw.create_sessions(env_family="robosuite", n=1, env_config=LIFT)
    sid = group.ids[0]
    with pytest.raises(ZettaError) as err:
        await group.perceive()
    assert err.value.code == grpc.StatusCode.FAILED_PRECONDITION and sid in err.value.details
    await group.reset(seed=0)
    with pytest.raises(ZettaError) as err:
        await group.perceive(["object", "cube"])
    assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT and "known: object, target, others" in err.value.details
    bad_motions = [
        (types_pb2.Motion(position=[0.1, 0.2], max_steps=5), "position"),
        (types_pb2.Motion(position=[0.1, float("nan"), 1.0], max_steps=5), "position"),
        (types_pb2.Motion(max_steps=0), "max_steps"),
        (types_pb2.Motion(max_steps=101), "max_steps"),
        (types_pb2.Motion(max_steps=5, gripper=2.0), "gripper"),
        (types_pb2.Motion(max_steps=5, max_action=-0.5), "max_action"),
        (types_pb2.Motion(max_steps=5, orientation=[0.0, 0.0, 1.0]), "orientation"),
        (types_pb2.Motion(max_steps=5, orientation=[0.0, 0.0, 0.0, 2.0]), "orientation"),
        (types_pb2.Motion(max_steps=5, orientation=[0.0, 0.0, 0.0, 1.0], hand_down=True), "orientation"),
        (types_pb2.Motion(max_steps=5, angle_tolerance_rad=-0.1), "angle_tolerance_rad"),
    ]
    for motion, field in bad_motions:
        with pytest.raises(ZettaError) as err:
            await gw.call("Move", gateway_pb2.MoveRequest(session_ids=[sid], motions=[motion]))
        assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT, motion
        assert field in err.value.details and sid in err.value.details and err.value.session_ids == [sid]
    with pytest.raises(ZettaError) as err:
        await gw.call("Move", gateway_pb2.MoveRequest(session_ids=[sid], motions=[]))
    assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT and "one per session" in err.value.details
    # Nothing ran: the episode is where the reset left it.
    assert (await group.move(None, max_steps=1))[0].episode_step == 1


async def test_perceive_uses_the_noise_model_of_the_sessions_harness(gw, tmp_path) -> None:
    """A session whose episode runs a harness perceives with that package's ``[perception]`` model,
    as the harness does: a package that assumes a 30 cm calibration bias reads its cube far off,
    the same episode without a harness reads it within the default model's few centimetres."""
    from tests.integration.test_harness_loop import SKILL, write_package

    pkg = write_package(tmp_path / "pkg")
    (pkg / "SKILL.md").write_text(SKILL.replace("[runtime]", "[perception]\nbias_m = 0.3\n\n[runtime]"))
    errors = {}
    for name, harness in (("harness", str(pkg)), ("none", "")):
        group = await gw.create_sessions(env_family="robosuite", n=1, env_config=LIFT)
        await group.reset(seed=7, harness_dir=harness)
        truth = _centre((await group.observe())[0]["task_object_bbox"])
        seen = [r.first("object") for _ in range(4) for r in await group.perceive()]
        errors[name] = [float(np.linalg.norm(d.position - truth)) for d in seen if d is not None]
        await group.close()
    assert errors["none"] and max(errors["none"]) < 0.05, errors
    assert errors["harness"] and min(errors["harness"]) > 0.1, errors
