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
