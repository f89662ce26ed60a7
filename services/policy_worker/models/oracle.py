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
* ``on`` a region drawn on the table: push the object there with the closed gripper;
* ``turnon``/``turnoff`` (a knob): push the lever along its tangent with a finger;
* ``open``/``close`` of a drawer: turn the hand to face the handle, grasp the handle bar and pull
  or push it along the drawer's axis;
* multi-predicate goals need no sequencing here: the env moves to the next stage when one holds
  (e.g. "open the top drawer and put the bowl inside" is open(drawer), then in(bowl, drawer)).

Like the scripted policy it is stateless: every decision comes from the current observation, so
the policy worker can batch it with any session and an episode can be resumed at any step.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from services.common.rotations import quat_to_mat as _quat_to_mat
from services.common.rotations import rotvec as _rotvec
from services.common.specs import TensorSpec
from services.env_worker.milestones import STAGE_KINDS, TEMPLATE_NAMES
from services.policy_worker.models.scripted import PickPlaceParams, ScriptedPickPlacePolicy

_OPEN, _CLOSE = -1.0, 1.0
_PICK_PLACE, _PUSH, _HANDLE = "pick_place", "push", "handle"


#: The hand pointing down with the fingers closing along world y (robosuite's default Panda pose),
#: as the rotation of the ``robot0_eef_quat`` frame.
DOWN = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class OracleParams:
    """Generic offsets (metres) and gains of the skills; none is specific to a task."""

    #: Pick-and-place offsets: the scripted ones, carrying higher (a region site can sit under a
    #: fixture's knobs and rims, so its box top understates what the object must clear).
    pick: PickPlaceParams = PickPlaceParams(carry_clearance=0.1)
    #: Orientation gain: fraction of the rotation error corrected per step, and the largest
    #: rotation action (OSC scales 1.0 to 0.5 rad).
    rot_gain: float = 1.0
    max_rot_action: float = 0.6
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
    # -- handle (knob lever, drawer bar) ---------------------------------------------------------
    #: Offset of each open finger from the grip site along the finger axis, and a finger's half
    #: thickness along it.
    finger_offset: float = 0.042
    finger_half: float = 0.006
    handle_gap: float = 0.006
    #: Grip site height relative to the handle's centre for a finger push (the pads span -5..+12 mm).
    handle_dz: float = -0.002
    handle_hover: float = 0.05
    handle_tolerance: float = 0.008
    handle_max_action: float = 1.0
    #: Extra travel commanded past the handle's goal position.
    overshoot: float = 0.05
    #: Drawer grasp: how far the grip site sits behind the bar's front face, the approach standoff
    #: in front of it, and the finger gap below which the bar counts as held.
    bar_depth: float = 0.004
    bar_standoff: float = 0.06
    bar_closed_gap: float = 0.012
    #: Finger gap while approaching a bar: wide enough for the bar, narrow enough that the lower
    #: finger stays above the table under a low drawer.
    bar_open_gap: float = 0.045
    #: Alignment tolerance across the pull (OSC sags about a centimetre with the hand sideways).
    bar_tolerance: float = 0.02
    #: The sideways hand sags under OSC: aim this much below the bar.
    bar_sag: float = 0.008
    #: Largest orientation error (rad) tolerated before moving in for a drawer grasp.
    bar_ori_tolerance: float = 0.15
    # -- an object under its target (an opened drawer slid over it) ------------------------------
    #: How far a fixture's walls and handle reach beyond the region it holds (its box grows by this).
    cover_margin: float = 0.02
    #: Half width of the hand across its finger axis: a rim grasp shifts along the rim until the
    #: hand clears the cover, by at most ``cover_shift`` of the rim's radius.
    hand_half_across: float = 0.035
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


class _SidedPick(ScriptedPickPlacePolicy):
    """The scripted pick-and-place with a rim grasp on a chosen side (axis and sign) of the object.

    The oracle sets ``side`` before each decision (the worker runs one decision at a time).
    """

    side: tuple[int, float] = (1, 1.0)
    #: Offset of a rim grasp along the rim (across the finger axis), from the rim's middle.
    shift: float = 0.0
    #: How far below the target's top the held object's bottom is let go (0: just above it).
    sink: float = 0.0

    def _carry(self, center: np.ndarray, bottom: float, target_center: np.ndarray, target_top: float) -> np.ndarray:
        p = self.params
        if self.sink <= 0.0 or np.linalg.norm(center[:2] - target_center[:2]) > p.carry_xy_tolerance:
            return super()._carry(center, bottom, target_center, target_top)
        # Over the dish: down inside it before letting go.
        held = np.array([center[0], center[1], bottom])
        release = np.array([target_center[0], target_center[1], target_top - self.sink])
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

    @staticmethod
    def input_specs() -> list[TensorSpec]:
        """Observation tensors the oracle reads (a subset of the manipulation schema)."""
        return [
            TensorSpec("robot0_eef_pos", "float32", (3,)),
            TensorSpec("robot0_eef_quat", "float32", (4,)),
            TensorSpec("robot0_gripper_qpos", "float32", (2,)),
            TensorSpec("task_object_pos", "float32", (3,), privileged=True),
            TensorSpec("task_object_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_target_pos", "float32", (3,), privileged=True),
            TensorSpec("task_target_bbox", "float32", (6,), privileged=True),
            TensorSpec("task_grasped", "float32", (1,), privileged=True),
            TensorSpec("task_stage", "float32", (len(STAGE_KINDS),), privileged=True),
            TensorSpec("task_template", "float32", (len(TEMPLATE_NAMES),), privileged=True),
            TensorSpec("task_motion_dir", "float32", (3,), privileged=True),
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
            self._pick.side = (axis, sign)
            self._pick.shift = self._rim_shift(obj, axis, cover if _overlap(obj, target) else None)
            self._pick.sink = self._sink(obs)
            self._pick.params = self._axis_params[axis]
            action = self._pick._act(
                obs["robot0_eef_pos"], obs["robot0_gripper_qpos"], obs["task_object_bbox"],
                obs["task_target_bbox"], held,
            )
            if held or (axis == 1 and not self._tilted(obs, 0.2)):
                return action  # keep the hand as it is (as the scripted policy does)
            finger_axis = np.eye(3)[axis][:2]
            action[3:6] = self._orient(obs, self._fingers_across(obs, finger_axis))
            return action
        action[3:6] = self._orient(obs, DOWN)
        return action

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
        p = self.params
        current = _quat_to_mat(obs["robot0_eef_quat"])
        error = _rotvec(desired @ current.T)
        return np.clip(error * p.rot_gain / 0.5, -p.max_rot_action, p.max_rot_action)

    @staticmethod
    def _aperture(gap: float, wanted: float) -> float:
        """Gripper command that brings the finger gap to ``wanted`` and holds it there (the gripper
        integrates its command, so 0 keeps the current opening)."""
        if gap > wanted + 0.004:
            return 0.5
        if gap < wanted - 0.004:
            return -0.5
        return 0.0

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
            desired = self._fingers_across(obs, perp)
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

    @staticmethod
    def _fingers_across(obs: dict[str, np.ndarray], axis_xy: np.ndarray) -> np.ndarray:
        """Hand pointing down with the fingers closing along ``axis_xy`` (the sign nearest the current pose).

        The hand is narrow across its finger axis (about 7 cm) and wide along it (about 21 cm), so a
        push with the side of the fingers needs little room behind the object.
        """
        y = np.array([axis_xy[0], axis_xy[1], 0.0])
        y /= max(float(np.linalg.norm(y)), 1e-9)
        if float(y @ _quat_to_mat(obs["robot0_eef_quat"])[:, 1]) < 0:
            y = -y
        z = np.array([0.0, 0.0, -1.0])
        return np.column_stack([np.cross(y, z), y, z])

    # -- handles: knob levers and drawer bars ------------------------------------------------------

    def _handle(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        direction = obs["task_motion_dir"]
        if not direction.any():
            action = self._pick._action(np.zeros(3), _OPEN)
            action[3:6] = self._orient(obs, DOWN)
            return action
        stage = obs["task_stage"]
        knob = stage[STAGE_KINDS.index("turnon")] > 0 or stage[STAGE_KINDS.index("turnoff")] > 0
        if not knob and abs(direction[2]) < 0.3 and self._is_bar(obs):
            return self._pull_bar(obs)  # open/close: a drawer's bar
        return self._finger_push(obs)  # turnon/turnoff: a knob's lever

    def _is_bar(self, obs: dict[str, np.ndarray]) -> bool:
        """A handle that moves along a straight line sideways: the handle goal lies on the motion line."""
        handle = obs["task_object_bbox"]
        center = (handle[:3] + handle[3:]) / 2
        offset = obs["task_target_pos"] - center
        along = float(offset @ obs["task_motion_dir"])
        return along > 0.02 and float(np.linalg.norm(offset - along * obs["task_motion_dir"])) < 1e-3

    def _finger_push(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Push the handle along its motion direction with the trailing finger of the open gripper."""
        p = self.params
        eef = obs["robot0_eef_pos"]
        handle, d, center, extent = _handle_frame(obs)
        # Finger on the -d side of the handle; the grip site sits finger_offset further along y.
        finger = center - d * (extent + p.finger_half + p.handle_gap)
        side = np.sign(d[1]) if abs(d[1]) > 1e-6 else 1.0
        site = finger + np.array([0.0, side * p.finger_offset, 0.0])
        site[2] = center[2] + p.handle_dz
        remaining = float(np.linalg.norm(obs["task_target_pos"] - center))
        rel = eef - site
        along = float(rel @ d)
        lateral = rel - along * d
        lateral[2] = 0.0
        engaged = (-p.handle_tolerance <= along <= 0.03 and np.linalg.norm(lateral) < p.handle_tolerance
                   and abs(eef[2] - site[2]) < 0.015)
        if engaged:
            goal = site + d * (remaining + p.overshoot)
            action = self._move(eef, goal, _OPEN, p.handle_max_action)
        else:
            hover = handle[5] + p.handle_hover
            if np.linalg.norm((eef - site)[:2]) > p.handle_tolerance:
                if eef[2] < hover - 0.02:
                    action = self._move(eef, np.array([eef[0], eef[1], hover]), _OPEN, p.handle_max_action)
                else:
                    action = self._move(eef, np.array([site[0], site[1], hover]), _OPEN, p.handle_max_action)
            else:
                action = self._move(eef, site, _OPEN, p.handle_max_action)
        action[3:6] = self._orient(obs, DOWN)
        return action

    def _pull_bar(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Face the bar (fingers horizontal, closing vertically), grasp it and move it along the axis."""
        p = self.params
        eef = obs["robot0_eef_pos"]
        handle, d, center, extent = _handle_frame(obs)
        # The handle protrudes toward the side it is pulled from; face it from there.
        out = d if float((obs["task_target_pos"] - center) @ d) > 0 else -d
        approach = -out  # hand z axis (palm to fingertips) points at the cabinet
        finger_axis = np.array([0.0, 0.0, 1.0])
        desired = np.column_stack([np.cross(finger_axis, approach), finger_axis, approach])
        ori_error = float(np.linalg.norm(_rotvec(desired @ _quat_to_mat(obs["robot0_eef_quat"]).T)))
        grasp = center + out * (extent - p.bar_depth)
        grasp[2] = center[2] - p.bar_sag
        standoff = grasp + out * p.bar_standoff
        gap = float(obs["robot0_gripper_qpos"][0] - obs["robot0_gripper_qpos"][1])
        rel = eef - grasp
        along = float(rel @ out)
        lateral = rel - along * out
        at_grasp = abs(along) < p.handle_tolerance and np.linalg.norm(lateral) < p.bar_tolerance
        remaining = float(np.linalg.norm(obs["task_target_pos"] - center))
        holding = bool(obs["task_grasped"][0] > 0.5)
        if holding:
            goal = eef + d * (remaining + p.overshoot)
            action = self._move(eef, goal, _CLOSE, p.handle_max_action)
        elif at_grasp:
            if gap < p.bar_closed_gap:  # closed on nothing: back off
                action = self._move(eef, standoff, self._aperture(gap, p.bar_open_gap), p.handle_max_action)
            else:
                action = self._move(eef, grasp, _CLOSE, p.handle_max_action)
        elif ori_error > p.bar_ori_tolerance or np.linalg.norm((eef - standoff) - ((eef - standoff) @ out) * out) > p.bar_tolerance:
            # Turn and line up in front of the bar first, well clear of the cabinet.
            action = self._move(eef, standoff, self._aperture(gap, p.bar_open_gap), p.handle_max_action)
        else:
            action = self._move(eef, grasp, self._aperture(gap, p.bar_open_gap), p.handle_max_action)
        action[3:6] = self._orient(obs, desired)
        return action


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """The two boxes overlap horizontally."""
    return bool(a[0] < b[3] and b[0] < a[3] and a[1] < b[4] and b[1] < a[4])


def _handle_frame(obs: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The handle's box, its horizontal motion direction, its centre and its half-extent along it."""
    handle = obs["task_object_bbox"]
    d = obs["task_motion_dir"].copy()
    d[2] = 0.0
    d /= max(float(np.linalg.norm(d)), 1e-9)
    center = (handle[:3] + handle[3:]) / 2
    half = (handle[3:] - handle[:3]) / 2
    extent = float(abs(d[0]) * half[0] + abs(d[1]) * half[1])
    return handle, d, center, extent
