"""The orchestrator: adjudicates critic proposals with the task knowledge and picks the mode.

Critics only propose; a proposal becomes an intervention only when an adjudication rule of the
package's SKILL.md accepts it (the paper's evidence-driven decision: sigma_t = A_orch(P_t, R, T, K)).
A rule names the evidence it accepts, the mode (recovery playbook) it grants, a priority, and
conditions on the milestones (K): ``requires_milestone`` (each must have been reached),
``unless_milestone`` (none may have been reached), ``missing`` (the first missing milestone must be
one of these). A milestone condition is either a full name (``grasped(bowl_1)``) or a kind
(``grasped``), which matches that kind on whatever object the task binds, so rules stay generic.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.harness.runtime.api import Proposal

POLICY = "policy"


def milestone_kind(name: str) -> str:
    """``grasped(cream_cheese_1)`` -> ``grasped``; a handle's ``reached(r.handle)`` and
    ``contact(r.handle)`` -> ``reached_handle`` and ``contact_handle``, the kinds
    services/env_worker/milestones.py gives them (an articulation stage's, not an object's)."""
    kind, _, rest = name.partition("(")
    if rest.split("#", 1)[0].endswith(".handle)") and kind in ("reached", "contact"):
        return f"{kind}_handle"
    return kind


def _matches(spec: str, names: Iterable[str]) -> bool:
    if "(" in spec:
        return spec in names
    return any(milestone_kind(n) == spec for n in names)


def first_missing(milestone_names: Sequence[str], reached: frozenset[str]) -> str:
    """m*: the first milestone of M not reached so far ("" when all were)."""
    for name in milestone_names:
        if name not in reached:
            return name
    return ""


def _strings(value: Any, what: str) -> tuple[str, ...]:
    if isinstance(value, str):
        return (value,)
    if isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise ValueError(f"{what} must be a string or a list of strings, got {value!r}")


@dataclass(frozen=True)
class Rule:
    """One SKILL.md ``[[adjudication]]`` entry."""

    evidence: str
    mode: str
    priority: int = 0
    requires_milestone: tuple[str, ...] = ()
    unless_milestone: tuple[str, ...] = ()
    missing: tuple[str, ...] = ()

    @classmethod
    def from_table(cls, table: Mapping[str, Any]) -> "Rule":
        """Parse and check one rule table."""
        known = {"evidence", "mode", "priority", "requires_milestone", "unless_milestone", "missing"}
        unknown = sorted(set(table) - known)
        if unknown:
            raise ValueError(f"[[adjudication]] has unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
        if not isinstance(table.get("evidence"), str) or not isinstance(table.get("mode"), str):
            raise ValueError(f"[[adjudication]] needs string 'evidence' and 'mode', got {dict(table)!r}")
        if table["mode"] == POLICY:
            raise ValueError("[[adjudication]] mode 'policy' is the policy itself, not a recovery")
        return cls(
            evidence=table["evidence"],
            mode=table["mode"],
            priority=int(table.get("priority", 0)),
            requires_milestone=_strings(table.get("requires_milestone", ()), "requires_milestone"),
            unless_milestone=_strings(table.get("unless_milestone", ()), "unless_milestone"),
            missing=_strings(table.get("missing", ()), "missing"),
        )

    def why_not(self, reached: frozenset[str], missing_now: str) -> str:
        """Why the task knowledge vetoes this rule now ("" when it allows it)."""
        for spec in self.requires_milestone:
            if not _matches(spec, reached):
                return f"requires milestone {spec}"
        for spec in self.unless_milestone:
            if _matches(spec, reached):
                return f"milestone {spec} already reached"
        if self.missing and not any(_matches(spec, [missing_now]) for spec in self.missing):
            return f"first missing milestone is {missing_now or 'none'}, not {'/'.join(self.missing)}"
        return ""


@dataclass(frozen=True)
class Verdict:
    """The orchestrator's answer for one step: the accepted proposal and rule (None: stay on the
    policy) and, per rejected proposal, why."""

    accepted: Proposal | None
    rule: Rule | None
    rejected: tuple[tuple[Proposal, str], ...]


class Orchestrator:
    """Adjudicates with the package's rules; ``exhausted(mode)`` says a playbook used its budget."""

    def __init__(self, rules: Sequence[Rule]) -> None:
        self.rules = sorted(rules, key=lambda r: -r.priority)

    def adjudicate(self, proposals: Sequence[Proposal], reached: frozenset[str], milestone_names: Sequence[str],
                   exhausted: Mapping[str, bool]) -> Verdict:
        """Pick the highest-priority rule that accepts one of the proposals."""
        if not proposals:
            return Verdict(None, None, ())
        missing_now = first_missing(milestone_names, reached)
        reasons: dict[int, str] = {}
        for rule in self.rules:
            for i, proposal in enumerate(proposals):
                if proposal.evidence != rule.evidence:
                    continue
                veto = rule.why_not(reached, missing_now)
                if not veto and exhausted.get(rule.mode, False):
                    veto = f"playbook {rule.mode} used its budget this episode"
                if veto:
                    reasons.setdefault(i, veto)
                    continue
                rejected = tuple((p, reasons.get(j, "lower priority")) for j, p in enumerate(proposals) if j != i)
                return Verdict(proposal, rule, rejected)
        rejected = tuple((p, reasons.get(i, "no adjudication rule accepts this evidence")) for i, p in enumerate(proposals))
        return Verdict(None, None, rejected)
