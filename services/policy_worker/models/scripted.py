"""A scripted pick-and-place policy on privileged state, for tests, baselines and warm-ups.

It is stateless on purpose: the phase (approach, descend, close, lift, carry, lower, release,
retreat) is decided from the current observation alone, so the policy worker can batch it with
any other session's requests and an episode can be resumed at any step (e.g. after a recovery
skill hands control back). It needs only the privileged task state that the manipulation
families publish (``task_object_pos``, ``task_target_pos``, ``task_grasped``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.common.specs import TensorSpec

_OPEN, _CLOSE = -1.0, 1.0


@dataclass(frozen=True)
class PickPlaceParams:
    """Generic geometric offsets (metres) and gains; none is specific to a task."""

    #: End-effector height above the object's origin when the fingers close.
    grasp_height: float = 0.01
    #: Height above the object from which the gripper descends vertically.
    hover_height: float = 0.10
    #: Height of the held object above the target while it is carried sideways.
    carry_height: float = 0.12
    #: Height of the object above the target at which it is let go.
    release_height: float = 0.04
    #: Horizontal alignment needed before descending or lowering.
    xy_tolerance: float = 0.01
    #: Vertical tolerance of "at grasp height" and "at release height".
    z_tolerance: float = 0.01
    #: How close (horizontally) a released object must be to the target to count as placed.
    place_tolerance: float = 0.04
    #: Finger gap (m) above which the gripper counts as open, and below which a closing gripper
    #: has missed the object.
    open_gap: float = 0.07
    closed_gap: float = 0.004
    #: Action per metre of position error, and the largest translational action.
    gain: float = 12.0
    max_action: float = 1.0


class ScriptedPickPlacePolicy:
    """Batched, stateless pick-and-place controller emitting OSC_POSE delta actions."""

    name = "scripted-pick-place"

    def __init__(self, params: PickPlaceParams | None = None, chunk_size: int = 1) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.params = params or PickPlaceParams()
        self.chunk_size = chunk_size

    @staticmethod
    def input_specs() -> list[TensorSpec]:
        """The observation tensors the policy reads (a subset of the manipulation schema)."""
        return [
            TensorSpec("robot0_eef_pos", "float32", (3,)),
            TensorSpec("robot0_gripper_qpos", "float32", (2,)),
            TensorSpec("task_object_pos", "float32", (3,), privileged=True),
            TensorSpec("task_target_pos", "float32", (3,), privileged=True),
            TensorSpec("task_grasped", "float32", (1,), privileged=True),
        ]

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """Actions of shape [B, chunk_size, 7]; the instruction is ignored (the goal is in the state).

        A chunk repeats the one action: the policy has no model of how the state evolves.
        """
        eef = np.asarray(batch["robot0_eef_pos"], dtype=np.float64)
        actions = np.stack(
            [
                self._act(
                    eef[i],
                    np.asarray(batch["robot0_gripper_qpos"][i], dtype=np.float64),
                    np.asarray(batch["task_object_pos"][i], dtype=np.float64),
                    np.asarray(batch["task_target_pos"][i], dtype=np.float64),
                    bool(batch["task_grasped"][i][0] > 0.5),
                )
                for i in range(len(eef))
            ]
        ) if len(eef) else np.zeros((0, 7))
        return np.repeat(actions[:, None, :], self.chunk_size, axis=1).astype(np.float32)

    def _act(self, eef: np.ndarray, fingers: np.ndarray, obj: np.ndarray, target: np.ndarray, grasped: bool) -> np.ndarray:
        p = self.params
        if not obj.any() or not target.any():
            return self._action(np.zeros(3), _OPEN)  # no pick-and-place goal: hold still, hand open
        gap = float(fingers[0] - fingers[1])
        if grasped:
            return self._carry(obj, target)
        to_target_xy = np.linalg.norm(obj[:2] - target[:2])
        placed_z = -p.z_tolerance * 3 <= obj[2] - target[2] <= p.release_height + 2 * p.z_tolerance
        if to_target_xy < p.place_tolerance and placed_z:
            return self._move(eef, eef + [0.0, 0.0, 0.1], _OPEN)  # retreat from the placed object
        grasp = obj + [0.0, 0.0, p.grasp_height]
        aligned = np.linalg.norm(eef[:2] - grasp[:2]) < p.xy_tolerance * 1.5
        if aligned and abs(eef[2] - grasp[2]) < p.z_tolerance:
            if gap < p.closed_gap:
                return self._move(eef, eef + [0.0, 0.0, 0.03], _OPEN)  # closed on nothing: back off
            return self._move(eef, grasp, _CLOSE)
        if gap < p.open_gap:
            return self._move(eef, eef + [0.0, 0.0, 0.01], _OPEN)  # open fully before approaching
        hover = obj + [0.0, 0.0, p.hover_height]
        if np.linalg.norm(eef[:2] - grasp[:2]) > p.xy_tolerance:
            return self._move(eef, self._climb_first(eef, hover), _OPEN)
        return self._move(eef, grasp, _OPEN)

    def _carry(self, obj: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Grasped: lift to carry height, move over the target, lower, then let go."""
        p = self.params
        above = target + [0.0, 0.0, p.carry_height]
        if np.linalg.norm(obj[:2] - target[:2]) > p.xy_tolerance:
            return self._move(obj, self._climb_first(obj, above), _CLOSE)
        release = target + [0.0, 0.0, p.release_height]
        if abs(obj[2] - release[2]) > p.z_tolerance:
            return self._move(obj, release, _CLOSE)
        return self._action(np.zeros(3), _OPEN)

    def _climb_first(self, point: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Rise to the goal's height before moving sideways, so nothing on the table is swept."""
        if point[2] < goal[2] - 0.02:
            return np.array([point[0], point[1], goal[2]])
        return goal

    def _move(self, current: np.ndarray, goal: np.ndarray, gripper: float) -> np.ndarray:
        return self._action(np.asarray(goal, dtype=np.float64) - current, gripper)

    def _action(self, error: np.ndarray, gripper: float) -> np.ndarray:
        p = self.params
        delta = np.clip(error * p.gain, -p.max_action, p.max_action)
        return np.concatenate([delta, np.zeros(3), [gripper]])
