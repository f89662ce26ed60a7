"""Generic recoveries: bounded, object-relative routines that take control from the policy.

A recovery is built fresh for each intervention from its parameters, started on the window that
triggered it, and asked for one action per env step until it returns ``None`` (finished; then
``status`` says ``done`` or ``failed``). The runtime, not the recovery, decides when control goes
back to the policy (the re-entry contract, services/harness/runtime/reentry.py). All motion targets
are recomputed every step from the live object and target boxes, so a recovery follows an object
that moves and never replays a recorded trajectory.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from services.common import handles
from services.harness.runtime.api import Window
from services.harness.runtime.orchestrator import first_missing, milestone_kind
from services.common.rotations import hand_down
from services.harness.runtime.library import tools as t
from services.harness.runtime.library.schema import Param, RecoverySpec

RUNNING, DONE, FAILED = "running", "done", "failed"


@dataclass
class EpisodeMemory:
    """What recoveries remember within one episode: grasps that failed (so no retry repeats an
    equivalent one) and the last grasp a recovery made (charged as failed if it is needed again)."""

    failed_grasps: list[t.GraspProposal] = field(default_factory=list)
    last_grasp: t.GraspProposal | None = None


class Recovery:
    """Base: ``start`` once, then ``act`` every step until it returns None."""

    name = "recovery"

    def __init__(self, params: Mapping[str, float]) -> None:
        self.p = dict(params)
        self.status = RUNNING
        self.memory = EpisodeMemory()
        #: Why the recovery failed, when it did.
        self.reason = ""

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        """Begin on the window that triggered the intervention."""
        self.memory = memory

    def act(self, w: Window) -> np.ndarray | None:
        """The next action, or None once finished."""
        raise NotImplementedError

    def _finish(self, status: str, reason: str = "") -> None:
        self.status, self.reason = status, reason


def _hold(gripper: float = t.KEEP) -> np.ndarray:
    return np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, gripper])


class Freeze(Recovery):
    """Stop all motion for ``steps`` steps, keeping the gripper as it is."""

    name = "freeze"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        self._left = int(self.p["steps"])

    def act(self, w: Window) -> np.ndarray | None:
        if self._left <= 0:
            self._finish(DONE)
            return None
        self._left -= 1
        return _hold()


class ReleaseAndRestage(Recovery):
    """Open the gripper and rise to ``rise`` above the live object's top."""

    name = "release_and_restage"

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        eef = t.vec(now, "robot0_eef_pos")
        obj = t.vec(now, "task_object_bbox")
        goal_z = (obj[5] if t.has_box(obj) else eef[2]) + self.p["rise"]
        opened = t.scalar(now, "phi_gripper_aperture") >= self.p["open_gap"]
        if opened and eef[2] >= goal_z - self.p["tolerance"]:
            self._finish(DONE)
            return None
        goal = np.array([eef[0], eef[1], max(goal_z, eef[2])])
        return t.move_action(eef, goal, t.OPEN, max_action=self.p["max_action"])


class Pregrasp(Recovery):
    """Move, hand open and pointing down, to ``hover`` above a fresh object-relative grasp (none
    equivalent to a failed one), rising first over anything in the straight line."""

    name = "pregrasp"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        box = t.vec(w.now, "task_object_bbox")
        self.proposal = t.fresh_grasp(box, memory.failed_grasps, self.p["equivalence"], self.p) if t.has_box(box) else None

    def act(self, w: Window) -> np.ndarray | None:
        if self.proposal is None:
            self._finish(FAILED, "no grasp proposal left that has not failed")
            return None
        now = w.now
        eef, box = t.vec(now, "robot0_eef_pos"), t.vec(now, "task_object_bbox")
        goal = self.proposal.point(box) + [0.0, 0.0, self.p["hover"]]
        hand = t.quat_to_mat(t.vec(now, "robot0_eef_quat"))
        desired = hand_down(np.eye(3)[self.proposal.finger_axis][:2], hand)
        turned = float(np.linalg.norm(t.rotvec(desired @ hand.T)))
        if np.linalg.norm(goal - eef) < self.p["tolerance"] and turned < self.p["angle_tolerance"]:
            self._finish(DONE)
            return None
        obstacles = [t.vec(now, "task_target_bbox"), box]
        waypoint = t.clear_waypoint(eef, goal, obstacles, self.p["margin"], self.p["clearance"])
        action = t.move_action(eef, waypoint, t.OPEN, max_action=self.p["max_action"])
        action[3:6] = t.orient_action(t.vec(now, "robot0_eef_quat"), desired)
        return action


class Regrasp(Recovery):
    """Bounded regrasp with a memory of failed grasps: release and restage, pregrasp on a fresh
    proposal, descend, close, and check the grasp holds through a short lift; a failed attempt
    (closed on nothing, slipped in the lift, or blocked on the way) is remembered and the next one
    uses a different proposal, up to ``max_attempts``."""

    name = "regrasp"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        if memory.last_grasp is not None:  # the previous grasp did not last: never propose it again
            memory.failed_grasps.append(memory.last_grasp)
            memory.last_grasp = None
        self.attempts = 0
        self._begin_attempt(w)

    def _begin_attempt(self, w: Window) -> None:
        self.phase = "restage"
        self._restage = ReleaseAndRestage(self.p)
        self._restage.start(w, self.memory)
        self._pregrasp = Pregrasp(self.p)
        self._pregrasp.start(w, self.memory)
        self._closing = 0
        self._lift_from = 0.0
        self._phase_seen, self._phase_steps = "", 0

    def _stalled(self, w: Window, eef: np.ndarray) -> bool:
        """The hand has not moved ``stall_motion`` over the last ``stall_steps`` steps of this phase
        (an obstacle, a joint limit, or the controller settling short of its goal)."""
        if self.phase != self._phase_seen:
            self._phase_seen, self._phase_steps = self.phase, 0
        self._phase_steps += 1
        n = int(self.p["stall_steps"])
        if self._phase_steps <= n or len(w.frames) <= n:
            return False
        return float(np.linalg.norm(eef - t.vec(w.frames[-n], "robot0_eef_pos"))) < self.p["stall_motion"]

    def _fail_attempt(self, w: Window, why: str) -> np.ndarray | None:
        proposal = self._pregrasp.proposal
        if proposal is not None:
            self.memory.failed_grasps.append(proposal)
        self.attempts += 1
        if self.attempts >= int(self.p["max_attempts"]):
            self._finish(FAILED, f"{self.attempts} grasp attempts failed (last: {why})")
            return None
        self._begin_attempt(w)
        return self.act(w)

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        eef = t.vec(now, "robot0_eef_pos")
        if self.phase == "restage":
            action = self._restage.act(w)
            if action is not None and not self._stalled(w, eef):
                return action
            self.phase = "pregrasp"  # restaged, or as high as the arm gets
        if self.phase == "pregrasp":
            action = self._pregrasp.act(w)
            if action is not None:
                if self._stalled(w, eef):
                    return self._fail_attempt(w, "blocked on the way to the pregrasp")
                return action
            if self._pregrasp.status == FAILED:
                self._finish(FAILED, self._pregrasp.reason)
                return None
            self.phase = "descend"
        proposal = self._pregrasp.proposal
        assert proposal is not None
        box = t.vec(now, "task_object_bbox")
        hand = t.quat_to_mat(t.vec(now, "robot0_eef_quat"))
        rot = t.orient_action(t.vec(now, "robot0_eef_quat"), hand_down(np.eye(3)[proposal.finger_axis][:2], hand))
        if self.phase == "descend":
            grasp = proposal.point(box)
            error = float(np.linalg.norm(grasp - eef))
            if error < self.p["tolerance"]:
                self.phase = "close"
            elif self._stalled(w, eef):
                if error > 2.5 * self.p["tolerance"]:
                    return self._fail_attempt(w, "blocked on the way down")
                self.phase = "close"  # settled just short of the grip point: close there
            else:
                action = t.move_action(eef, grasp, t.OPEN, max_action=self.p["max_action"])
                action[3:6] = rot
                return action
        if self.phase == "close":
            if self._closing < int(self.p["close_steps"]):
                self._closing += 1
                return _hold(t.CLOSE)
            if not t.grasped(now):
                return self._fail_attempt(w, "closed without a grasp")
            self.phase, self._lift_from = "lift", float(eef[2])
        if not t.grasped(now):
            return self._fail_attempt(w, "grasp lost in the lift check")
        if eef[2] - self._lift_from >= self.p["lift"]:
            self.memory.last_grasp = proposal
            self._finish(DONE)
            return None
        goal = np.array([eef[0], eef[1], self._lift_from + self.p["lift"] + 0.01])
        return t.move_action(eef, goal, t.CLOSE, max_action=self.p["carry_max_action"])


class FineAlignment(Recovery):
    """Keep the grasp and bring the held object over the live target with small arm motions:
    its centre over the target's centre, its bottom ``clearance`` above the target's top. When
    the object stops getting closer for ``stall_steps`` steps (an arm against a joint limit or an
    obstacle) it is done if the object's centre is already over the target's box (inset by
    ``inset``), and fails otherwise instead of pushing on."""

    name = "fine_alignment"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        self._errors: list[float] = []

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        if not any(t.grasped(f) for f in w.frames[-int(self.p["lost_steps"]):]):
            self._finish(FAILED, "the object is not held")
            return None
        obj, target = t.vec(now, "task_object_bbox"), t.vec(now, "task_target_bbox")
        if not t.has_box(target):
            self._finish(FAILED, "the stage has no target")
            return None
        center = t.box_center(obj)
        held = np.array([center[0], center[1], obj[2]])
        tc = t.box_center(target)
        goal = np.array([tc[0], tc[1], target[5] + self.p["clearance"]])
        if np.linalg.norm(held[:2] - goal[:2]) < self.p["tolerance"] and abs(held[2] - goal[2]) < self.p["z_tolerance"]:
            self._finish(DONE)
            return None
        self._errors.append(float(np.linalg.norm(held - goal)))
        n = int(self.p["stall_steps"])
        if len(self._errors) > n and self._errors[-n - 1] - self._errors[-1] < self.p["stall_motion"]:
            inset = self.p["inset"]
            over = all(target[k] + inset <= center[k] <= target[3 + k] - inset for k in (0, 1))
            if over and obj[2] >= target[5] - self.p["z_tolerance"]:
                self._finish(DONE)
            else:
                self._finish(FAILED, "blocked short of the target")
            return None
        if held[2] < goal[2] - 0.02 and np.linalg.norm(held[:2] - goal[:2]) > self.p["tolerance"]:
            goal = np.array([held[0], held[1], goal[2]])  # rise before moving across
        return t.move_action(held, goal, t.CLOSE, gain=self.p["gain"], max_action=self.p["max_action"])


class LowerUntilSupportedThenRelease(Recovery):
    """Lower the held object over the target until it is supported (it stops following the hand,
    or its bottom reaches the target's floor), then open the gripper."""

    name = "lower_until_supported_then_release"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        self.phase = "lower"
        self._opening = 0
        self._steps = 0

    def _supported(self, w: Window) -> bool:
        now = w.now
        obj, target = t.vec(now, "task_object_bbox"), t.vec(now, "task_target_bbox")
        if obj[2] <= target[2] + self.p["gap"]:
            return True
        n = int(self.p["stall_steps"])
        if len(w.frames) < n:
            return False
        z0 = t.vec(w.frames[-n], "task_object_bbox")[2]
        return abs(obj[2] - z0) < self.p["stall_motion"]

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        obj, target = t.vec(now, "task_object_bbox"), t.vec(now, "task_target_bbox")
        if self.phase == "lower":
            if not t.has_box(target):
                self._finish(FAILED, "the stage has no target")
                return None
            self._steps += 1
            if not t.grasped(now) or (self._steps > int(self.p["stall_steps"]) and self._supported(w)):
                self.phase = "release"
            else:
                tc = t.box_center(target)
                center = t.box_center(obj)
                held = np.array([center[0], center[1], obj[2]])
                goal = np.array([tc[0], tc[1], target[2]])
                return t.move_action(held, goal, t.CLOSE, max_action=self.p["speed"], min_action=0.0)
        if t.scalar(now, "phi_gripper_aperture") >= self.p["open_gap"] or self._opening >= int(self.p["release_steps"]):
            self._finish(DONE)
            return None
        self._opening += 1
        return _hold(t.OPEN)


class RetreatUntilSeparated(Recovery):
    """Gripper open, move straight up until the grip site is ``distance`` from the object's box."""

    name = "retreat_until_separated"

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        if t.scalar(now, "phi_eef_object_dist") >= self.p["distance"] and t.scalar(now, "phi_grasp") < 0.5:
            self._finish(DONE)
            return None
        eef = t.vec(now, "robot0_eef_pos")
        return t.move_action(eef, eef + [0.0, 0.0, 0.05], t.OPEN, max_action=self.p["max_action"])


class OperateHandle(Recovery):
    """Carry an articulation stage (open/close a drawer, turn a knob on/off) to its goal with the
    oracle's handle motions (services/common/handles.py), recomputed every step from the live handle
    box and motion direction: a drawer's bar is faced, gripped and pulled or pushed along the
    drawer's axis (hooked from above where the palm would reach into the table under a low bar, its
    last centimetres pushed with a finger), a knob's lever is pushed along its tangent with a finger.
    Done once the stage's goal milestone is reached or the env moves on to the next stage; the hand
    then opens and backs off ``retreat`` from the fixture and ``rise`` up (at most ``release_steps``
    steps). A hand that starts (or stalls) within ``restage_radius`` of the handle, where the
    policy left it (resting on the bar, under it), first rises straight up to ``restage_height``
    over the handle's top, so the approach starts from above as the oracle's does. An attempt
    stalls when for ``stall_steps`` steps neither the hand moved ``stall_motion`` nor the handle came
    ``min_progress`` closer to its goal; the next attempt restages first. Fails when the stage is
    not an articulation, after ``max_steps`` operating steps, or after ``max_attempts`` stalls."""

    name = "operate_handle"

    #: Parameters passed through to the shared handle geometry (HandleParams fields).
    GEOMETRY = ("overshoot", "handle_tolerance", "handle_hover", "bar_standoff", "bar_open_gap", "bar_sag",
                "hook_tilt", "hook_press")

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        now = w.now
        geometry = {k: self.p[k] for k in self.GEOMETRY if k in self.p}
        geometry["handle_max_action"] = self.p.get("max_action", 1.0)
        self.skill = handles.HandleSkill(dataclasses.replace(handles.HandleParams(), **geometry),
                                         self._move, t.STAGE_KINDS)
        self.kind = t.stage_kind(now) if t.articulation_stage(now) else ""
        # The stage's goal milestone: the first of its kind from m* on (open(r), turnon(s), ...).
        names = list(w.milestone_names)
        m_star = first_missing(names, now.milestones)
        tail = names[names.index(m_star):] if m_star in names else []
        self.goal = next((n for n in tail if milestone_kind(n) == self.kind), "")
        self.phase = "operate"
        self.attempts = 0
        self._restage_at = -1.0
        if self.kind:
            self._maybe_restage(now)
        self._steps = 0
        self._track: list[tuple[np.ndarray, float]] = []
        self._out = np.zeros(3)
        self._release_from = np.zeros(3)
        self._released = 0

    def _move(self, eef: np.ndarray, goal: np.ndarray, gripper: float, limit: float) -> np.ndarray:
        return t.move_action(eef, goal, gripper, max_action=limit)

    def _maybe_restage(self, now) -> None:
        """Rise first when the hand is near the handle and below the restage height."""
        handle = t.vec(now, "task_object_bbox")
        eef = t.vec(now, "robot0_eef_pos")
        top = float(handle[5]) + self.p["restage_height"]
        if t.scalar(now, "phi_eef_object_dist") < self.p["restage_radius"] and eef[2] < top - 0.01:
            self.phase, self._restage_at, self._restage_steps = "restage", top, 0

    def _goal_holds(self, w: Window) -> bool:
        now = w.now
        if self.goal and self.goal in now.milestones:
            return True
        return t.stage_kind(now) != self.kind  # the env moved on: this stage's goal holds

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        eef = np.asarray(t.vec(now, "robot0_eef_pos"), dtype=np.float64)
        if self.phase == "restage":
            self._restage_steps += 1
            if eef[2] < self._restage_at - 0.01 and self._restage_steps <= 30 and not self._goal_holds(w):
                return t.move_action(eef, np.array([eef[0], eef[1], self._restage_at]), t.OPEN, max_action=0.5)
            self.phase, self._track = "operate", []
        if self.phase == "operate":
            if not self.kind:
                self._finish(FAILED, "the stage is not an articulation with a published handle")
                return None
            if self._goal_holds(w):
                self.phase, self._release_from = "release", eef.copy()
            else:
                return self._operate(w, eef)
        if self._released >= int(self.p["release_steps"]):
            self._finish(DONE)
            return None
        goal = self._release_from + self._out * self.p["retreat"] + np.array([0.0, 0.0, self.p["rise"]])
        opened = t.scalar(now, "phi_gripper_aperture") >= self.p["open_gap"]
        if opened and np.linalg.norm(goal - eef) < 0.01:
            self._finish(DONE)
            return None
        self._released += 1
        return t.move_action(eef, goal, t.OPEN, max_action=0.5)

    def _operate(self, w: Window, eef: np.ndarray) -> np.ndarray | None:
        self._steps += 1
        if self._steps > int(self.p["max_steps"]):
            self._finish(FAILED, f"the {self.kind} stage's goal does not hold after {self._steps - 1} steps")
            return None
        now = w.now
        left = t.handle_remaining(now)
        self._track.append((eef, left))
        n = int(self.p["stall_steps"])
        if len(self._track) > n:
            eef0, left0 = self._track[-n - 1]
            if float(np.linalg.norm(eef - eef0)) < self.p["stall_motion"] and left0 - left < self.p["min_progress"]:
                self.attempts += 1
                if self.attempts >= int(self.p["max_attempts"]):
                    self._finish(FAILED, f"no progress for {n} steps in {self.attempts} attempt(s): the hand "
                                         f"stalled {left:.3f} m short of the goal")
                    return None
                self._track = []
                self._maybe_restage(now)
                if self.phase == "restage":
                    return self.act(w)
        obs = t.float_obs(now)
        self._out = self.skill.outward(obs)
        return self.skill.act(obs)


class Chain(Recovery):
    """Several recoveries one after the other (a playbook's steps); fails as soon as one fails."""

    name = "chain"

    def __init__(self, parts: Sequence[Recovery]) -> None:
        super().__init__({})
        self.parts = list(parts)
        self._i = 0

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        self._i = 0
        self.parts[0].start(w, memory)

    def act(self, w: Window) -> np.ndarray | None:
        while self._i < len(self.parts):
            part = self.parts[self._i]
            action = part.act(w)
            if action is not None:
                return action
            if part.status == FAILED:
                self._finish(FAILED, f"{part.name}: {part.reason}")
                return None
            self._i += 1
            if self._i < len(self.parts):
                self.parts[self._i].start(w, self.memory)
        self._finish(DONE)
        return None


def _f(default: float, low: float, high: float, doc: str) -> Param:
    return Param(default, low, high, "float", doc)


def _i(default: int, low: int, high: int, doc: str) -> Param:
    return Param(default, low, high, "int", doc)


_RESTAGE = {
    "rise": _f(0.08, 0.0, 0.3, "height (m) over the object's top to rise to"),
    "open_gap": _f(0.07, 0.02, 0.08, "finger gap (m) that counts as open"),
    "tolerance": _f(0.01, 0.001, 0.05, "position tolerance (m)"),
    "max_action": _f(1.0, 0.05, 1.0, "largest translational action"),
}
_PREGRASP = {
    "hover": _f(0.06, 0.0, 0.3, "height (m) over the grip point"),
    "tolerance": _f(0.01, 0.001, 0.05, "position tolerance (m)"),
    "angle_tolerance": _f(0.15, 0.01, 1.0, "orientation tolerance (rad)"),
    "margin": _f(0.01, 0.0, 0.1, "obstacle growth (m) in the collision check"),
    "clearance": _f(0.06, 0.0, 0.3, "height (m) over a crossed obstacle"),
    "equivalence": _f(0.008, 0.001, 0.05, "grip points closer than this (m) are the same grasp"),
    "max_width": _f(0.07, 0.02, 0.08, "widest object extent (m) across the fingers"),
    "max_action": _f(1.0, 0.05, 1.0, "largest translational action"),
}

#: Name -> recovery template with its parameter schema (the evolver's search space).
RECOVERIES: dict[str, RecoverySpec] = {
    s.name: s
    for s in (
        RecoverySpec("freeze", Freeze, {"steps": _i(5, 1, 100, "steps to hold still")}, Freeze.__doc__ or ""),
        RecoverySpec("release_and_restage", ReleaseAndRestage, _RESTAGE, ReleaseAndRestage.__doc__ or ""),
        RecoverySpec("pregrasp", Pregrasp, _PREGRASP, Pregrasp.__doc__ or ""),
        RecoverySpec("regrasp", Regrasp, {
            **_RESTAGE, **_PREGRASP,
            "max_attempts": _i(3, 1, 10, "grasp attempts per intervention"),
            "close_steps": _i(10, 1, 50, "steps the gripper closes before the grasp is judged"),
            "lift": _f(0.04, 0.0, 0.2, "lift (m) over which the grasp must hold"),
            "stall_steps": _i(15, 3, 100, "steps without motion after which a phase counts as blocked"),
            "stall_motion": _f(0.004, 0.0, 0.05, "hand travel (m) under which it has not moved"),
            "carry_max_action": _f(0.5, 0.05, 1.0, "largest translational action while holding"),
        }, Regrasp.__doc__ or ""),
        RecoverySpec("fine_alignment", FineAlignment, {
            "clearance": _f(0.04, 0.0, 0.2, "height (m) of the object bottom over the target top"),
            "tolerance": _f(0.01, 0.001, 0.05, "horizontal tolerance (m)"),
            "z_tolerance": _f(0.015, 0.001, 0.05, "vertical tolerance (m)"),
            "gain": _f(10.0, 1.0, 30.0, "action per metre of error"),
            "max_action": _f(0.4, 0.05, 1.0, "largest translational action"),
            "lost_steps": _i(3, 1, 20, "frames without the grasp before alignment gives up"),
            "stall_steps": _i(15, 3, 100, "steps without getting closer that count as blocked"),
            "stall_motion": _f(0.003, 0.0, 0.05, "how much closer (m) counts as progress"),
            "inset": _f(0.01, -0.05, 0.1, "margin (m) inside the target box that counts as over it"),
        }, FineAlignment.__doc__ or ""),
        RecoverySpec("lower_until_supported_then_release", LowerUntilSupportedThenRelease, {
            "speed": _f(0.25, 0.05, 1.0, "largest downward action"),
            "gap": _f(0.005, 0.0, 0.05, "object bottom over the target's floor (m) that counts as supported"),
            "stall_steps": _i(6, 2, 50, "steps over which a stalled object counts as supported"),
            "stall_motion": _f(0.003, 0.0, 0.02, "object travel (m) under which it has stalled"),
            "open_gap": _f(0.07, 0.02, 0.08, "finger gap (m) that counts as released"),
            "release_steps": _i(15, 1, 60, "most steps spent opening"),
        }, LowerUntilSupportedThenRelease.__doc__ or ""),
        RecoverySpec("operate_handle", OperateHandle, {
            "max_steps": _i(250, 20, 600, "steps of operating before the intervention fails"),
            "stall_steps": _i(40, 5, 200, "steps without progress that count as stalled"),
            "stall_motion": _f(0.01, 0.0, 0.1, "hand travel (m) over stall_steps that counts as progress"),
            "min_progress": _f(0.005, 0.0, 0.05, "handle travel (m) toward its goal that counts as progress"),
            "max_action": _f(1.0, 0.1, 1.0, "largest translational action"),
            "overshoot": _f(0.05, 0.0, 0.15, "travel (m) commanded past the handle's goal position"),
            "handle_tolerance": _f(0.008, 0.002, 0.03, "position tolerance (m) of the finger push's start"),
            "handle_hover": _f(0.05, 0.01, 0.15, "height (m) over the handle to move across at"),
            "bar_standoff": _f(0.06, 0.02, 0.15, "standoff (m) in front of a bar before moving in to grip it"),
            "bar_open_gap": _f(0.045, 0.02, 0.08, "finger gap (m) while approaching a bar"),
            "bar_sag": _f(0.008, 0.0, 0.03, "how far (m) below a bar the sideways hand aims"),
            "hook_tilt": _f(0.4, 0.0, 0.8, "tilt (rad) of the fingers hooking a low bar"),
            "hook_press": _f(0.05, 0.0, 0.1, "how hard (m of goal offset) the hook presses into the bar"),
            "max_attempts": _i(1, 1, 5, "stalled attempts before the intervention fails"),
            "restage_radius": _f(0.0, 0.0, 0.3, "grip site to handle box (m) within which the hand rises first (0: never)"),
            "restage_height": _f(0.1, 0.02, 0.3, "height (m) over the handle's top to rise to"),
            "release_steps": _i(25, 0, 100, "most steps spent opening and backing off once the goal holds"),
            "retreat": _f(0.05, 0.0, 0.2, "how far (m) the hand backs off from the fixture once done"),
            "rise": _f(0.05, 0.0, 0.2, "how far (m) the hand rises once done"),
            "open_gap": _f(0.07, 0.02, 0.08, "finger gap (m) that counts as open"),
        }, OperateHandle.__doc__ or ""),
        RecoverySpec("retreat_until_separated", RetreatUntilSeparated, {
            "distance": _f(0.06, 0.0, 0.3, "grip site to object box (m) that counts as separated"),
            "max_action": _f(0.5, 0.05, 1.0, "largest translational action"),
        }, RetreatUntilSeparated.__doc__ or ""),
    )
}
