"""Phase III gates: historical regression on the cluster, the do-nothing control, then held-out success.

A consolidated candidate is admitted only if (1) it solves at least ``regression_min`` of the
seeds of clusters of at least ``min_cluster`` seeds (the paper asks for all of them: 1.0; one seed
is no regression), (2) the same harness around a do-nothing policy (zero actions) succeeds on at
most ``max_control`` of the task's dev seeds (a harness that solves the task by itself is not a
correction of the policy), and (3) its held-out (gate) success is strictly higher than the current
harness's on the same seeds. Anything else goes to the buffer of rejected candidates (the store's
``rejected`` table) and is never evaluated again. Test seeds never reach this module.

A success with an intervention still in control at the success step (a placement recovery that
finished the task) counts as a success, as in the paper, and every results table reports how many
there were. ``require_hand_back`` asks for more: regression and held-out then count only successes
with the policy in control (``Rollout.credited``). The do-nothing control always counts every
success: there, any success is the harness solving the task by itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from services.evolver.store import Rollout
from zetta_wire.stats import wilson


@dataclass(frozen=True)
class GateParams:
    """Thresholds of the gates."""

    regression_min: float = 1.0
    #: Fewest seeds a regression is measured on: a one-seed cluster proves nothing.
    min_cluster: int = 3
    #: Largest do-nothing success on the dev seeds a harness may have.
    max_control: float = 0.05
    #: Count only successes with the policy in control at the success step (no intervention still
    #: in control: it handed back before the task was done), in validation, regression and held-out.
    require_hand_back: bool = False

    def won(self, rollout: Rollout) -> bool:
        """Whether a rollout counts as a success for the evolver's decisions."""
        return rollout.credited if self.require_hand_back else rollout.success

    def successes(self, rollouts: Sequence[Rollout]) -> tuple[int, int]:
        """(successes the decisions count, episodes)."""
        return sum(self.won(r) for r in rollouts), len(rollouts)


@dataclass(frozen=True)
class Verdict:
    """Why a candidate was admitted or refused, with the numbers."""

    admitted: bool
    reason: str
    regression: tuple[int, int]
    heldout: tuple[int, int]
    current: tuple[int, int]
    bare: tuple[int, int]
    control: tuple[int, int] = (0, 0)

    @property
    def delta_over_bare(self) -> float:
        """Delta SR = SR(held-out | candidate) - SR(held-out | bare policy)."""
        return _rate(self.heldout) - _rate(self.bare)

    def to_dict(self) -> dict[str, Any]:
        """JSON form with Wilson intervals."""
        def block(x: tuple[int, int]) -> dict[str, Any]:
            lo, hi = wilson(*x)
            return {"successes": x[0], "episodes": x[1], "rate": _rate(x), "wilson95": [lo, hi]}

        return {"admitted": self.admitted, "reason": self.reason, "regression": block(self.regression),
                "heldout": block(self.heldout), "current": block(self.current), "bare": block(self.bare),
                "control": block(self.control), "delta_over_bare": self.delta_over_bare}


def _rate(x: tuple[int, int]) -> float:
    return x[0] / x[1] if x[1] else 0.0


def count(rollouts: Sequence[Rollout]) -> tuple[int, int]:
    """(successes, episodes), every success counted."""
    return sum(r.success for r in rollouts), len(rollouts)


def regression_gate(regression: Sequence[Rollout], params: GateParams = GateParams()) -> str | None:
    """Why the candidate fails historical regression, or None when it passes."""
    s, n = params.successes(regression)
    if n < params.min_cluster:
        return f"historical regression on {n} seed(s): it needs clusters of at least {params.min_cluster}"
    if s / n < params.regression_min:
        return f"historical regression {s}/{n} below {params.regression_min:.0%} of the cluster"
    return None


def control_gate(control: Sequence[Rollout], params: GateParams = GateParams()) -> str | None:
    """Why the harness fails the do-nothing control, or None when it passes."""
    s, n = count(control)
    if n == 0:
        return "no do-nothing control was run"
    if s / n > params.max_control:
        return (f"the harness around a do-nothing policy succeeds on {s}/{n} dev seeds, over "
                f"{params.max_control:.0%}: it solves the task by itself")
    return None


def judge(regression: Sequence[Rollout], heldout: Sequence[Rollout], current: Sequence[Rollout],
          bare: Sequence[Rollout], control: Sequence[Rollout], params: GateParams = GateParams()) -> Verdict:
    """Every gate; held-out rollouts of candidate, current and bare must be on the same seeds."""
    seeds = sorted(r.seed for r in heldout)
    if seeds != sorted(r.seed for r in current) or seeds != sorted(r.seed for r in bare):
        raise ValueError("held-out comparison on different seeds: candidate, current and bare must share them")
    reg, held, cur, base = (params.successes(x) for x in (regression, heldout, current, bare))
    ctl = count(control)
    why = regression_gate(regression, params) or control_gate(control, params)
    if why is not None:
        return Verdict(False, why, reg, held, cur, base, ctl)
    if held[0] <= cur[0]:
        return Verdict(False, f"held-out {held[0]}/{held[1]} is not a strict improvement over the current "
                              f"harness's {cur[0]}/{cur[1]}", reg, held, cur, base, ctl)
    return Verdict(True, f"held-out {held[0]}/{held[1]} > current {cur[0]}/{cur[1]}; regression {reg[0]}/{reg[1]}; "
                         f"do-nothing control {ctl[0]}/{ctl[1]}", reg, held, cur, base, ctl)
