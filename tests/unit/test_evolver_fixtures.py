"""Constructed pick-and-place traces for the evolver's unit tests (and a check that they are sane).

A success reaches, grasps, lifts and places the object; a "miss" heads for the wrong spot and never
reaches it (m* = reached); a "drop" lifts the object and loses it on the way (m* = on). Small
per-seed jitter makes members of one mechanism close but not identical.
"""

from __future__ import annotations

import numpy as np

from services.evolver.trace import Trace, TraceRecorder

MILESTONES = ["reached(a)", "grasped(a)", "lifted(a)", "on(a,b)", "released(a)"]
OBJ = np.array([0.1, 0.0, 0.05])
TGT = np.array([0.3, 0.0, 0.05])
K = 30


def _lerp(a: np.ndarray, b: np.ndarray, u: float) -> np.ndarray:
    return a + (b - a) * min(max(u, 0.0), 1.0)


def make_trace(kind: str, seed: int = 0) -> Trace:
    """A trace of ``kind`` in {"success", "miss", "drop"}; frames every 2 env steps."""
    rng = np.random.default_rng(seed)
    jitter = rng.normal(0, 0.003, 3)
    rec = TraceRecorder(MILESTONES)
    start = np.array([0.0, 0.0, 0.3]) + jitter
    obj = OBJ.copy()
    reached = np.zeros(24, np.float32)
    for k in range(K):
        if kind == "miss":
            eef = _lerp(start, np.array([0.1, 0.25, 0.05]), k / 10)
        elif k <= 10:
            eef = _lerp(start, OBJ + np.array([0, 0, 0.01]), k / 9)
        else:
            eef = _lerp(OBJ + np.array([0, 0, 0.01]), TGT + np.array([0, 0, 0.06]), (k - 10) / 14)
        grasp = 1.0 if kind != "miss" and 10 <= k <= 27 else 0.0
        if kind == "drop" and k >= 22:
            grasp = 0.0
        if grasp:
            obj = eef - np.array([0, 0, 0.01])
        elif kind == "drop" and k >= 22:
            obj = np.array([obj[0], obj[1], 0.05])
        elif k > 27 and kind == "success":
            obj = TGT.copy()
        mu = np.zeros(24, np.float32)
        if np.linalg.norm(eef - obj) < 0.03:
            mu[0] = 1
        mu[1] = grasp
        mu[2] = float(grasp and obj[2] > 0.08)
        if kind == "success" and k >= 26:
            mu[3] = 1
            obj = TGT.copy()
        if kind == "success" and k >= 28:
            mu[4] = 1
        reached = np.maximum(reached, mu)
        obs = {
            "robot0_eef_pos": eef.astype(np.float32),
            "robot0_eef_quat": np.array([1, 0, 0, 0], np.float32),
            "robot0_gripper_qpos": np.array([0.04 - 0.03 * grasp, -0.04 + 0.03 * grasp], np.float32),
            "robot0_joint_pos": np.zeros(7, np.float32),
            "task_object_pos": obj.astype(np.float32),
            "task_target_pos": TGT.astype(np.float32),
            "task_object_bbox": np.concatenate([obj - 0.02, obj + 0.02]).astype(np.float32),
            "phi_grasp": np.array([grasp], np.float32),
            "phi_finger_contact": np.array([grasp, grasp], np.float32),
            "phi_gripper_aperture": np.array([0.08 - 0.06 * grasp], np.float32),
            "phi_eef_object_dist": np.array([max(0.0, float(np.linalg.norm(eef - obj)) - 0.02)], np.float32),
            "phi_eef_motion": np.zeros(6, np.float32),
            "phi_collision_intensity": np.zeros(1, np.float32),
            "milestones": mu,
            "milestones_reached": reached.copy(),
            "agentview_image": np.zeros((4, 4, 3), np.uint8),
        }
        closed = grasp or (kind == "drop" and k >= 10)
        actions = None if k == 0 else np.tile(np.array([0, 0, 0, 0, 0, 0, 1.0 if closed else -1.0], np.float32), (2, 1))
        rec.frame(2 * k, obs, actions)
    return rec.finish()


def test_fixture_traces_have_the_intended_outcomes() -> None:
    """Success sees every milestone; a miss never reaches; a drop loses the object before on()."""
    ok, miss, drop = make_trace("success"), make_trace("miss"), make_trace("drop")
    assert ok.mu_reached[-1][:5].all()
    assert not miss.mu_reached[-1][0]
    assert drop.mu_reached[-1][:3].all() and not drop.mu_reached[-1][3]
    assert "agentview_image" not in ok.obs and ok.actions.shape == (2 * (K - 1), 7)
