"""The oracle's contract with the policy worker: batched, stateless, one skill per stage predicate.

Its success on the real tasks is measured by scripts/oracle_report.py (docs/oracle.md); the real
episodes it runs in the default suite are in tests/unit/test_libero_task_state.py.
"""

from __future__ import annotations

import numpy as np

from services.common.milestone_kinds import OBSTACLE_SLOTS, STAGE_KINDS, TEMPLATE_NAMES
from services.policy_worker.models.base import FACTORIES, load_model
from services.policy_worker.models.oracle import DOWN, OraclePolicy


def _obs(stage: str, template: str, rows: int = 1) -> dict[str, np.ndarray]:
    batch = {spec.name: np.zeros((rows, *spec.shape), dtype=spec.dtype) for spec in OraclePolicy.input_specs()}
    batch["robot0_eef_pos"][:] = [-0.2, 0.0, 1.17]
    batch["robot0_eef_quat"][:] = [1.0, 0.0, 0.0, 0.0]  # xyzw of diag(1, -1, -1): pointing down
    batch["robot0_gripper_qpos"][:] = [0.04, -0.04]
    batch["task_object_bbox"][:] = [-0.02, 0.08, 0.9, 0.02, 0.1, 0.92]
    batch["task_object_pos"][:] = [0.0, 0.09, 0.91]
    batch["task_target_bbox"][:] = [0.05, -0.05, 0.9, 0.15, 0.05, 0.92]
    batch["task_target_pos"][:] = [0.1, 0.0, 0.91]
    batch["task_stage"][:, STAGE_KINDS.index(stage)] = 1.0
    batch["task_template"][:, TEMPLATE_NAMES.index(template)] = 1.0
    batch["task_motion_dir"][:] = [0.0, 1.0, 0.0]
    return batch


def test_registered_and_batched() -> None:
    assert "oracle" in FACTORIES and load_model("oracle").name == "oracle"
    policy = OraclePolicy(chunk_size=3)
    actions = policy.infer(_obs("on", "pick_place", rows=4), [""] * 4)
    assert actions.shape == (4, 3, 7) and actions.dtype == np.float32
    assert np.all(actions == actions[:1, :1]) and np.all(np.abs(actions) <= 1.0)


def test_skill_follows_the_stage() -> None:
    policy = OraclePolicy()
    row = {k: v[0].astype(np.float64) for k, v in _obs("on", "pick_place").items()}
    assert policy.skill(row) == "pick_place"
    row = {k: v[0].astype(np.float64) for k, v in _obs("on", "slide").items()}
    assert policy.skill(row) == "push", "a compact object onto a table region is pushed"
    row["task_object_bbox"] = np.array([-0.07, -0.07, 0.9, 0.07, 0.07, 0.92])
    assert policy.skill(row) == "pick_place", "a plate is carried by its rim"
    for kind in ("open", "close", "turnon", "turnoff"):
        row = {k: v[0].astype(np.float64) for k, v in _obs(kind, "articulate").items()}
        assert policy.skill(row) == "handle"


def test_stateless_same_observation_same_action() -> None:
    policy = OraclePolicy()
    obs = _obs("turnon", "articulate")
    first = policy.infer(obs, [""])
    policy.infer(_obs("on", "pick_place"), [""])  # anything in between
    assert np.array_equal(first, policy.infer(obs, [""]))
    assert np.allclose(DOWN @ DOWN.T, np.eye(3))


def _row(stage: str, obj: list[float], target: list[float], eef: list[float], grasped: bool) -> dict[str, np.ndarray]:
    row = {k: v[0].astype(np.float64) for k, v in _obs(stage, "pick_place").items()}
    row["task_object_bbox"], row["task_target_bbox"] = np.array(obj), np.array(target)
    row["robot0_eef_pos"] = np.array(eef)
    row["task_grasped"][:] = float(grasped)
    return row


# An opened drawer (the region it holds, its floor 10 cm above the table) over a bowl's corner.
BOWL = [-0.14, -0.049, 0.9, -0.033, 0.058, 0.951]
DRAWER = [-0.066, -0.171, 1.061, 0.139, -0.02, 1.121]


def test_covered_bowl_is_gripped_off_the_rim_middle_and_slid_out_before_lifting() -> None:
    policy = OraclePolicy()
    p = policy.params
    # Free: the rim grasp on the side facing the robot, as before.
    free = _row("in", BOWL, [0.2, 0.2, 1.061, 0.4, 0.4, 1.121], [-0.2, 0.0, 1.17], grasped=False)
    policy.act(free)
    assert policy._pick.shift == 0.0
    # Covered: the grasp moves along the rim, away from the drawer, until the hand clears it.
    covered = _row("in", BOWL, DRAWER, [-0.2, 0.0, 1.17], grasped=False)
    policy.act(covered)
    shift = policy._pick.shift
    center_y = (BOWL[1] + BOWL[4]) / 2
    assert shift > 0 and center_y + shift - p.hand_half_across >= DRAWER[4] + p.cover_margin - 1e-9
    # Held: slide out the shortest way (+y here), rising under the drawer, never straight up.
    held = _row("in", BOWL, DRAWER, [-0.128, center_y + shift, 0.931], grasped=True)
    action = policy.act(held)
    assert action[1] > 0.1 and abs(action[0]) < 1e-9 and action[2] > 0 and action[6] == 1.0
    # Out of the footprint: the usual carry takes over (up first, then over the drawer).
    out = BOWL[:]
    out[1], out[4] = DRAWER[4] + p.cover_margin + 0.01, DRAWER[4] + p.cover_margin + 0.117
    assert policy._cover(np.array(out), np.array(DRAWER)) is None


def test_an_object_that_fits_is_lowered_into_a_deep_dish() -> None:
    policy = OraclePolicy()
    bowl = [-0.15, -0.04, 0.9, -0.043, 0.066, 0.951]
    bottle = [-0.118, -0.009, 1.0, -0.074, 0.035, 1.157]  # held over the bowl's centre
    row = _row("on", bottle, bowl, [-0.096, 0.013, 1.13], grasped=True)
    assert policy._sink(row) > 0
    assert policy.act(row)[2] < 0, "a held bottle over the bowl goes down into it"
    row["task_object_bbox"][2] = bowl[5] - policy._sink(row)  # its bottom inside the bowl: let go
    row["task_object_bbox"][5] = row["task_object_bbox"][2] + 0.157
    assert policy.act(row)[6] == -1.0
    cheese = _row("on", [-0.138, -0.008, 1.0, -0.056, 0.034, 1.018], bowl, [-0.096, 0.013, 1.0], grasped=True)
    assert policy._sink(cheese) == 0.0, "too wide to fit: let go above the rim, as before"
    plate = _row("on", bottle, [-0.17, -0.06, 0.9, -0.03, 0.08, 0.919], [-0.096, 0.013, 1.13], grasped=True)
    assert policy._sink(plate) == 0.0, "a shallow dish is not sunk into"


def _obstacles(*boxes: list[float]) -> np.ndarray:
    out = np.zeros((OBSTACLE_SLOTS, 6))
    if boxes:
        out[: len(boxes)] = boxes
    return out


# LIBERO-Goal-S 1 (put the bowl on the stove), measured from the scene: the swap puts the stove's cook
# region (a thin site box under the stove's top) under two slats of the wine rack (tilted boards,
# here their boxes), the stove's knobs beside it.
SWAP_BOWL = [-0.246, -0.118, 0.9, -0.139, -0.011, 0.951]
COOK_REGION = [-0.189, -0.323, 0.902, -0.039, -0.173, 0.908]
RACK_SLATS = ([-0.402, -0.278, 1.002, -0.133, -0.139, 1.092], [-0.399, -0.147, 1.009, -0.135, -0.137, 1.025])
STOVE = [-0.209, -0.343, 0.885, -0.019, -0.153, 0.925]
KNOB = [0.018, -0.261, 0.906, 0.088, -0.237, 0.955]


def test_near_its_elbow_limit_the_hand_pitches_toward_the_base() -> None:
    policy = OraclePolicy()
    cheese = [-0.437, 0.205, 0.9, -0.356, 0.247, 0.918]
    row = _row("in", cheese, [-0.255, -0.097, 0.9, -0.148, 0.01, 0.951], [-0.40, 0.21, 1.0], grasped=False)
    row["robot0_joint_pos"] = np.array([0.15, 0.0, 0.5, -2.44, 0.0, 2.2, 1.0])
    assert np.all(policy.act(row)[3:6] == 0.0), "elbow far from its limit: the hand is left as it is"
    row["robot0_joint_pos"][3] = -2.95
    rotation = policy.act(row)[3:6]
    assert rotation[1] > 0.1, "pitched about +y: the fingertips point back toward the base (-x)"
    assert policy._elbow_pitch(row) == policy.params.max_pitch
    plate = _row("on", [-0.45, 0.1, 0.9, -0.3, 0.25, 0.92], COOK_REGION, [-0.40, 0.21, 1.0], grasped=False)
    plate["robot0_joint_pos"] = row["robot0_joint_pos"]
    assert policy._elbow_pitch(plate) == 0.0, "a plate's rim is gripped at the table: never pitched"


def test_held_bowl_goes_round_the_rack_and_is_let_go_where_nothing_hangs_over_the_stove() -> None:
    policy = OraclePolicy()
    p = policy.params
    obstacles = _obstacles(*RACK_SLATS, STOVE, KNOB)
    # Gripped from +y (the side the oracle picks here, next test): the hand's fingers close along y.
    grip = np.array([-0.1925, -0.0225, 0.931])
    moving = np.stack([np.array(SWAP_BOWL), policy._palm(grip, np.array([0.0, 1.0]))])
    via, release, carry_z, release_z = policy._route(moving, np.array(COOK_REGION), obstacles, 0.0)
    half = (SWAP_BOWL[3] - SWAP_BOWL[0]) / 2
    assert release[0] - half >= RACK_SLATS[0][3] + p.route_margin - 1e-9, "not under the slats"
    assert release[0] + half <= KNOB[0] - p.route_margin + 1e-9, "nor on the knobs"
    assert COOK_REGION[0] < release[0] < COOK_REGION[3] and COOK_REGION[1] < release[1] < COOK_REGION[4]
    assert release_z == STOVE[5] + p.pick.release_gap, "let go just above the stove's top, not the region's site"
    assert np.allclose(via, [release[0], (SWAP_BOWL[1] + SWAP_BOWL[4]) / 2]), "out from beside the rack first"
    assert carry_z >= COOK_REGION[5] + p.pick.carry_clearance
    # Without obstacles: straight over the target's centre at the usual height.
    via, release, carry_z, _ = policy._route(moving, np.array(COOK_REGION), _obstacles(), 0.0)
    centre = (np.array(COOK_REGION[:2]) + COOK_REGION[3:5]) / 2
    assert np.allclose(via, centre) and np.allclose(release, centre)
    assert carry_z == COOK_REGION[5] + p.pick.carry_clearance


def test_the_rim_is_gripped_where_the_hand_has_a_way_down() -> None:
    policy = OraclePolicy()
    obstacles = _obstacles(*RACK_SLATS, STOVE, KNOB)
    facing_robot = policy._grasp_side(np.array(SWAP_BOWL), np.array(COOK_REGION))
    assert facing_robot == (0, -1.0)
    # From the robot's side the hand (21 cm along its fingers) would sit under the slats.
    assert policy._clear_side(np.array(SWAP_BOWL), np.array(COOK_REGION), obstacles, facing_robot) == (1, 1.0)
    assert policy._clear_side(np.array(SWAP_BOWL), np.array(COOK_REGION), _obstacles(), facing_robot) == facing_robot


# LIBERO-Goal-T 0 (open the bottom drawer): the bar 3.8 cm over the table, drawers opening along +y.
TABLE = [-0.8, -0.8, 0.85, 0.8, 0.8, 0.9]


def _drawer_row(bar: list[float]) -> dict[str, np.ndarray]:
    row = {k: v[0].astype(np.float64) for k, v in _obs("open", "articulate").items()}
    row["task_object_bbox"] = np.array(bar)
    row["task_object_pos"] = (row["task_object_bbox"][:3] + row["task_object_bbox"][3:]) / 2
    row["task_target_pos"] = row["task_object_pos"] + [0.0, 0.15, 0.0]
    row["task_motion_dir"] = np.array([0.0, 1.0, 0.0])
    row["task_obstacle_bbox"] = _obstacles(TABLE)
    return row


def test_a_bar_too_low_to_grip_from_the_front_is_hooked_from_above() -> None:
    policy = OraclePolicy()
    low = _drawer_row([-0.002, -0.14, 0.938, 0.087, -0.125, 0.954])
    middle = _drawer_row([-0.002, -0.14, 1.007, 0.087, -0.125, 1.024])
    assert policy._front_blocked(low) and not policy._front_blocked(middle)
    assert policy.act(low)[6] == 1.0, "hooked with the fingers closed"
    assert policy.act(middle)[6] != 1.0, "a front grasp approaches with the fingers open"
    # At the hook pose the hand drags the bar along the drawer's axis, pressing into it.
    p = policy.params
    approach = np.array([0.0, -np.sin(p.hook_tilt), -np.cos(p.hook_tilt)])
    center = low["task_object_pos"]
    tip = np.array([center[0], -0.14 - p.hook_gap, 0.954 - p.hook_depth])
    low["robot0_eef_pos"] = tip - approach * p.hook_tip
    finger = np.array([-1.0, 0.0, 0.0])
    low["robot0_eef_quat"] = _xyzw(np.column_stack([np.cross(finger, approach), finger, approach]))
    action = policy.act(low)
    assert action[1] > 0.5 and action[2] < 0.0
    low["task_obstacle_bbox"] = _obstacles()
    assert not policy._front_blocked(low), "nothing known under the bar: gripped from the front"


def _xyzw(mat: np.ndarray) -> np.ndarray:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, mat.reshape(9))
    return np.array([q[1], q[2], q[3], q[0]])
