"""Handle geometry and motions for articulation stages: a knob's lever, a drawer's bar.

One module for the scripted oracle (services/policy_worker/models/oracle.py) and the harness
library's articulation recoveries (services/harness/runtime/library/recoveries.py), like
services/common/rotations.py for orientations: both compute the same handle frame, the same finger
push along a lever's tangent, the same front grasp and pull of a bar, and the same hook of a bar
too low to grip from the front, from the observation tensors the env families publish for an
articulation stage (services/env_worker/families/task_state.py):

* ``task_object_bbox``: the handle's box (the drawer's moving geom furthest along the opening
  direction; a knob's lever); ``task_target_pos``: where the handle's centre must go;
  ``task_motion_dir``: the direction it must move; ``task_stage``: the stage's predicate kind;
* ``task_grasped``, ``robot0_gripper_qpos``, ``robot0_eef_pos``/``_quat``; ``task_obstacle_bbox``
  (optional) for the surface under a low drawer.

Nothing here names a task: every target is recomputed from the live handle box at every step.
:class:`HandleSkill` is stateless; the caller supplies the translation primitive (``move``) so the
oracle keeps its own gains and the harness its own, and the parameters (:class:`HandleParams`, or
any object with the same attributes: the oracle's params derive from it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from services.common.rotations import quat_to_mat, rotvec

OPEN, CLOSE = -1.0, 1.0
#: The hand pointing down with the fingers closing along world y (robosuite's default Panda pose),
#: as the rotation of the ``robot0_eef_quat`` frame.
DOWN = np.diag([1.0, -1.0, -1.0])
#: Predicate kinds of an articulation stage, as in services/env_worker/milestones.py.
ARTICULATION_KINDS = ("open", "close", "turnon", "turnoff")
KNOB_KINDS = ("turnon", "turnoff")

#: The motions of :meth:`HandleSkill.mode`.
NONE, PUSH, PULL, HOOK = "none", "finger_push", "pull_bar", "hook_bar"

#: ``move(eef, goal, gripper, limit)`` -> a 7-d OSC_POSE delta action (rotation part zero).
Move = Callable[[np.ndarray, np.ndarray, float, float], np.ndarray]
Obs = Mapping[str, np.ndarray]


@dataclass(frozen=True)
class HandleParams:
    """Generic offsets (metres) and gains of the handle motions; none is specific to a task."""

    #: Orientation gain: fraction of the rotation error corrected per step, and the largest
    #: rotation action (OSC scales 1.0 to 0.5 rad).
    rot_gain: float = 1.0
    max_rot_action: float = 0.6
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
    #: A bar gripped from the front is pushed with a finger over its last centimetres (a stretched
    #: arm's grasp slips there).
    bar_finish: float = 0.02
    #: Hook of a low bar (the palm of a front grasp would reach into the table): the closed fingers,
    #: closing along the bar, tilted this far from straight down toward the cabinet, their tips
    #: ``hook_tip`` beyond the grip site put ``hook_gap`` behind the bar and ``hook_depth`` below its
    #: top, coming down from ``hook_hover`` back along the fingers; within ``hook_tolerance`` of
    #: that pose the hand drags the bar along its axis, pressing ``hook_press`` into it (friction).
    hook_tilt: float = 0.4
    hook_gap: float = 0.006
    hook_depth: float = 0.006
    hook_tip: float = 0.012
    hook_hover: float = 0.05
    hook_tolerance: float = 0.025
    hook_press: float = 0.05
    # -- the hand's size -----------------------------------------------------------------------------
    #: Half width of the hand across its finger axis.
    hand_half_across: float = 0.035
    #: The hand's collision box above its grip site: half length along the finger axis.
    palm_half_along: float = 0.105


def _pull_side(obs: Obs, center: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The unit direction along the drawer's axis ``d`` that moves the bar toward its goal."""
    return d if float((obs["task_target_pos"] - center) @ d) > 0 else -d


def _turn_left(obs: Obs, desired: np.ndarray) -> float:
    """Angle (rad) the hand still has to turn to reach the rotation ``desired``."""
    return float(np.linalg.norm(rotvec(desired @ quat_to_mat(obs["robot0_eef_quat"]).T)))


def handle_frame(obs: Obs) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The handle's box, its horizontal motion direction, its centre and its half-extent along it."""
    handle = obs["task_object_bbox"]
    d = obs["task_motion_dir"].copy()
    d[2] = 0.0
    d /= max(float(np.linalg.norm(d)), 1e-9)
    center = (handle[:3] + handle[3:]) / 2
    half = (handle[3:] - handle[:3]) / 2
    extent = float(abs(d[0]) * half[0] + abs(d[1]) * half[1])
    return handle, d, center, extent


def remaining(obs: Obs) -> float:
    """How far (m) the handle's centre still is from where the stage's goal puts it."""
    handle = obs["task_object_bbox"]
    return float(np.linalg.norm(obs["task_target_pos"] - (handle[:3] + handle[3:]) / 2))


def stage_kind(obs: Obs, kinds: tuple[str, ...]) -> str:
    """The predicate kind of the stage being worked on (``task_stage`` one-hot over ``kinds``), "" if none."""
    stage = obs.get("task_stage")
    if stage is None or len(stage) != len(kinds) or not np.any(stage):
        return ""
    return kinds[int(np.argmax(stage))]


def is_knob(obs: Obs, kinds: tuple[str, ...]) -> bool:
    """The stage turns a knob (its lever is pushed, never gripped)."""
    stage = obs["task_stage"]
    return bool(stage[kinds.index("turnon")] > 0 or stage[kinds.index("turnoff")] > 0)


def aperture(gap: float, wanted: float) -> float:
    """Gripper command that brings the finger gap to ``wanted`` and holds it there (the gripper
    integrates its command, so 0 keeps the current opening)."""
    if gap > wanted + 0.004:
        return 0.5
    if gap < wanted - 0.004:
        return -0.5
    return 0.0


class HandleSkill:
    """Stateless handle motions on the live observation: :meth:`act` is the oracle's handle skill.

    ``kinds`` is the order of the ``task_stage`` one-hot (services/env_worker/milestones.STAGE_KINDS,
    passed in so this module depends on no service).
    """

    def __init__(self, params: HandleParams, move: Move, kinds: tuple[str, ...]) -> None:
        self.params = params
        self.move = move
        self.kinds = kinds

    # -- dispatch --------------------------------------------------------------------------------

    def mode(self, obs: Obs) -> str:
        """Which motion the stage needs now: none (no motion direction), a finger push (a knob's
        lever, or a bar's last centimetres), a front grasp and pull of a bar, or a hook of a low bar."""
        direction = obs["task_motion_dir"]
        if not direction.any():
            return NONE
        if not is_knob(obs, self.kinds) and abs(direction[2]) < 0.3 and self.is_bar(obs):
            # open/close: a drawer's bar. Hooked from above where the hand cannot grip it from the
            # front; gripped from the front, the last centimetres are pushed with a finger (a
            # stretched arm's grasp slips there).
            if self.front_blocked(obs):
                return HOOK
            if remaining(obs) > self.params.bar_finish:
                return PULL
        return PUSH  # turnon/turnoff: a knob's lever

    def act(self, obs: Obs) -> np.ndarray:
        """The next action of the handle motion for the current stage."""
        mode = self.mode(obs)
        if mode == NONE:
            eef = obs["robot0_eef_pos"]
            action = self.move(eef, eef, OPEN, self.params.handle_max_action)
            action[3:6] = self.orient(obs, DOWN)
            return action
        if mode == HOOK:
            return self.hook_bar(obs)
        if mode == PULL:
            return self.pull_bar(obs)
        return self.finger_push(obs)

    def orient(self, obs: Obs, desired: np.ndarray) -> np.ndarray:
        """Rotation part of an action turning the hand toward ``desired``."""
        p = self.params
        error = rotvec(desired @ quat_to_mat(obs["robot0_eef_quat"]).T)
        return np.clip(error * p.rot_gain / 0.5, -p.max_rot_action, p.max_rot_action)

    def is_bar(self, obs: Obs) -> bool:
        """A handle that moves along a straight line sideways: the handle goal lies on the motion line."""
        handle = obs["task_object_bbox"]
        center = (handle[:3] + handle[3:]) / 2
        offset = obs["task_target_pos"] - center
        along = float(offset @ obs["task_motion_dir"])
        return along > 1e-3 and float(np.linalg.norm(offset - along * obs["task_motion_dir"])) < 1e-3

    def front_blocked(self, obs: Obs) -> bool:
        """The hand gripping the bar from the front (fingers closing vertically) would reach into the
        surface the cabinet stands on: its palm is tall along the fingers, and a low drawer's bar sits
        closer to the table than half of it."""
        obstacles = obs.get("task_obstacle_bbox")
        if obstacles is None:
            return False
        p = self.params
        handle = obs["task_object_bbox"]
        reach = p.hand_half_across
        surface = (np.any(obstacles != 0.0, axis=1) & (obstacles[:, 5] < handle[2])
                   & (obstacles[:, 0] <= handle[0] - reach) & (obstacles[:, 3] >= handle[3] + reach)
                   & (obstacles[:, 1] <= handle[1] - reach) & (obstacles[:, 4] >= handle[4] + reach))
        if not surface.any():
            return False
        lowest = (handle[2] + handle[5]) / 2 - p.bar_sag - p.palm_half_along
        return bool(lowest < float(obstacles[surface, 5].max()))

    # -- motions ---------------------------------------------------------------------------------

    def push_site(self, obs: Obs) -> np.ndarray:
        """Where the grip site goes to push the handle with the trailing finger of the open gripper."""
        p = self.params
        _, d, center, extent = handle_frame(obs)
        # Finger on the -d side of the handle; the grip site sits finger_offset further along y.
        finger = center - d * (extent + p.finger_half + p.handle_gap)
        side = np.sign(d[1]) if abs(d[1]) > 1e-6 else 1.0
        site = finger + np.array([0.0, side * p.finger_offset, 0.0])
        site[2] = center[2] + p.handle_dz
        return np.asarray(site)

    def finger_push(self, obs: Obs) -> np.ndarray:
        """Push the handle along its motion direction with the trailing finger of the open gripper."""
        p = self.params
        eef = obs["robot0_eef_pos"]
        handle, d, center, extent = handle_frame(obs)
        site = self.push_site(obs)
        left = float(np.linalg.norm(obs["task_target_pos"] - center))
        rel = eef - site
        along = float(rel @ d)
        lateral = rel - along * d
        lateral[2] = 0.0
        engaged = (-p.handle_tolerance <= along <= 0.03 and np.linalg.norm(lateral) < p.handle_tolerance
                   and abs(eef[2] - site[2]) < 0.015)
        if engaged:
            goal = site + d * (left + p.overshoot)
            action = self.move(eef, goal, OPEN, p.handle_max_action)
        else:
            hover = handle[5] + p.handle_hover
            if np.linalg.norm((eef - site)[:2]) > p.handle_tolerance:
                if eef[2] < hover - 0.02:
                    action = self.move(eef, np.array([eef[0], eef[1], hover]), OPEN, p.handle_max_action)
                else:
                    action = self.move(eef, np.array([site[0], site[1], hover]), OPEN, p.handle_max_action)
            else:
                action = self.move(eef, site, OPEN, p.handle_max_action)
        action[3:6] = self.orient(obs, DOWN)
        return action

    def hook_bar(self, obs: Obs) -> np.ndarray:
        """Hook the closed fingertips behind the bar from above, tilted, and drag it along the axis."""
        p = self.params
        eef = obs["robot0_eef_pos"]
        handle, d, center, extent = handle_frame(obs)
        out = _pull_side(obs, center, d)
        up = np.array([0.0, 0.0, 1.0])
        tilt = p.hook_tilt
        approach = -up * np.cos(tilt) - out * np.sin(tilt)  # fingertips down and toward the cabinet
        finger_axis = np.cross(up, out)  # closing along the bar
        desired = np.column_stack([np.cross(finger_axis, approach), finger_axis, approach])
        ori_error = _turn_left(obs, desired)
        # The fingertip's end (hook_tip beyond the grip site along the approach) just behind the bar.
        tip = center - out * (extent + p.hook_gap)
        tip[2] = handle[5] - p.hook_depth
        site = tip - approach * p.hook_tip
        hover = site - approach * p.hook_hover
        rel = eef - site
        along = float(rel @ approach)  # negative: back along the fingers, above the hook pose
        lateral = float(np.linalg.norm(rel - along * approach))
        left = float(np.linalg.norm(obs["task_target_pos"] - center))
        if abs(along) < p.hook_tolerance and lateral < p.hook_tolerance and ori_error < p.bar_ori_tolerance:
            # Hooked: drag the bar along its axis, pressing into it.
            goal = eef + out * (left + p.overshoot) - up * p.hook_press
            action = self.move(eef, goal, CLOSE, p.handle_max_action)
        elif ori_error > p.bar_ori_tolerance or (lateral > p.hook_tolerance and along >= -0.01):
            # Not turned yet, or off the line of approach near the bar: over the hover point first.
            goal = hover if np.linalg.norm(eef - hover) > p.hook_tolerance else site
            action = self.move(eef, goal, CLOSE, p.handle_max_action)
        else:
            action = self.move(eef, site, CLOSE, p.handle_max_action)  # down the line of approach
        action[3:6] = self.orient(obs, desired)
        return action

    def pull_bar(self, obs: Obs) -> np.ndarray:
        """Face the bar (fingers horizontal, closing vertically), grasp it and move it along the axis."""
        p = self.params
        eef = obs["robot0_eef_pos"]
        handle, d, center, extent = handle_frame(obs)
        # The handle protrudes toward the side it is pulled from; face it from there.
        out = _pull_side(obs, center, d)
        approach = -out  # hand z axis (palm to fingertips) points at the cabinet
        finger_axis = np.array([0.0, 0.0, 1.0])
        desired = np.column_stack([np.cross(finger_axis, approach), finger_axis, approach])
        ori_error = _turn_left(obs, desired)
        grasp = center + out * (extent - p.bar_depth)
        grasp[2] = center[2] - p.bar_sag
        standoff = grasp + out * p.bar_standoff
        gap = float(obs["robot0_gripper_qpos"][0] - obs["robot0_gripper_qpos"][1])
        rel = eef - grasp
        along = float(rel @ out)
        lateral = rel - along * out
        at_grasp = abs(along) < p.handle_tolerance and np.linalg.norm(lateral) < p.bar_tolerance
        left = float(np.linalg.norm(obs["task_target_pos"] - center))
        holding = bool(obs["task_grasped"][0] > 0.5)
        if holding:
            goal = eef + d * (left + p.overshoot)
            action = self.move(eef, goal, CLOSE, p.handle_max_action)
        elif at_grasp:
            if gap < p.bar_closed_gap:  # closed on nothing: back off
                action = self.move(eef, standoff, aperture(gap, p.bar_open_gap), p.handle_max_action)
            else:
                action = self.move(eef, grasp, CLOSE, p.handle_max_action)
        elif ori_error > p.bar_ori_tolerance or np.linalg.norm((eef - standoff) - ((eef - standoff) @ out) * out) > p.bar_tolerance:
            # Turn and line up in front of the bar first, well clear of the cabinet.
            action = self.move(eef, standoff, aperture(gap, p.bar_open_gap), p.handle_max_action)
        else:
            action = self.move(eef, grasp, aperture(gap, p.bar_open_gap), p.handle_max_action)
        action[3:6] = self.orient(obs, desired)
        return action

    def outward(self, obs: Obs) -> np.ndarray:
        """Horizontal unit vector from the fixture toward the side the hand works from: for a bar,
        the side it is pulled from (its protruding front), for a lever the -d side it is pushed from."""
        _, d, center, _ = handle_frame(obs)
        if self.mode(obs) in (PULL, HOOK):
            return d if float((obs["task_target_pos"] - center) @ d) > 0 else -d
        return -d
