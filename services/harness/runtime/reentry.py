"""The VLA re-entry contract Psi: when a recovery may hand control back to the policy.

Psi(s_t) = FailureCleared AND Stability(s_t) > gamma, where stability must have held for ``k``
consecutive steps (the paper's "physical state has reached equilibrium": no transient left to
cause a secondary failure once the policy resumes). ``FailureCleared`` is decided by the runtime:
the critic that proposed the intervention no longer reports that evidence, no critic reports an
evidence kind listed in ``[reentry] clears``, and the plan's ``clear_when`` predicate (if any)
holds.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from services.harness.runtime.api import Window
from services.harness.runtime.library.predicates import STABILITY_PARAMS, contact_stability
from services.harness.runtime.library.schema import resolve


@dataclass
class ReentryContract:
    """gamma, k and the Stability parameters of SKILL.md ``[reentry]``; tracks the stable run."""

    gamma: float = 0.6
    k: int = 5
    stability: Mapping[str, float] = field(default_factory=lambda: resolve(STABILITY_PARAMS, {}, "stability"))
    #: Evidence kinds that must be gone (no critic proposes them) before any recovery hands back.
    clears: tuple[str, ...] = ()
    stable_steps: int = 0
    last_stability: float = 0.0

    @classmethod
    def from_skill(cls, table: Mapping[str, Any]) -> "ReentryContract":
        """Build from SKILL.md's ``[reentry]`` table (gamma, k, clears, ``[reentry.stability]``)."""
        gamma = float(table.get("gamma", 0.6))
        k = int(table.get("k", 5))
        if not 0.0 <= gamma <= 1.0 or k < 1:
            raise ValueError(f"[reentry]: gamma must be in [0, 1] and k >= 1, got gamma={gamma}, k={k}")
        stability = resolve(STABILITY_PARAMS, table.get("stability", {}), "[reentry.stability]")
        return cls(gamma, k, stability, tuple(table.get("clears", ())))

    def reset(self) -> None:
        """A new intervention starts counting from zero."""
        self.stable_steps = 0
        self.last_stability = 0.0

    def holds(self, w: Window, failure_cleared: bool) -> bool:
        """Psi at this step; call once per step while a finished recovery waits to hand back."""
        self.last_stability = contact_stability(w, self.stability)
        self.stable_steps = self.stable_steps + 1 if self.last_stability >= self.gamma else 0
        return failure_cleared and self.stable_steps >= self.k
