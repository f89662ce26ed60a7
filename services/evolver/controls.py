"""Per-arm numbers of a results table: success, who did the work, and the do-nothing control.

A success the recoveries carried is not a success of the policy. Every arm of a results table
(the bare policy, the harness, the harness around a do-nothing policy) reports, besides its success
rate with a Wilson 95 % interval, the share of actions recoveries took over its successful
episodes and the share of its successes in which the policy was in control at the success step
(no intervention still in control when the episode ended: ``in_control_at_success``). Actions
the policy took while a recovery redirected it count as the recovery's; ``redirected_share`` says
how many of them there were.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from services.evolver.store import Rollout, RolloutStore
from zetta_wire.stats import wilson


def redirected_actions(interventions: Sequence[Mapping[str, Any]]) -> int:
    """Actions the policy took under a redirected instruction (interventions that record one)."""
    return sum(int(iv.get("actions", 0)) for iv in interventions if iv.get("instruction"))


def arm(store: RolloutStore, rollouts: Sequence[Rollout]) -> dict[str, Any]:
    """One arm's numbers, JSON-ready (each successful episode's trace is read once, when it had
    interventions)."""
    n = len(rollouts)
    wins = [r for r in rollouts if r.success]
    lo, hi = wilson(len(wins), n)
    actions = sum(r.policy_steps + r.recovery_steps for r in wins)
    in_control = sum(not r.in_control_at_success for r in wins)
    redirected = sum(redirected_actions(store.trace(r).interventions) for r in wins if r.interventions)
    return {
        "successes": len(wins), "episodes": n, "rate": len(wins) / n if n else 0.0, "wilson95": [lo, hi],
        "seeds": sorted(r.seed for r in rollouts),
        "recovery_share": sum(r.recovery_steps for r in wins) / actions if actions else 0.0,
        "redirected_share": redirected / actions if actions else 0.0,
        "policy_in_control_at_success": in_control / len(wins) if wins else 0.0,
    }
