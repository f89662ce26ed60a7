"""Generic recoveries: bounded, object-relative routines that take control from the policy.

A recovery is built fresh for each intervention from its parameters, started on the window that
triggered it, and asked for one action per env step until it returns ``None`` (finished; then
``status`` says ``done`` or ``failed``). The runtime, not the recovery, decides when control goes
back to the policy (the re-entry contract, services/harness/runtime/reentry.py). All motion targets
are recomputed every step from the perception tool's estimates of the object and target boxes, so a
recovery follows an object that moves and never replays a recorded trajectory. Nothing here runs
the task end to end, and nothing is shared with the scripted oracle (services/policy_worker/models):
a recovery stages, regrasps, places or retreats, then the policy goes on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from services.harness.runtime.api import Window
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

    def redundant(self) -> bool:
        """Whether, once started, this recovery would change nothing the policy does (a redirection
        under the episode's own instruction): the runtime then does not start it, and nothing is
        recorded as an intervention."""
        return False

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
        obj = t.object_box(now)
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
        box = t.object_box(w.now)
        self.proposal = t.fresh_grasp(box, memory.failed_grasps, self.p["equivalence"], self.p) if t.has_box(box) else None

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        eef, box = t.vec(now, "robot0_eef_pos"), t.object_box(now)
        if not t.has_box(box):
            return _hold(t.OPEN)  # the detector missed the object on this frame: wait for the next
        if self.proposal is None:
            self.proposal = t.fresh_grasp(box, self.memory.failed_grasps, self.p["equivalence"], self.p)
        if self.proposal is None:
            self._finish(FAILED, "no grasp proposal left that has not failed")
            return None
        goal = self.proposal.point(box) + [0.0, 0.0, self.p["hover"]]
        hand = t.quat_to_mat(t.vec(now, "robot0_eef_quat"))
        desired = hand_down(np.eye(3)[self.proposal.finger_axis][:2], hand)
        turned = float(np.linalg.norm(t.rotvec(desired @ hand.T)))
        if np.linalg.norm(goal - eef) < self.p["tolerance"] and turned < self.p["angle_tolerance"]:
            self._finish(DONE)
            return None
        obstacles = [t.target_box(now), box]
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
        box = t.object_box(now)
        if self.phase == "descend" and not t.has_box(box):
            return _hold(t.OPEN)
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
        obj, target = t.object_box(now), t.target_box(now)
        if not (t.has_box(obj) and t.has_box(target)):
            return _hold(t.CLOSE)  # not detected on this frame (the step budget bounds the wait)
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
        obj, target = t.object_box(now), t.target_box(now)
        if not (t.has_box(obj) and t.has_box(target)):
            return False
        if obj[2] <= target[2] + self.p["gap"]:
            return True
        n = int(self.p["stall_steps"])
        if len(w.frames) < n:
            return False
        before = t.object_box(w.frames[-n])
        return t.has_box(before) and abs(obj[2] - before[2]) < self.p["stall_motion"]

    def act(self, w: Window) -> np.ndarray | None:
        now = w.now
        obj, target = t.object_box(now), t.target_box(now)
        if self.phase == "lower":
            if not (t.has_box(obj) and t.has_box(target)):
                return _hold(t.CLOSE)  # not detected on this frame
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
        dist = t.eef_object_dist(now)
        if dist is not None and dist >= self.p["distance"] and t.scalar(now, "phi_grasp") < 0.5:
            self._finish(DONE)
            return None
        eef = t.vec(now, "robot0_eef_pos")
        return t.move_action(eef, eef + [0.0, 0.0, 0.05], t.OPEN, max_action=self.p["max_action"])


@dataclass(frozen=True)
class PolicyUnder:
    """What a recovery returns instead of an action to let the frozen policy act under another
    instruction on this step (instruction redirection)."""

    instruction: str


def _words(name: str) -> str:
    """A scene name as words: ``cream_cheese_1`` -> ``cream cheese``, ``wooden_cabinet_1_top_region`` ->
    ``wooden cabinet top``."""
    parts = [p for p in name.split("_") if p and not p.isdigit() and p not in ("region", "contain", "init")]
    return " ".join(parts)


def _milestone_parts(milestone: str) -> tuple[str, list[str]]:
    """A milestone's kind and raw arguments: ``in(bowl_1,plate_1)#2`` -> ``in``, ``[bowl_1, plate_1]``."""
    kind, _, rest = milestone.split("#")[0].partition("(")
    return kind.strip(), [a for a in rest.rstrip(")").split(",") if a]


def subgoal_instruction(milestone: str) -> str:
    """The instruction of the sub-goal a milestone names ("" when it names none the policy knows):
    ``grasped(cream_cheese_1)`` -> ``pick up the cream cheese``, ``open(wooden_cabinet_1_top_region)``
    -> ``open the wooden cabinet top``, ``in(bowl_1,plate_1)`` -> ``put the bowl in the plate``."""
    kind, raw = _milestone_parts(milestone)
    if not raw or raw[0].endswith(".handle"):
        return ""  # reached(r.handle): a handle is not something the policy is asked to pick up
    args = [_words(a) for a in raw]
    if kind in ("reached", "grasped", "lifted"):
        return f"pick up the {args[0]}"
    if kind in ("above", "on", "released") and len(args) == 2:
        return f"put the {args[0]} on the {args[1]}"
    if kind == "in" and len(args) == 2:
        return f"put the {args[0]} in the {args[1]}"
    if kind in ("open", "close"):
        return f"{kind} the {args[0]}"
    if kind in ("turnon", "turnoff"):
        return f"turn {kind[4:]} the {args[0]}"
    return ""


#: Words that end the object phrase of an instruction ("put the bowl | on the plate").
_PHRASE_ENDS = frozenset({"on", "in", "into", "onto", "inside", "to", "of", "at", "and", "from", "under", "next",
                          "over", "toward", "towards", "with"})
#: Milestone kinds of a pick sub-goal and of a placement.
_PICK_KINDS = frozenset({"reached", "grasped", "lifted"})
_PLACE_KINDS = frozenset({"above", "on", "in", "released"})
_PICK_PLACE_KINDS = _PICK_KINDS | _PLACE_KINDS
#: Words that pick one part of a fixture ("the middle drawer", "on top of the cabinet"): a sentence
#: naming a part the sub-goal's fixture or target does not name acts on another part.
_PARTS = frozenset({"top", "middle", "bottom", "upper", "lower", "left", "right", "front", "back"})


def _parse(sentence: str) -> tuple[str, list[str], list[str]]:
    """An instruction's verb, the words of the object it acts on and the words after them:
    ``put the wine bottle on top of the cabinet`` -> ``put``, ``[wine, bottle]``,
    ``[on, top, of, the, cabinet]``."""
    words = sentence.lower().replace(",", " ").split()
    verb_len = 2 if words[:2] in (["pick", "up"], ["turn", "on"], ["turn", "off"]) else 1
    verb, rest = " ".join(words[:verb_len]), words[verb_len:]
    if rest[:1] == ["the"]:
        rest = rest[1:]
    cut = next((i for i, w in enumerate(rest) if w in _PHRASE_ENDS), len(rest))
    return verb, rest[:cut], rest[cut:]


def policy_instruction(milestone: str, known: Sequence[str], episode_instruction: str = "") -> str:
    """The instruction the policy was trained on (one of ``known``) that serves the sub-goal a
    milestone names, "" when none does. A pick sub-goal (reached, grasped, lifted) is served by a
    pick-and-place instruction on the same object (``lifted(wine_bottle_1)``: ``put the wine bottle
    on the rack``; the redirection ends once the object is lifted, before the trained placement); a
    placement (above, on, in, released) by one on the same object and target; an articulation
    (open, close, turnon, turnoff) by one with the same verb that shares the most words with the
    fixture, its object phrase counting double. A sentence that names a part (top, middle, bottom,
    ...) the target or fixture does not name serves nothing: "open the middle drawer" does not open
    the bottom one. Ties go to the sentence sharing more words with the
    episode's own instruction, then to the first in order."""
    kind, raw = _milestone_parts(milestone)
    args = [_words(a).split() for a in raw]
    if not args or not known:
        return ""
    goal = set(episode_instruction.lower().split())
    scored: list[tuple[int, int, str]] = []
    for sentence in known:
        if not sentence.strip():
            continue
        verb, obj, after = _parse(sentence)
        if kind in _PICK_PLACE_KINDS:
            if verb not in ("put", "place", "pick up") or not obj or obj[-1] != args[0][-1] or not set(obj) <= set(args[0]):
                continue
            if kind in _PLACE_KINDS:
                if len(args) < 2 or not set(args[1]) & set(after) or (set(after) & _PARTS) - set(args[1]):
                    continue
            score = 0
        elif kind in ("open", "close", "turnon", "turnoff"):
            if verb != {"turnon": "turn on", "turnoff": "turn off"}.get(kind, kind):
                continue
            if (set(obj) | set(after)) & _PARTS - set(args[0]):
                continue
            score = 2 * len(set(args[0]) & set(obj)) + len(set(args[0]) & set(after))
            if score == 0:
                continue
        else:
            continue
        scored.append((score, len(goal & set(sentence.lower().split())), sentence))
    if not scored:
        return ""
    best = max(s[:2] for s in scored)
    return next(s for *key, s in scored if tuple(key) == best)


def redirection(milestone_names: Sequence[str], reached: frozenset[str] | set[str], known: Sequence[str],
                episode_instruction: str) -> tuple[str, str]:
    """(instruction, goal) of an instruction redirection: the sub-goal of the first missing
    milestone that names one, asked under a sentence the policy was trained on when one serves it
    (:func:`policy_instruction`), else under the sub-goal's own words; the goal is the last milestone
    of the run that shares its instruction (reached, grasped, lifted: "pick up the bowl" is done once
    the bowl is lifted). ("", first missing milestone) when no missing milestone names a sub-goal.
    The runtime's recovery and the evolver's replay both call this, so they agree on what is asked."""
    missing = [m for m in milestone_names if m not in reached]
    first = next((i for i, m in enumerate(missing) if subgoal_instruction(m)), -1)
    if first < 0:
        return "", missing[0] if missing else ""
    own = subgoal_instruction(missing[first])
    goal = missing[first]
    for m in missing[first + 1:]:
        if subgoal_instruction(m) != own:
            break
        goal = m
    return policy_instruction(missing[first], known, episode_instruction) or own, goal


def same_instruction(a: str, b: str) -> bool:
    """Whether two instructions are the same sentence (case and spacing aside)."""
    return a.lower().split() == b.lower().split()


class RedirectInstruction(Recovery):
    """Instruction redirection: the frozen policy keeps acting, under the instruction of the
    sub-goal the first missing milestone that names one gives, for at most ``steps`` steps. The
    instruction is one the policy was trained on when one serves the sub-goal
    (:func:`policy_instruction`: ``put the wine bottle on the rack`` while the bottle is
    not lifted), else the sub-goal's own words (``pick up the wine bottle``). Done when the last
    milestone of that sub-goal is reached; fails when no missing milestone names a sub-goal or the
    steps run out. A redirection under the episode's own instruction is :meth:`redundant`: the
    policy is already asked that, so the runtime does not start it.
    The policy does the work it can do; the harness only chooses what it is asked."""

    name = "redirect_instruction"

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        super().start(w, memory)
        self.instruction, self.goal = redirection(w.milestone_names, w.now.milestones, w.policy_instructions,
                                                  w.instruction)
        self._episode_instruction = w.instruction
        self._left = int(self.p["steps"])

    def redundant(self) -> bool:
        return bool(self.instruction) and same_instruction(self.instruction, self._episode_instruction)

    def act(self, w: Window) -> np.ndarray | PolicyUnder | None:  # type: ignore[override]
        if not self.instruction:
            self._finish(FAILED, f"milestone {self.goal!r} names no sub-goal instruction")
            return None
        if self.goal in w.now.milestones:
            self._finish(DONE)
            return None
        if self._left <= 0:
            self._finish(FAILED, f"{self.goal} not reached after {int(self.p['steps'])} steps under "
                                 f"{self.instruction!r}")
            return None
        self._left -= 1
        return PolicyUnder(self.instruction)


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

    def redundant(self) -> bool:
        return len(self.parts) == 1 and self.parts[0].redundant()

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
            "stall_motion": _f(0.01, 0.0, 0.05, "perceived object travel (m) under which it has stalled"),
            "open_gap": _f(0.07, 0.02, 0.08, "finger gap (m) that counts as released"),
            "release_steps": _i(15, 1, 60, "most steps spent opening"),
        }, LowerUntilSupportedThenRelease.__doc__ or ""),
        RecoverySpec("redirect_instruction", RedirectInstruction, {
            "steps": _i(150, 5, 160, "steps the policy acts under the sub-goal's instruction (at most the "
                                     "redirection cap, services/harness/runtime/limits.py)"),
        }, RedirectInstruction.__doc__ or ""),
        RecoverySpec("retreat_until_separated", RetreatUntilSeparated, {
            "distance": _f(0.06, 0.0, 0.3, "grip site to object box (m) that counts as separated"),
            "max_action": _f(0.5, 0.05, 1.0, "largest translational action"),
        }, RetreatUntilSeparated.__doc__ or ""),
    )
}
