"""Loop 1: profile the frozen policy on dev seeds, build I_succ and the failed-seed manifest.

I_succ(mu) gathers the object-relative states of successful rollouts by milestone progress: the
number of leading milestones of M observed so far (so "progress p" means m_1..m_p were seen and
m_{p+1} is the one being worked on). A failure's progress never passes its m*, so its states are
compared with successful states that were working on the same milestone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.evolver.gate import GateParams
from services.evolver.store import Rollout, RolloutStore
from services.evolver.trace import STATE_DIM, Trace, relative_state


def progress(trace: Trace) -> np.ndarray:
    """Per frame, the count of leading milestones of M observed so far ([K] ints)."""
    reached = trace.mu_reached
    if reached.shape[1] == 0:
        return np.zeros(trace.frames, dtype=np.int64)
    missing = ~reached
    first_missing = np.where(missing.any(axis=1), missing.argmax(axis=1), reached.shape[1])
    return first_missing.astype(np.int64)


def spread(traces: Sequence[Trace], min_scale: float = 0.01) -> np.ndarray:
    """Per dimension of the relative state, its standard deviation over every frame of ``traces``
    (at least ``min_scale``; ones when there are no frames)."""
    states = [relative_state(tr.obs) for tr in traces if tr.frames]
    if not states:
        return np.ones(STATE_DIM, dtype=np.float32)
    return np.maximum(np.concatenate(states).std(axis=0), min_scale).astype(np.float32)


@dataclass
class SuccessIndex:
    """I_succ: reference states by milestone progress, plus the scale that normalizes distances."""

    states: dict[int, np.ndarray] = field(default_factory=dict)
    scale: np.ndarray = field(default_factory=lambda: np.ones(STATE_DIM, dtype=np.float32))
    rollouts: int = 0

    def at(self, p: int) -> np.ndarray:
        """Reference states working on milestone p+1 ([n, D]; n = 0 when none)."""
        return self.states.get(int(p), np.zeros((0, len(self.scale)), dtype=np.float32))

    @classmethod
    def build(cls, traces: Sequence[Trace], min_scale: float = 0.01,
              fallback: Sequence[Trace] = ()) -> "SuccessIndex":
        """The index of the given successful traces; the scale is each dimension's spread (at least
        ``min_scale``) over all their states, so no dimension dominates by its units. With no
        success at all the scale is the spread over ``fallback`` (the failures): distances stay in
        units of how much states vary, not in metres, where a fixed clustering radius would lump
        every failure with the same m* together."""
        by_p: dict[int, list[np.ndarray]] = {}
        for tr in traces:
            rel = relative_state(tr.obs)
            for p in np.unique(progress(tr)):
                by_p.setdefault(int(p), []).append(rel[progress(tr) == p])
        states = {p: np.concatenate(v).astype(np.float32) for p, v in by_p.items()}
        return cls(states=states, scale=spread(traces or fallback, min_scale), rollouts=len(traces))


@dataclass(frozen=True)
class Failure:
    """One entry of the failed-seed manifest M_fail."""

    rollout: Rollout
    m_star: str

    def to_dict(self) -> dict[str, Any]:
        """JSON form for manifests and reports."""
        return {"key": self.rollout.key, "task": self.rollout.task, "seed": self.rollout.seed, "m_star": self.m_star,
                "steps": self.rollout.steps, "trace": self.rollout.trace_path, "video": self.rollout.video_path}


@dataclass
class Profile:
    """Loop 1's output for one task and harness: the valid rollouts, I_succ and M_fail."""

    suite: str
    task: str
    harness: str
    rollouts: list[Rollout]
    index: SuccessIndex
    failures: list[Failure]
    #: What counts as a success (GateParams.require_hand_back).
    gate: GateParams = GateParams()

    @property
    def successes(self) -> int:
        """Successful rollouts, as the gate counts them."""
        return self.gate.successes(self.rollouts)[0]

    def manifest(self) -> dict[str, Any]:
        """The failed-seed manifest with m* per failure."""
        return {"suite": self.suite, "task": self.task, "harness": self.harness or "bare",
                "rollouts": len(self.rollouts), "successes": self.successes,
                "failures": [f.to_dict() for f in self.failures]}


def build_profile(store: RolloutStore, rollouts: Sequence[Rollout], suite: str, task: str, harness: str,
                  gate: GateParams = GateParams()) -> Profile:
    """I_succ and M_fail from valid rollouts already in the store; a success the ``gate`` does not
    count (an intervention finished it, under ``require_hand_back``) is in neither."""
    succ = [store.trace(r) for r in rollouts if gate.won(r)]
    failures = [Failure(r, r.first_missing or "<none>") for r in rollouts if not r.success]
    return Profile(suite, task, harness, list(rollouts), SuccessIndex.build(succ), failures, gate)
