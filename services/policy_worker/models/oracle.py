"""Scripted oracle for LIBERO-style goals: one generic skill per goal predicate, on privileged state.

The env families publish the goal stage being worked on (``task_stage``: on, in, open, close,
turnon, turnoff, up), derived from the task's BDDL goal, with the geometry the stage needs: the
object (or the handle of the drawer or knob) to move, where it must go, the direction of motion,
and whether the object is held (services/env_worker/families/task_state.py). The oracle maps the
stage to a skill and never looks at the task's name or instruction:

* ``on``/``in`` onto something raised, or into a container: pick and place
  (:class:`~services.policy_worker.models.scripted.ScriptedPickPlacePolicy`'s motions). Two
  geometric cases are read off the boxes: an object under its target (an opened drawer slid over
  the bowl it must receive) is gripped off the middle of its rim, where the hand clears the
  drawer, and slid out of the target's footprint before it is lifted; an object that fits in a
  deep dish (a bottle in a bowl) is lowered into it before it is let go, where dropped from above
  the rim it would tip over;
* ``on``/``in`` around obstacles (``task_obstacle_bbox``: the boxes of what stands near the object
  and the target): the held object and the hand above it are let go over the point of the target
  nearest its centre with nothing in the way down, just above what the object will rest on there,
  and carried there straight or by an L of two axis-aligned legs, raised over an obstacle only
  where neither is free (LIBERO-Goal-S: the swapped stove sits under the wine rack's slats). A
  wide object is gripped by another side of its rim where the hand has no way down from the side
  facing the robot;
* reaching low near the robot's base, the hand pitches toward the base as the elbow nears its
  limit (folded there, the arm slides sideways instead of going where it is sent);
* ``on`` a region drawn on the table: push the object there with the closed gripper;
* ``turnon``/``turnoff`` (a knob): push the lever along its tangent with a finger;
* ``open``/``close`` of a drawer: turn the hand to face the handle, grasp the handle bar and pull
  or push it along the drawer's axis; a bar so low that the palm of that grasp would reach into
  the table under it (a bottom drawer) is hooked from above instead, the closed fingertips tilted
  down behind it, and dragged by friction;
* multi-predicate goals need no sequencing here: the env moves to the next stage when one holds
  (e.g. "open the top drawer and put the bowl inside" is open(drawer), then in(bowl, drawer)).

Like the scripted policy it is stateless: every decision comes from the current observation, so
the policy worker can batch it with any session and an episode can be resumed at any step.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from services.common.handles import DOWN, HandleParams, HandleSkill
from services.common.handles import aperture as _aperture_command
from services.common.rotations import hand_down
from services.common.rotations import quat_to_mat as _quat_to_mat
from services.common.specs import TensorSpec
from services.common.milestone_kinds import OBSTACLE_SLOTS, STAGE_KINDS, TEMPLATE_NAMES
from services.policy_worker.models.scripted import PickPlaceParams, ScriptedPickPlacePolicy

_OPEN, _CLOSE = -1.0, 1.0
_PICK_PLACE, _PUSH, _HANDLE = "pick_place", "push", "handle"



@dataclass(frozen=True)
class OracleParams(HandleParams):
    """Generic offsets (metres) and gains of the skills; none is specific to a task.

    The orientation gains, the handle (knob lever, drawer bar) offsets and the hand's size are
    :class:`~services.common.handles.HandleParams`', shared with the harness library's articulation
    recoveries.
    """

    #: Pick-and-place offsets: the scripted ones, carrying higher (a region site can sit under a
    #: fixture's knobs and rims, so its box top understates what the object must clear).
    pick: PickPlaceParams = PickPlaceParams(carry_clearance=0.1)
    #: Pick-and-place first turns the hand down, backing off this far, when it is turned more than this.
    reorient_angle: float = 0.6
    reorient_backoff: float = 0.05
    #: Horizontal direction from the workspace to the robot's base (robosuite and LIBERO put the
    #: arm at -x, facing +x).
    robot_side: tuple[float, float] = (-1.0, 0.0)
    # -- push --------------------------------------------------------------------------------
    #: Half thickness of the closed fingers across their closing axis: they push with that side.
    pusher_half_x: float = 0.013
    #: Gap between the pusher and the object before the push starts.
    push_gap: float = 0.006
    #: Height of the grip site above the pushed object's bottom (the fingertips are ~13 mm lower).
    push_height: float = 0.02
    #: Lateral error (perpendicular to the push) beyond which the gripper restages.
    push_lateral_tolerance: float = 0.025
    push_max_action: float = 0.3
    #: Horizontal error up to which a descent already under way goes on (correcting as it goes).
    descend_tolerance: float = 0.02
    #: How far below the wanted height the push aims: OSC settles about a centimetre above its goal.
    press: float = 0.012
    push_z_tolerance: float = 0.01
    #: A dish (shallower than ``shallow``, wider than ``inside_extent`` from its centre) is pushed
    #: by the inner wall of its leading rim: ``rim_inset`` inside its edge, with the fingertips
    #: (``finger_below`` under the grip site) ``rim_overlap`` below the rim's top.
    shallow: float = 0.03
    inside_extent: float = 0.05
    rim_inset: float = 0.012
    finger_below: float = 0.013
    rim_overlap: float = 0.016
    #: Height above the object's top for moving over to the push start.
    push_hover: float = 0.04
    # -- an object under its target (an opened drawer slid over it) ------------------------------
    #: How far a fixture's walls and handle reach beyond the region it holds (its box grows by this).
    cover_margin: float = 0.02
    #: A rim grasp shifts along the rim until the hand clears the cover (``hand_half_across``, the
    #: hand's half width across its finger axis), by at most ``cover_shift`` of the rim's radius.
    cover_shift: float = 0.6
    #: A grasped covered object is slid out of the cover's footprint this far beyond its edge,
    #: raised on the way until its top is ``cover_headroom`` below the target's bottom (never
    #: lowered: where there is less room it slides on the table).
    cover_clearance: float = 0.015
    cover_headroom: float = 0.04
    # -- into a deep dish (on a bowl) -------------------------------------------------------------
    #: An object at most ``sink_fit`` as wide as a deep dish (taller than ``shallow``, wider than
    #: ``inside_extent``) is lowered into it and let go with its bottom ``sink_depth`` of the dish's
    #: height below the rim; dropped from above the rim, a tall object tips over.
    sink_fit: float = 0.5
    sink_depth: float = 0.6
    # -- reaching low near the base -----------------------------------------------------------------
    #: The Panda's elbow (joint 4) folds to its limit when the hand, pointing down, reaches low near
    #: the base, and the arm then slides sideways instead of going where it is sent. Within
    #: ``elbow_margin`` of the limit the hand pitches toward the base, ``elbow_gain`` rad per rad,
    #: at most ``max_pitch``: the wrist moves out and the elbow opens. A hand tilted more than
    #: ``level_tolerance`` is levelled again once the elbow has room.
    elbow_limit: float = -3.072
    elbow_margin: float = 0.5
    elbow_gain: float = 3.0
    max_pitch: float = 0.5
    level_tolerance: float = 0.1
    # -- carrying around obstacles (task_obstacle_bbox) -----------------------------------------------
    #: The hand's collision box above its grip site: half length along the finger axis
    #: (``palm_half_along``; half width across is ``hand_half_across``), and its bottom and top above
    #: the grip site.
    palm_low: float = 0.024
    palm_high: float = 0.126
    #: Horizontal clearance kept from obstacles, and the clearance over an obstacle's top when the
    #: carry height rises over it (by at most ``max_route_rise`` above the usual carry height).
    route_margin: float = 0.01
    route_clearance: float = 0.03
    max_route_rise: float = 0.3
    #: Obstacles whose top is at most this far above the target's top are what the object rests on.
    support_tolerance: float = 0.02
    #: Release points are searched on a grid of this step, this far inside the target's box.
    release_step: float = 0.005
    release_inset: float = 0.01


class _SidedPick(ScriptedPickPlacePolicy):
    """The scripted pick-and-place with a rim grasp on a chosen side (axis and sign) of the object.

    The oracle sets ``side`` before each decision (the worker runs one decision at a time).
    """

    side: tuple[int, float] = (1, 1.0)
    #: Offset of a rim grasp along the rim (across the finger axis), from the rim's middle.
    shift: float = 0.0
    #: How far below the target's top the held object's bottom is let go (0: just above it).
    sink: float = 0.0
    #: Where a held object goes: (waypoint xy, release xy, carry height and release height of its
    #: bottom); None: straight over the target's centre, ``carry_clearance`` above its top.
    route: tuple[np.ndarray, np.ndarray, float, float] | None = None

    def _carry(self, center: np.ndarray, bottom: float, target_center: np.ndarray, target_top: float) -> np.ndarray:
        p = self.params
        if self.route is None:
            via = release_xy = target_center[:2]
            carry_z = target_top + p.carry_clearance
            release_z = target_top - self.sink if self.sink > 0.0 else target_top + p.release_gap
        else:
            via, release_xy, carry_z, release_z = self.route
        held = np.array([center[0], center[1], bottom])
        if np.linalg.norm(center[:2] - release_xy) > p.carry_xy_tolerance:
            goal = via if np.linalg.norm(center[:2] - via) > p.carry_xy_tolerance else release_xy
            return self._move(held, self._climb_first(held, np.array([*goal, carry_z])), _CLOSE, p.carry_max_action)
        release = np.array([*release_xy, release_z])
        if abs(bottom - release[2]) > p.z_tolerance or np.linalg.norm(center[:2] - release[:2]) > p.xy_tolerance:
            return self._move(held, release, _CLOSE, p.carry_max_action)
        return self._action(np.zeros(3), _OPEN)

    def _grasp_point(self, obj: np.ndarray) -> np.ndarray:
        p = self.params
        axis, sign = self.side
        center = (obj[:3] + obj[3:]) / 2
        if (obj[3 + axis] - obj[axis]) / 2 <= p.max_center_half_width:
            return np.array([center[0], center[1], max(obj[5] - p.grasp_depth, obj[2] + p.min_grasp_height)])
        point = np.array([center[0], center[1], max(obj[5] - p.rim_depth, obj[2] + p.min_grasp_height)])
        if not self.shift:
            point[axis] = (obj[3 + axis] - p.rim_inset) if sign > 0 else (obj[axis] + p.rim_inset)
            return point
        radius = (obj[3 + axis] - obj[axis]) / 2
        point[1 - axis] += self.shift
        # The rim is round: off its middle it lies closer to the centre along the finger axis.
        reach = float(np.sqrt(max(radius * radius - self.shift * self.shift, 0.0))) - p.rim_inset
        point[axis] = center[axis] + sign * reach
        return point


class OraclePolicy:
    """Batched, stateless skill-per-predicate controller emitting OSC_POSE delta actions."""

    name = "oracle"

    def __init__(self, params: OracleParams | None = None, chunk_size: int = 1) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.params = params or OracleParams()
        self.chunk_size = chunk_size
        self._pick = _SidedPick(self.params.pick)
        self._axis_params = {
            axis: dataclasses.replace(self.params.pick, finger_axis=axis) for axis in (0, 1)
        }
        #: The handle motions (services/common/handles.py), with the pick-and-place translation gains.
        self._handles = HandleSkill(self.params, self._move, STAGE_KINDS)

    @staticmethod
    def input_specs() -> list[TensorSpec]:
        """Observation tensors the oracle reads (a subset of the manipulation schema)."""
        return [
            TensorSpec("robot0_eef_pos", "float32", (3,)),
            TensorSpec("robot0_eef_quat", "float32", (4,)),
            TensorSpec("robot0_gripper_qpos", "float32", (2,)),
            TensorSpec("robot0_joint_pos", "float32", (7,)),
            TensorSpec("task_object_pos", "float32", (3,), privileged=True),
            TensorSpec("task_object_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_target_pos", "float32", (3,), privileged=True),
            TensorSpec("task_target_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_grasped", "float32", (1,), privileged=True),
            TensorSpec("task_stage", "float32", (len(STAGE_KINDS),), privileged=True),
            TensorSpec("task_template", "float32", (len(TEMPLATE_NAMES),), privileged=True),
            TensorSpec("task_motion_dir", "float32", (3,), privileged=True),
            TensorSpec("task_obstacle_bbox", "float32", (OBSTACLE_SLOTS, 6), privileged=True),
        ]

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """Actions [B, chunk_size, 7]; the instruction is not used (the goal is in the state)."""
        rows = len(batch["robot0_eef_pos"])
        actions = np.zeros((rows, 7))
        for i in range(rows):
            obs = {k: np.asarray(v[i], dtype=np.float64) for k, v in batch.items()}
            actions[i] = self.act(obs)
        return np.repeat(actions[:, None, :], self.chunk_size, axis=1).astype(np.float32)

    # -- dispatch --------------------------------------------------------------------------------

    def skill(self, obs: dict[str, np.ndarray]) -> str:
        """The skill for the current stage."""
        stage = obs["task_stage"]
        kind = STAGE_KINDS[int(np.argmax(stage))] if stage.any() else "other"
        template = obs["task_template"]
        template = TEMPLATE_NAMES[int(np.argmax(template))] if template.any() else "predicate"
        if kind in ("open", "close", "turnon", "turnoff"):
            return _HANDLE
        held = bool(obs["task_grasped"][0] > 0.5)
        if template == "slide" and not held and not self._dish(obs["task_object_bbox"]):
            return _PUSH  # a region drawn on the table: pushing gets the object there
        return _PICK_PLACE  # (a dish's sloped rim rides over a pusher: it is carried instead)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        skill = self.skill(obs)
        if skill == _HANDLE:
            action = self._handle(obs)
        elif skill == _PUSH:
            action = self._push(obs)
        else:
            action = self._pick_place(obs)
        return action

    def _pick_place(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        p = self.params
        hand = _quat_to_mat(obs["robot0_eef_quat"])
        tilt = float(np.arccos(np.clip(-hand[2, 2], -1.0, 1.0)))  # hand z axis away from straight down
        if tilt > p.reorient_angle and not obs["task_grasped"][0] > 0.5:
            # Still turned from a previous stage (a drawer pull): back away along the hand's
            # approach axis and up while turning down, clear of what it was holding.
            eef = obs["robot0_eef_pos"]
            action = self._move(eef, eef - hand[:, 2] * p.reorient_backoff + [0.0, 0.0, p.reorient_backoff], _OPEN, 1.0)
        else:
            held = bool(obs["task_grasped"][0] > 0.5)
            obj, target = obs["task_object_bbox"], obs["task_target_bbox"]
            axis, sign = self._grasp_side(obj, target)
            cover = self._cover(obj, target)
            if held and cover is not None:
                return self._slide_out(obs, cover)
            self._pick.sink = self._sink(obs)
            self._pick.route = None
            obstacles = obs.get("task_obstacle_bbox")
            if not held and obstacles is not None and cover is None:
                axis, sign = self._clear_side(obj, target, obstacles, (axis, sign))
            self._pick.side = (axis, sign)
            self._pick.shift = self._rim_shift(obj, axis, cover if _overlap(obj, target) else None)
            if held and obstacles is not None:
                moving = np.stack([obj, self._palm(obs["robot0_eef_pos"], hand[:, 1])])
                self._pick.route = self._route(moving, target, obstacles, self._pick.sink)
            self._pick.params = self._axis_params[axis]
            action = self._pick._act(
                obs["robot0_eef_pos"], obs["robot0_gripper_qpos"], obs["task_object_bbox"],
                obs["task_target_bbox"], held,
            )
            pitch = self._elbow_pitch(obs)
            level = tilt < p.level_tolerance
            if pitch <= 0.0 and level and (held or (axis == 1 and not self._tilted(obs, 0.2))):
                return action  # keep the hand as it is (as the scripted policy does)
            if held:  # level the hand (or pitch it) without turning what it holds
                finger_axis = hand[:2, 1]
            else:
                finger_axis = np.eye(3)[axis][:2]
            action[3:6] = self._orient(obs, self._pitched(hand_down(finger_axis, hand), pitch))
            return action
        action[3:6] = self._orient(obs, DOWN)
        return action

    def _elbow_pitch(self, obs: dict[str, np.ndarray]) -> float:
        """How far to pitch the hand toward the base (see ``OracleParams.elbow_margin``); never for a
        shallow dish, whose rim is gripped with the fingertips at the table (a pitched hand puts a
        finger into it)."""
        p = self.params
        obj = obs["task_object_bbox"]
        if obj.any() and obj[5] - obj[2] < p.shallow and self._dish(obj):
            return 0.0
        q = float(obs["robot0_joint_pos"][3])
        return float(np.clip((p.elbow_limit + p.elbow_margin - q) * p.elbow_gain, 0.0, p.max_pitch))

    def _pitched(self, frame: np.ndarray, pitch: float) -> np.ndarray:
        """``frame`` with its approach axis turned by ``pitch`` toward the robot's base."""
        if pitch <= 0.0:
            return frame
        toward = np.array([*self.params.robot_side, 0.0])
        z = np.cos(pitch) * np.array([0.0, 0.0, -1.0]) + np.sin(pitch) * toward
        y = frame[:, 1] - (frame[:, 1] @ z) * z
        y /= np.linalg.norm(y)
        return np.column_stack([np.cross(y, z), y, z])

    def _grasp_side(self, obj: np.ndarray, target: np.ndarray) -> tuple[int, float]:
        """Fingers close along y for an object narrow enough to grasp across; a wide one (a bowl, a
        plate) is gripped by the rim on the side facing the robot, where the hand has room (a rim on
        the far side reaches under drawers and next to fixtures)."""
        p = self.params.pick
        if not obj.any():
            return 1, 1.0
        half = (obj[3:5] - obj[:2]) / 2
        if half[1] <= p.max_center_half_width:
            return 1, 1.0
        if half[0] <= p.max_center_half_width:
            return 0, 1.0
        if obj[5] - obj[2] < self.params.shallow:
            return 1, 1.0  # a plate: its rim along y, as the scripted policy grips it
        toward = np.asarray(self.params.robot_side, dtype=np.float64)
        axis = int(np.argmax(np.abs(toward)))
        return axis, float(np.sign(toward[axis]))

    def _clear_side(self, obj: np.ndarray, target: np.ndarray, obstacles: np.ndarray,
                    default: tuple[int, float]) -> tuple[int, float]:
        """The rim side to grip a wide object by so that the hand can let it go on the target: the
        default side unless obstacles leave the hand no way down onto the target from it, then the
        next side round the rim (the two beside it, then the far one)."""
        p = self.params
        half = (obj[3:5] - obj[:2]) / 2
        if not obstacles.any() or min(half) <= p.pick.max_center_half_width or obj[5] - obj[2] < p.shallow:
            return default
        axis, sign = default
        sides = [default, (1 - axis, 1.0), (1 - axis, -1.0), (axis, -sign)]
        sink = self._pick.sink
        for side in sides:
            self._pick.side = side
            self._pick.shift = 0.0
            grip = self._pick._grasp_point(obj)
            moving = np.stack([obj, self._palm(grip, np.eye(3)[side[0]])])
            if self._route(moving, target, obstacles, sink) is not None:
                return side
        return default

    # -- an object under its target ---------------------------------------------------------------

    def _cover(self, obj: np.ndarray, target: np.ndarray) -> np.ndarray | None:
        """The target's box grown by the fixture around it, when the target lies over the object.

        An opened drawer can slide over the object it must receive: lifting the object straight up
        would hit the drawer's floor, and a hand coming down over its footprint its walls.
        """
        if not obj.any() or not target.any() or obj[5] >= target[2]:
            return None
        m = self.params.cover_margin
        cover = np.concatenate([target[:3] - [m, m, 0.0], target[3:] + [m, m, 0.0]])
        return cover if _overlap(obj, cover) else None

    def _rim_shift(self, obj: np.ndarray, axis: int, cover: np.ndarray | None) -> float:
        """How far along the rim to grasp so the hand (narrow across its finger axis) clears the cover."""
        if cover is None or (obj[3 + axis] - obj[axis]) / 2 <= self.params.pick.max_center_half_width:
            return 0.0
        p = self.params
        across = 1 - axis
        center = (obj[across] + obj[3 + across]) / 2
        away = center - (cover[across] + cover[3 + across]) / 2
        limit = p.cover_shift * (obj[3 + axis] - obj[axis]) / 2
        if away > 0:
            return float(np.clip(cover[3 + across] + p.hand_half_across - center, 0.0, limit))
        return float(np.clip(cover[across] - p.hand_half_across - center, -limit, 0.0))

    def _slide_out(self, obs: dict[str, np.ndarray], cover: np.ndarray) -> np.ndarray:
        """Slide the grasped object horizontally out of the cover's footprint, the shortest way."""
        p = self.params
        obj = obs["task_object_bbox"]
        exits = np.array([cover[3] - obj[0], cover[4] - obj[1], obj[3] - cover[0], obj[4] - cover[1]])
        k = int(np.argmin(exits))
        step = np.zeros(3)
        step[k % 2] = (exits[k] + p.cover_clearance) * (1.0 if k < 2 else -1.0)
        step[2] = max(cover[2] - p.cover_headroom - obj[5], 0.0)
        return self._move(obs["robot0_eef_pos"], obs["robot0_eef_pos"] + step, _CLOSE, p.pick.carry_max_action)

    def _palm(self, grip: np.ndarray, finger_axis: np.ndarray) -> np.ndarray:
        """World box of the hand above a grip site at ``grip`` whose fingers close along ``finger_axis`` (xy)."""
        p = self.params
        a = np.abs(finger_axis[:2]) / max(float(np.linalg.norm(finger_axis[:2])), 1e-9)
        half = a * p.palm_half_along + a[::-1] * p.hand_half_across
        return np.array([grip[0] - half[0], grip[1] - half[1], grip[2] + p.palm_low,
                         grip[0] + half[0], grip[1] + half[1], grip[2] + p.palm_high])

    def _route(self, moving: np.ndarray, target: np.ndarray, obstacles: np.ndarray, sink: float
               ) -> tuple[np.ndarray, np.ndarray, float, float] | None:
        """Where to carry what the hand holds (``moving``: the object's box, then the palm's) so both clear
        the obstacles: (waypoint, release point, carry height and release height of the object's
        bottom); None if the hand has no way down onto the target.

        The object is let go over the point of the target nearest its centre where nothing stands in
        the way down, just above what it will rest on there, and carried there at the lowest height
        (from the usual one up) where a straight line or an L of two axis-aligned legs is free, the
        shortest of those.
        """
        obstacles = obstacles[np.any(obstacles != 0.0, axis=1)]
        p, pick = self.params, self.params.pick
        obj = moving[0]
        ref = np.array([(obj[0] + obj[3]) / 2, (obj[1] + obj[4]) / 2, obj[2]])
        low = float(target[5] - sink if sink > 0.0 else target[5] + pick.release_gap)
        carry_z = float(target[5] + pick.carry_clearance)
        release = self._release_point(obj, ref, target, obstacles, low, carry_z)
        if release is None:
            return None
        release_z = low
        if sink <= 0.0:  # just above what it rests on: the target, or a fixture's surface standing on it
            foot = np.array([*(obj[:2] + release - ref[:2]), -np.inf, *(obj[3:5] + release - ref[:2]), np.inf])
            flat = obstacles[obstacles[:, 5] <= target[5] + p.support_tolerance]
            under = flat[_hits(foot[None], flat, 0.0)[0]]
            release_z = float(max([target[5], *under[:, 5]])) + pick.release_gap
        tops = np.sort(obstacles[:, 5][obstacles[:, 5] + p.route_clearance > carry_z]) + p.route_clearance
        for z in (carry_z, *tops[tops <= carry_z + p.max_route_rise]):
            best = None
            for via in (release, np.array([release[0], ref[1]]), np.array([ref[0], release[1]])):
                path = np.array([ref, [*ref[:2], z], [*via, z], [*release, z], [*release, release_z + p.support_tolerance]])
                if _path_free(moving, ref, path, obstacles, p.route_margin):
                    length = float(np.linalg.norm(via - ref[:2]) + np.linalg.norm(release - via))
                    if best is None or length < best[0] - 1e-6:
                        best = (length, via)
            if best is not None:
                return best[1], release, float(z), release_z
        return None

    def _release_point(self, obj: np.ndarray, ref: np.ndarray, target: np.ndarray, obstacles: np.ndarray,
                       low: float, high: float) -> np.ndarray | None:
        """The point of the target nearest its centre over which the object goes down from ``high`` to
        ``low`` clear of the obstacles (what it is let go on does not count); None if there is none."""
        p = self.params
        above = obstacles[obstacles[:, 5] > low + p.support_tolerance]
        column = obj[None].copy()
        column[:, 5] += high - low
        center = (target[:2] + target[3:5]) / 2
        xs = np.arange(target[0] + p.release_inset, target[3] - p.release_inset + 1e-9, p.release_step)
        ys = np.arange(target[1] + p.release_inset, target[4] - p.release_inset + 1e-9, p.release_step)
        grid = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2) if len(xs) and len(ys) else np.zeros((0, 2))
        points = np.concatenate([center[None], grid])
        shifts = np.concatenate([points - ref[:2], np.full((len(points), 1), low - ref[2])], axis=1)
        boxes = column[None] + np.tile(shifts, 2)[:, None]  # [point, box, 6]
        blocked = _hits(boxes.reshape(-1, 6), above, p.route_margin).any(axis=1).reshape(len(points), -1).any(axis=1)
        if not blocked[0]:
            return center
        free = points[~blocked]
        if not len(free):
            return None
        return free[int(np.argmin(np.linalg.norm(free - center, axis=1)))]

    def _sink(self, obs: dict[str, np.ndarray]) -> float:
        """How deep into the target a held object is let go: inside a deep dish (a bowl) that it fits
        in, for an ``on`` stage; 0 (just above the target) otherwise."""
        p = self.params
        obj, target = obs["task_object_bbox"], obs["task_target_bbox"]
        stage = obs["task_stage"]
        if not obj.any() or not target.any() or not stage.any() or STAGE_KINDS[int(np.argmax(stage))] != "on":
            return 0.0
        height = float(target[5] - target[2])
        dish = height >= p.shallow and self._dish(target)
        fits = float(np.max(obj[3:5] - obj[:2])) <= p.sink_fit * float(np.min(target[3:5] - target[:2]))
        return p.sink_depth * height if dish and fits else 0.0

    @staticmethod
    def _tilted(obs: dict[str, np.ndarray], angle: float) -> bool:
        hand = _quat_to_mat(obs["robot0_eef_quat"])
        return bool(np.arccos(np.clip(-hand[2, 2], -1.0, 1.0)) > angle or abs(hand[1, 1]) < np.cos(angle))

    def _dish(self, box: np.ndarray) -> bool:
        """Wide in every horizontal direction, like a plate or a bowl: gripped by the rim, not pushed
        (a pusher rides up a dish's sloped rim instead of moving it)."""
        return bool(min(box[3] - box[0], box[4] - box[1]) / 2 > self.params.inside_extent)

    # -- primitives ------------------------------------------------------------------------------

    def _orient(self, obs: dict[str, np.ndarray], desired: np.ndarray) -> np.ndarray:
        return self._handles.orient(obs, desired)

    @staticmethod
    def _aperture(gap: float, wanted: float) -> float:
        return _aperture_command(gap, wanted)

    def _move(self, eef: np.ndarray, goal: np.ndarray, gripper: float, limit: float) -> np.ndarray:
        return self._pick._move(eef, goal, gripper, limit)

    # -- push (on a table region) ----------------------------------------------------------------

    def _push(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        p = self.params
        eef = obs["robot0_eef_pos"]
        box, target = obs["task_object_bbox"], obs["task_target_bbox"]
        origin = obs["task_object_pos"]  # the region checks the body origin, not the box centre
        goal_xy = (target[:2] + target[3:5]) / 2
        delta = goal_xy - origin[:2]
        distance = float(np.linalg.norm(delta))
        top = box[5]
        desired = DOWN
        if distance < 1e-3:
            action = self._move(eef, np.array([eef[0], eef[1], top + p.push_hover]), _CLOSE, p.push_max_action)
        else:
            u = delta / distance
            perp = np.array([-u[1], u[0]])
            desired = hand_down(perp, _quat_to_mat(obs["robot0_eef_quat"]))
            center = (box[:2] + box[3:5]) / 2
            half = (box[3:5] - box[:2]) / 2
            extent = abs(u[0]) * half[0] + abs(u[1]) * half[1]
            pusher = p.pusher_half_x  # the fingers close across the push: it pushes with their side
            rel = eef[:2] - center
            along, lateral = float(rel @ u), float(rel @ perp)
            low = box[2] + p.push_height
            if top - box[2] < p.shallow and extent > p.inside_extent:
                # A dish: push its leading rim from inside; the hand stays over the dish, where
                # there is room, instead of behind it (next to a cabinet or the robot's base).
                contact = extent - p.rim_inset - pusher
                low = top + p.finger_below - p.rim_overlap
            else:
                contact = -(extent + pusher)
            start_xy = center + u * (contact - p.push_gap)
            engaged = (contact - p.push_gap - 0.02 <= along <= contact + 0.015
                       and abs(lateral) < p.push_lateral_tolerance and eef[2] < low + p.push_z_tolerance)
            if engaged:
                # Push the object by what is left, steering the pusher back onto the line.
                goal = np.array([*(eef[:2] + delta - perp * lateral), low - p.press])
                action = self._move(eef, goal, _CLOSE, p.push_max_action)
            elif np.linalg.norm(eef[:2] - start_xy) > (p.descend_tolerance if eef[2] < top + p.push_hover - 0.01
                                                       else p.handle_tolerance):
                hover = top + p.push_hover
                if eef[2] < hover - 0.02:
                    action = self._move(eef, np.array([eef[0], eef[1], hover]), _CLOSE, p.push_max_action)
                else:
                    action = self._move(eef, np.array([*start_xy, hover]), _CLOSE, p.push_max_action)
            else:
                action = self._move(eef, np.array([*start_xy, low - p.press]), _CLOSE, p.push_max_action)
        action[3:6] = self._orient(obs, desired)
        return action

    # -- handles: knob levers and drawer bars ------------------------------------------------------

    def _handle(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """open/close a drawer's bar (gripped from the front and pulled, or hooked from above where
        the palm would reach into the table; the last centimetres pushed with a finger), turnon/
        turnoff a knob's lever (pushed along its tangent with a finger): services/common/handles.py."""
        return self._handles.act(obs)

    def _is_bar(self, obs: dict[str, np.ndarray]) -> bool:
        return self._handles.is_bar(obs)

    def _finger_push(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self._handles.finger_push(obs)

    def _front_blocked(self, obs: dict[str, np.ndarray]) -> bool:
        return self._handles.front_blocked(obs)

    def _hook_bar(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self._handles.hook_bar(obs)

    def _pull_bar(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return self._handles.pull_bar(obs)


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """The two boxes overlap horizontally."""
    return bool(a[0] < b[3] and b[0] < a[3] and a[1] < b[4] and b[1] < a[4])


def _hits(boxes: np.ndarray, obstacles: np.ndarray, margin: float) -> np.ndarray:
    """[len(boxes), len(obstacles)]: which boxes come within ``margin`` (horizontally) of which obstacles."""
    return ((obstacles[None, :, 0] - margin < boxes[:, None, 3]) & (obstacles[None, :, 3] + margin > boxes[:, None, 0])
            & (obstacles[None, :, 1] - margin < boxes[:, None, 4]) & (obstacles[None, :, 4] + margin > boxes[:, None, 1])
            & (obstacles[None, :, 2] < boxes[:, None, 5]) & (obstacles[None, :, 5] > boxes[:, None, 2]))


def _path_free(moving: np.ndarray, ref: np.ndarray, path: np.ndarray, obstacles: np.ndarray, margin: float) -> bool:
    """``moving`` (boxes at reference point ``ref``) carried through the points of ``path`` (straight
    legs, sampled every centimetre) hits no obstacle, except one it touches from the start until it
    has left it (it may move away from what it stands next to)."""
    samples = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        n = int(np.ceil(np.linalg.norm(b - a) / 0.01))
        samples += [a + (b - a) * (k / n) for k in range(1, n + 1)] if n else []
    hit = np.zeros((len(samples), len(obstacles)), dtype=bool)
    for k, point in enumerate(samples):
        hit[k] = _hits(moving + np.tile(point - ref, 2), obstacles, margin).any(axis=0)
    left = np.maximum.accumulate(~hit, axis=0)
    return not bool((hit & left).any())

