"""A scripted pick-and-place policy on privileged state, for tests, baselines and warm-ups.

It is stateless on purpose: the phase (approach, descend, close, lift, carry, lower, release,
retreat) is decided from the current observation alone, so the policy worker can batch it with
any other session's requests and an episode can be resumed at any step (e.g. after a recovery
skill hands control back). It needs only the privileged task state that the manipulation
families publish: the boxes of the task object and of its target, and the grasp flag. The boxes
let one set of generic offsets handle a flat cheese box, a bowl (grasped by its rim) and a tall
bottle (grasped below its top).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.common.specs import TensorSpec

_OPEN, _CLOSE = -1.0, 1.0
#: Vertical steps (m) of the recovery moves: leave a placed object, back off a missed grasp, and
#: the small rise while the fingers reopen.
_RETREAT, _BACK_OFF, _REOPEN_RISE = 0.10, 0.03, 0.01
#: How far below its goal height the hand may be before it rises without moving sideways.
_CLIMB_MARGIN = 0.02


@dataclass(frozen=True)
class PickPlaceParams:
    """Generic geometric offsets (metres) and gains; none is specific to a task."""

    #: World axis along which the fingers close (the default Panda pose closes along y).
    finger_axis: int = 1
    #: Objects at most this half-wide along the finger axis are grasped across their centre;
    #: wider ones (bowls) by their rim.
    max_center_half_width: float = 0.032
    #: Grasp depth below the object's top, and the least height of the grasp above its bottom.
    grasp_depth: float = 0.03
    min_grasp_height: float = 0.012
    #: Rim grasp: how far inside the object's outer edge, and how deep below its top.
    rim_inset: float = 0.012
    rim_depth: float = 0.02
    #: Height above the object's top from which the gripper descends vertically.
    hover_height: float = 0.10
    #: Clearance of the held object's bottom over the target's top while carried sideways.
    carry_clearance: float = 0.06
    #: Clearance of the object's bottom over the target's top at which it is let go.
    release_gap: float = 0.015
    #: Horizontal alignment needed before descending to grasp, and before lowering a held object
    #: (looser: near the edge of its reach the arm cannot close the last millimetres).
    xy_tolerance: float = 0.01
    carry_xy_tolerance: float = 0.02
    #: Vertical tolerance of "at grasp height" and "at release height".
    z_tolerance: float = 0.01
    #: A released object counts as placed when its centre is this close (horizontally) to the
    #: target's and its bottom is at most ``placed_depth`` below the target's top (inside a bowl).
    place_tolerance: float = 0.04
    placed_depth: float = 0.06
    #: Finger gap (m) above which the gripper counts as open, and below which a closing gripper
    #: has missed the object.
    open_gap: float = 0.07
    closed_gap: float = 0.004
    #: Action per metre of position error, the largest translational action, and the least one
    #: while the error exceeds ``settle_distance`` (OSC does not compensate a held object's weight,
    #: so a purely proportional command stalls a few centimetres short when carrying).
    gain: float = 12.0
    max_action: float = 1.0
    min_action: float = 0.2
    #: Largest translational action while holding something (a rim grasp slips under fast moves).
    carry_max_action: float = 0.5
    settle_distance: float = 0.005
    #: Height (m) above the grasp point at which the fingers close. 0 closes at the grasp point; the
    #: weakened variant ("scripted-pick-place-weak") closes 4 cm early, on nothing, and retries the
    #: same way forever: a known failure a bounded regrasp fixes, which the evolver's tests use.
    close_height: float = 0.0


class ScriptedPickPlacePolicy:
    """Batched, stateless pick-and-place controller emitting OSC_POSE delta actions."""

    def __init__(self, params: PickPlaceParams | None = None, chunk_size: int = 1, name: str = "scripted-pick-place"
                 ) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.name = name
        self.params = params or PickPlaceParams()
        self.chunk_size = chunk_size

    @staticmethod
    def input_specs() -> list[TensorSpec]:
        """The observation tensors the policy reads (a subset of the manipulation schema)."""
        return [
            TensorSpec("robot0_eef_pos", "float32", (3,)),
            TensorSpec("robot0_gripper_qpos", "float32", (2,)),
            TensorSpec("task_object_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_target_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_grasped", "float32", (1,), privileged=True),
        ]

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """Actions of shape [B, chunk_size, 7]; the instruction is ignored (the goal is in the state).

        A chunk repeats the one action: the policy has no model of how the state evolves.
        """
        rows = len(batch["robot0_eef_pos"])
        actions = np.zeros((rows, 7))
        for i in range(rows):
            actions[i] = self._act(
                np.asarray(batch["robot0_eef_pos"][i], dtype=np.float64),
                np.asarray(batch["robot0_gripper_qpos"][i], dtype=np.float64),
                np.asarray(batch["task_object_bbox"][i], dtype=np.float64),
                np.asarray(batch["task_target_bbox"][i], dtype=np.float64),
                bool(batch["task_grasped"][i][0] > 0.5),
            )
        return np.repeat(actions[:, None, :], self.chunk_size, axis=1).astype(np.float32)

    def _act(
        self, eef: np.ndarray, fingers: np.ndarray, obj: np.ndarray, target: np.ndarray, grasped: bool
    ) -> np.ndarray:
        p = self.params
        if not obj.any() or not target.any():
            return self._action(np.zeros(3), _OPEN)  # no pick-and-place goal: hold still, hand open
        obj_center, obj_bottom = (obj[:3] + obj[3:]) / 2, obj[2]
        target_center, target_top = (target[:3] + target[3:]) / 2, target[5]
        if grasped:
            return self._carry(obj_center, obj_bottom, target_center, target_top)
        placed_xy = np.linalg.norm(obj_center[:2] - target_center[:2]) < p.place_tolerance
        if placed_xy and -p.placed_depth <= obj_bottom - target_top <= p.release_gap + 3 * p.z_tolerance:
            return self._move(eef, eef + [0.0, 0.0, _RETREAT], _OPEN)
        grasp = self._grasp_point(obj)
        gap = float(fingers[0] - fingers[1])
        aligned = np.linalg.norm(eef[:2] - grasp[:2]) < p.xy_tolerance * 1.5
        if aligned and eef[2] - grasp[2] < p.z_tolerance + p.close_height:
            if gap < p.closed_gap:
                return self._move(eef, eef + [0.0, 0.0, _BACK_OFF], _OPEN)  # closed on nothing
            return self._move(eef, grasp, _CLOSE)
        if gap < p.open_gap:
            return self._move(eef, eef + [0.0, 0.0, _REOPEN_RISE], _OPEN)  # open fully before approaching
        if np.linalg.norm(eef[:2] - grasp[:2]) > p.xy_tolerance:
            hover = np.array([grasp[0], grasp[1], obj[5] + p.hover_height])
            return self._move(eef, self._climb_first(eef, hover), _OPEN)
        return self._move(eef, grasp, _OPEN)

    def _grasp_point(self, obj: np.ndarray) -> np.ndarray:
        """Across the centre for narrow objects; on the rim, one finger inside, for wide ones."""
        p = self.params
        center = (obj[:3] + obj[3:]) / 2
        if (obj[3 + p.finger_axis] - obj[p.finger_axis]) / 2 <= p.max_center_half_width:
            return np.array([center[0], center[1], max(obj[5] - p.grasp_depth, obj[2] + p.min_grasp_height)])
        # A shallow dish (a plate) is gripped as low as the table allows.
        point = np.array([center[0], center[1], max(obj[5] - p.rim_depth, obj[2] + p.min_grasp_height)])
        point[p.finger_axis] = obj[3 + p.finger_axis] - p.rim_inset
        return point

    def _carry(self, center: np.ndarray, bottom: float, target_center: np.ndarray, target_top: float) -> np.ndarray:
        """Grasped: lift clear of the target, move over it, lower, then let go.

        Motions are computed for the object (its box centre and bottom), which moves with the hand,
        so the grasp offset does not matter.
        """
        p = self.params
        held = np.array([center[0], center[1], bottom])
        if np.linalg.norm(center[:2] - target_center[:2]) > p.carry_xy_tolerance:
            above = np.array([target_center[0], target_center[1], target_top + p.carry_clearance])
            return self._move(held, self._climb_first(held, above), _CLOSE, p.carry_max_action)
        release = np.array([target_center[0], target_center[1], target_top + p.release_gap])
        if abs(bottom - release[2]) > p.z_tolerance or np.linalg.norm(center[:2] - release[:2]) > p.xy_tolerance:
            return self._move(held, release, _CLOSE, p.carry_max_action)
        return self._action(np.zeros(3), _OPEN)

    def _climb_first(self, point: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Rise to the goal's height before moving sideways, so nothing on the table is swept."""
        if point[2] < goal[2] - _CLIMB_MARGIN:
            return np.array([point[0], point[1], goal[2]])
        return goal

    def _move(self, current: np.ndarray, goal: np.ndarray, gripper: float, limit: float | None = None) -> np.ndarray:
        return self._action(np.asarray(goal, dtype=np.float64) - current, gripper, limit)

    def _action(self, error: np.ndarray, gripper: float, limit: float | None = None) -> np.ndarray:
        p = self.params
        limit = p.max_action if limit is None else limit
        delta = error * p.gain
        largest = np.abs(delta).max()
        if np.linalg.norm(error) > p.settle_distance and largest < p.min_action:
            delta *= p.min_action / largest
        return np.concatenate([np.clip(delta, -limit, limit), np.zeros(3), [gripper]])
