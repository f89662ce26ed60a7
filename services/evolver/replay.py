"""Diagnostic replay: run critic predicates over a stored trace as the runtime would have.

The runtime feeds critics a sliding window of Frames; the replay rebuilds those frames from the
trace as the runtime builds them (the observation tensors a harness may read, the perception
tool with its default noise over the recorded state, the last action that led to each frame,
milestones reached so far) and reports the first env step at which a predicate held. The trace is recorded at the policy's call
rate, so a window of n frames spans n policy calls here.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from services.harness.runtime import signals
from services.harness.runtime.api import Frame, Window
from services.harness.runtime.perception import Perception, episode_seed
from services.evolver.trace import Trace

#: Frames a replayed critic sees at once (the runtime's window is at least this long).
WINDOW = 64


def frames(trace: Trace) -> list[Frame]:
    """The trace as the runtime's Frames."""
    reached = trace.mu_reached
    last_action: dict[int, np.ndarray] = {}
    for i, k in enumerate(trace.action_frame):
        last_action[int(k)] = trace.actions[i]
    names = trace.milestone_names
    out: list[Frame] = []
    perception: Perception | None = None
    for k in range(trace.frames):
        obs = {name: v[k] for name, v in trace.obs.items()}
        if perception is None:
            perception = Perception(episode_seed(obs, ""))
        mu = frozenset(n for n, r in zip(names, reached[k]) if r)
        out.append(Frame(step=int(trace.frame_step[k]), obs=signals.visible(obs), action=last_action.get(k),
                         milestones=mu, perceive=perception.sensor(obs)))
    return out


def first_fire(trace: Trace, fn: Callable[[Window, Mapping[str, float]], Any], params: Mapping[str, float],
               instruction: str = "", start: int = 0, cached: list[Frame] | None = None) -> int | None:
    """The env step at which ``fn(window, params)`` first returned evidence, or None."""
    fs = cached if cached is not None else frames(trace)
    for k in range(start, len(fs)):
        window = Window(frames=fs[max(0, k - WINDOW + 1): k + 1], instruction=instruction,
                        milestone_names=trace.milestone_names)
        try:
            hit = fn(window, params)
        except Exception:  # noqa: BLE001 - a template that raises on this trace is simply silent here
            return None
        if hit:
            return fs[k].step
    return None


def resume_frame(trace: Trace, step: int) -> int:
    """The first frame after the last intervention that ended at or before env step ``step`` (0 when
    none did): where the policy had control back before a failure at ``step``. A critic firing
    earlier already had its chance (it may be what started that intervention); what a new critic
    must catch is the failure that followed the hand-back."""
    ends = [int(iv.get("end_step", -1)) for iv in trace.interventions]
    done = [e for e in ends if 0 <= e <= step]
    if not done:
        return 0
    later = np.flatnonzero(trace.frame_step > max(done))
    return int(later[0]) if len(later) else trace.frames
