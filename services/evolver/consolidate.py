"""Phase III consolidation: clusters' validated patches become one harness version.

Each cluster contributes a stack: the patches its internal versions stacked, each validated on top
of the ones before it, so within a stack a later patch replaces an earlier one with the same
critic or evidence kind. Across clusters, critic unification is the union of the stacks' critics
and recovery integration keeps one plan per evidence kind; where two clusters set the same critic
or plan differently, the earlier stack (the gate passes the largest cluster first) keeps its
setting, because that is the one its cluster's historical regression measured. The result is one
draft, one version, and the gate regresses it on every cluster it merges before it is admitted.
"""

from __future__ import annotations

from collections.abc import Sequence

from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft
from services.evolver.repair import Candidate


def consolidate(parent: HarnessDraft, stacks: Sequence[Sequence[Candidate]]) -> HarnessDraft:
    """``parent`` with every cluster's stack merged in (no stacks: the parent itself)."""
    critics: dict[str, CriticDraft] = {}
    plans: dict[str, PlanDraft] = {}
    for stack in stacks:
        own_critics: dict[str, CriticDraft] = {}
        own_plans: dict[str, PlanDraft] = {}
        for p in stack:
            own_critics[p.critic_name] = p.critic
            own_plans[p.critic.evidence] = p.plan
        for k, c in own_critics.items():
            critics.setdefault(k, c)
        for k, pl in own_plans.items():
            plans.setdefault(k, pl)
    return parent.with_patch(critics, plans)
