"""Earliest observable divergence: t_EOD = min{t | dist(s_t, I_succ(mu_t)) > epsilon}.

dist is the nearest-neighbour distance of the object-relative state (trace.relative_state),
scaled per dimension by I_succ's spread, to the successful states working on the same milestone.
A divergence must persist for ``persist`` frames so one noisy frame does not count. When I_succ
has no state at that milestone (no success got there, e.g. a policy with no successes at all),
there is no reference to diverge from: t_EOD falls back to the point of closest approach after the
failure's last milestone gain (the m*-1 -> m* transition the paper focuses on): the hand's closest
approach to the object while not holding it, the object's closest approach to the target while
holding it. From there on the rollout moves away from what m* needs. The same fallback serves a
failure that never strays farther than epsilon from I_succ (a policy that sometimes succeeds
fails near its successful states): the end of the episode would be no place to repair. The EOD
says it was not referenced.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.evolver.profile import SuccessIndex, progress
from services.evolver.trace import Trace, relative_state


@dataclass(frozen=True)
class EODParams:
    """The metric's parameters: threshold epsilon (in scaled units) and persistence in frames."""

    epsilon: float = 3.0
    persist: int = 2


@dataclass(frozen=True)
class EOD:
    """Where and how a failure diverged."""

    frame: int
    step: int
    distance: float
    progress: int
    referenced: bool

    def to_dict(self) -> dict[str, float | int | bool | None]:
        """JSON form (strict JSON: an unreferenced distance is null, not Infinity)."""
        return {"frame": self.frame, "step": self.step,
                "distance": self.distance if np.isfinite(self.distance) else None, "progress": self.progress,
                "referenced": self.referenced}


def distances(trace: Trace, index: SuccessIndex) -> np.ndarray:
    """Per frame, the scaled distance to the nearest reference at the same progress (inf: none)."""
    rel = relative_state(trace.obs) / index.scale
    prog = progress(trace)
    out = np.full(trace.frames, np.inf)
    for p in np.unique(prog):
        ref = index.at(int(p))
        if len(ref) == 0:
            continue
        rows = np.flatnonzero(prog == p)
        diff = rel[rows, None, :] - (ref / index.scale)[None, :, :]
        out[rows] = np.sqrt((diff * diff).sum(-1)).min(axis=1)
    return out


def t_eod(trace: Trace, index: SuccessIndex, params: EODParams = EODParams()) -> EOD:
    """The failure's earliest observable divergence against I_succ."""
    d = distances(trace, index)
    prog = progress(trace)
    over = (d > params.epsilon) & np.isfinite(d)
    run = 0
    for k, flag in enumerate(over):
        run = run + 1 if flag else 0
        if run >= params.persist:
            first = k - params.persist + 1
            return EOD(first, int(trace.frame_step[first]), float(d[first]), int(prog[first]), True)
    final = int(prog[-1]) if trace.frames else 0
    gained = np.flatnonzero(prog == final)
    first = int(gained[0]) if len(gained) else 0
    k = first + closest_approach(trace, first)
    return EOD(k, int(trace.frame_step[k]) if trace.frames else 0, float("inf"), final, False)


def closest_approach(trace: Trace, start: int) -> int:
    """Frames after ``start`` to the closest approach toward the next milestone: hand to object while
    the object is not held at ``start``, object to target while it is."""
    obs = trace.obs
    if not trace.frames or "robot0_eef_pos" not in obs or "task_object_pos" not in obs:
        return 0
    held = "phi_grasp" in obs and obs["phi_grasp"][start][0] > 0.5
    a = obs["task_object_pos"][start:]
    b = obs["task_target_pos"][start:] if held and "task_target_pos" in obs else obs["robot0_eef_pos"][start:]
    return int(np.argmin(np.linalg.norm(a - b, axis=1)))
