"""Runs episodes through the real stack (gateway -> env workers -> policy worker) into the store.

Every episode is an :class:`EpisodeKey`. A key already in the store is skipped (resume). An attempt
that fails for infrastructure reasons (the session was LOST with its worker, the worker or the
simulator errored, the call timed out) or ends without its full evidence (the video asked for, the
harness report) is logged as invalid and the same key runs again on a fresh session, up to
``max_attempts``; a policy failure is a valid rollout like a success. The video path is read on
this machine: with remote env workers, point ZETTA_VIDEO_DIR at storage both can see.
"""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import grpc

from services.common.policies import DEFAULT_POLICY
from services.evolver.store import EpisodeKey, Outcome, Rollout, RolloutStore
from services.evolver.trace import TraceRecorder
from zetta import ClientCredentials, Gateway, SessionGroup, ZettaError
from zetta_wire.codec import decode, decode_observation
from zetta_wire.v1 import gateway_pb2, types_pb2

#: Status codes that mean the infrastructure, not the policy, failed the attempt (a worker or the
#: simulator crashed or was unreachable, a lease ran out, a deadline passed under load).
INFRA_CODES = frozenset({grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.INTERNAL, grpc.StatusCode.DEADLINE_EXCEEDED,
                         grpc.StatusCode.NOT_FOUND, grpc.StatusCode.ABORTED, grpc.StatusCode.UNKNOWN,
                         grpc.StatusCode.RESOURCE_EXHAUSTED})


def is_infrastructure(exc: ZettaError) -> bool:
    """Whether a failed call invalidates the attempt (rerun it) rather than reveal a mistake to report.

    FAILED_PRECONDITION only counts when the session was LOST with its worker; otherwise it is a
    configuration error (no video directory, no critic service) that a rerun would only repeat.
    NOT_FOUND counts for a session closed under the client (lease), not for an unknown harness."""
    if exc.code == grpc.StatusCode.FAILED_PRECONDITION:
        return " LOST " in f" {exc.details} "
    if exc.code == grpc.StatusCode.NOT_FOUND:
        return "harness" not in exc.details
    return exc.code in INFRA_CODES


class InfrastructureError(RuntimeError):
    """An episode key stayed invalid after every allowed attempt."""


class IncompleteRollout(RuntimeError):
    """An episode finished without its full evidence (video, harness report): not a valid rollout."""


@dataclass(frozen=True)
class RunConfig:
    """How episodes are run: the frozen policy, its chunk use, the budget and the recording."""

    gateway: str
    model: str = DEFAULT_POLICY
    execute_steps: int = 2
    max_steps: int = 0
    record_video: bool = False
    concurrency: int = 2
    max_attempts: int = 5
    #: Inference budget per policy call (PolicySpec.timeout_ms). Offline evaluation is not a
    #: latency SLO: a generous budget keeps a loaded machine from turning slow calls into invalid
    #: attempts; it stays under the gateway's own step deadline (ZETTA_STEP_TIMEOUT_MS, 30 s).
    policy_timeout_ms: int = 25_000
    #: How long a rollout waits for an env slot while the pool is full or has no live worker. A
    #: loaded machine can miss heartbeats long enough for its workers to be marked LOST until the
    #: next heartbeat lands; a run of hours waits that out (an experiment died after 30 s of it).
    open_timeout_s: float = 600.0


def _reset_spec(key: EpisodeKey, record_video: bool) -> types_pb2.ResetSpec:
    return types_pb2.ResetSpec(task=key.task, seed=key.seed, init_state_index=key.init_state, record_video=record_video,
                               harness=key.harness, record_steps=True)


def interventions(report: types_pb2.HarnessReport) -> list[dict[str, Any]]:
    """The episode's interventions as plain dicts (who proposed, evidence, decision, span, outcome)."""
    return [{"id": iv.id, "recovery": iv.kind, "critic": iv.proposer, "evidence": iv.evidence,
             "details": dict(iv.details), "decision": iv.decision, "start_step": iv.start_step,
             "end_step": iv.end_step, "outcome": iv.outcome, "actions": iv.actions, "instruction": iv.instruction}
            for iv in report.interventions]


async def run_one(gw: Gateway, session_id: str, key: EpisodeKey, cfg: RunConfig) -> Outcome:
    """One episode on one session, recording its trace; raises ZettaError on infrastructure failure."""
    start = time.perf_counter()
    reset = (await gw.call("Reset", gateway_pb2.ResetRequest(
        session_ids=[session_id], specs=[_reset_spec(key, cfg.record_video)]))).results[0]
    recorder = TraceRecorder(list(reset.milestone_names), reset.instruction)
    first = decode_observation(reset.observation)
    recorder.frame(0, first)
    recorder.step(first)
    budget = cfg.max_steps or reset.max_steps
    policy = types_pb2.PolicySpec(model=cfg.model, execute_steps=cfg.execute_steps, timeout_ms=cfg.policy_timeout_ms)
    video = reset.video_path
    while True:
        r = (await gw.call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=[session_id], policy=policy))).results[0]
        recorder.frame(r.episode_step, decode_observation(r.observation), decode(r.executed_actions))
        for obs in r.step_observations:
            recorder.step(decode_observation(obs))
        recorder.recovery_steps += r.recovery_actions
        video = r.video_path or video
        if r.terminated or r.truncated or r.episode_step >= budget:
            if r.HasField("harness_report"):
                recorder.interventions.extend(interventions(r.harness_report))
            elif key.harness and (r.terminated or r.truncated):
                raise IncompleteRollout("the episode ended without its harness report")
            if cfg.record_video and not (video and os.path.exists(video)):
                raise IncompleteRollout(f"the episode's video is missing ({video or 'no path'})")
            return Outcome(success=r.success, steps=r.episode_step, first_missing=r.first_missing_milestone,
                           milestones_reached=list(r.milestones_reached), trace=recorder.finish(), video_path=video,
                           wall_s=time.perf_counter() - start)


class Runner:
    """Runs episode keys on a pool of sessions, filing each valid rollout in the store."""

    def __init__(self, store: RolloutStore, cfg: RunConfig, env_config: dict[str, Any]) -> None:
        self.store = store
        self.cfg = cfg
        self.env_config = env_config

    async def run(self, keys: Sequence[EpisodeKey], round_: int = 0,
                  on_done: Callable[[Rollout, bool], None] | None = None) -> list[Rollout]:
        """Every key's rollout, from the store when it is there, else run now; in the order of keys.

        ``on_done(rollout, was_cached)`` is called as each key completes (progress bars)."""
        results: dict[EpisodeKey, Rollout] = {}
        todo: asyncio.Queue[EpisodeKey] = asyncio.Queue()
        for k in keys:
            have = self.store.get(k)
            if have is not None:
                results[k] = have
                if on_done:
                    on_done(have, True)
            else:
                todo.put_nowait(k)
        if todo.empty():
            return [results[k] for k in keys]
        # Token and TLS from ZETTA_TOKEN and ZETTA_TLS_* (docs/security.md), as every zetta command.
        async with Gateway(self.cfg.gateway, **ClientCredentials.from_env().gateway_kwargs()) as gw:
            workers = [self._worker(gw, todo, results, round_, on_done)
                       for _ in range(min(self.cfg.concurrency, todo.qsize()))]
            await asyncio.gather(*workers)
        return [results[k] for k in keys]

    async def _worker(self, gw: Gateway, todo: asyncio.Queue[EpisodeKey], results: dict[EpisodeKey, Rollout],
                      round_: int, on_done: Callable[[Rollout, bool], None] | None) -> None:
        session: SessionGroup | None = None
        try:
            while not todo.empty():
                key = todo.get_nowait()
                for attempt in range(1, self.cfg.max_attempts + 1):
                    if session is None:
                        session = await self._open(gw)
                    try:
                        outcome = await run_one(gw, session.ids[0], key, self.cfg)
                    except (ZettaError, IncompleteRollout) as exc:
                        if isinstance(exc, ZettaError) and not is_infrastructure(exc):
                            raise
                        self.store.log_invalid(key, f"attempt {attempt}: {exc}")
                        await _close_quietly(session)
                        session = None
                        await asyncio.sleep(min(30.0, 2.0 ** attempt))  # let an overloaded stack recover
                        continue
                    results[key] = self.store.add(key, outcome, round_)
                    if on_done:
                        on_done(results[key], False)
                    break
                else:
                    raise InfrastructureError(f"{key}: no valid rollout after {self.cfg.max_attempts} attempts; "
                                              f"see the store's invalid log")
        finally:
            if session is not None:
                await _close_quietly(session)

    async def _open(self, gw: Gateway) -> SessionGroup:
        deadline = time.monotonic() + self.cfg.open_timeout_s
        tries = 0
        while True:
            tries += 1
            try:
                return await gw.create_sessions("libero", n=1, env_config=self.env_config)
            except ZettaError as exc:
                # Full pool: wait as told. A worker that just died is still routed to until its
                # heartbeats time out, and a live one missed beats on a loaded machine: wait for
                # the registry to catch up.
                if exc.code not in (grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.UNAVAILABLE):
                    raise
                wait = (exc.retry_after_ms or 500) / 1000
                if time.monotonic() + wait > deadline:
                    raise InfrastructureError(
                        f"no env slot could be opened in {self.cfg.open_timeout_s:.0f} s ({tries} tries); the "
                        f"gateway last said {exc.code.name}: {exc}. Check the env workers' logs, then run the "
                        "same command again: finished rollouts are kept") from None
                await asyncio.sleep(wait)


async def _close_quietly(session: SessionGroup) -> None:
    try:
        await session.close()
    except ZettaError:
        pass
