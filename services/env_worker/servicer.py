"""EnvWorkerService: runs resets, steps and whole episodes on the slots of this worker.

A batch is checked whole before anything runs (every session bound, every episode live, every
action of the right shape), then each session's work runs on its slot's pinned thread, so the
slots of one call advance side by side while the event loop stays free for other calls.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import Sequence
from concurrent.futures import Future

import grpc
import numpy as np
from google.protobuf import json_format

from services.common import grpc_errors as ge
from services.common.grpc_errors import ServiceError, timed_unary
from services.common.primitives import check_motion
from services.common.spec_codec import spec_to_wire
from zetta_wire.codec import TensorDecodeError, decode, encode, encode_observation
from services.env_worker import harness_loop, metrics, primitives
from services.env_worker.chunks import ChunkRun, run_chunk, step_result
from services.env_worker.families import ResetError, ResetSpec, Slot
from services.env_worker.policy_client import PolicyClient
from services.env_worker.slots import BoundSlot, Episode, SlotTable, action_spec_check, new_episode_id
from services.env_worker.video import VideoError
from zetta_wire.v1 import env_worker_pb2, env_worker_pb2_grpc, types_pb2

log = logging.getLogger(__name__)


def _timed(method: str):
    """Env worker hop latency of every call (grpc_errors.timed_unary)."""
    return timed_unary("env_worker", method)


def _milestone_report(env: Slot) -> tuple[list[str], list[str], str]:
    """The episode's milestones M, those observed, and m* (read on the slot's thread)."""
    return env.milestone_names(), env.milestones_reached(), env.first_missing_milestone()


class EnvWorkerServicer(env_worker_pb2_grpc.EnvWorkerServiceServicer):
    """The slots of one worker process."""

    def __init__(self, table: SlotTable, policy: PolicyClient, worker_id: str = "", video_dir: str = "",
                 resource_sharing: bool = True, critic_address: str = "") -> None:
        self.table = table
        #: Where resets that name a harness get its package (ZETTA_CRITIC_ADDR for registry references).
        self.harness_source = harness_loop.HarnessSource(critic_address)
        #: False (ZETTA_RESOURCE_SHARING=false): each session gets a group of its own, compiling its
        #: own scene; a baseline for the throughput bench, never faster.
        self.resource_sharing = resource_sharing
        self.policy = policy
        self.worker_id = worker_id
        #: Where episode videos go (ZETTA_VIDEO_DIR, checked at start-up); empty: no videos.
        self.video_dir = video_dir
        self._episodes_in_flight = 0
        self._idle = asyncio.Event()
        self._idle.set()

    # ---- slot lifecycle -------------------------------------------------------------------

    @_timed("OpenSlots")
    async def OpenSlots(self, request, context) -> env_worker_pb2.OpenSlotsResponse:
        config = json_format.MessageToDict(request.env_config)
        family = self.table.group(request.env_family, config)
        slots = self.table.bind(list(request.session_ids), request.env_family, family)
        if not self.resource_sharing:
            for s in slots:
                if s.env is None and s.family is family:
                    s.family = type(family)(family.config)
        try:
            await asyncio.gather(*(s.run(self._build, s) for s in slots if s.env is None))
        except ServiceError:
            for s in slots:
                self._close(s.session_id)
            raise
        except Exception as exc:  # a simulator failure is reported, not crashed on
            for s in slots:
                self._close(s.session_id)
            raise ge.ServiceError(
                grpc.StatusCode.INTERNAL, f"building {request.env_family} environments failed: {exc}"
            ) from exc
        resp = env_worker_pb2.OpenSlotsResponse()
        for spec in family.obs_schema().values():
            spec_to_wire(spec, resp.observation_schema.add())
        spec_to_wire(family.action_spec(), resp.action_spec)
        return resp

    def _build(self, slot: BoundSlot) -> None:
        try:
            env = slot.family.init()
        except ResetError as exc:
            raise ge.invalid(str(exc)) from None
        if not self.table.holds(slot):
            env.close()  # the session was closed while its env was being built
            return
        renderer = getattr(env, "renderer", None)
        if renderer is not None:
            renderer.warm()  # the GL context now, not in the first reset (rendering.SlotRenderer.warm)
        slot.env = env

    @_timed("CloseSlots")
    async def CloseSlots(self, request, context) -> env_worker_pb2.CloseSlotsResponse:
        # Answer once the envs are closed, so that what closing finishes (an episode's video file)
        # is complete when the client hears the session is closed.
        closing = {sid: self._close(sid) for sid in request.session_ids}
        pending = [asyncio.wrap_future(f) for futures in closing.values() if futures for f in futures]
        for outcome in await asyncio.gather(*pending, return_exceptions=True):
            if isinstance(outcome, BaseException):
                log.error("closing an env failed: %s", outcome)
        return env_worker_pb2.CloseSlotsResponse(closed_session_ids=[s for s, f in closing.items() if f is not None])

    def _close(self, session_id: str) -> list[Future[None]] | None:
        """Unbind the session and close its env on the slot's thread; None if it was not bound."""
        slot = self.table.release(session_id)
        if slot is None:
            return None
        futures = []
        if slot.env is not None:
            futures.append(slot.executor.submit(slot.env.close))
        if slot.harness is not None:  # its sandbox child, on the slot's thread (it may be mid-step)
            futures.append(slot.executor.submit(slot.harness.close))
        if not self.resource_sharing:
            futures.append(slot.executor.submit(slot.family.close))  # the session's own group: its scene too
        return futures

    def close_all(self, keep: Sequence[str] = ()) -> list[str]:
        """Drop every slot not in ``keep`` (after the registry declared them LOST)."""
        dropped = [sid for sid in self.table.session_ids() if sid not in set(keep)]
        for sid in dropped:
            self._close(sid)
        return dropped

    # ---- episodes ---------------------------------------------------------------------------

    @_timed("ResetSlots")
    async def ResetSlots(self, request, context) -> env_worker_pb2.ResetSlotsResponse:
        sids = list(request.session_ids)
        slots = self.table.get(sids)
        if len(request.specs) != len(sids):
            raise ge.invalid(f"expected one spec per session ({len(sids)}), got {len(request.specs)}")
        results = await asyncio.gather(*(s.run(self._reset, s, spec) for s, spec in zip(slots, request.specs)))
        return env_worker_pb2.ResetSlotsResponse(results=results)

    def _reset(self, slot: BoundSlot, spec: types_pb2.ResetSpec) -> types_pb2.ResetResult:
        start = time.perf_counter()
        episode_id = new_episode_id()
        video_path = ""
        if spec.record_video:
            if not self.video_dir:
                raise ge.failed_precondition(
                    f"session {slot.session_id} asked for a video but this env worker has no ZETTA_VIDEO_DIR",
                    [slot.session_id],
                )
            video_path = os.path.join(self.video_dir, f"{episode_id}.mp4")
        package = self.harness_source.load(spec, slot.session_id)
        harness = harness_loop.bind(slot.harness, package)  # a package that makes no harness fails here
        if slot.env is None:
            slot.env = slot.family.init()
        try:
            obs, instruction = slot.env.reset(
                ResetSpec(task=spec.task, seed=spec.seed, init_state_index=spec.init_state_index,
                          instruction=spec.instruction, video_path=video_path)
            )
        except ResetError as exc:
            # The env dropped its episode when the reset began: so does the slot, so the next step
            # is FAILED_PRECONDITION "call Reset first" rather than an env error.
            slot.episode = None
            raise ge.invalid(f"reset of session {slot.session_id}: {exc}; the session has no running episode "
                             "until a reset succeeds", [slot.session_id]) from None
        except VideoError as exc:
            slot.episode = None
            raise ge.ServiceError(grpc.StatusCode.INTERNAL, f"video of session {slot.session_id}: {exc}") from None
        episode = Episode(
            episode_id=episode_id,
            instruction=spec.instruction or instruction,
            max_steps=slot.family.max_episode_steps(spec.task),
            record_steps=spec.record_steps,
        )
        episode.perception = primitives.episode_perception(
            obs, episode.instruction, harness.runtime.noise if harness is not None else None)
        slot.episode = episode
        slot.last_obs = obs
        metrics.RESETS.labels(slot.family_name).inc()
        metrics.RESET_SECONDS.labels(slot.family_name).observe(time.perf_counter() - start)
        result = types_pb2.ResetResult(
            session_id=slot.session_id,
            episode_id=episode.episode_id,
            instruction=episode.instruction,
            max_steps=episode.max_steps,
            video_path=video_path,
            milestone_names=slot.env.milestone_names(),
        )
        slot.harness = harness
        if harness is not None:
            harness.reset(obs, episode.instruction, result.milestone_names)
            result.harness_content_hash = harness.package.content_hash
        encode_observation(obs, result.observation)
        return result

    @_timed("ObserveSlots")
    async def ObserveSlots(self, request, context) -> env_worker_pb2.ObserveSlotsResponse:
        slots = self.table.get(list(request.session_ids))
        return env_worker_pb2.ObserveSlotsResponse(results=[self._observe(s) for s in slots])

    @staticmethod
    def _observe(slot: BoundSlot) -> types_pb2.ObserveResult:
        result = types_pb2.ObserveResult(session_id=slot.session_id)
        if slot.episode is not None:
            result.episode_id = slot.episode.episode_id
            result.episode_step = slot.env.episode_step
        if slot.last_obs is not None:
            encode_observation(slot.last_obs, result.observation)
        return result

    @_timed("StepSlots")
    async def StepSlots(self, request, context) -> env_worker_pb2.StepSlotsResponse:
        sids = list(request.session_ids)
        slots = self.table.get(sids)
        if len(request.actions) != len(sids):
            raise ge.invalid(f"expected one action per session ({len(sids)}), got {len(request.actions)}")
        chunks = []
        for slot, tensor in zip(slots, request.actions):
            slot.require_episode()
            try:
                action = decode(tensor)
            except TensorDecodeError as exc:
                raise ge.invalid(f"action of session {slot.session_id}: {exc}", [slot.session_id]) from None
            chunks.append(action_spec_check(slot.family.action_spec(), action, slot.session_id))
        results = await asyncio.gather(*(s.run(self._execute, s, c) for s, c in zip(slots, chunks)))
        return env_worker_pb2.StepSlotsResponse(results=results)

    @_timed("PerceiveSlots")
    async def PerceiveSlots(self, request, context) -> env_worker_pb2.PerceiveSlotsResponse:
        slots = self.table.get(list(request.session_ids))
        for slot in slots:
            slot.require_episode()
        queries, grasps = list(request.queries), request.grasps
        results = await asyncio.gather(*(s.run(primitives.perceive, s, queries, grasps) for s in slots))
        return env_worker_pb2.PerceiveSlotsResponse(results=results)

    @_timed("MoveSlots")
    async def MoveSlots(self, request, context) -> env_worker_pb2.MoveSlotsResponse:
        sids = list(request.session_ids)
        slots = self.table.get(sids)
        if len(request.motions) != len(sids):
            raise ge.invalid(f"expected one motion per session ({len(sids)}), got {len(request.motions)}")
        for slot, motion in zip(slots, request.motions):
            slot.require_episode()
            primitives.require_no_harness(slot)
            check_motion(slot.session_id, motion)
        results = await asyncio.gather(*(s.run(primitives.move, s, m) for s, m in zip(slots, request.motions)))
        return env_worker_pb2.MoveSlotsResponse(results=results)

    @staticmethod
    def _execute(slot: BoundSlot, chunk: np.ndarray) -> types_pb2.StepResult:
        """Execute a chunk on the slot's thread, stopping at the end of the episode; the StepResult
        a StepSlots or PolicyStepSlots caller reads."""
        return step_result(slot, run_chunk(slot, chunk))

    # ---- policy ------------------------------------------------------------------------------

    async def _infer(self, slot: BoundSlot, policy: types_pb2.PolicySpec) -> tuple[np.ndarray, str]:
        """The action chunk for the slot's last observation, and the model that answered."""
        episode = slot.require_episode()
        assert slot.last_obs is not None
        token = f"{self.worker_id}/{slot.session_id}/{episode.episode_id}/{slot.env.episode_step}"
        redirect = ""
        if slot.harness is not None:
            # A recovery that redirects the policy asks it under an instruction it was trained on
            # where one serves the sub-goal: the harness learns the serving model's from here.
            try:
                slot.harness.policy_instructions = await self.policy.model_instructions(policy.model)
            except grpc.aio.AioRpcError as err:
                raise ge.from_rpc_error(err, "policy worker", component="policy worker") from None
            redirect = slot.harness.redirect
        instruction = redirect or policy.instruction or episode.instruction
        out = await self.policy.infer(token, policy.model, slot.last_obs, instruction, policy.timeout_ms)
        actions = decode(out.actions)
        return action_spec_check(slot.family.action_spec(), actions, slot.session_id), out.model

    async def _next_chunk(self, slot: BoundSlot, policy: types_pb2.PolicySpec) -> tuple[np.ndarray, bool]:
        """The policy's chunk, or (while a harness recovery has control) a placeholder the recovery's
        actions replace, without asking the policy; and whether the policy was asked."""
        if slot.harness is not None and slot.harness.in_recovery:
            spec = slot.family.action_spec()
            n = policy.execute_steps if policy.execute_steps > 0 else harness_loop.RECOVERY_CHUNK
            return harness_loop.placeholder_chunk(n, int(spec.shape[0]), np.dtype(spec.dtype)), False
        chunk, _ = await self._infer(slot, policy)
        return chunk, True

    async def _policy_step(self, slot: BoundSlot, policy: types_pb2.PolicySpec) -> types_pb2.StepResult:
        async with slot.busy:
            chunk, _ = await self._next_chunk(slot, policy)
            if policy.execute_steps > 0:
                chunk = chunk[: policy.execute_steps]
            return await slot.run(self._execute, slot, chunk)

    @_timed("PolicyStepSlots")
    async def PolicyStepSlots(self, request, context) -> env_worker_pb2.PolicyStepSlotsResponse:
        slots = self.table.get(list(request.session_ids))
        for s in slots:
            s.require_episode()
        results = await asyncio.gather(*(self._policy_step(s, request.policy) for s in slots))
        return env_worker_pb2.PolicyStepSlotsResponse(results=results)

    @_timed("InferSlots")
    async def InferSlots(self, request, context) -> env_worker_pb2.InferSlotsResponse:
        slots = self.table.get(list(request.session_ids))
        for s in slots:
            s.require_episode()
        answers = await asyncio.gather(*(self._infer(s, request.policy) for s in slots))
        return env_worker_pb2.InferSlotsResponse(
            results=[
                types_pb2.InferResult(session_id=s.session_id, actions=encode(chunk), model=model)
                for s, (chunk, model) in zip(slots, answers)
            ]
        )

    @_timed("RunEpisodes")
    async def RunEpisodes(self, request, context) -> env_worker_pb2.RunEpisodesResponse:
        sids = list(request.session_ids)
        slots = self.table.get(sids)
        if request.specs and len(request.specs) != len(sids):
            raise ge.invalid(f"expected no spec or one per session ({len(sids)}), got {len(request.specs)}")
        if not request.specs:
            for s in slots:
                s.require_episode()
        self._episodes_in_flight += 1
        self._idle.clear()
        try:
            summaries = await asyncio.gather(
                *(
                    self._run_episode(s, request.specs[i] if request.specs else None, request.policy, request.max_steps)
                    for i, s in enumerate(slots)
                )
            )
        finally:
            self._episodes_in_flight -= 1
            if self._episodes_in_flight == 0:
                self._idle.set()
        return env_worker_pb2.RunEpisodesResponse(summaries=summaries)

    async def _run_episode(
        self, slot: BoundSlot, spec: types_pb2.ResetSpec | None, policy: types_pb2.PolicySpec, max_steps: int
    ) -> types_pb2.EpisodeSummary:
        start = time.perf_counter()
        if spec is not None:
            await slot.run(self._reset, slot, spec)
        episode = slot.require_episode()
        budget = min(max_steps, episode.max_steps) if max_steps > 0 else episode.max_steps
        first_step = slot.env.episode_step
        reward = 0.0
        calls = 0
        last: ChunkRun | None = None
        async with slot.busy:
            while slot.env.episode_step - first_step < budget and not episode.ended:
                chunk, asked = await self._next_chunk(slot, policy)
                calls += asked
                remaining = budget - (slot.env.episode_step - first_step)
                n = policy.execute_steps if policy.execute_steps > 0 else len(chunk)
                last = await slot.run(run_chunk, slot, chunk[: min(n, remaining)])
                reward += last.reward
            # The summary's video is complete: one that the budget cut short is finished here.
            video_path = await slot.run(slot.env.finish_video)
            names, reached, missing = await slot.run(_milestone_report, slot.env)
            harness = slot.harness.report() if slot.harness is not None else None
        if last is not None and last.outcome.success:
            reason = types_pb2.STOP_REASON_SUCCESS
        elif last is not None and last.outcome.terminated:
            reason = types_pb2.STOP_REASON_TERMINATED
        else:
            reason = types_pb2.STOP_REASON_MAX_STEPS
        return types_pb2.EpisodeSummary(
            session_id=slot.session_id,
            episode_id=episode.episode_id,
            steps=slot.env.episode_step - first_step,
            reward=reward,
            success=bool(last is not None and last.outcome.success),
            stop_reason=reason,
            wall_ms=(time.perf_counter() - start) * 1000.0,
            policy_calls=calls,
            video_path=video_path,
            milestone_names=names,
            milestones_reached=reached,
            first_missing_milestone=missing,
            harness_report=harness,
        )

    async def wait_idle(self) -> None:
        """Wait until no RunEpisodes call is in flight (used when draining)."""
        await self._idle.wait()
