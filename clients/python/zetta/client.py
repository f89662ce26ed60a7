"""Async Python SDK over the gateway, shaped like the paper's listing.

    async with zetta.Gateway("127.0.0.1:50051") as gw:
        sessions = await gw.create_sessions(env_family="libero", n=16, env_config={...})
        await sessions.reset(task="put_the_bowl_on_the_plate")
        while not all_done:
            results = await sessions.policy_step()
        await sessions.close()

A :class:`SessionGroup` sends one RPC per call for all its sessions. Single :class:`Session`
handles are batched too, without the caller asking: calls of the same kind and parameters made in
the same event-loop turn (e.g. from ``asyncio.gather`` over many sessions) leave as one RPC.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable, Coroutine, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import grpc
import numpy as np
from google.protobuf import struct_pb2

from zetta.credentials import gateway_channel
from zetta_wire.channel import CHANNEL_OPTIONS
from zetta_wire.codec import decode, decode_observation, encode
from zetta_wire.errors import parse_error_metadata
from zetta_wire.v1 import gateway_pb2, gateway_pb2_grpc, types_pb2


class ZettaError(Exception):
    """A failed call: the gRPC status, its message, and the sessions at fault."""

    def __init__(self, code: grpc.StatusCode, details: str, session_ids: Sequence[str] = (),
                 retry_after_ms: int | None = None, more_failed_sessions: int = 0) -> None:
        super().__init__(f"{code.name}: {details}")
        self.code = code
        self.details = details
        self.session_ids = list(session_ids)
        self.retry_after_ms = retry_after_ms
        #: Failed sessions the server left out of ``session_ids`` to keep the metadata bounded.
        self.more_failed_sessions = more_failed_sessions

    @classmethod
    def from_rpc(cls, err: grpc.aio.AioRpcError) -> "ZettaError":
        """Lift the trailing metadata the gateway sets into attributes."""
        details = parse_error_metadata(err.trailing_metadata())
        return cls(err.code(), err.details() or "", details.session_ids, details.retry_after_ms, details.more)


@dataclass
class ResetResult:
    """First observation of a new episode."""

    session_id: str
    episode_id: str
    observation: dict[str, np.ndarray]
    instruction: str
    max_steps: int
    #: Where the env worker writes this episode's MP4 when ``record_video`` was asked; "" otherwise.
    video_path: str = ""
    #: The episode's ordered milestones M; entry k names element k of the "milestones" tensors.
    milestone_names: list[str] = field(default_factory=list)
    #: Content hash of the harness running over the episode; "" when none runs.
    harness_content_hash: str = ""


@dataclass
class StepResult:
    """Outcome of executed actions."""

    session_id: str
    observation: dict[str, np.ndarray]
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    executed_actions: np.ndarray
    episode_step: int
    info: dict[str, float] = field(default_factory=dict)
    #: Path of the episode's complete video, on the step that ended a recorded episode.
    video_path: str = ""
    #: First milestone of M not observed so far (m* once the episode ended); "" when all were.
    first_missing_milestone: str = ""
    #: Milestones of M observed so far, in order.
    milestones_reached: list[str] = field(default_factory=list)
    #: With a harness: who acts next ("policy" or the recovery in control) and the intervention id.
    harness_mode: str = ""
    harness_intervention: str = ""
    #: With a harness: how many of ``executed_actions`` a recovery chose instead of the policy.
    recovery_actions: int = 0
    #: With a harness, on the result that ended the episode: the episode's harness report.
    harness_report: "HarnessReport | None" = None
    #: With ``reset(record_steps=True)``: the observation after each executed action, without camera images.
    step_observations: list[dict[str, np.ndarray]] = field(default_factory=list)

    @property
    def done(self) -> bool:
        """The episode is over (terminated or truncated)."""
        return self.terminated or self.truncated


@dataclass
class EpisodeSummary:
    """A whole episode run inside a worker."""

    session_id: str
    episode_id: str
    steps: int
    reward: float
    success: bool
    stop_reason: str
    wall_ms: float
    policy_calls: int
    #: Path of the episode's complete video on the env worker; "" when none was recorded.
    video_path: str = ""
    #: The episode's ordered milestones M, those observed, and m* (first never observed; "" if none).
    milestone_names: list[str] = field(default_factory=list)
    milestones_reached: list[str] = field(default_factory=list)
    first_missing_milestone: str = ""
    #: With a harness: who acted and every intervention of the episode.
    harness_report: "HarnessReport | None" = None


@dataclass
class HarnessReport:
    """What a harness did over an episode: action counts by mode and every intervention.

    ``policy_share`` makes a success that recoveries did most of the work for visible as such.
    """

    harness: str
    version: str
    content_hash: str
    policy_actions: int
    recovery_actions: int
    actions_by_mode: dict[str, int]
    #: One dict per intervention: id, kind, proposer, evidence, details, decision, start_step,
    #: end_step, outcome, actions, instruction (the policy's, when the recovery redirected it).
    interventions: list[dict[str, Any]]
    interventions_by_kind: dict[str, int]
    #: One dict per critic switched off: name, step, reason.
    disabled_critics: list[dict[str, Any]]
    proposals: int
    rejected: int

    @property
    def policy_share(self) -> float:
        """Share of the episode's actions chosen by the policy (1.0 when none were executed)."""
        total = self.policy_actions + self.recovery_actions
        return self.policy_actions / total if total else 1.0


@dataclass
class Grasp:
    """A grasp proposal: the grip point (world, m) and the horizontal axis the fingers close along (0 = x, 1 = y)."""

    grip_point: np.ndarray
    finger_axis: int


@dataclass
class Detection:
    """One perception estimate: a noisy centre and box (world, m), as a detector reports them."""

    query: str
    position: np.ndarray
    box: np.ndarray
    #: Grasp proposals on the box, best first (for "object", when asked).
    grasps: list[Grasp] = field(default_factory=list)


@dataclass
class PerceiveResult:
    """What the perception tool saw in one session: detections that found something (a miss is absent)."""

    session_id: str
    episode_id: str
    episode_step: int
    detections: list[Detection]

    def first(self, query: str) -> Detection | None:
        """The first detection for ``query`` ("object", "target", "others"), None when it missed."""
        return next((d for d in self.detections if d.query == query), None)


def _perceive_result(m: types_pb2.PerceiveResult) -> PerceiveResult:
    return PerceiveResult(m.session_id, m.episode_id, m.episode_step, [
        Detection(d.query, np.array(d.position), np.array(d.box),
                  [Grasp(np.array(g.grip_point), g.finger_axis) for g in d.grasps]) for d in m.detections])


def _motion(position: Sequence[float] | np.ndarray | None, gripper: float, max_steps: int, tolerance_m: float,
            hand_down: bool, max_action: float, orientation: Sequence[float] | np.ndarray | None = None,
            angle_tolerance_rad: float = 0.0) -> types_pb2.Motion:
    return types_pb2.Motion(position=[] if position is None else [float(v) for v in position], gripper=gripper,
                            max_steps=max_steps, tolerance_m=tolerance_m, hand_down=hand_down, max_action=max_action,
                            orientation=[] if orientation is None else [float(v) for v in orientation],
                            angle_tolerance_rad=angle_tolerance_rad)


def _harness_report(m: types_pb2.HarnessReport | None) -> HarnessReport | None:
    if m is None or not m.harness:
        return None
    return HarnessReport(
        harness=m.harness, version=m.version, content_hash=m.content_hash,
        policy_actions=m.policy_actions, recovery_actions=m.recovery_actions,
        actions_by_mode=dict(m.actions_by_mode),
        interventions=[
            {"id": i.id, "kind": i.kind, "proposer": i.proposer, "evidence": i.evidence, "details": dict(i.details),
             "decision": i.decision, "start_step": i.start_step, "end_step": i.end_step, "outcome": i.outcome,
             "actions": i.actions, "instruction": i.instruction}
            for i in m.interventions
        ],
        interventions_by_kind=dict(m.interventions_by_kind),
        disabled_critics=[{"name": d.name, "step": d.step, "reason": d.reason} for d in m.disabled_critics],
        proposals=m.proposals, rejected=m.rejected,
    )


def _reset_result(m: types_pb2.ResetResult) -> ResetResult:
    return ResetResult(m.session_id, m.episode_id, decode_observation(m.observation), m.instruction, m.max_steps,
                       video_path=m.video_path, milestone_names=list(m.milestone_names),
                       harness_content_hash=m.harness_content_hash)


def _step_result(m: types_pb2.StepResult) -> StepResult:
    return StepResult(
        session_id=m.session_id,
        observation=decode_observation(m.observation),
        reward=m.reward,
        terminated=m.terminated,
        truncated=m.truncated,
        success=m.success,
        executed_actions=decode(m.executed_actions),
        episode_step=m.episode_step,
        info=dict(m.info),
        video_path=m.video_path,
        first_missing_milestone=m.first_missing_milestone,
        milestones_reached=list(m.milestones_reached),
        harness_mode=m.harness_mode,
        harness_intervention=m.harness_intervention,
        recovery_actions=m.recovery_actions,
        harness_report=_harness_report(m.harness_report) if m.HasField("harness_report") else None,
        step_observations=[decode_observation(o) for o in m.step_observations],
    )


def _summary(m: types_pb2.EpisodeSummary) -> EpisodeSummary:
    return EpisodeSummary(
        session_id=m.session_id,
        episode_id=m.episode_id,
        steps=m.steps,
        reward=m.reward,
        success=m.success,
        stop_reason=types_pb2.StopReason.Name(m.stop_reason).removeprefix("STOP_REASON_").lower(),
        wall_ms=m.wall_ms,
        policy_calls=m.policy_calls,
        video_path=m.video_path,
        milestone_names=list(m.milestone_names),
        milestones_reached=list(m.milestones_reached),
        first_missing_milestone=m.first_missing_milestone,
        harness_report=_harness_report(m.harness_report) if m.HasField("harness_report") else None,
    )


def _reset_spec(task: str = "", seed: int = 0, init_state_index: int = 0, instruction: str = "",
                record_video: bool = False, harness: str = "", harness_dir: str = "",
                record_steps: bool = False) -> types_pb2.ResetSpec:
    return types_pb2.ResetSpec(task=str(task), seed=seed, init_state_index=init_state_index, instruction=instruction,
                               record_video=record_video, harness=harness, harness_dir=harness_dir,
                               record_steps=record_steps)


def _policy_spec(model: str = "", instruction: str = "", execute_steps: int = 0, timeout_ms: int = 0) -> types_pb2.PolicySpec:
    return types_pb2.PolicySpec(model=model, instruction=instruction, execute_steps=execute_steps, timeout_ms=timeout_ms)


class Gateway:
    """A connection to the gateway; one channel, reused by every call and session."""

    def __init__(self, address: str, token: str | None = None, tls_ca: str | bytes | Path | None = None,
                 client_cert: str | bytes | Path | None = None, client_key: str | bytes | Path | None = None) -> None:
        """``token``: the bearer token of a gateway with auth on; ``tls_ca``: the CA (PEM file or
        bytes) of a gateway serving TLS (docs/security.md)."""
        self.address = address
        self._channel = gateway_channel(address, CHANNEL_OPTIONS, token, tls_ca, client_cert, client_key)
        self._stub = gateway_pb2_grpc.GatewayServiceStub(self._channel)
        self._batcher = _Batcher(self)
        self._background: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> "Gateway":
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def call(self, method: str, request: Any, timeout: float | None = None) -> Any:
        """Invoke a GatewayService method, raising ZettaError on failure."""
        try:
            return await getattr(self._stub, method)(request, timeout=timeout)
        except grpc.aio.AioRpcError as err:
            raise ZettaError.from_rpc(err) from None
        except grpc.aio.UsageError as err:
            raise ZettaError(grpc.StatusCode.CANCELLED,
                             f"{method} on a closed Gateway ({err}); open a new Gateway to go on") from None

    async def create_sessions(
        self,
        env_family: str,
        n: int = 1,
        env_config: Mapping[str, Any] | None = None,
        lease_seconds: int = 0,
        keepalive: bool = True,
    ) -> "SessionGroup":
        """Create ``n`` sessions (all or none); with keepalive their leases renew until closed."""
        config = struct_pb2.Struct()
        config.update(dict(env_config or {}))
        resp = await self.call(
            "CreateSessions",
            gateway_pb2.CreateSessionsRequest(env_family=env_family, env_config=config, lease_seconds=lease_seconds, count=n),
        )
        group = SessionGroup(self, list(resp.sessions))
        if keepalive:
            group.start_keepalive()
        return group

    async def list_workers(self) -> list[gateway_pb2.WorkerInfo]:
        """Env workers and their health."""
        return list((await self.call("ListWorkers", gateway_pb2.ListWorkersRequest())).workers)

    async def list_sessions(self, env_family: str = "") -> list[types_pb2.SessionInfo]:
        """Sessions in the registry."""
        return list((await self.call("ListSessions", gateway_pb2.ListSessionsRequest(env_family=env_family))).sessions)

    def run_in_background(self, coro: Coroutine[Any, Any, None]) -> "asyncio.Task[None]":
        """A task that uses this channel: :meth:`close` cancels it before the channel goes, so it
        never calls a closed channel (lease renewals of groups nobody closed)."""
        task = asyncio.create_task(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)
        return task

    async def close(self) -> None:
        """Stop this channel's background tasks, then close the channel."""
        tasks = list(self._background)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await self._channel.close()


class SessionGroup:
    """A batch of sessions; every method is one RPC covering all of them."""

    def __init__(self, gateway: Gateway, infos: Sequence[types_pb2.SessionInfo]) -> None:
        self.gateway = gateway
        self.infos = list(infos)
        self.ids = [i.session_id for i in infos]
        self._keepalive: asyncio.Task[None] | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def __iter__(self) -> Iterator["Session"]:
        return (Session(self.gateway, sid) for sid in self.ids)

    def __getitem__(self, i: int) -> "Session":
        return Session(self.gateway, self.ids[i])

    def subset(self, session_ids: Sequence[str]) -> "SessionGroup":
        """A group over some of these sessions (e.g. those whose episode is still running)."""
        wanted = set(session_ids)
        return SessionGroup(self.gateway, [i for i in self.infos if i.session_id in wanted])

    @property
    def action_shape(self) -> tuple[int, ...]:
        """Shape of one action."""
        return tuple(self.infos[0].action_spec.shape)

    def start_keepalive(self) -> None:
        """Renew the leases at a third of their length until :meth:`close`."""
        expiry = min((i.lease_expires_unix_ms for i in self.infos), default=0)
        if not expiry:
            return
        import time

        period = max(1.0, (expiry / 1000.0 - time.time()) / 3)

        async def renew() -> None:
            while True:
                await asyncio.sleep(period)
                try:
                    await self.renew()
                except ZettaError:
                    return

        self._keepalive = self.gateway.run_in_background(renew())

    async def reset(
        self,
        task: str | int = "",
        seed: int | Sequence[int] = 0,
        init_state_index: int | Sequence[int] = 0,
        instruction: str = "",
        record_video: bool = False,
        harness: str = "",
        harness_dir: str = "",
        record_steps: bool = False,
    ) -> list[ResetResult]:
        """Start episodes; ``seed`` and ``init_state_index`` may be one value or one per session.

        ``record_video`` has each env worker write the episode as an MP4 (``ResetResult.video_path``).
        ``harness`` ("NAME@VERSION" from the critic registry) or ``harness_dir`` (a package directory
        on the env worker) runs a harness over the episode (docs/harness.md). ``record_steps``
        returns every step's observation with each step (``StepResult.step_observations``), for
        traces that replay critics as the runtime runs them.
        """
        seeds = list(seed) if isinstance(seed, Sequence) else [seed] * len(self)
        inits = list(init_state_index) if isinstance(init_state_index, Sequence) else [init_state_index] * len(self)
        specs = [_reset_spec(str(task), s, i, instruction, record_video, harness, harness_dir, record_steps)
                 for s, i in zip(seeds, inits)]
        resp = await self.gateway.call("Reset", gateway_pb2.ResetRequest(session_ids=self.ids, specs=specs))
        return [_reset_result(r) for r in resp.results]

    async def observe(self) -> list[dict[str, np.ndarray]]:
        """Current observations, without side effects."""
        resp = await self.gateway.call("Observe", gateway_pb2.ObserveRequest(session_ids=self.ids))
        return [decode_observation(r.observation) for r in resp.results]

    async def action_step(self, actions: np.ndarray | Sequence[np.ndarray]) -> list[StepResult]:
        """Execute one action (or chunk) per session."""
        tensors = [encode(np.asarray(a, dtype=np.float32) if np.asarray(a).dtype == np.float64 else np.asarray(a)) for a in actions]
        resp = await self.gateway.call("ActionStep", gateway_pb2.ActionStepRequest(session_ids=self.ids, actions=tensors))
        return [_step_result(r) for r in resp.results]

    async def policy_step(self, model: str = "", instruction: str = "", execute_steps: int = 0,
                          timeout_ms: int = 0) -> list[StepResult]:
        """Observe, infer (batched across sessions and workers) and execute, as one call."""
        resp = await self.gateway.call(
            "PolicyStep",
            gateway_pb2.PolicyStepRequest(session_ids=self.ids,
                                          policy=_policy_spec(model, instruction, execute_steps, timeout_ms)),
        )
        return [_step_result(r) for r in resp.results]

    async def policy_infer(self, model: str = "", instruction: str = "", timeout_ms: int = 0) -> list[np.ndarray]:
        """Action chunks for the current observations, not executed."""
        resp = await self.gateway.call(
            "PolicyInfer",
            gateway_pb2.PolicyInferRequest(session_ids=self.ids, policy=_policy_spec(model, instruction, 0, timeout_ms)),
        )
        return [decode(r.actions) for r in resp.results]

    async def run_episode(
        self,
        task: str | int | None = None,
        seed: int | Sequence[int] = 0,
        init_state_index: int | Sequence[int] = 0,
        model: str = "",
        max_steps: int = 0,
        execute_steps: int = 0,
        record_video: bool = False,
        harness: str = "",
        harness_dir: str = "",
    ) -> list[EpisodeSummary]:
        """Run whole episodes inside the workers (reset first when ``task`` is given).

        ``record_video`` (with ``task``) writes each episode as an MP4 (``EpisodeSummary.video_path``);
        ``harness``/``harness_dir`` (with ``task``) run a harness over them (``EpisodeSummary.harness_report``).
        """
        specs: list[types_pb2.ResetSpec] = []
        if task is not None:
            seeds = list(seed) if isinstance(seed, Sequence) else [seed] * len(self)
            inits = list(init_state_index) if isinstance(init_state_index, Sequence) else [init_state_index] * len(self)
            specs = [_reset_spec(str(task), s, i, "", record_video, harness, harness_dir) for s, i in zip(seeds, inits)]
        resp = await self.gateway.call(
            "RunEpisode",
            gateway_pb2.RunEpisodeRequest(session_ids=self.ids, specs=specs, policy=_policy_spec(model, "", execute_steps),
                                          max_steps=max_steps),
        )
        return [_summary(s) for s in resp.summaries]

    async def perceive(self, queries: Sequence[str] = (), grasps: bool = False) -> list[PerceiveResult]:
        """The perception tool on each session's current state: noisy boxes of the stage's "object",
        its "target" and the "others" (default: object and target), with grasp proposals if asked."""
        resp = await self.gateway.call("Perceive", gateway_pb2.PerceiveRequest(session_ids=self.ids, queries=list(queries),
                                                                               grasps=grasps))
        return [_perceive_result(r) for r in resp.results]

    async def move(self, positions: Sequence[Sequence[float] | np.ndarray | None] | None = None, gripper: float = 0.0,
                   max_steps: int = 20, tolerance_m: float = 0.0, hand_down: bool = False,
                   max_action: float = 0.0,
                   orientations: Sequence[Sequence[float] | np.ndarray | None] | None = None,
                   angle_tolerance_rad: float = 0.0) -> list[StepResult]:
        """A bounded closed-loop motion in each session: servo the grip site to ``positions[i]`` (None or
        omitted: hold) and the hand to ``orientations[i]`` (an xyzw world-frame quaternion; None: free)
        with the gripper command (-1 open, +1 close, 0 keep) for at most ``max_steps``."""
        goals = list(positions) if positions is not None else [None] * len(self)
        turns = list(orientations) if orientations is not None else [None] * len(self)
        motions = [_motion(p, gripper, max_steps, tolerance_m, hand_down, max_action, q, angle_tolerance_rad)
                   for p, q in zip(goals, turns, strict=True)]
        resp = await self.gateway.call("Move", gateway_pb2.MoveRequest(session_ids=self.ids, motions=motions))
        return [_step_result(r) for r in resp.results]

    async def renew(self, lease_seconds: int = 0) -> None:
        """Push the leases out."""
        await self.gateway.call("RenewSessions", gateway_pb2.RenewSessionsRequest(session_ids=self.ids,
                                                                                  lease_seconds=lease_seconds))

    async def close(self) -> None:
        """Close the sessions (idempotent) and stop renewing their leases."""
        if self._keepalive is not None:
            self._keepalive.cancel()
            self._keepalive = None
        await self.gateway.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=self.ids))


class Session:
    """One session; its calls are coalesced with concurrent calls on other sessions."""

    def __init__(self, gateway: Gateway, session_id: str) -> None:
        self.gateway = gateway
        self.session_id = session_id

    async def reset(self, task: str | int = "", seed: int = 0, init_state_index: int = 0, instruction: str = "",
                    record_video: bool = False, harness: str = "", harness_dir: str = "",
                    record_steps: bool = False) -> ResetResult:
        """Start an episode (with a harness when ``harness`` or ``harness_dir`` is given;
        ``record_steps`` as :meth:`SessionGroup.reset`)."""
        spec = _reset_spec(str(task), seed, init_state_index, instruction, record_video, harness, harness_dir,
                           record_steps)
        return _reset_result(await self.gateway._batcher.submit("Reset", self.session_id, spec))

    async def policy_step(self, model: str = "", instruction: str = "", execute_steps: int = 0,
                          timeout_ms: int = 0) -> StepResult:
        """Observe, infer and execute."""
        spec = _policy_spec(model, instruction, execute_steps, timeout_ms)
        return _step_result(await self.gateway._batcher.submit("PolicyStep", self.session_id, spec))

    async def action_step(self, action: np.ndarray) -> StepResult:
        """Execute an action or a chunk."""
        return _step_result(await self.gateway._batcher.submit("ActionStep", self.session_id, encode(np.asarray(action))))

    async def run_episode(self, task: str | int | None = None, seed: int = 0, init_state_index: int = 0,
                          model: str = "", max_steps: int = 0, record_video: bool = False, execute_steps: int = 0,
                          harness: str = "", harness_dir: str = "") -> EpisodeSummary:
        """Run a whole episode in the worker."""
        group = SessionGroup(self.gateway, [types_pb2.SessionInfo(session_id=self.session_id)])
        return (await group.run_episode(task, seed, init_state_index, model, max_steps, execute_steps, record_video,
                                        harness, harness_dir))[0]

    async def perceive(self, queries: Sequence[str] = (), grasps: bool = False) -> PerceiveResult:
        """The perception tool on the current state (SessionGroup.perceive)."""
        req = gateway_pb2.PerceiveRequest(queries=list(queries), grasps=grasps)
        return _perceive_result(await self.gateway._batcher.submit("Perceive", self.session_id, req))

    async def move(self, position: Sequence[float] | np.ndarray | None = None, gripper: float = 0.0,
                   max_steps: int = 20, tolerance_m: float = 0.0, hand_down: bool = False,
                   max_action: float = 0.0, orientation: Sequence[float] | np.ndarray | None = None,
                   angle_tolerance_rad: float = 0.0) -> StepResult:
        """A bounded closed-loop motion to a position or a pose (SessionGroup.move)."""
        motion = _motion(position, gripper, max_steps, tolerance_m, hand_down, max_action, orientation,
                         angle_tolerance_rad)
        return _step_result(await self.gateway._batcher.submit("Move", self.session_id, motion))

    def stream(self) -> "StepStream":
        """A bidirectional stream for this session's step loop: one stream instead of a call per step."""
        return StepStream(self.gateway, self.session_id)

    async def close(self) -> None:
        """Close this session."""
        await self.gateway.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=[self.session_id]))


class StepStream:
    """Request/response over one gRPC stream; each call waits for its own answer."""

    def __init__(self, gateway: Gateway, session_id: str) -> None:
        self.session_id = session_id
        self._call = gateway._stub.StepStream()
        self._first = True

    async def _roundtrip(self, req: gateway_pb2.StepStreamRequest) -> gateway_pb2.StepStreamResponse:
        if self._first:
            req.session_id = self.session_id
            self._first = False
        try:
            await self._call.write(req)
            resp = await self._call.read()
        except grpc.aio.AioRpcError as err:
            raise ZettaError.from_rpc(err) from None
        if resp is grpc.aio.EOF:
            status = await self._call.code()
            raise ZettaError(status, await self._call.details() or "stream closed")
        return cast(gateway_pb2.StepStreamResponse, resp)

    async def reset(self, task: str | int = "", seed: int = 0, init_state_index: int = 0, instruction: str = "",
                    record_video: bool = False) -> ResetResult:
        """Start an episode."""
        req = gateway_pb2.StepStreamRequest(reset=_reset_spec(str(task), seed, init_state_index, instruction,
                                                              record_video))
        return _reset_result((await self._roundtrip(req)).reset)

    async def policy_step(self, model: str = "", instruction: str = "", execute_steps: int = 0) -> StepResult:
        """Observe, infer and execute."""
        req = gateway_pb2.StepStreamRequest(policy=_policy_spec(model, instruction, execute_steps))
        return _step_result((await self._roundtrip(req)).step)

    async def action_step(self, action: np.ndarray) -> StepResult:
        """Execute an action or a chunk."""
        req = gateway_pb2.StepStreamRequest(action=encode(np.asarray(action)))
        return _step_result((await self._roundtrip(req)).step)

    async def observe(self) -> dict[str, np.ndarray]:
        """Current observation."""
        req = gateway_pb2.StepStreamRequest(observe=gateway_pb2.ObserveOp())
        return decode_observation((await self._roundtrip(req)).observe.observation)

    async def close(self) -> None:
        """End the stream."""
        await self._call.done_writing()


class _Batcher:
    """Coalesces single-session calls of the same kind and parameters made in one loop turn."""

    _REQUESTS: dict[str, Callable[[list[str], list[Any]], Any]] = {
        "Reset": lambda ids, payloads: gateway_pb2.ResetRequest(session_ids=ids, specs=payloads),
        "ActionStep": lambda ids, payloads: gateway_pb2.ActionStepRequest(session_ids=ids, actions=payloads),
        "PolicyStep": lambda ids, payloads: gateway_pb2.PolicyStepRequest(session_ids=ids, policy=payloads[0]),
        "Perceive": lambda ids, payloads: gateway_pb2.PerceiveRequest(session_ids=ids, queries=payloads[0].queries,
                                                                      grasps=payloads[0].grasps),
        "Move": lambda ids, payloads: gateway_pb2.MoveRequest(session_ids=ids, motions=payloads),
    }
    #: Calls whose payload is shared by the whole batch must agree on it to be merged.
    _SHARED = {"PolicyStep", "Perceive"}

    def __init__(self, gateway: Gateway) -> None:
        self._gateway = gateway
        self._pending: dict[tuple[str, bytes], list[tuple[str, Any, asyncio.Future[Any]]]] = {}
        self._scheduled = False

    async def submit(self, method: str, session_id: str, payload: Any) -> Any:
        key = (method, payload.SerializeToString() if method in self._SHARED else b"")
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending.setdefault(key, []).append((session_id, payload, fut))
        if not self._scheduled:
            self._scheduled = True
            asyncio.get_running_loop().call_soon(self._flush)
        return await fut

    def _flush(self) -> None:
        self._scheduled = False
        pending, self._pending = self._pending, {}
        for (method, _), calls in pending.items():
            task = self._gateway.run_in_background(self._send(method, calls))
            task.add_done_callback(functools.partial(_fail_if_cancelled, method, calls))

    async def _send(self, method: str, calls: list[tuple[str, Any, asyncio.Future[Any]]]) -> None:
        # A session may appear once per RPC; repeats wait for the next one.
        first: list[tuple[str, Any, asyncio.Future[Any]]] = []
        later: list[tuple[str, Any, asyncio.Future[Any]]] = []
        seen: set[str] = set()
        for c in calls:
            (later if c[0] in seen else first).append(c)
            seen.add(c[0])
        request = self._REQUESTS[method]([c[0] for c in first], [c[1] for c in first])
        try:
            resp = await self._gateway.call(method, request)
        except Exception as exc:  # noqa: BLE001 - whatever the call raised, its callers must not hang
            _fail(first, exc)
        else:
            results = list(resp.results)
            for (_, _, fut), res in zip(first, results):
                if not fut.done():
                    fut.set_result(res)
            _fail(first[len(results):], ZettaError(
                grpc.StatusCode.INTERNAL, f"{method} answered {len(results)} results for {len(first)} sessions"))
        if later:
            await self._send(method, later)


def _fail(calls: list[tuple[str, Any, "asyncio.Future[Any]"]], exc: BaseException) -> None:
    """Fail the waiting futures of ``calls`` with ``exc`` (those already done keep their outcome)."""
    for _, _, fut in calls:
        if not fut.done():
            fut.set_exception(exc)


def _fail_if_cancelled(method: str, calls: list[tuple[str, Any, "asyncio.Future[Any]"]],
                       task: "asyncio.Task[None]") -> None:
    """A send cancelled by :meth:`Gateway.close` (before or during its RPC) tells every caller why."""
    if task.cancelled():
        _fail(calls, ZettaError(grpc.StatusCode.CANCELLED,
                                f"the Gateway closed while {method} was in flight; open a new Gateway to go on"))
