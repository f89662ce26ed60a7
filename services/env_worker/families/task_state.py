"""Privileged task state of a manipulation scene: the current goal stage, milestones and signals.

One :class:`TaskState` per environment (rebuilt when a slot switches task) turns a goal plan
(services/env_worker/milestones.py) into what the observation carries besides the robot:

* the stage being worked on and its geometry: ``task_object_*`` (the object to move, or the
  handle of the drawer/knob to actuate), ``task_target_*`` (where it must go), ``task_grasped``,
  ``task_stage`` (predicate kind, one-hot) and ``task_motion_dir``;
* ``milestones`` / ``milestones_reached`` (mu_t and its running union);
* the physio-auxiliary signals ``phi_*`` (services/env_worker/signals.py).

It reads raw MuJoCo arrays through ``env.sim`` and a few robosuite attributes (robot gripper geoms,
controller scaling), and LIBERO's scene dictionaries in :func:`for_libero`; it does not import
either package, so both families can use it. Success is not decided here: the families use the
environment's own ``_check_success``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from services.common.milestone_kinds import OBSTACLE_SLOTS
from services.env_worker import signals as sig
from services.env_worker.milestones import (
    LIFT_HEIGHT,
    GoalPlan,
    MilestoneTracker,
    SceneFacts,
    derive_plan,
)

_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_GEOM_BOX, _GEOM_CYLINDER, _GEOM_CAPSULE = 6, 5, 3
_JOINT_FREE, _JOINT_SLIDE, _JOINT_HINGE = 0, 2, 3
#: Body name prefixes of the robot (arm and gripper) for collision intensity; the mount is static.
ROBOT_PREFIXES = ("robot0_", "gripper0_")
#: How far (m) around the stage's object and target boxes, and below the lower of their bottoms
#: (the table under them, not the floor), obstacles are reported (in OBSTACLE_SLOTS rows).
OBSTACLE_REACH = 0.15
OBSTACLE_DEPTH = 0.05


def _raw(env: Any) -> tuple[Any, Any]:
    return env.sim.model._model, env.sim.data._data


def geoms_box(model: Any, data: Any, ids: np.ndarray) -> np.ndarray:
    """World axis-aligned box [min xyz, max xyz] around geoms, from their compiled local boxes."""
    return _geoms_box(model.geom_aabb, data.geom_xmat, data.geom_xpos, np.asarray(ids, dtype=np.int64))


@njit(cache=True)
def _geoms_box(aabb: np.ndarray, xmat: np.ndarray, xpos: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """The corners of each geom's local box, rotated and moved into the world, and the box around
    them all: one compiled loop in place of ten numpy calls (a 40-geom bowl cost 45 us, now 3).
    Each corner coordinate sums its three products as (x + z) + y, the order numpy's einsum used
    here before, so the boxes are the same bits as they were."""
    out = np.empty(6)
    out[:3] = np.inf
    out[3:] = -np.inf
    corner = np.empty(3)
    for k in ids:
        for n in range(8):
            for j in range(3):
                corner[j] = aabb[k, j] + aabb[k, 3 + j] * _BOX_CORNERS[n, j]
            for i in range(3):
                row = 3 * i
                w = (xmat[k, row] * corner[0] + xmat[k, row + 2] * corner[2]) + xmat[k, row + 1] * corner[1]
                w = w + xpos[k, i]
                out[i] = min(out[i], w)
                out[3 + i] = max(out[3 + i], w)
    return out


def warm_up() -> float:
    """Compile :func:`_geoms_box` (or load it from numba's disk cache); returns the seconds it took."""
    import time

    start = time.perf_counter()
    _geoms_box(np.zeros((1, 6)), np.eye(3).reshape(1, 9), np.zeros((1, 3)), np.zeros(1, dtype=np.int64))
    return time.perf_counter() - start


def site_box(model: Any, data: Any, site: int) -> np.ndarray:
    """World axis-aligned box around a site (LIBERO regions are box or cylinder sites)."""
    size = model.site_size[site]
    kind = model.site_type[site]
    if kind == _GEOM_BOX:
        half = size
    elif kind in (_GEOM_CYLINDER, _GEOM_CAPSULE):
        half = np.array([size[0], size[0], size[1]])
    else:
        half = np.full(3, size[0])
    world = _BOX_CORNERS * half @ data.site_xmat[site].reshape(3, 3).T + data.site_xpos[site]
    return np.concatenate([world.min(axis=0), world.max(axis=0)])


def _quat_xyzw(mat: np.ndarray) -> np.ndarray:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.asarray(mat, dtype=np.float64).reshape(9))
    return np.array([q[1], q[2], q[3], q[0]])


def collision_geoms(model: Any, bodies: set[int]) -> np.ndarray:
    """Geoms of ``bodies`` that take part in collisions (LIBERO's visual meshes do not)."""
    ids = [
        g for g in range(model.ngeom)
        if int(model.geom_bodyid[g]) in bodies and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]
    return np.array(ids, dtype=np.int64)


def subtree(model: Any, root: int) -> set[int]:
    """``root`` and every body below it."""
    out = {root}
    for body in range(root + 1, model.nbody):
        if int(model.body_parentid[body]) in out:
            out.add(body)
    return out


@dataclass(frozen=True)
class Part:
    """A goal argument: a body (object, fixture) with its collision geoms, or a site (region)."""

    name: str
    body_id: int | None
    site_id: int | None
    geoms: np.ndarray

    def pose(self, model: Any, data: Any) -> tuple[np.ndarray, np.ndarray]:
        """Position and xyzw quaternion."""
        if self.body_id is not None:
            q = data.xquat[self.body_id]
            return np.array(data.xpos[self.body_id]), np.array([q[1], q[2], q[3], q[0]])
        if self.site_id is not None:
            return np.array(data.site_xpos[self.site_id]), _quat_xyzw(data.site_xmat[self.site_id])
        return np.zeros(3), np.zeros(4)

    def bbox(self, model: Any, data: Any) -> np.ndarray:
        """World box of the collision geoms, or of the site; a point box at the pose otherwise."""
        if len(self.geoms):
            return geoms_box(model, data, self.geoms)
        if self.site_id is not None:
            return site_box(model, data, self.site_id)
        pos = self.pose(model, data)[0]
        return np.concatenate([pos, pos])


@dataclass(frozen=True)
class Articulation:
    """The joint behind an articulated goal argument (drawer, door, knob) and its handle.

    ``targets`` maps a predicate kind (open, close, turnon, turnoff) to the joint position the
    benchmark's ranges put in the middle of that state. The handle is the moving geom to pull or
    push: for a slide joint the one furthest along the opening direction (a drawer's handle bar),
    for a hinge the one furthest from the axis among the highest (a knob's lever, a door's edge).
    """

    name: str
    joint: int
    qposadr: int
    hinge: bool
    body: int
    moving_geoms: np.ndarray
    handle_geom: int
    targets: Mapping[str, float]

    def qpos(self, data: Any) -> float:
        return float(data.qpos[self.qposadr])

    def handle_bbox(self, model: Any, data: Any) -> np.ndarray:
        return geoms_box(model, data, np.array([self.handle_geom]))

    def motion(self, model: Any, data: Any, kind: str) -> tuple[np.ndarray, float]:
        """Unit world direction the handle moves to reach ``kind``'s state, and how far (m) it still is."""
        goal = self.targets.get(kind)
        if goal is None:
            return np.zeros(3), 0.0
        delta = goal - self.qpos(data)
        axis = np.array(data.xaxis[self.joint])
        if not self.hinge:
            return np.sign(delta) * axis, abs(delta)
        center = (self.handle_bbox(model, data)[:3] + self.handle_bbox(model, data)[3:]) / 2
        radial = center - data.xanchor[self.joint]
        radial = radial - axis * float(radial @ axis)
        tangent = np.cross(axis, radial)
        norm = float(np.linalg.norm(tangent))
        if norm < 1e-9:
            return np.zeros(3), 0.0
        return np.sign(delta) * tangent / norm, abs(delta) * float(np.linalg.norm(radial))


def articulation(model: Any, data: Any, name: str, joint_name: str, ranges: Mapping[str, Any]) -> Articulation:
    """Resolve the joint ``joint_name`` of ``name`` and pick its handle (see :class:`Articulation`)."""
    import mujoco

    joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint_name)
    if joint < 0:
        raise ValueError(f"{name}: no joint {joint_name!r}")
    body = int(model.jnt_bodyid[joint])
    geoms = collision_geoms(model, subtree(model, body))
    if not len(geoms):
        raise ValueError(f"{name}: joint {joint_name!r} moves no collision geom")
    targets = {
        kind: float(np.mean(ranges[f"default_{kind}_ranges"]))
        for kind in ("open", "close", "turnon", "turnoff")
        if len(ranges.get(f"default_{kind}_ranges", ()) or ()) == 2
    }
    hinge = int(model.jnt_type[joint]) == _JOINT_HINGE
    axis = np.array(data.xaxis[joint])
    centers = np.array(data.geom_xpos[geoms])
    if not hinge:
        sign = np.sign(targets["open"] - targets["close"]) if {"open", "close"} <= set(targets) else 1.0
        handle = int(geoms[np.argmax(centers @ (sign * axis))])
    else:
        tops = np.array([geoms_box(model, data, np.array([g]))[5] for g in geoms])
        high = tops >= tops.max() - 0.01
        radial = centers - data.xanchor[joint]
        radial = radial - np.outer(radial @ axis, axis)
        distance = np.where(high, np.linalg.norm(radial, axis=1), -1.0)
        handle = int(geoms[np.argmax(distance)])
    return Articulation(name, joint, int(model.jnt_qposadr[joint]), hinge, body, geoms, handle, targets)


class Obstacles:
    """World boxes of what stands around a stage's object and target (``task_obstacle_bbox``).

    The collision geoms of everything but the robot: a free-moving object as one box (its geoms
    together), a fixture geom by geom (a wine rack or a cabinet is far from a box), leaving out the
    body the stage moves (the object, or the drawer behind a handle). A scripted controller plans
    around them (services/policy_worker/models/oracle.py); the nearest to the line from the object
    to the target come first and zero rows pad, so the tensor has one shape for every scene.
    """

    def __init__(self, model: Any, robot_prefixes: tuple[str, ...]) -> None:
        import mujoco

        free = {int(model.jnt_bodyid[j]) for j in range(model.njnt) if int(model.jnt_type[j]) == _JOINT_FREE}
        groups: dict[tuple[str, int], list[int]] = {}
        for g in range(model.ngeom):
            if not (model.geom_contype[g] or model.geom_conaffinity[g]):
                continue
            body = int(model.geom_bodyid[g])
            if (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or "").startswith(robot_prefixes):
                continue
            root = body
            while root and root not in free:
                root = int(model.body_parentid[root])
            groups.setdefault(("object", root) if root in free else ("geom", g), []).append(g)
        members = list(groups.values())
        self._geoms = np.array([g for ids in members for g in ids], dtype=np.int64)
        self._starts = np.cumsum([0] + [len(ids) for ids in members[:-1]]).astype(np.int64)
        self._bodies = np.array([int(model.geom_bodyid[ids[0]]) for ids in members], dtype=np.int64)
        self._masks: dict[frozenset[int], np.ndarray] = {}

    def boxes(self, model: Any, data: Any, moved: frozenset[int], obj: np.ndarray, target: np.ndarray) -> np.ndarray:
        """[OBSTACLE_SLOTS, 6] boxes near ``obj`` and ``target`` (world boxes), ``moved`` bodies left out."""
        out = np.zeros((OBSTACLE_SLOTS, 6))
        if not len(self._geoms):
            return out
        ids = self._geoms
        local = model.geom_aabb[ids]
        rot = data.geom_xmat[ids].reshape(-1, 3, 3)
        center = np.einsum("kij,kj->ki", rot, local[:, :3]) + data.geom_xpos[ids]
        half = np.einsum("kij,kj->ki", np.abs(rot), local[:, 3:])  # the rotated box's world extent
        boxes = np.concatenate([np.minimum.reduceat(center - half, self._starts),
                                np.maximum.reduceat(center + half, self._starts)], axis=1)
        lo = np.minimum(obj[:2], target[:2]) - OBSTACLE_REACH
        hi = np.maximum(obj[3:5], target[3:5]) + OBSTACLE_REACH
        keep = ((boxes[:, 0] < hi[0]) & (boxes[:, 3] > lo[0]) & (boxes[:, 1] < hi[1]) & (boxes[:, 4] > lo[1])
                & (boxes[:, 5] > min(obj[2], target[2]) - OBSTACLE_DEPTH) & self._others(moved))
        boxes = boxes[keep]
        # Distance of each box to the segment between the two box centres, nearest first.
        a, b = (obj[:2] + obj[3:5]) / 2, (target[:2] + target[3:5]) / 2
        ab = b - a
        t = np.clip(((boxes[:, :2] + boxes[:, 3:5]) / 2 - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        nearest = a + t[:, None] * ab
        gap = np.maximum(np.maximum(boxes[:, :2] - nearest, nearest - boxes[:, 3:5]), 0.0)
        order = np.argsort(np.hypot(gap[:, 0], gap[:, 1]), kind="stable")[:OBSTACLE_SLOTS]
        out[:len(order)] = boxes[order]
        return out

    def _others(self, moved: frozenset[int]) -> np.ndarray:
        """Which groups do not belong to the ``moved`` bodies (cached per set)."""
        mask = self._masks.get(moved)
        if mask is None:
            mask = self._masks[moved] = ~np.isin(self._bodies, list(moved))
        return mask


class TaskState:
    """Stage, milestones and signals of one environment; implements milestones.Probe."""

    def __init__(
        self,
        env: Any,
        plan: GoalPlan,
        parts: Mapping[str, Part],
        articulations: Mapping[str, Articulation],
        holds: Callable[[tuple[str, ...]], bool],
    ) -> None:
        self.env = env
        self.plan = plan
        self.parts = dict(parts)
        self.articulations = dict(articulations)
        self._holds = holds
        self.tracker = MilestoneTracker(plan)
        model, _ = _raw(env)
        gripper = env.robots[0].gripper
        names = gripper.important_geoms
        self._geoms = sig.robot_geoms(
            model, names["left_finger"], names["right_finger"], list(gripper.contact_geoms), ROBOT_PREFIXES
        )
        self.signals = sig.SignalTracker(self._geoms)
        self._eef_site = int(env.robots[0].eef_site_id)
        self._contacts = sig.Contacts.empty()
        self._forces = False  # whether _contacts holds the forces too
        self._action: np.ndarray | None = None  # the last executed action (None after a reset)
        self._sets: dict[str, frozenset[int]] = {}
        self._boxes: dict[str, np.ndarray] = {}  # boxes of the state being observed
        self._obstacles = Obstacles(model, ROBOT_PREFIXES)
        self._moved: dict[int, frozenset[int]] = {}
        self._started = False
        self._grasped = 0.0
        #: Set by a family whose goal has no target to point at (robosuite Lift): a fixed point.
        self.lift_target: np.ndarray | None = None

    # -- episode ---------------------------------------------------------------------------------

    def start(self) -> None:
        """A new episode begins with the next :meth:`observe` (call after the reset's settle steps)."""
        self.signals.reset()
        self._started = False

    def advance(self, action: np.ndarray | None) -> None:
        """What every step must do, observed or not: latch milestones and the signals' state.

        ``action`` is the one just executed (None at reset). The tensors of this state come from
        :meth:`observation`, called only where an observation is read (the last step of an action
        chunk without a harness), since building them costs several times what the latching does.
        """
        model, data = _raw(self.env)
        # Which robot geoms touch what; forces are read only if this state is observed.
        self._contacts = sig.read_contacts(model, data, self._geoms.all_geoms, forces=False)
        self._forces = False
        self._boxes = {}
        self._action = action
        if not self._started:
            self.tracker.start(self)
            self._started = True
        else:
            self.tracker.update(self, latch_only=True)
        geoms, _, pos = self._subject(model, data)
        self.signals.track(self._contacts, geoms, pos, self.eef(), self._eef_mat(data))
        self._grasped = float(self.signals.grasping)

    def observation(self) -> dict[str, np.ndarray]:
        """Task tensors of the state the last :meth:`advance` reached."""
        model, data = _raw(self.env)
        if not self._forces:
            self._contacts = sig.read_contacts(model, data, self._geoms.all_geoms)  # only the robot's are read
            self._forces = True
        self.tracker.refresh(self)
        out = self._stage_tensors(model, data)
        out.update(self.tracker.tensors())
        out.update(self._signals(model, data, self._action, out))
        out["task_grasped"] = out["phi_grasp"].copy()
        return out

    def names(self) -> list[str]:
        return self.plan.names

    def info(self) -> dict[str, float]:
        """Numeric diagnostics of the last observation, for StepResult.info."""
        explicit = [ok for ok, s in zip(self.tracker.stage_holds, self.plan.stages, strict=True) if not s.implied]
        return {
            "grasped": self._grasped,
            "goal_predicates_met": float(sum(explicit)),
            "goal_predicates": float(len(explicit)),
            "stage": float(self.tracker.stage),
            "milestones_reached": float(self.tracker.reached.sum()),
        }

    # -- milestones.Probe ------------------------------------------------------------------------

    def eef(self) -> np.ndarray:
        return np.array(self.env.sim.data._data.site_xpos[self._eef_site])

    def bbox(self, name: str) -> np.ndarray:
        box = self._boxes.get(name)
        if box is None:
            box = self._boxes[name] = self.parts[name].bbox(*_raw(self.env))
        return box

    def gripper_contact(self, name: str) -> tuple[bool, bool, bool]:
        geoms = self._geom_set(name, self.parts[name].geoms)
        g = self._geoms
        return (
            sig.touches(self._contacts, g.left, geoms),
            sig.touches(self._contacts, g.right, geoms),
            sig.touches(self._contacts, g.gripper, geoms),
        )

    def handle_bbox(self, name: str) -> np.ndarray:
        return self.articulations[name].handle_bbox(*_raw(self.env))

    def handle_contact(self, name: str) -> bool:
        return sig.touches(self._contacts, self._geoms.gripper,
                           self._geom_set(name + ".handle", self.articulations[name].moving_geoms))

    def _geom_set(self, key: str, geoms: np.ndarray) -> frozenset[int]:
        found = self._sets.get(key)
        if found is None:
            found = self._sets[key] = frozenset(int(g) for g in geoms)
        return found

    def holds(self, predicate: tuple[str, ...]) -> bool:
        return bool(self._holds(predicate))

    # -- internals -------------------------------------------------------------------------------

    def _current(self) -> tuple[Any, str]:
        stage = self.plan.stages[self.tracker.stage] if self.plan.stages else None
        return stage, (stage.template if stage is not None else "predicate")

    def _stage_tensors(self, model: Any, data: Any) -> dict[str, np.ndarray]:
        zeros3, zeros6 = np.zeros(3), np.zeros(6)
        out = {
            "task_object_pos": zeros3, "task_object_quat": np.zeros(4), "task_object_bbox": zeros6,
            "task_target_pos": zeros3, "task_target_bbox": zeros6, "task_motion_dir": zeros3,
            "task_obstacle_bbox": np.zeros((OBSTACLE_SLOTS, 6)),
        }
        stage, template = self._current()
        if stage is None:
            return out
        if template == "articulate":
            art = self.articulations[stage.subject]
            box = art.handle_bbox(model, data)
            center = (box[:3] + box[3:]) / 2
            direction, remaining = art.motion(model, data, stage.kind)
            goal = center + direction * remaining
            q = data.xquat[art.body]
            out.update(
                task_object_pos=center, task_object_quat=np.array([q[1], q[2], q[3], q[0]]), task_object_bbox=box,
                task_target_pos=goal, task_target_bbox=np.concatenate([goal, goal]), task_motion_dir=direction,
            )
            out["task_obstacle_bbox"] = self._obstacle_boxes(model, data, art.body, box, out["task_target_bbox"])
            return out
        part = self.parts.get(stage.subject)
        if part is None:
            return out
        pos, quat = part.pose(model, data)
        box = self.bbox(part.name)
        out.update(task_object_pos=pos, task_object_quat=quat, task_object_bbox=box)
        target = self.parts.get(stage.target)
        if target is not None:
            tbox = self.bbox(target.name)
            out.update(task_target_pos=target.pose(model, data)[0], task_target_bbox=tbox)
            offset = ((tbox[:2] + tbox[3:5]) - (box[:2] + box[3:5])) / 2
            norm = float(np.linalg.norm(offset))
            if norm > 1e-3:
                out["task_motion_dir"] = np.array([offset[0] / norm, offset[1] / norm, 0.0])
        elif template == "lift":
            goal = self.lift_target if self.lift_target is not None else (
                np.array([(box[0] + box[3]) / 2, (box[1] + box[4]) / 2, box[2] + 2 * LIFT_HEIGHT])
            )
            out.update(task_target_pos=goal, task_target_bbox=np.concatenate([goal, goal]),
                       task_motion_dir=np.array([0.0, 0.0, 1.0]))
        if out["task_target_bbox"].any():
            out["task_obstacle_bbox"] = self._obstacle_boxes(model, data, part.body_id, box, out["task_target_bbox"])
        return out

    def _obstacle_boxes(self, model: Any, data: Any, body: int | None, obj: np.ndarray, target: np.ndarray
                        ) -> np.ndarray:
        """What stands around the stage's object and target, the moved body (and below it) left out."""
        key = -1 if body is None else int(body)
        moved = self._moved.get(key)
        if moved is None:
            moved = self._moved[key] = frozenset(subtree(model, body)) if body is not None else frozenset()
        return self._obstacles.boxes(model, data, moved, obj, target)

    def _subject(self, model: Any, data: Any) -> tuple[frozenset[int], int | None, np.ndarray]:
        """Collision geoms, body and position of what the current stage moves (the object, or the
        handle of an articulation); no geoms, None and zeros when the stage names nothing."""
        current, template = self._current()
        if current is not None and template == "articulate":
            art = self.articulations[current.subject]
            box = art.handle_bbox(model, data)
            return self._geom_set(art.name + ".handle", art.moving_geoms), art.body, (box[:3] + box[3:]) / 2
        if current is not None and current.subject in self.parts:
            part = self.parts[current.subject]
            return self._geom_set(part.name, part.geoms), part.body_id, part.pose(model, data)[0]
        return frozenset(), None, np.zeros(3)

    def _eef_mat(self, data: Any) -> np.ndarray:
        return np.array(data.site_xmat[self._eef_site]).reshape(3, 3)

    def _signals(self, model: Any, data: Any, action: np.ndarray | None, stage: Mapping[str, np.ndarray]
                 ) -> dict[str, np.ndarray]:
        geoms, body, _ = self._subject(model, data)
        velocity = sig.body_velocity(model, data, body) if body is not None else np.zeros(6)
        commanded = np.zeros(3)
        if action is not None:
            c = self.env.robots[0].controller
            commanded = sig.commanded_translation(
                np.asarray(action), np.broadcast_to(c.input_max, 6), np.broadcast_to(c.input_min, 6),
                np.broadcast_to(c.output_max, 6), np.broadcast_to(c.output_min, 6),
            )
        robot = self.env.robots[0]
        finger_qpos = np.array(data.qpos[robot._ref_gripper_joint_pos_indexes])
        return self.signals.tensors(
            sig.SignalInputs(
                contacts=self._contacts,
                object_geoms=geoms,
                object_bbox=stage["task_object_bbox"],
                object_pos=stage["task_object_pos"],
                object_vel=velocity,
                eef_pos=self.eef(),
                eef_mat=self._eef_mat(data),
                finger_qpos=finger_qpos,
                commanded=commanded,
            )
        )


# ---------------------------------------------------------------------------------------------
# Builders


def _body_part(model: Any, name: str, body: int, geom_names: list[str]) -> Part:
    import mujoco

    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in geom_names]
    return Part(name, body, None, np.array([i for i in ids if i >= 0], dtype=np.int64))


def for_libero(env: Any, goal: Any = None) -> TaskState:
    """The task state of a LIBERO domain env, from its parsed BDDL goal and scene dictionaries.

    ``goal`` replaces the env's own goal (a list of predicates), e.g. to check another task's goal
    against the same scene.
    """
    import mujoco

    model, data = _raw(env)
    sites = env.object_sites_dict
    things = {**env.fixtures_dict, **env.objects_dict}

    def real_joints(names: Any) -> list[str]:
        out = []
        for j in names or ():
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, j) if isinstance(j, str) else -1
            if jid >= 0 and int(model.jnt_type[jid]) in (_JOINT_SLIDE, _JOINT_HINGE):
                out.append(j)
        return out

    joints: dict[str, tuple[str, str]] = {}  # articulated name -> (joint, owner whose ranges apply)
    for name, site in sites.items():
        js = real_joints(getattr(site, "joints", None))
        if js and site.parent_name in things:
            joints[name] = (js[0], site.parent_name)
    for name, thing in things.items():
        js = real_joints(getattr(thing, "joints", None))
        if js:
            joints[name] = (js[0], name)
    facts = SceneFacts(
        articulated=frozenset(joints),
        containers={n: s.parent_name for n, s in sites.items() if getattr(s, "parent_name", None)},
        table_regions=frozenset(n for n, s in sites.items() if not getattr(s, "parent_name", None)),
    )
    plan = derive_plan(env.parsed_problem["goal_state"] if goal is None else goal, facts)
    parts: dict[str, Part] = {}
    articulations: dict[str, Articulation] = {}
    for stage in plan.stages:
        for name in stage.predicate[1:]:
            if name in parts:
                continue
            if name in env.obj_body_id:
                parts[name] = _body_part(model, name, env.obj_body_id[name], list(things[name].contact_geoms))
            elif name in sites:
                parts[name] = Part(name, None, mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name),
                                   np.zeros(0, np.int64))
            elif name in things:
                body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, things[name].root_body)
                parts[name] = _body_part(model, name, body, list(things[name].contact_geoms))
            if name in joints and stage.template == "articulate" and name not in articulations:
                joint, owner = joints[name]
                ranges = things[owner].object_properties.get("articulation", {})
                articulations[name] = articulation(model, data, name, joint, ranges)
    return TaskState(env, plan, parts, articulations, lambda p: bool(env._eval_predicate(list(p))))


def for_robosuite(env: Any, object_attr: str, target_attr: str | None) -> TaskState:
    """A robosuite task as a one-stage goal: lift the object, or put it on the target (Stack)."""
    import mujoco

    model, _ = _raw(env)
    goal = [("on", object_attr, target_attr)] if target_attr else [("up", object_attr)]
    plan = derive_plan(goal, SceneFacts())
    parts = {}
    for attr in filter(None, (object_attr, target_attr)):
        thing = getattr(env, attr)
        body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, thing.root_body)
        parts[attr] = _body_part(model, attr, body, list(thing.contact_geoms))
    return TaskState(env, plan, parts, {}, lambda p: bool(env._check_success()))


class TaskProgressSlot:
    """Mixin for slots holding a :class:`TaskState` in ``self._state``: the milestone reports."""

    _state: TaskState | None

    def milestone_names(self) -> list[str]:
        """The episode's milestone sequence M."""
        return self._state.names() if self._state is not None else []

    def milestones_reached(self) -> list[str]:
        """Milestones observed so far in the episode, in the order of M."""
        return self._state.tracker.reached_names() if self._state is not None else []

    def first_missing_milestone(self) -> str:
        """m*: the first milestone of M not observed so far ("" when all were)."""
        return self._state.tracker.first_missing() if self._state is not None else ""
