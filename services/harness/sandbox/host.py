"""A harness runtime's package code behind the sandbox: critics and recoveries by proxy.

:class:`SandboxedCode` owns one sandbox child (services/harness/sandbox/client.py) for one
runtime. It loads the package's tools there, runs the enabled code critics and package recoveries
there, and when the child was killed (a call over its hard limit, a crash) starts a fresh one on
the next call and restores the window, so that the episode goes on with the critic that overran
switched off. The child gets every frame, but only with a call: the frames since the last one
travel ahead of it in the same write (the runtime calls every few steps, and a round trip, not a
frame, is what costs).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from services.harness.runtime.api import Frame, Proposal, Window
from services.harness.runtime.perception import QUERIES
from services.harness.runtime.library.recoveries import FAILED, RUNNING, EpisodeMemory, PolicyUnder
from services.harness.sandbox import codec
from services.harness.sandbox.client import CallFailed, CriticResult, Loaded, SandboxClient, SandboxError, SandboxLimits

log = logging.getLogger("zetta.harness.sandbox")

#: A perception query is answered along with each frame sent until the critics have not asked it
#: of the newest frame in this many calls in a row (then it costs a round trip when asked, which
#: starts it again).
PREFETCH_STEPS = 8
#: Queries that cost much more than a round trip (``others``: a detection per object, each drawn
#: and sent) go along only while the critics asked them of the last frame.
PREFETCH_STEPS_BY_QUERY = {"others": 1}


class SandboxedCode:
    """The package code of one runtime, in its own sandbox child."""

    def __init__(self, sources: Mapping[str, str], params: Mapping[str, Mapping[str, Any]], window: int,
                 limits: SandboxLimits | None = None, checked: bool = True) -> None:
        self._sources = dict(sources)
        self._params = {k: dict(v) for k, v in params.items()}
        self._window = window
        self._checked = checked
        self.limits = limits or SandboxLimits.from_env()
        self._client: SandboxClient | None = None
        self._episode: tuple[str, tuple[str, ...], tuple[str, ...]] = ("", (), ())
        #: The step of the newest frame the child has (-1: none of this episode's).
        self._sent = -1
        #: A step sent and not collected yet: its perception server, hard limits and cap.
        self._inflight: tuple[Callable[[int, str], Any], Callable[[int], float], float | None] | None = None
        self.respawns = 0
        #: Per perception query (QUERIES), how many calls ago the critics last asked it of the
        #: newest frame: answered along with the frames while under PREFETCH_STEPS.
        self._unasked = [PREFETCH_STEPS] * len(QUERIES)
        self._prefetch = tuple((i, q, PREFETCH_STEPS_BY_QUERY.get(q, PREFETCH_STEPS)) for i, q in enumerate(QUERIES))
        loaded = self._spawn()
        self.critics = loaded.critics
        self.callables = loaded.callables

    @property
    def isolation(self) -> Mapping[str, Any]:
        return self._client.isolation if self._client is not None else {}

    @property
    def pid(self) -> int:
        return self._client.pid if self._client is not None else -1

    def _spawn(self) -> Loaded:
        client = SandboxClient(self.limits)
        try:
            loaded = client.load(self._window, self._sources, self._params, self._checked)
        except BaseException:
            client.close()
            raise
        self._client = client
        return loaded

    def close(self) -> None:
        self._inflight = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def start(self, instruction: str, milestone_names: Sequence[str], policy_instructions: Sequence[str] = ()) -> None:
        self._episode = (instruction, tuple(milestone_names), tuple(policy_instructions))
        self._sent = -1
        try:
            self._drain()  # the last episode's step still in flight: its answer is of no use now
            if self._client is None or self._client.dead:
                return  # respawned (and started) at the next step
            self._client.start(*self._episode)
        except (SandboxError, CallFailed):
            self.close()

    def set_policy_instructions(self, instructions: Sequence[str]) -> None:
        """What the policy was trained on, learned during the episode: the child's windows carry it
        from now on (a respawned child gets it with the episode's start)."""
        self._episode = (self._episode[0], self._episode[1], tuple(instructions))
        try:
            if self._client is not None and not self._client.dead:
                self._client.set_policy_instructions(instructions)
        except (SandboxError, CallFailed):
            self.close()

    @property
    def inflight(self) -> bool:
        """A step was sent (:meth:`send`) and its results are not collected yet."""
        return self._inflight is not None

    def _drain(self) -> None:
        """Collect and drop the answer to a step still in flight (before any other call)."""
        if self._inflight is not None:
            self.collect()

    def _live(self, frames: Sequence[Frame]) -> SandboxClient:
        """The child, respawned with the window's earlier frames when the last one was killed."""
        if self._client is not None and not self._client.dead:
            return self._client
        self.close()
        loaded = self._spawn()
        if loaded.critics != self.critics:
            self.close()
            raise SandboxError(-1, "the package's critics changed on respawn")
        self.respawns += 1
        client = self._client
        assert client is not None
        client.start(*self._episode)
        self._sent = -1  # the whole window goes ahead of the next call
        return client

    def _prefetched(self, f: Frame) -> list[tuple[str, Any]]:
        """Answers to the perception queries the critics asked of recent frames, for frame ``f``
        (critics look back too: a query the child asks that is not among them costs a round trip)."""
        unasked = self._unasked
        return [(q, f.perceive(q)) for i, q, steps in self._prefetch if unasked[i] < steps]

    def _unsent(self, client: SandboxClient, frames: Sequence[Frame]) -> bytes:
        """The frames of ``frames`` the child has not seen, as messages to send ahead of a call."""
        first = len(frames)
        while first > 0 and frames[first - 1].step > self._sent:
            first -= 1
        return b"".join(client.push_message(f.step, f.obs, f.action, f.milestones, self._prefetched(f))
                        for f in frames[first:])

    def step(self, frames: Sequence[Frame], runs: Sequence[tuple[int, bool]], hard_limit: Callable[[int], float],
             cap_s: float | None = None) -> list[CriticResult]:
        """Send the newest frame of ``frames`` and run the critics ``runs`` ((index, timed in CPU));
        the results as :meth:`SandboxClient.step` returns them."""
        self.send(frames, runs, hard_limit, cap_s)
        return self.collect()

    def send(self, frames: Sequence[Frame], runs: Sequence[tuple[int, bool]], hard_limit: Callable[[int], float],
             cap_s: float | None = None) -> None:
        """The first half of :meth:`step`: the child runs the critics while the caller goes on;
        :meth:`collect` waits for their results (``frames`` must not change until then)."""
        self._drain()
        client = self._live(frames)
        before = self._unsent(client, frames[:-1])
        f = frames[-1]
        # The queries the critics asked of recent frames are answered along with the frames (one
        # round trip per call, not one per query); any other query costs a round trip when asked.
        client.send_step(f.step, f.obs, f.action, f.milestones, runs, self._prefetched(f), before)
        self._sent = f.step
        self._inflight = (_perceiver(frames), hard_limit, cap_s)

    def collect(self) -> list[CriticResult]:
        """The results of the step :meth:`send` sent (SandboxError: the child was killed)."""
        assert self._inflight is not None and self._client is not None, "collect() without a step in flight"
        perceive, hard_limit, cap_s = self._inflight
        self._inflight = None
        client = self._client
        results = client.results(hard_limit, perceive, cap_s)
        unasked = self._unasked
        asked = client.asked
        for i in range(len(unasked)):
            unasked[i] = 0 if asked >> i & 1 else unasked[i] + 1
        return results

    def recovery(self, ref: str, params: Mapping[str, Any], hard_limit_s: float,
                 frames: Callable[[], Sequence[Frame]]) -> "RemoteRecovery":
        return RemoteRecovery(self, ref, params, hard_limit_s, frames)

    def client(self) -> SandboxClient | None:
        return self._client

    def sync(self, frames: Sequence[Frame]) -> bytes:
        """What to send ahead of a recovery call so that the child's window ends at ``frames[-1]``."""
        self._drain()
        client = self._client
        if client is None or not frames:
            return b""
        before = self._unsent(client, frames)
        self._sent = frames[-1].step
        return before


def _perceiver(frames: Sequence[Frame]) -> Callable[[int, str], Any]:
    def perceive(step: int, query: str) -> Any:
        for f in reversed(frames):
            if f.step == step:
                return f.perceive(query)
        return None

    return perceive


def to_proposal(name: str, proposal: tuple[str, str, dict[str, float]]) -> Proposal:
    """A proposal as the child reported it ((evidence, mode, details)), under the critic's name."""
    evidence, mode, details = proposal
    return Proposal(name, evidence, mode, details)


class RemoteRecovery:
    """A package recovery (``"<stem>:<factory>"`` in a playbook) run in the sandbox child."""

    name = "package"

    def __init__(self, code: SandboxedCode, ref: str, params: Mapping[str, Any], hard_limit_s: float,
                 frames: Callable[[], Sequence[Frame]]) -> None:
        self.code = code
        self.ref = ref
        self.params = dict(params)
        self.hard_limit_s = hard_limit_s
        self.frames = frames
        self.status = RUNNING
        self.reason = ""
        self.memory = EpisodeMemory()

    def _client(self) -> SandboxClient:
        client = self.code.client()
        if client is None or client.dead:
            raise SandboxError(-1, "the sandbox was restarted; the package recovery's state is gone")
        return client

    def start(self, w: Window, memory: EpisodeMemory) -> None:
        client, frames = self._client(), self.frames()
        client.recovery_start(self.ref, self.params, self.hard_limit_s, _perceiver(frames), self.code.sync(frames))

    def act(self, w: Window) -> np.ndarray | PolicyUnder | None:
        try:
            client, frames = self._client(), self.frames()
            action, status, reason = client.recovery_act(self.hard_limit_s, _perceiver(frames), self.code.sync(frames))
        except CallFailed as exc:
            self.status, self.reason = FAILED, f"raised in the sandbox: {exc}"
            return None
        self.status, self.reason = status or RUNNING, reason
        if isinstance(action, str):
            return PolicyUnder(action)
        return action


__all__ = ["CallFailed", "RemoteRecovery", "SandboxError", "SandboxedCode", "codec", "to_proposal"]
