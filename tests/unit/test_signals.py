"""Physical signals phi_t on constructed MuJoCo states and hand-made contact sets.

The contact-force tests build tiny models (a box on a plane, two finger pads squeezing a box)
so the expected values are known from physics: weight, friction-free squeeze, free fall.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from services.env_worker import signals as sig

BOX_ON_PLANE = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="box" pos="0 0 0.05"><freejoint/><geom name="box" type="box" size="0.05 0.05 0.05" mass="2"/></body>
    <body name="ball" pos="1 1 2"><freejoint/><geom name="ball" type="sphere" size="0.02" mass="0.1"/></body>
  </worldbody>
</mujoco>
"""

#: Two pads on slide joints, pushed together by position actuators onto a free box.
PINCH = """
<mujoco>
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <body name="left" pos="0 -0.05 0"><joint name="l" type="slide" axis="0 1 0"/>
      <geom name="left" type="box" size="0.01 0.01 0.01" mass="0.1"/></body>
    <body name="right" pos="0 0.05 0"><joint name="r" type="slide" axis="0 1 0"/>
      <geom name="right" type="box" size="0.01 0.01 0.01" mass="0.1"/></body>
    <body name="obj" pos="0 0 0"><freejoint/><geom name="obj" type="box" size="0.02 0.02 0.02" mass="0.05"/></body>
    <geom name="wall" type="box" pos="0.5 0 0" size="0.01 0.1 0.1"/>
  </worldbody>
  <actuator>
    <position joint="l" kp="200" ctrlrange="-1 1"/>
    <position joint="r" kp="200" ctrlrange="-1 1"/>
  </actuator>
</mujoco>
"""


def _gid(model: mujoco.MjModel, name: str) -> int:
    return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name)


def test_contact_force_of_a_resting_box_is_its_weight() -> None:
    model = mujoco.MjModel.from_xml_string(BOX_ON_PLANE)
    data = mujoco.MjData(model)
    for _ in range(300):
        mujoco.mj_step(model, data)
    contacts = sig.read_contacts(model, data)
    floor, box = np.array([_gid(model, "floor")]), np.array([_gid(model, "box")])
    assert sig.touches(contacts, floor, box) and sig.touches(contacts, box, floor)
    np.testing.assert_allclose(sig.force_on(contacts, floor, box), [0, 0, 2 * 9.81], atol=0.05)
    np.testing.assert_allclose(sig.force_on(contacts, box, floor), [0, 0, -2 * 9.81], atol=0.05)
    # The box as "robot": its floor contact is a collision unless the floor is excluded.
    assert abs(sig.collision_intensity(contacts, box, np.zeros(0)) - 2 * 9.81) < 0.05
    assert sig.collision_intensity(contacts, box, floor) == 0.0


def test_contacts_involving_some_geoms_are_those_rows_of_all_contacts() -> None:
    model, data = _pinch_state(0.04)  # pads squeeze the box; nothing else touches
    everything = sig.read_contacts(model, data)
    left = _gid(model, "left")
    assert len(everything.geom1) >= 2
    only = sig.read_contacts(model, data, frozenset({left}))
    rows = [i for i in range(len(everything.geom1)) if left in (everything.geom1[i], everything.geom2[i])]
    assert 0 < len(rows) < len(everything.geom1)
    for field in ("geom1", "geom2", "force", "normal"):  # the same values, bit for bit, in MuJoCo's order
        assert np.array_equal(getattr(only, field), getattr(everything, field)[rows])
    assert len(sig.read_contacts(model, data, frozenset({_gid(model, "wall")})).geom1) == 0
    assert only.pairs == list(zip(only.geom1.tolist(), only.geom2.tolist()))
    geoms = _geoms(model)
    assert geoms.all_geoms == geoms.left | geoms.right | geoms.gripper | geoms.robot


def test_free_fall_velocity() -> None:
    model = mujoco.MjModel.from_xml_string(BOX_ON_PLANE)
    data = mujoco.MjData(model)
    for _ in range(100):  # 0.2 s
        mujoco.mj_step(model, data)
    ball = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "ball")
    vel = sig.body_velocity(model, data, ball)
    np.testing.assert_allclose(vel[:3], [0, 0, -9.81 * 0.2], atol=0.05)
    np.testing.assert_allclose(vel[3:], 0, atol=1e-6)


def _pinch_state(close: float) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(PINCH)
    data = mujoco.MjData(model)
    data.ctrl[:] = [close, -close]
    for _ in range(500):
        mujoco.mj_step(model, data)
    return model, data


def _inputs(model: mujoco.MjModel, data: mujoco.MjData, eef: np.ndarray, commanded: np.ndarray) -> sig.SignalInputs:
    obj = np.array([_gid(model, "obj")])
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "obj")
    return sig.SignalInputs(
        contacts=sig.read_contacts(model, data),
        object_geoms=obj,
        object_bbox=np.concatenate([data.xpos[body] - 0.02, data.xpos[body] + 0.02]),
        object_pos=np.array(data.xpos[body]),
        object_vel=sig.body_velocity(model, data, body),
        eef_pos=eef,
        eef_mat=np.eye(3),
        finger_qpos=np.array([data.qpos[0], data.qpos[1]]),
        commanded=commanded,
    )


def _geoms(model: mujoco.MjModel) -> sig.GripperGeoms:
    left, right = frozenset({_gid(model, "left")}), frozenset({_gid(model, "right")})
    return sig.GripperGeoms(left, right, left | right, left | right)


def test_bilateral_contact_grasp_and_squeeze_force() -> None:
    model, data = _pinch_state(0.04)  # pads travel 4 cm inward: both press the 4 cm box
    tracker = sig.SignalTracker(_geoms(model))
    out = tracker.compute(_inputs(model, data, np.zeros(3), np.zeros(3)))
    assert out["phi_finger_contact"].tolist() == [1.0, 1.0] and out["phi_grasp"][0] == 1.0
    assert abs(out["phi_contact_force"][1]) < 0.5, "the two squeezes cancel"
    assert out["phi_collision_intensity"][0] == 0.0, "touching the task object is no collision"
    assert out["phi_object_gripper_drift"][0] == 0.0, "the grasp just began"
    assert out["phi_gripper_aperture"][0] > 0.0

    open_model, open_data = _pinch_state(0.0)
    released = sig.SignalTracker(_geoms(open_model)).compute(_inputs(open_model, open_data, np.zeros(3), np.zeros(3)))
    assert released["phi_finger_contact"].tolist() == [0.0, 0.0] and released["phi_grasp"][0] == 0.0


def test_drift_and_realized_motion() -> None:
    model, data = _pinch_state(0.04)
    tracker = sig.SignalTracker(_geoms(model))
    tracker.compute(_inputs(model, data, np.zeros(3), np.zeros(3)))
    # The hand moves 1 cm in x while the object stays: it drifted 1 cm in the hand's frame.
    out = tracker.compute(_inputs(model, data, np.array([0.01, 0.0, 0.0]), np.array([0.02, 0.0, 0.0])))
    np.testing.assert_allclose(out["phi_object_gripper_drift"], [0.01], atol=1e-6)
    np.testing.assert_allclose(out["phi_eef_motion"], [0.02, 0, 0, 0.01, 0, 0], atol=1e-6)
    tracker.reset()
    out = tracker.compute(_inputs(model, data, np.array([0.01, 0.0, 0.0]), np.zeros(3)))
    assert not out["phi_eef_motion"].any(), "no realized motion right after a reset"


def test_pure_helpers() -> None:
    assert sig.aabb_distance(np.array([0.0, 0.0, 0.0]), np.array([-1, -1, -1, 1, 1, 1.0])) == 0.0
    assert abs(sig.aabb_distance(np.array([2.0, 0.0, 0.0]), np.array([-1, -1, -1, 1, 1, 1.0])) - 1.0) < 1e-12
    ones = np.ones(6)
    np.testing.assert_allclose(
        sig.commanded_translation(np.array([1.0, -0.5, 2.0]), ones, -ones, 0.05 * ones, -0.05 * ones),
        [0.05, -0.025, 0.05],
    )
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    np.testing.assert_allclose(sig.in_frame(np.array([0.0, 1.0, 0.0]), np.zeros(3), rot), [1.0, 0.0, 0.0], atol=1e-12)
    specs = {s.name: s for s in sig.signal_specs()}
    assert all(s.privileged and s.dtype == "float32" for s in specs.values())
    assert set(sig.zero_signals()) == set(specs)


def test_tracked_steps_keep_the_state_of_computed_ones() -> None:
    """Steps that only track (no tensors) leave the grasp reference and the last end-effector
    position where computing every step would: the next computed signals are the same."""
    model, data = _pinch_state(0.04)
    every, tracked = sig.SignalTracker(_geoms(model)), sig.SignalTracker(_geoms(model))
    path = [np.array([0.01 * k, 0.0, 0.002 * k * k]) for k in range(6)]
    for k, eef in enumerate(path):
        x = _inputs(model, data, eef, np.array([0.02, 0.0, 0.0]))
        expected = every.compute(x)
        bare = sig.read_contacts(model, data, forces=False)  # what a step that builds no observation reads
        tracked.track(bare, x.object_geoms, x.object_pos, x.eef_pos, x.eef_mat)
    got = tracked.tensors(x)  # observed only now
    for name, value in expected.items():
        assert np.array_equal(got[name], value), name
    assert got["phi_object_gripper_drift"][0] > 0.0 and got["phi_eef_motion"][3:].any()


def test_a_contact_without_a_geom_involves_no_geom_set() -> None:
    """MuJoCo marks a flex's side of a contact with geom -1; the lookup must not wrap to the last geom."""
    model, _ = _pinch_state(0.04)
    last = model.ngeom - 1
    mask = sig._geom_mask(frozenset({last}), model.ngeom)
    assert mask[last] and not mask[-1] and not mask[np.array([-1])].any()


def test_contacts_without_forces_name_the_same_pairs() -> None:
    model, data = _pinch_state(0.04)
    full, bare = sig.read_contacts(model, data), sig.read_contacts(model, data, forces=False)
    assert np.array_equal(full.geom1, bare.geom1) and np.array_equal(full.geom2, bare.geom2)
    assert bare.force.shape == (0, 3) and bare.normal.shape == (0,), "no forces were read"
    with pytest.raises(IndexError):
        sig.force_on(bare, np.array([_gid(model, "left")]), np.array([_gid(model, "obj")]))
