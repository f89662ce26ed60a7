"""Tools of the built-in library: perception on live frames, motion with collision checks, grasp proposals.

Objects are known only through the frame's perception tool (``frame.perceive``: noisy boxes of
the object the current step is about, of its target and of the rest of the scene;
services/harness/runtime/perception.py), the robot through proprioception (``robot0_eef_pos``/
``_quat``) and the physical signals ``phi_*``; never a task constant, so a recovery written with
these tools transfers to any pick-and-place stage. Actions are robosuite OSC_POSE deltas:
translation scaled to [-1, 1] (1.0 = 5 cm), rotation as an axis-angle scaled to [-1, 1] (1.0 =
0.5 rad), then the gripper (-1 opens, +1 closes, 0 keeps the current opening: the Panda gripper
integrates its command).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.common.rotations import quat_to_mat, rotvec
from services.harness.runtime.api import Detection, Frame
from services.common.milestone_kinds import STAGE_KINDS

OPEN, CLOSE, KEEP = -1.0, 1.0, 0.0
#: The hand pointing down with the fingers closing along world y (the default Panda pose).
DOWN = np.diag([1.0, -1.0, -1.0])
#: Stage kinds that move a handle (a drawer, a knob) instead of carrying an object.
ARTICULATION_KINDS = ("open", "close", "turnon", "turnoff")
#: Seconds per env step (LIBERO and robosuite run their controllers at 20 Hz).
STEP_S = 0.05
_NO_BOX = np.zeros(6)


# ---- reading a frame ----------------------------------------------------------------------------


def vec(frame: Frame, name: str) -> np.ndarray:
    """Observation tensor ``name`` of a frame, not copied: read it, never write it (zeros(1) when absent)."""
    value = frame.obs.get(name)
    if value is None:
        return np.zeros(1)
    return value if isinstance(value, np.ndarray) else np.asarray(value, dtype=np.float64)


def scalar(frame: Frame, name: str) -> float:
    """First element of an observation tensor (the ``phi_*`` scalars)."""
    value = frame.obs.get(name)
    return float(value[0]) if value is not None and len(value) else 0.0


def detection(frame: Frame, query: str) -> Detection | None:
    """The perception tool's estimate of ``"object"`` or ``"target"`` on this frame (None: not detected)."""
    found: Any = frame.perceive(query)
    return found if isinstance(found, Detection) else None


def object_box(frame: Frame) -> np.ndarray:
    """Estimated box of the object the current step is about (zeros when not detected)."""
    d = detection(frame, "object")
    return _NO_BOX if d is None else d.box


def target_box(frame: Frame) -> np.ndarray:
    """Estimated box of where the object must go (zeros when not detected or the step has none)."""
    d = detection(frame, "target")
    return _NO_BOX if d is None else d.box


def object_pos(frame: Frame) -> np.ndarray | None:
    """Estimated centre of the object, None when not detected."""
    d = detection(frame, "object")
    return None if d is None else d.pos


def box_center(box: np.ndarray) -> np.ndarray:
    """Centre of an [min xyz, max xyz] box."""
    return (box[:3] + box[3:]) / 2


def has_box(box: np.ndarray) -> bool:
    """Whether a box is bound (zeros when nothing was detected)."""
    if box is _NO_BOX:
        return False
    if type(box) is np.ndarray and box.ndim == 1:
        return any(box.tolist())  # (a Python loop over six floats: cheaper than np.any)
    return bool(np.any(box))


def _floats(a: object, n: int) -> list[float] | None:
    """``a`` as a list of ``n`` Python floats, None when it has another shape."""
    values = a.tolist() if type(a) is np.ndarray else np.asarray(a, dtype=np.float64).tolist()
    return values if type(values) is list and len(values) == n and type(values[0]) is not list else None


def box_distance(point: np.ndarray, box: np.ndarray) -> float:
    """Distance (m) from a point to a box, 0 inside it."""
    p, b = _floats(point, 3), _floats(box, 6)
    if p is None or b is None:
        gap = np.maximum(np.maximum(box[:3] - point, point - box[3:]), 0.0)
        return float(np.linalg.norm(gap))
    # Per-step hot path (every distance-based critic): float arithmetic, not six numpy calls.
    x, y, z = p
    gx, gy, gz = max(b[0] - x, x - b[3], 0.0), max(b[1] - y, y - b[4], 0.0), max(b[2] - z, z - b[5], 0.0)
    return math.sqrt(gx * gx + gy * gy + gz * gz)


def eef_object_dist(frame: Frame) -> float | None:
    """Distance (m) from the grip site to the estimated object box; None when not detected."""
    box = object_box(frame)
    return box_distance(vec(frame, "robot0_eef_pos"), box) if has_box(box) else None


def object_speed(frames: Sequence[Frame], horizon: int) -> float:
    """Estimated speed (m/s) of the object over the last ``horizon`` frames (0 when not seen at both ends)."""
    if len(frames) < 2:
        return 0.0
    n = min(max(1, horizon), len(frames) - 1)
    a, b = object_pos(frames[-n - 1]), object_pos(frames[-1])
    if a is None or b is None:
        return 0.0
    return distance(a, b) / (n * STEP_S)


def distance(a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance between two points (float arithmetic for 3-vectors)."""
    p, q = _floats(a, 3), _floats(b, 3)
    if p is None or q is None:
        return float(np.linalg.norm(np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)))
    dx, dy, dz = q[0] - p[0], q[1] - p[1], q[2] - p[2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


def grasped(frame: Frame) -> bool:
    """The grasp predicate (both fingers touch the task object)."""
    value = frame.obs.get("phi_grasp")
    return value is not None and len(value) > 0 and float(value[0]) > 0.5


def gripper_command(action: np.ndarray | None) -> float:
    """The gripper part of an action, 0 when there is none."""
    return 0.0 if action is None or len(action) < 7 else float(action[6])


def other_object_positions(frame: Frame) -> np.ndarray:
    """Estimated positions of the scene's other objects ([n, 3]; those the detector missed are absent)."""
    found: Any = frame.perceive("others")
    pos = [d.pos for d in found or () if isinstance(d, Detection)]
    return np.array(pos, dtype=np.float64).reshape(-1, 3)


# ---- the stage being worked on (task knowledge) -------------------------------------------------


def stage_kind(frame: Frame) -> str:
    """Predicate kind of the goal stage being worked on (``task_stage`` one-hot; "" when unpublished)."""
    stage = frame.obs.get("task_stage")
    if stage is None or len(stage) != len(STAGE_KINDS) or not np.any(stage):
        return ""
    return STAGE_KINDS[int(np.argmax(stage))]


def articulation_stage(frame: Frame) -> bool:
    """The stage moves a handle (open/close a drawer, turn a knob) and the handle is detected."""
    return stage_kind(frame) in ARTICULATION_KINDS and has_box(object_box(frame))


# ---- orientation --------------------------------------------------------------------------------


def orient_action(eef_quat: np.ndarray, desired: np.ndarray, gain: float = 1.0, limit: float = 0.6) -> np.ndarray:
    """Rotation part of an action turning the hand toward ``desired`` (OSC scales 1.0 to 0.5 rad)."""
    error = rotvec(desired @ quat_to_mat(eef_quat).T)
    return np.clip(error * gain / 0.5, -limit, limit)


# ---- straight-line motion with collision checks -------------------------------------------------


def segment_hits_box(p0: np.ndarray, p1: np.ndarray, box: np.ndarray, margin: float = 0.0) -> bool:
    """Whether the segment p0-p1 passes through the box grown by ``margin`` (slab test)."""
    lo, hi = box[:3] - margin, box[3:] + margin
    d = p1 - p0
    t0, t1 = 0.0, 1.0
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if p0[k] < lo[k] or p0[k] > hi[k]:
                return False
            continue
        a, b = (lo[k] - p0[k]) / d[k], (hi[k] - p0[k]) / d[k]
        if a > b:
            a, b = b, a
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return False
    return True


def clear_waypoint(start: np.ndarray, goal: np.ndarray, obstacles: Iterable[np.ndarray], margin: float,
                   clearance: float) -> np.ndarray:
    """The next waypoint of a straight-line move from ``start`` to ``goal`` that avoids the boxes.

    If the straight line crosses an obstacle (grown by ``margin``), the move first rises straight
    up to ``clearance`` above the highest crossed box, then goes across at that height.
    """
    blocking = [b for b in obstacles if has_box(b) and segment_hits_box(start, goal, b, margin)]
    if not blocking:
        return goal
    safe_z = max(float(b[5]) for b in blocking) + clearance
    if start[2] < safe_z - 0.01:
        return np.array([start[0], start[1], max(safe_z, goal[2])])
    return np.array([goal[0], goal[1], max(safe_z, goal[2])])


def move_action(current: np.ndarray, goal: np.ndarray, gripper: float, gain: float = 12.0, max_action: float = 1.0,
                min_action: float = 0.2, settle: float = 0.005) -> np.ndarray:
    """Proportional translation toward ``goal`` (OSC_POSE units), clipped; a floor on the largest
    component while farther than ``settle`` keeps a loaded arm from stalling short of the goal."""
    error = np.asarray(goal, dtype=np.float64) - np.asarray(current, dtype=np.float64)
    delta = error * gain
    largest = float(np.abs(delta).max())
    if np.linalg.norm(error) > settle and 0.0 < largest < min_action:
        delta *= min_action / largest
    return np.concatenate([np.clip(delta, -max_action, max_action), np.zeros(3), [gripper]])


# ---- grasp proposals ----------------------------------------------------------------------------


@dataclass(frozen=True)
class GraspProposal:
    """A grasp relative to the live object box: the grip point's offset from the box's top centre
    (metres, world axes) and the horizontal axis the fingers close along (0 = x, 1 = y)."""

    offset: tuple[float, float, float]
    finger_axis: int

    def point(self, box: np.ndarray) -> np.ndarray:
        """The grip point on the object as it is now."""
        top = np.array([(box[0] + box[3]) / 2, (box[1] + box[4]) / 2, box[5]])
        return top + np.asarray(self.offset)

    def equivalent(self, other: "GraspProposal", tolerance: float) -> bool:
        """Same finger axis and grip points within ``tolerance``: retrying it would repeat a failure."""
        return self.finger_axis == other.finger_axis and float(
            np.linalg.norm(np.subtract(self.offset, other.offset))
        ) < tolerance


def sample_grasps(box: np.ndarray, max_width: float = 0.07, depths: Sequence[float] = (0.03, 0.015, 0.045),
                  shifts: Sequence[float] = (0.0, 0.012, -0.012), min_height: float = 0.012,
                  rim_inset: float = 0.012, rim_depths: Sequence[float] = (0.02, 0.012)) -> list[GraspProposal]:
    """Object-relative grasp proposals, best first.

    Axes across which the object is narrower than ``max_width`` (the open hand's reach) come first,
    narrowest first; for each, grip depths below the top (not lower than ``min_height`` above the
    bottom), then small shifts along the object's long horizontal side. An object wider than the
    hand both ways (a bowl, a plate) cannot be gripped across: it is gripped by its rim, the grip
    point ``rim_inset`` inside one edge with the fingers closing across the wall (one inside, one
    outside), ``rim_depths`` below the top; each of the four sides in turn.
    """
    widths = [float(box[3] - box[0]), float(box[4] - box[1])]
    height = float(box[5] - box[2])
    axes = sorted((0, 1), key=lambda a: widths[a])
    out: list[GraspProposal] = []
    if not any(widths[a] <= max_width for a in axes):
        for axis in axes:
            for sign in (1.0, -1.0):
                for depth in rim_depths:
                    offset = [0.0, 0.0, -min(depth, max(height - min_height, 0.0))]
                    offset[axis] = sign * max(widths[axis] / 2 - rim_inset, 0.0)
                    out.append(GraspProposal((offset[0], offset[1], offset[2]), axis))
        return out
    for axis in (a for a in axes if widths[a] <= max_width):
        along = 1 - axis
        for depth in depths:
            dz = -min(depth, max(height - min_height, 0.0))
            for shift in shifts:
                offset = [0.0, 0.0, dz]
                offset[along] = shift
                out.append(GraspProposal((offset[0], offset[1], offset[2]), axis))
    return out


def fresh_grasp(box: np.ndarray, failed: Sequence[GraspProposal], tolerance: float,
                params: Mapping[str, float] | None = None) -> GraspProposal | None:
    """The best proposal not equivalent to any failed one; None when every proposal failed."""
    p = dict(params or {})
    for proposal in sample_grasps(box, max_width=p.get("max_width", 0.07)):
        if not any(proposal.equivalent(f, tolerance) for f in failed):
            return proposal
    return None
