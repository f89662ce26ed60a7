"""Diagnostic replay: run critic predicates over a stored trace as the runtime would have.

The runtime feeds critics a sliding window of Frames; the replay rebuilds those frames from the
trace as the runtime builds them (the observation tensors a harness may read, the perception
tool with its default noise over the recorded state, the last action that led to each frame,
milestones reached so far) and reports the first env step at which a predicate held. A trace that
recorded every step (``Trace.step_obs``, what the evolver's rollouts record) replays step by step,
as the runtime runs critics: library predicates at every step, a code critic every
``ZETTA_CODE_CRITIC_EVERY`` steps, so a window of n frames spans n env steps as it does at runtime.
A trace recorded at the policy's call rate only replays one frame per call.

Library predicates are platform code and run here. A code critic (package code: one an LLM wrote,
tools/c_llm_<hash>.py) never runs in the evolver's process: :class:`SandboxedCritic` loads it in a
harness sandbox child (services/harness/sandbox/, the one the env worker uses) and replays the
trace through it frame by frame, under the platform's hard limit per call; a critic that raises,
answers something else than a Proposal or None, overruns or kills its child fails the replay with
:class:`ReplayFailed` and the reason. ``ZETTA_HARNESS_SANDBOX=off`` (trusted code only) runs it
in-process instead, as the env worker then does.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from services.harness.runtime import signals
from services.harness.runtime.api import Frame, Window
from services.harness.runtime.library.recoveries import redirection, same_instruction
from services.harness.runtime.orchestrator import first_missing, milestone_kind
from services.harness.runtime.perception import Perception, episode_seed
from services.evolver.trace import Trace

#: Frames a replayed critic sees at once (the runtime's window is at least this long).
WINDOW = 64


def frames(trace: Trace) -> list[Frame]:
    """The trace as the runtime's Frames: one per env step when it recorded every step."""
    if trace.step_obs:
        return _frames(trace.step_obs, list(range(trace.steps)), [None, *trace.actions], trace.milestone_names,
                       trace.instruction)
    last_action: dict[int, np.ndarray] = {}
    for i, k in enumerate(trace.action_frame):
        last_action[int(k)] = trace.actions[i]
    return _frames(trace.obs, [int(s) for s in trace.frame_step], [last_action.get(k) for k in range(trace.frames)],
                   trace.milestone_names, trace.instruction)


def _frames(series: Mapping[str, np.ndarray], steps: list[int], actions: list[np.ndarray | None],
            names: list[str], instruction: str) -> list[Frame]:
    """Frames over ``series`` ([K, ...] per tensor) at env ``steps``, each with the action that led to
    it and the milestones observed up to it. The perception tool's noise is drawn as the runtime drew
    it in that episode: seeded from the reset state and the episode's instruction."""
    mu = series.get("milestones")
    reached = (np.maximum.accumulate(mu[:, : len(names)] > 0.5, axis=0) if mu is not None and len(steps)
               else np.zeros((len(steps), len(names)), dtype=bool))
    out: list[Frame] = []
    perception: Perception | None = None
    for k, step in enumerate(steps):
        obs = {name: v[k] for name, v in series.items()}
        if perception is None:
            perception = Perception(episode_seed(obs, instruction))
        out.append(Frame(step=step, obs=signals.visible(obs), action=actions[k],
                         milestones=frozenset(n for n, r in zip(names, reached[k]) if r),
                         perceive=perception.sensor(obs)))
    return out


def _replayed(trace: Trace, fs: list[Frame], start: int) -> range:
    """Indices into ``fs`` from ``start`` (a frame of the trace, as :func:`resume_frame` gives it)
    on: on a trace that recorded every step, from that frame's env step."""
    if not trace.step_obs:
        return range(start, len(fs))
    return range(int(trace.frame_step[start]) if start < trace.frames else len(fs), len(fs))


class ReplayFailed(RuntimeError):
    """A code critic failed on a sandboxed replay (it raised, returned something that is not a
    Proposal, overran the hard limit or its sandbox child died); the message says which and why."""


class SandboxedCritic:
    """One code critic of a package (``tools/<stem>.py``, its ``critic_*`` function) loaded in its
    own sandbox child for diagnostic replays: :func:`first_fire` runs it there. Its parameters are
    the package's (``params/<stem>.toml``), bound at load. :meth:`close` kills the child."""

    def __init__(self, stem: str, source: str, params: Mapping[str, Any], window: int = WINDOW) -> None:
        from services.harness.runtime.budget import PlatformLimits
        from services.harness.sandbox.client import CallFailed, SandboxError
        from services.harness.sandbox.host import SandboxedCode

        self.stem = stem
        limits = PlatformLimits.from_env()
        self.hard_limit_s = limits.hard_limit_s
        #: The runtime's cadence of code critics (env steps).
        self.every = limits.code_critic_every
        try:
            self.code = SandboxedCode({stem: source}, {stem: dict(params)}, window)
        except (SandboxError, CallFailed) as exc:
            raise ReplayFailed(f"{stem} does not load in the sandbox: {exc}") from None
        mine = [i for i, name in enumerate(self.code.critics) if name.startswith(stem + ".")]
        if len(mine) != 1:
            self.code.close()
            raise ReplayFailed(f"{stem} defines {len(mine)} critic functions; a code critic has exactly one")
        self.index = mine[0]
        self.name = self.code.critics[self.index]

    def close(self) -> None:
        self.code.close()

    def __enter__(self) -> "SandboxedCritic":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def first_fire(self, trace: Trace, instruction: str = "", start: int = 0,
                   cached: list[Frame] | None = None, stages: tuple[str, ...] = (),
                   redirect: Sequence[str] | None = None) -> int | None:
        """The env step at which the critic first proposed (at a frame :func:`granted` grants), or
        None; raises ReplayFailed."""
        from services.harness.sandbox import codec
        from services.harness.sandbox.client import SandboxError

        fs = cached if cached is not None else frames(trace)
        self.code.start(instruction or trace.instruction, trace.milestone_names)
        limit = self.hard_limit_s
        run = [(self.index, False)]
        every = self.every if trace.step_obs else 1
        try:
            # The critic runs from ``start`` on, at the runtime's cadence; the frames before a call
            # reach the child's window ahead of it.
            for k in _replayed(trace, fs, start):
                if fs[k].step % every or not granted(trace, fs[k], stages, redirect):
                    continue
                res = self.code.step(fs[max(0, k - WINDOW + 1): k + 1], run, lambda i: limit)[0]
                if res.kind == codec.R_PROPOSAL:
                    return fs[k].step
                if res.kind == codec.R_ERROR:
                    raise ReplayFailed(f"{self.name} failed at env step {fs[k].step} of a replay in the sandbox: "
                                       f"{res.error}")
        except SandboxError as exc:
            self.code.close()  # the next replay starts a fresh child
            raise ReplayFailed(f"{self.name} was stopped on a replay in the sandbox: {exc.reason}") from None
        return None


def granted(trace: Trace, frame: Frame, stages: tuple[str, ...], redirect: Sequence[str] | None = None) -> bool:
    """Whether the runtime would start a patch's recovery on a firing at this frame: the orchestrator
    grants a critic gated on ``stages`` (kinds of first missing milestone, a rule's ``missing``;
    every frame when empty; once every milestone is reached nothing is missing, and no gated rule
    grants anything), and, for an instruction redirection (``redirect``: the sentences the policy
    was trained on), the redirection would not ask the episode's own instruction (the runtime does
    not start a redundant recovery; recoveries.RedirectInstruction.redundant). A trace recorded
    without its instruction is granted as before."""
    if stages and milestone_kind(first_missing(trace.milestone_names, frame.milestones)) not in stages:
        return False
    if redirect is None or not trace.instruction:
        return True
    asked, _ = redirection(trace.milestone_names, frame.milestones, redirect, trace.instruction)
    return not (asked and same_instruction(asked, trace.instruction))


def first_fire(trace: Trace, fn: Callable[[Window, Mapping[str, float]], Any] | SandboxedCritic,
               params: Mapping[str, float], instruction: str = "", start: int = 0,
               cached: list[Frame] | None = None, stages: tuple[str, ...] = (),
               redirect: Sequence[str] | None = None) -> int | None:
    """The env step at which ``fn(window, params)`` first returned evidence, or None; with
    ``stages`` or ``redirect``, only frames where the runtime would start the patch's recovery count
    (:func:`granted`: a firing the orchestrator vetoes, or a redirection the runtime does not start,
    interrupts nothing). The window's instruction is ``instruction``, else the trace's own. A
    :class:`SandboxedCritic` runs in its sandbox child (with the parameters it was loaded with) and
    raises ReplayFailed when it fails; a library predicate that raises is silent on that trace."""
    if isinstance(fn, SandboxedCritic):
        return fn.first_fire(trace, instruction, start, cached, stages, redirect)
    fs = cached if cached is not None else frames(trace)
    # The runtime's window is widened past every integer parameter (a horizon in frames), so is this.
    size = max([WINDOW, *(int(v) + 1 for v in params.values() if float(v).is_integer())])
    for k in _replayed(trace, fs, start):
        if not granted(trace, fs[k], stages, redirect):
            continue
        window = Window(frames=fs[max(0, k - size + 1): k + 1], instruction=instruction or trace.instruction,
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
