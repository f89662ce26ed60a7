"""Semantic milestones mu_t, derived from a task's goal predicates, and the first missing one m*.

The paper's Loop 1 records with every step which task milestones hold (mu_t) and, for a failed
episode, the first milestone of the ordered sequence M = <m_1, ..., m_goal> that was never observed
(m*). Nothing here is written per task: a goal is a conjunction of BDDL predicates, and each
predicate type has a milestone *template* (:data:`TEMPLATES`) instantiated with the predicate's
arguments. A goal becomes a sequence of *stages*, one per predicate, in the order they must be
achieved, plus the stages a predicate implies (an ``in`` whose target region sits in a drawer or
behind a door needs that container open first). The milestones of the stages, in order, are M.

Templates (``x`` the moved object, ``y`` the target, ``r`` an articulated region or fixture):

========================  =============================================================================
predicate                 milestones
========================  =============================================================================
on(x, y), in(x, y)        reached(x), grasped(x), lifted(x), above(x,y), on|in(x,y), released(x)
on(x, table region)       reached(x), contact(x), toward(x,y), on(x,y), released(x)  (a slide suffices)
open(r), close(r)         reached(r.handle), contact(r.handle), open|close(r)
turnon(r), turnoff(r)     reached(r.handle), contact(r.handle), turnon|turnoff(r)  (the knob's lever)
up(x)                     reached(x), grasped(x), lifted(x), up(x)
anything else             the predicate itself
========================  =============================================================================

Order: stages follow the BDDL goal, except that an implied ``open`` goes right before the stage
that needs it and a ``close`` of a container goes after every ``in`` into it ("put the bowl in
the drawer and close it" lists ``close`` first). The goal milestone of a stage is always the
official predicate (LIBERO's ``_eval_predicate``); success of the episode is only ever the
environment's own ``_check_success``.

Evaluation needs a :class:`Probe` (positions, boxes, contacts and predicates of the live scene),
so this module is pure logic, unit-tested with a fake probe; the families implement the probe.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from services.common.milestone_kinds import MAX_MILESTONES, STAGE_KINDS, TEMPLATE_NAMES, TEMPLATES
from services.common.specs import TensorSpec

#: How close (m) the grip site must come to an object's box (or a handle's) for reached(.).
REACH_TOLERANCE = 0.03
#: How far (m) an object's bottom must rise above its resting height for lifted(.).
LIFT_HEIGHT = 0.03
#: Horizontal margin (m) around a target's box for above(.,.).
ABOVE_MARGIN = 0.01
#: toward(x, y): the horizontal distance to the target shrank to this fraction of the initial one.
TOWARD_FRACTION = 0.5

_ARTICULATED = ("open", "close", "turnon", "turnoff")


@dataclass(frozen=True)
class SceneFacts:
    """What derivation needs to know about the scene beyond the goal's names.

    ``articulated``: names (regions or fixtures) whose state is a joint (drawers, doors, knobs).
    ``containers``: region name -> the object or fixture it belongs to.
    ``table_regions``: regions drawn on the table itself, reachable by sliding an object.
    """

    articulated: frozenset[str] = frozenset()
    containers: Mapping[str, str] = field(default_factory=dict)
    table_regions: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Milestone:
    """One milestone: its unique name, its kind (see :data:`TEMPLATES`) and its stage."""

    name: str
    kind: str
    stage: int


@dataclass(frozen=True)
class Stage:
    """One predicate to achieve, with the template that expands it into milestones."""

    predicate: tuple[str, ...]
    template: str
    implied: bool = False
    #: Indices of the implied stages that must hold before this one can be worked on.
    requires: tuple[int, ...] = ()

    @property
    def kind(self) -> str:
        return self.predicate[0] if self.predicate[0] in STAGE_KINDS else "other"

    @property
    def subject(self) -> str:
        return self.predicate[1] if len(self.predicate) > 1 else ""

    @property
    def target(self) -> str:
        return self.predicate[2] if len(self.predicate) > 2 else ""


@dataclass(frozen=True)
class GoalPlan:
    """The ordered stages of a goal and the milestone sequence M they expand to."""

    stages: tuple[Stage, ...]
    milestones: tuple[Milestone, ...]

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.milestones]


def _template(predicate: Sequence[str], facts: SceneFacts) -> str:
    kind = predicate[0]
    if kind in ("on", "in") and len(predicate) == 3:
        if kind == "on" and predicate[2] in facts.table_regions:
            return "slide"
        return "pick_place"
    if kind in _ARTICULATED and len(predicate) == 2 and predicate[1] in facts.articulated:
        return "articulate"
    if kind == "up" and len(predicate) == 2:
        return "lift"
    return "predicate"


def _needs_open(predicate: Sequence[str], facts: SceneFacts) -> str:
    """The articulated container an ``in`` goal's target lies in, or ""."""
    if predicate[0] != "in" or len(predicate) != 3:
        return ""
    region = predicate[2]
    if region in facts.articulated:
        return region
    parent = facts.containers.get(region, "")
    return parent if parent in facts.articulated else ""


def _closes(close: Sequence[str], other: Sequence[str], facts: SceneFacts) -> bool:
    """Whether ``close`` shuts the container that the ``in`` goal ``other`` fills."""
    if close[0] != "close" or other[0] != "in" or len(other) != 3 or len(close) != 2:
        return False
    target = other[2]
    return close[1] in (target, facts.containers.get(target, "")) or facts.containers.get(close[1], "") == target


def derive_plan(goal: Sequence[Sequence[str]], facts: SceneFacts) -> GoalPlan:
    """Expand a BDDL goal (list of predicates, e.g. ``[["on", "bowl_1", "plate_1"]]``) into a plan."""
    goals = [tuple(str(a) for a in p) for p in goal if p]
    # A close that shuts a container goes after every in() into it.
    ordered: list[tuple[str, ...]] = []
    deferred = [p for p in goals if any(_closes(p, q, facts) for q in goals)]
    ordered = [p for p in goals if p not in deferred] + deferred
    explicit = {p for p in ordered}
    stages: list[Stage] = []
    for predicate in ordered:
        requires: tuple[int, ...] = ()
        container = _needs_open(predicate, facts)
        if container and ("open", container) not in explicit:
            implied = ("open", container)
            existing = [i for i, s in enumerate(stages) if s.predicate == implied]
            if existing:
                requires = (existing[0],)
            else:
                stages.append(Stage(implied, _template(implied, facts), implied=True))
                requires = (len(stages) - 1,)
        stages.append(Stage(predicate, _template(predicate, facts), requires=requires))
    milestones: list[Milestone] = []
    used: dict[str, int] = {}
    for index, stage in enumerate(stages):
        p = stage.predicate
        values = {"p": p[0], "x": stage.subject, "y": stage.target, "args": ",".join(p[1:])}
        for kind, pattern in TEMPLATES[stage.template]:
            name = pattern.format(**values)
            used[name] = used.get(name, 0) + 1
            if used[name] > 1:
                name = f"{name}#{used[name]}"
            milestones.append(Milestone(name, kind, index))
    if len(milestones) > MAX_MILESTONES:
        raise ValueError(f"goal {goals} expands to {len(milestones)} milestones; the schema holds {MAX_MILESTONES}")
    return GoalPlan(tuple(stages), tuple(milestones))


def milestone_specs() -> list[TensorSpec]:
    """Schema entries of the milestone tensors."""
    return [
        TensorSpec(
            "milestones", "float32", (MAX_MILESTONES,), privileged=True,
            description=(
                "mu_t: 1.0 where milestone k holds at this step; the episode's milestone names, in order, are "
                "ResetResult.milestone_names (zero-padded)"
            ),
        ),
        TensorSpec(
            "milestones_reached", "float32", (MAX_MILESTONES,), privileged=True,
            description="1.0 where milestone k held at some step of the episode so far (zero-padded)",
        ),
        TensorSpec(
            "task_stage", "float32", (len(STAGE_KINDS),), privileged=True,
            description="one-hot predicate kind of the goal stage being worked on: " + ", ".join(STAGE_KINDS),
        ),
        TensorSpec(
            "task_template", "float32", (len(TEMPLATE_NAMES),), privileged=True,
            description=(
                "one-hot milestone template of the stage being worked on (how the goal expands): "
                + ", ".join(TEMPLATE_NAMES)
            ),
        ),
        TensorSpec(
            "task_motion_dir", "float32", (3,), privileged=True,
            description=(
                "unit world direction the task object must move: the handle's motion that advances an articulated "
                "stage (open, close, turn), the horizontal object-to-target direction otherwise; zeros if none"
            ),
        ),
    ]


# ---------------------------------------------------------------------------------------------
# Evaluation


class Probe(Protocol):
    """Read access to the live scene, implemented by each family."""

    def eef(self) -> np.ndarray:
        """Grip site position."""
        ...

    def bbox(self, name: str) -> np.ndarray:
        """World box [min xyz, max xyz] of an object or fixture's geoms, or of a region site."""
        ...

    def gripper_contact(self, name: str) -> tuple[bool, bool, bool]:
        """Left finger, right finger, any gripper geom touching the named object."""
        ...

    def handle_bbox(self, name: str) -> np.ndarray:
        """World box of the handle of an articulated region or fixture."""
        ...

    def handle_contact(self, name: str) -> bool:
        """Any gripper geom touches the moving part of an articulated region or fixture."""
        ...

    def holds(self, predicate: tuple[str, ...]) -> bool:
        """The official predicate of the benchmark."""
        ...


def _center(box: np.ndarray) -> np.ndarray:
    return (box[:3] + box[3:]) / 2


def _distance_to_box(point: np.ndarray, box: np.ndarray) -> float:
    gap = np.maximum(np.maximum(box[:3] - point, point - box[3:]), 0.0)
    return float(np.linalg.norm(gap))


class MilestoneTracker:
    """Evaluates a plan's milestones every step, latches which were reached, and picks the stage."""

    def __init__(self, plan: GoalPlan) -> None:
        self.plan = plan
        n = len(plan.milestones)
        self.current = np.zeros(n, dtype=bool)
        self.reached = np.zeros(n, dtype=bool)
        self.stage = 0
        #: Whether each stage's predicate holds at the last update.
        self.stage_holds: list[bool] = [False] * len(plan.stages)
        self._rest: dict[str, float] = {}
        self._start_dist: dict[tuple[str, str], float] = {}
        #: Milestones whose ``current`` flag the last update skipped (``latch_only``).
        self._stale = np.zeros(n, dtype=bool)

    def start(self, probe: Probe) -> None:
        """Begin an episode: remember resting heights and start distances, then evaluate step 0."""
        self.reached[:] = False
        self._rest = {}
        self._start_dist = {}
        for stage in self.plan.stages:
            if stage.template in ("pick_place", "slide", "lift"):
                box = probe.bbox(stage.subject)
                self._rest[stage.subject] = float(box[2])
                if stage.target:
                    self._start_dist[(stage.subject, stage.target)] = float(
                        np.linalg.norm(_center(box)[:2] - _center(probe.bbox(stage.target))[:2])
                    )
        self.update(probe)

    def update(self, probe: Probe, latch_only: bool = False) -> np.ndarray:
        """Evaluate the milestones now; returns the current hold flags (also latched in ``reached``).

        ``latch_only``: evaluate only the milestones not reached yet, for a step whose observation
        nobody reads (the steps inside an action chunk). Latching, the stage and the stage
        predicates are the same as a full update's; the current flags of the milestones skipped
        are filled in by :meth:`refresh` if this state's observation is asked for after all.
        """
        holds = [probe.holds(stage.predicate) for stage in self.plan.stages]
        self.stage_holds = holds
        self._stale = self.reached.copy() if latch_only else np.zeros_like(self.reached)
        self._evaluate(probe, ~self._stale)
        self.reached |= self.current
        self.stage = self._pick_stage(holds)
        return self.current

    def refresh(self, probe: Probe) -> np.ndarray:
        """The current flags of the state of the last :meth:`update`, evaluating those it skipped."""
        if self._stale.any():
            self._evaluate(probe, self._stale)
            self._stale[:] = False
        return self.current

    def _evaluate(self, probe: Probe, which: np.ndarray) -> None:
        """Set ``current[i]`` for every milestone i with ``which[i]`` from the probe's present state."""
        holds = self.stage_holds
        eef = probe.eef()
        cache: dict[tuple[str, str], object] = {}
        fetch = {"bbox": probe.bbox, "contact": probe.gripper_contact, "handle_bbox": probe.handle_bbox,
                 "handle_contact": probe.handle_contact}

        def get(what: str, name: str):
            key = (what, name)
            try:
                return cache[key]
            except KeyError:
                found = cache[key] = fetch[what](name)
                return found

        for i, m in enumerate(self.plan.milestones):
            if not which[i]:
                continue
            stage = self.plan.stages[m.stage]
            x, y = stage.subject, stage.target
            if m.kind == "goal":
                ok = holds[m.stage]
            elif m.kind == "reached":
                ok = _distance_to_box(eef, get("bbox", x)) <= REACH_TOLERANCE
            elif m.kind == "grasped":
                left, right, _ = get("contact", x)
                ok = left and right
            elif m.kind == "contact":
                ok = get("contact", x)[2]
            elif m.kind == "lifted":
                ok = self._lifted(x, get("bbox", x))
            elif m.kind == "above":
                box = get("bbox", x)
                ok = self._lifted(x, box)  # the target's box (often many geoms) only when it matters
                if ok:
                    target, c = get("bbox", y), _center(box)
                    ok = bool(np.all(c[:2] >= target[:2] - ABOVE_MARGIN)
                              and np.all(c[:2] <= target[3:5] + ABOVE_MARGIN))
            elif m.kind == "toward":
                start = self._start_dist.get((x, y), 0.0)
                now = float(np.linalg.norm(_center(get("bbox", x))[:2] - _center(get("bbox", y))[:2]))
                ok = now <= TOWARD_FRACTION * start if start > 0 else holds[m.stage]
            elif m.kind == "released":
                ok = holds[m.stage] and not get("contact", x)[2]
            elif m.kind == "reached_handle":
                ok = _distance_to_box(eef, get("handle_bbox", x)) <= REACH_TOLERANCE
            elif m.kind == "contact_handle":
                ok = bool(get("handle_contact", x))
            else:
                raise ValueError(f"unknown milestone kind {m.kind!r}")
            self.current[i] = ok

    def _lifted(self, name: str, box: np.ndarray) -> bool:
        rest = self._rest.get(name)
        return rest is not None and float(box[2]) >= rest + LIFT_HEIGHT

    def _pick_stage(self, holds: Sequence[bool]) -> int:
        stages = self.plan.stages
        explicit = [i for i, s in enumerate(stages) if not s.implied]
        for i in explicit:
            if not holds[i]:
                for pre in stages[i].requires:
                    if not holds[pre]:
                        return pre
                return i
        return explicit[-1] if explicit else 0

    # -- reporting ------------------------------------------------------------------------------

    def reached_names(self) -> list[str]:
        """Milestones observed so far, in plan order."""
        return [m.name for m, ok in zip(self.plan.milestones, self.reached, strict=True) if ok]

    def first_missing(self) -> str:
        """m*: the first milestone of the plan never observed so far; "" when all were.

        Also "" while every goal predicate of the task holds (the goal is reached; milestones after the
        goal, such as releasing the object, are not missing then).
        """
        explicit = [ok for ok, s in zip(self.stage_holds, self.plan.stages, strict=True) if not s.implied]
        if explicit and all(explicit):
            return ""
        for m, ok in zip(self.plan.milestones, self.reached, strict=True):
            if not ok:
                return m.name
        return ""

    def tensors(self) -> dict[str, np.ndarray]:
        """The ``milestones``, ``milestones_reached`` and ``task_stage`` observation tensors (after a
        ``latch_only`` update, call :meth:`refresh` first)."""
        if self._stale.any():
            raise RuntimeError("milestone flags skipped by a latch-only update were read: call refresh() first")
        current = np.zeros(MAX_MILESTONES, dtype=np.float32)
        reached = np.zeros(MAX_MILESTONES, dtype=np.float32)
        current[: len(self.current)] = self.current
        reached[: len(self.reached)] = self.reached
        stage = np.zeros(len(STAGE_KINDS), dtype=np.float32)
        template = np.zeros(len(TEMPLATE_NAMES), dtype=np.float32)
        if self.plan.stages:
            current_stage = self.plan.stages[self.stage]
            stage[STAGE_KINDS.index(current_stage.kind)] = 1.0
            template[TEMPLATE_NAMES.index(current_stage.template)] = 1.0
        return {"milestones": current, "milestones_reached": reached, "task_stage": stage, "task_template": template}


def first_missing(names: Sequence[str], observed: Sequence[str]) -> str:
    """m* from milestone names and the set observed in a trajectory (the paper's definition)."""
    seen = set(observed)
    return next((n for n in names if n not in seen), "")
