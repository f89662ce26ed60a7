"""Typed playbooks: multi-step recoveries composed from the library's recovery templates.

A single recovery template does one thing (regrasp, align, lower and release); what rescues a
failing episode is often a short sequence that brings the task from the stage where the policy
failed to one where it can take over again: acquire the object, or place a held one (align over the
receptacle, lower, release, retreat). No playbook runs the task end to end: each stays within the
runtime's cap (services/harness/runtime/limits.py: 80 actions, 160 for an instruction redirection,
during which the policy acts) and hands control back. A :class:`PlaybookSpec` names such a sequence
with its budgets (``max_steps``, ``max_uses``), its clearing condition and the kinds of first missing
milestone (``stages``) it is meant for. Nothing here names a task or an object: the steps act on
the live bindings, and the stages are milestone kinds, so a playbook transfers by rebinding.

The evolver's repair search pairs a critic template with a playbook whose stages contain the kind
of the cluster's m* (services/evolver/repair.py); a package declares one as a plans/*.toml table
(``recovery`` = the list of steps, ``params`` per step), exactly as a hand-written harness does.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from services.harness.runtime.library.predicates import PREDICATES
from services.harness.runtime.library.recoveries import RECOVERIES
from services.harness.runtime.library.schema import resolve

#: Milestone kinds of a pick-and-place stage (services/env_worker/milestones.py): acquiring the
#: object, then placing it. A drop on the way leaves the first missing milestone at a placing kind
#: (milestones count once reached), so playbooks that start by acquiring serve every kind.
ACQUIRE_STAGES = ("reached", "grasped", "lifted")
PLACE_STAGES = ("above", "on", "in", "released")
PICK_PLACE_STAGES = ACQUIRE_STAGES + PLACE_STAGES
#: Milestone kinds of an articulation stage (open/close a drawer, turn a knob on/off): reaching the
#: handle, touching it, then the stage's goal predicate (services/env_worker/milestones.py names the
#: handle milestones reached_handle and contact_handle; orchestrator.milestone_kind reads them so).
HANDLE_STAGES = ("reached_handle", "contact_handle")
ARTICULATION_STAGES = HANDLE_STAGES + ("open", "close", "turnon", "turnoff")


@dataclass(frozen=True)
class PlaybookSpec:
    """A named sequence of library recoveries with its budgets and where it applies."""

    name: str
    steps: tuple[str, ...]
    #: Kinds of first missing milestone under which the playbook may be granted.
    stages: tuple[str, ...]
    #: Per-step parameter overrides (step name -> {param: value}); the rest are the steps' defaults.
    args: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    max_steps: int = 80
    max_uses: int = 3
    #: Library predicate that must hold before the policy gets control back ("" = none).
    clear_when: str = ""
    #: What the playbook starts from: the object in hand (True: it fails at once without it), or
    #: either (None: it restages first, releasing whatever is held). Matched against the evidence's
    #: PredicateSpec.holding.
    holding: bool | None = None
    doc: str = ""

    def answers(self, holding: bool | None) -> bool:
        """Whether the playbook can start from evidence that implies ``holding`` (PredicateSpec.holding)."""
        return self.holding is None or holding is None or self.holding == holding


PLAYBOOKS: dict[str, PlaybookSpec] = {
    p.name: p
    for p in (
        PlaybookSpec(
            "acquire", ("regrasp",), PICK_PLACE_STAGES, max_steps=80, max_uses=1, clear_when="grasp_retained",
            doc="bounded regrasp with a memory of failed grasps and a lift check; the policy resumes holding "
                "the object (once per episode: a policy that loses it again needs more than a regrasp)"),
        PlaybookSpec(
            "place", ("fine_alignment", "lower_until_supported_then_release", "retreat_until_separated"),
            ("lifted",) + PLACE_STAGES, max_steps=80, max_uses=2, holding=True,
            doc="bring the held object over the live receptacle (rising first), lower it until supported, "
                "release, retreat"),
        PlaybookSpec(
            "redirect", ("redirect_instruction",), PICK_PLACE_STAGES + ARTICULATION_STAGES, max_steps=160, max_uses=2,
            doc="instruction redirection: the frozen policy acts under the instruction of the next sub-goal "
                "(pick up the object, open the drawer) until that milestone holds; the policy does the work, "
                "for as long as it takes in its own successes (the redirection cap)"),
    )
}


def check_playbooks() -> None:
    """Every playbook names library recoveries and a library predicate with in-range overrides
    (raises ValueError otherwise); run by the tests, so a broken entry never reaches a search."""
    from services.harness.runtime.limits import intervention_cap

    for p in PLAYBOOKS.values():
        if p.max_steps > intervention_cap(p.steps):
            raise ValueError(f"playbook {p.name}: max_steps {p.max_steps} over its cap {intervention_cap(p.steps)}")
        unknown = [s for s in p.steps if s not in RECOVERIES]
        if unknown or not p.steps:
            raise ValueError(f"playbook {p.name}: unknown recovery step(s) {unknown}")
        if set(p.args) - set(p.steps):
            raise ValueError(f"playbook {p.name}: arguments for steps it does not run: {sorted(set(p.args) - set(p.steps))}")
        for step, overrides in p.args.items():
            resolve(RECOVERIES[step].params, overrides, f"playbook {p.name}, step {step}")
        if p.clear_when and p.clear_when not in PREDICATES:
            raise ValueError(f"playbook {p.name}: clear_when {p.clear_when!r} is not a library predicate")
        if p.max_steps < 1 or p.max_uses < 1 or not p.stages:
            raise ValueError(f"playbook {p.name}: needs stages, max_steps >= 1 and max_uses >= 1")


def serving(kind: str, holding: bool | None = None) -> list[PlaybookSpec]:
    """Playbooks meant for a first missing milestone of this kind that can start from evidence
    implying ``holding``: those written for exactly that state first (a held object is placed
    before it is let go and acquired again), then the longest (most of the task carried)."""
    return sorted((p for p in PLAYBOOKS.values() if kind in p.stages and p.answers(holding)),
                  key=lambda p: (p.holding is None or p.holding != holding, -len(p.steps), p.name))
