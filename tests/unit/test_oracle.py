"""The oracle's contract with the policy worker: batched, stateless, one skill per stage predicate.

Its success on the real tasks is measured by scripts/oracle_report.py (docs/oracle.md); the real
episodes it runs in the default suite are in tests/unit/test_libero_task_state.py.
"""

from __future__ import annotations

import numpy as np

from services.env_worker.milestones import STAGE_KINDS, TEMPLATE_NAMES
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
