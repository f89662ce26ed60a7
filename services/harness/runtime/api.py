"""The contract between harness code (critics, recoveries, tools) and the runtime that runs it.

Harness packages are written by people, by the evolver's template search and by LLMs; this module
is the one thing their code may import from Zetta besides the predicate library, so it stays small
and stable. A critic reads a :class:`Window` of the recent trajectory and may return a
:class:`Proposal`; it never acts. The orchestrator decides.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from services.harness.runtime.perception import Detection, Sensor, no_sensor

__all__ = ["Detection", "Frame", "Proposal", "Window"]


@dataclass(frozen=True)
class Frame:
    """One env step as critics see it: s_t (the observation tensors a harness may read:
    services/harness/runtime/signals.py), a_t (the action that led here, None at reset), mu_t
    (milestones reached so far), the step, and ``perceive``, the perception tool for this state
    (``perceive("object")`` -> a noisy :class:`Detection` or None; services/harness/runtime/perception.py)."""

    step: int
    obs: Mapping[str, np.ndarray]
    action: np.ndarray | None
    milestones: frozenset[str]
    perceive: Sensor = no_sensor


@dataclass(frozen=True)
class Window:
    """The last frames of an episode, oldest first, plus the task knowledge critics may use.

    ``policy_instructions``: the instructions the frozen policy was trained on (its model's
    ListModels answer; empty when the model lists none or the policy has not been asked yet).
    They describe the policy, not the scene: a recovery that redirects the policy asks it under one
    of them, a sentence it knows, rather than one it never saw."""

    frames: Sequence[Frame]
    instruction: str
    milestone_names: Sequence[str]
    policy_instructions: Sequence[str] = ()

    @property
    def now(self) -> Frame:
        return self.frames[-1]


@dataclass(frozen=True)
class Proposal:
    """What a critic saw (``evidence``: a kind such as ``grasp_lost`` plus numbers that justify
    it) and the mode it suggests; the orchestrator may ignore it."""

    critic: str
    evidence: str
    suggested_mode: str
    details: Mapping[str, float] = field(default_factory=dict)
