"""Phase III consolidation: a cluster's validated patches become one harness version.

Critic unification: the union of the patches' critics; two patches with the same critic name (the
same template) keep the setting that caught more of the cluster, so the merged critic fires on
every member any of them caught at that setting's threshold. Recovery integration: per evidence
kind one recovery, the one of the best-covering patch. The result is one draft, one version.
"""

from __future__ import annotations

from collections.abc import Sequence

from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft
from services.evolver.repair import Candidate


def consolidate(parent: HarnessDraft, patches: Sequence[Candidate]) -> HarnessDraft:
    """``parent`` with every validated patch merged in (empty patches: the parent itself)."""
    critics: dict[str, tuple[float, CriticDraft]] = {}
    plans: dict[str, tuple[float, PlanDraft]] = {}
    for p in sorted(patches, key=lambda c: (-c.coverage, c.false_positive, c.edits)):
        if p.critic_name not in critics:
            critics[p.critic_name] = (p.coverage, p.critic)
        if p.critic.evidence not in plans:
            plans[p.critic.evidence] = (p.coverage, p.plan)
    return parent.with_patch({k: v for k, (_, v) in critics.items()}, {k: v for k, (_, v) in plans.items()})
