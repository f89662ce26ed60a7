"""Generic object-relative predicates over a trajectory window.

Each predicate reads what a harness may know of the current goal stage (the perception tool's
noisy boxes of the object and the target, the grip site, the physical signals ``phi_*``,
milestones) and returns the evidence details (numbers that justify it) when it holds, ``None``
otherwise. None names a task or holds a task
constant, so a critic built from them transfers by rebinding. Their parameters and ranges are in
:data:`PREDICATES` (what the evolver searches).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from services.harness.runtime.api import Frame, Window
from services.harness.runtime.library import tools as t
from services.harness.runtime.library.schema import Param, PredicateSpec

Details = Mapping[str, float] | None


def _look_back(w: Window, p: Mapping[str, float]) -> tuple[int, Frame, Frame] | None:
    """The ``horizon`` parameter as a frame count, the frame that many frames back and the current
    one, or ``None`` while the window is shorter than that."""
    n = int(p["horizon"])
    if len(w.frames) < n:
        return None
    return n, w.frames[-n], w.now


def grasp_retained(w: Window, p: Mapping[str, float]) -> Details:
    """The object has been held for ``steps`` frames with less than ``max_drift`` of slip."""
    n = int(p["steps"])
    if len(w.frames) < n:
        return None
    recent = w.frames[-n:]
    if not all(t.grasped(f) for f in recent):
        return None
    drift = t.scalar(w.now, "phi_object_gripper_drift")
    if drift > p["max_drift"]:
        return None
    return {"held_steps": float(n), "drift": drift}


def grasp_lost(w: Window, p: Mapping[str, float]) -> Details:
    """The object was held for at least ``min_held`` frames of the window, has not been for the last
    ``confirm`` frames, and the gripper is still commanded closed (not a deliberate release)."""
    confirm, min_held = int(p["confirm"]), int(p["min_held"])
    frames = w.frames
    if len(frames) < confirm + min_held:
        return None
    grasped = t.grasped
    if any(grasped(f) for f in frames[-confirm:]) or t.gripper_command(w.now.action) <= 0.0:
        return None
    held = sum(1 for f in frames[:-confirm] if grasped(f))
    if held < min_held:
        return None
    return {"held_steps": float(held), "steps_since": float(confirm),
            "eef_object_dist": t.eef_object_dist(w.now) or 0.0}


def failed_acquisition(w: Window, p: Mapping[str, float]) -> Details:
    """The gripper closed near the object without holding it: fingers nearly shut, no grasp, the
    grip site within ``near`` of the object's box."""
    now = w.now
    if t.grasped(now):
        return None
    aperture = t.scalar(now, "phi_gripper_aperture")
    if aperture > p["closed_gap"]:
        return None
    dist = t.eef_object_dist(now)
    if dist is None or dist > p["near"]:
        return None
    return {"aperture": aperture, "eef_object_dist": dist}


def stalled_progress(w: Window, p: Mapping[str, float]) -> Details:
    """Over the last ``horizon`` frames the hand moved less than ``min_motion`` in all and no new
    milestone was reached."""
    if (back := _look_back(w, p)) is None:
        return None
    n, first, now = back
    if now.milestones - first.milestones:
        return None
    if t.distance(t.vec(first, "robot0_eef_pos"), t.vec(now, "robot0_eef_pos")) >= p["min_motion"]:
        return None  # the straight distance bounds the path from below: no need to sum it
    track = np.array([f.obs["robot0_eef_pos"] for f in w.frames[-n:]], dtype=np.float64)
    path = float(np.linalg.norm(np.diff(track, axis=0), axis=1).sum())
    if path >= p["min_motion"]:
        return None
    return {"path": path, "steps": float(n)}


def non_approach(w: Window, p: Mapping[str, float]) -> Details:
    """Not holding the object, farther than ``near`` from it, and not ``min_gain`` closer than
    ``horizon`` frames ago: the policy hovers short of the object or wanders."""
    if (back := _look_back(w, p)) is None or t.grasped(back[2]):
        return None
    n, first, now = back
    dist, before = t.eef_object_dist(now), t.eef_object_dist(first)
    if dist is None or before is None or dist <= p["near"] or before - dist >= p["min_gain"]:
        return None
    return {"eef_object_dist": dist, "gain": before - dist, "steps": float(n)}


def hovering_unacquired(w: Window, p: Mapping[str, float]) -> Details:
    """The hand has stayed within ``near`` of the object's box for ``horizon`` frames without
    grasping it and without a new milestone: it hovers over the object (a policy switching between
    descending and re-aligning bobs there) and never closes on it."""
    if (back := _look_back(w, p)) is None:
        return None
    n, first, now = back
    if now.milestones - first.milestones:
        return None
    farthest = 0.0
    for f in w.frames[-n:]:
        dist = t.eef_object_dist(f)
        if t.grasped(f) or dist is None or dist > p["near"]:
            return None
        farthest = max(farthest, dist)
    return {"farthest": farthest, "steps": float(n)}


def articulation_stalled(w: Window, p: Mapping[str, float]) -> Details:
    """An articulation stage (open/close a drawer, turn a knob) is not progressing: over the last
    ``horizon`` frames, all in that stage, no new milestone was reached, the hand came less than
    ``min_approach`` closer to the (perceived) handle and the handle moved less than
    ``min_progress``. Covers a policy that never heads for the handle and one that touches it
    without moving it; silent on every other stage, so it clears once the env moves on."""
    if (back := _look_back(w, p)) is None:
        return None
    n, first, now = back
    if not (t.articulation_stage(now) and t.articulation_stage(first)) or t.stage_kind(first) != t.stage_kind(now):
        return None
    if now.milestones - first.milestones:
        return None
    d0, d1 = t.eef_object_dist(first), t.eef_object_dist(now)
    h0, h1 = t.object_pos(first), t.object_pos(now)
    if d0 is None or d1 is None or h0 is None or h1 is None:
        return None
    approach, moved = d0 - d1, t.distance(h0, h1)
    if approach >= p["min_approach"] or moved >= p["min_progress"]:
        return None
    return {"approach": approach, "handle_motion": moved, "eef_handle_dist": d1, "steps": float(n)}


def approach_wrong_object(w: Window, p: Mapping[str, float]) -> Details:
    """The hand closed in on another object (by ``min_gain`` over ``horizon`` frames, to within
    ``near`` of it) while not closing in on the task object and farther from it than from that one."""
    if (back := _look_back(w, p)) is None or t.grasped(back[2]):
        return None
    n, first, now = back
    obj, obj0 = t.object_pos(now), t.object_pos(first)
    if obj is None or obj0 is None:
        return None
    eef, eef0 = t.vec(now, "robot0_eef_pos"), t.vec(first, "robot0_eef_pos")
    task_dist = t.distance(eef, obj)
    if t.distance(eef0, obj0) - task_dist >= p["min_gain"]:
        return None  # closing in on the task object itself
    others = t.other_object_positions(now)
    others = others[np.linalg.norm(others - obj, axis=1) > p["separation"]] if len(others) else others
    if not len(others):
        return None
    d_now = np.linalg.norm(others - eef, axis=1)
    d_before = np.linalg.norm(others - eef0, axis=1)
    k = int(np.argmin(d_now))
    if d_now[k] > p["near"] or d_before[k] - d_now[k] < p["min_gain"] or task_dist <= d_now[k]:
        return None
    return {"wrong_object_dist": float(d_now[k]), "task_object_dist": task_dist, "gain": float(d_before[k] - d_now[k])}


def drift(w: Window, p: Mapping[str, float]) -> Details:
    """The held object slipped more than ``max_drift`` in the hand since the grasp began."""
    now = w.now
    value = t.scalar(now, "phi_object_gripper_drift")
    if not t.grasped(now) or value <= p["max_drift"]:
        return None
    return {"drift": value}


def held_near_target(w: Window, p: Mapping[str, float]) -> Details:
    """Holding the object, lifted, with its centre within ``radius`` (horizontally) of the target's
    and its bottom above the target's top: the moment for a placement."""
    now = w.now
    if not t.grasped(now):
        return None
    obj, target = t.object_box(now), t.target_box(now)
    if not (t.has_box(obj) and t.has_box(target)):
        return None
    horizontal = _horizontal(obj, target)
    height = float(obj[2] - target[5])
    if horizontal > p["radius"] or height < -p["below"]:
        return None
    return {"horizontal": horizontal, "height": height}


def held_stalled_transport(w: Window, p: Mapping[str, float]) -> Details:
    """Holding the object but not bringing it ``min_gain`` closer to the target (horizontally)
    over ``horizon`` frames while still farther than ``near``: coarse transport has stalled."""
    if (back := _look_back(w, p)) is None:
        return None
    n, first, now = back
    if not all(t.grasped(f) for f in (now, first)):
        return None
    obj, target = t.object_box(now), t.target_box(now)
    obj0 = t.object_box(first)
    if not (t.has_box(obj) and t.has_box(target) and t.has_box(obj0)):
        return None
    d_now, d_before = _horizontal(obj, target), _horizontal(obj0, target)
    if d_now <= p["near"] or d_before - d_now >= p["min_gain"]:
        return None
    return {"target_dist": d_now, "gain": d_before - d_now, "steps": float(n)}


def supported_placement(w: Window, p: Mapping[str, float]) -> Details:
    """The object rests on (or in) the target: its centre over the target's box (inset by
    ``inset``), its bottom within ``gap`` above the target's top or down inside it, and it has
    come to rest (speed under ``max_speed``)."""
    now = w.now
    obj, target = t.object_box(now), t.target_box(now)
    if not (t.has_box(obj) and t.has_box(target)):
        return None
    o, g = obj.tolist(), target.tolist()
    height = o[2] - g[5]
    if height > p["gap"]:
        return None
    cx, cy = (o[0] + o[3]) / 2, (o[1] + o[4]) / 2
    inset = p["inset"]
    if not (g[0] + inset <= cx <= g[3] - inset and g[1] + inset <= cy <= g[4] - inset):
        return None
    speed = t.object_speed(w.frames, int(p["speed_frames"]))
    if speed > p["max_speed"]:
        return None
    return {"height": height, "speed": speed}


def blocked_motion(w: Window, p: Mapping[str, float]) -> Details:
    """For ``horizon`` frames the hand was commanded to move but realized less than ``ratio`` of it
    (``phi_eef_motion``): something blocks the arm."""
    if (back := _look_back(w, p)) is None:
        return None
    n = back[0]
    if len(t.vec(w.now, "phi_eef_motion")) < 6:
        return None
    commanded, realized = _motion(w.frames[-n:])
    if commanded < p["min_command"] or realized > p["ratio"] * commanded:
        return None
    return {"commanded": commanded, "realized": realized,
            "collision": t.scalar(w.now, "phi_collision_intensity")}


def _horizontal(a: np.ndarray, b: np.ndarray) -> float:
    """Horizontal distance between the centres of two boxes (the hot path of the placement critics:
    float arithmetic rather than a dozen small numpy calls)."""
    p, q = a.tolist(), b.tolist()
    if len(p) != 6 or len(q) != 6:
        return float(np.linalg.norm(t.box_center(a)[:2] - t.box_center(b)[:2]))
    dx, dy = (p[0] + p[3]) / 2 - (q[0] + q[3]) / 2, (p[1] + p[4]) / 2 - (q[1] + q[4]) / 2
    return math.sqrt(dx * dx + dy * dy)


def _motion(frames: Sequence[Frame]) -> tuple[float, float]:
    """Summed commanded and realized hand path (m) over ``frames`` (``phi_eef_motion``: commanded
    translation, then realized)."""
    commanded = realized = 0.0
    sqrt = math.sqrt
    for f in frames:
        m = f.obs["phi_eef_motion"]
        if len(m) < 6:  # as the array version: every frame's must have six numbers
            motion = np.array([g.obs["phi_eef_motion"] for g in frames], dtype=np.float64)
            return (float(np.linalg.norm(motion[:, :3], axis=1).sum()),
                    float(np.linalg.norm(motion[:, 3:6], axis=1).sum()))
        a, b, c, x, y, z = m[:6].tolist()
        commanded += sqrt(a * a + b * b + c * c)
        realized += sqrt(x * x + y * y + z * z)
    return commanded, realized


def contact_stability(w: Window, p: Mapping[str, float]) -> float:
    """Stability(s_t) in (0, 1] of the re-entry contract: 1 at rest, falling with the object's
    speed as perceived over the last ``horizon`` frames (``speed_scale`` m/s), the hand's speed
    (``hand_scale`` m/s) and the oscillation of the grip force over those frames (``force_scale`` N)."""
    n = max(1, int(p["horizon"]))
    frames = w.frames[-n:]
    speed = t.object_speed(w.frames, n)
    hand = 0.0
    if len(w.frames) > 1:
        k = min(n, len(w.frames) - 1)
        hand = float(np.linalg.norm(t.vec(w.now, "robot0_eef_pos") - t.vec(w.frames[-k - 1], "robot0_eef_pos"))) / (k * t.STEP_S)
    forces = [t.vec(f, "phi_contact_force") for f in frames]
    forces = [f for f in forces if len(f) == 3]
    oscillation = 0.0
    if len(forces) > 1:
        stack = np.stack(forces)
        oscillation = float(np.linalg.norm(stack.std(axis=0)))
    return math.exp(-(speed / p["speed_scale"] + hand / p["hand_scale"] + oscillation / p["force_scale"]))


def _f(default: float, low: float, high: float, doc: str) -> Param:
    return Param(default, low, high, "float", doc)


def _i(default: int, low: int, high: int, doc: str) -> Param:
    return Param(default, low, high, "int", doc)


#: Name -> predicate template with its parameter schema (the evolver's search space).
PREDICATES: dict[str, PredicateSpec] = {
    s.name: s
    for s in (
        PredicateSpec("grasp_retained", grasp_retained, {
            "steps": _i(5, 1, 50, "frames the grasp must have held"),
            "max_drift": _f(0.02, 0.002, 0.1, "largest slip in the hand (m)"),
        }, grasp_retained.__doc__ or "", holding=True),
        PredicateSpec("grasp_lost", grasp_lost, {
            "confirm": _i(3, 1, 20, "frames without the grasp before it counts as lost"),
            "min_held": _i(5, 1, 50, "frames the grasp must have held in the window before"),
        }, grasp_lost.__doc__ or "", holding=False),
        PredicateSpec("failed_acquisition", failed_acquisition, {
            "closed_gap": _f(0.01, 0.0, 0.05, "finger gap (m) under which the hand counts as shut"),
            "near": _f(0.05, 0.0, 0.2, "grip site to object box (m) under which the closure was an attempt"),
        }, failed_acquisition.__doc__ or "", holding=False),
        PredicateSpec("stalled_progress", stalled_progress, {
            "horizon": _i(30, 2, 200, "frames looked back"),
            "min_motion": _f(0.02, 0.0, 0.3, "path length of the hand (m) that counts as progress"),
        }, stalled_progress.__doc__ or ""),
        PredicateSpec("non_approach", non_approach, {
            "horizon": _i(20, 2, 200, "frames looked back"),
            "near": _f(0.015, 0.0, 0.2, "grip site to object box (m) that counts as arrived"),
            "min_gain": _f(0.01, 0.0, 0.2, "how much closer (m) the hand must have come"),
        }, non_approach.__doc__ or "", holding=False),
        PredicateSpec("hovering_unacquired", hovering_unacquired, {
            "horizon": _i(45, 5, 200, "frames the hand must have stayed near the object"),
            "near": _f(0.12, 0.0, 0.3, "grip site to object box (m) that counts as at the object"),
        }, hovering_unacquired.__doc__ or "", holding=False),
        PredicateSpec("approach_wrong_object", approach_wrong_object, {
            "horizon": _i(15, 2, 200, "frames looked back"),
            "near": _f(0.08, 0.01, 0.3, "distance (m) to the other object that counts as approaching it"),
            "min_gain": _f(0.03, 0.0, 0.3, "how much closer (m) to the other object"),
            "separation": _f(0.03, 0.0, 0.2, "detections nearer than this (m) to the task object are the task object"),
        }, approach_wrong_object.__doc__ or "", holding=False),
        PredicateSpec("articulation_stalled", articulation_stalled, {
            "horizon": _i(40, 5, 200, "frames looked back"),
            "min_approach": _f(0.02, 0.0, 0.2, "how much closer (m) to the handle the hand must have come"),
            "min_progress": _f(0.015, 0.0, 0.1, "how far (m) the handle must have moved (above perception jitter)"),
        }, articulation_stalled.__doc__ or ""),
        PredicateSpec("drift", drift, {
            "max_drift": _f(0.03, 0.002, 0.2, "slip in the hand (m) that counts as drift"),
        }, drift.__doc__ or "", holding=True),
        PredicateSpec("held_near_target", held_near_target, {
            "radius": _f(0.06, 0.0, 0.3, "horizontal distance (m) of object to target centre"),
            "below": _f(0.0, 0.0, 0.1, "how far (m) the object bottom may be below the target top"),
        }, held_near_target.__doc__ or "", holding=True),
        PredicateSpec("held_stalled_transport", held_stalled_transport, {
            "horizon": _i(25, 2, 200, "frames looked back"),
            "near": _f(0.03, 0.0, 0.3, "horizontal distance (m) to the target that counts as arrived"),
            "min_gain": _f(0.02, 0.0, 0.3, "how much closer (m) the object must have come"),
        }, held_stalled_transport.__doc__ or "", holding=True),
        PredicateSpec("supported_placement", supported_placement, {
            "inset": _f(0.0, -0.05, 0.1, "margin (m) inside the target box for the object centre"),
            "gap": _f(0.02, 0.0, 0.1, "largest height (m) of the object bottom over the target top"),
            "max_speed": _f(0.05, 0.0, 1.0, "largest object speed (m/s) at rest"),
            "speed_frames": _i(10, 1, 20, "frames the perceived speed is measured over (averages out perception jitter)"),
        }, supported_placement.__doc__ or ""),
        PredicateSpec("blocked_motion", blocked_motion, {
            "horizon": _i(10, 2, 100, "frames looked back"),
            "min_command": _f(0.02, 0.0, 0.5, "commanded path (m) below which nothing is judged"),
            "ratio": _f(0.2, 0.0, 1.0, "realized / commanded path under which the arm counts as blocked"),
        }, blocked_motion.__doc__ or ""),
    )
}

#: Parameters of :func:`contact_stability` (the re-entry contract's Stability(s_t)).
STABILITY_PARAMS: dict[str, Param] = {
    "horizon": _i(10, 1, 50, "frames of speed and grip-force history (long enough to average out perception jitter)"),
    "speed_scale": _f(0.1, 0.001, 2.0, "perceived object speed (m/s) that divides stability by e"),
    "hand_scale": _f(0.1, 0.001, 1.0, "hand speed (m/s) that divides stability by e"),
    "force_scale": _f(5.0, 0.1, 100.0, "grip-force oscillation (N) that divides stability by e"),
}
