"""GatewayService: validates a batch, finds each session's worker, fans out, reassembles.

Validation happens before any side effect: a batch with one unknown session or one malformed
action fails whole, and nothing in it runs. The per-worker parts of a valid batch run
concurrently and their results are put back in request order.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import Any, TypeVar

import grpc
import numpy as np
from google.protobuf import json_format

from services.common import grpc_errors as ge
from services.common.grpc_errors import ServiceError, timed_unary
from services.common.metrics import HOP_LATENCY
from services.common.primitives import check_motion, check_queries
from zetta_wire.codec import TensorDecodeError, dtype_from_wire
from services.gateway import metrics
from services.gateway.actions import MAX_CHUNK, check_action_values, check_policy_spec, check_reset_spec
from services.gateway.auth import CALLER, Authenticator
from services.gateway.bounds import check_session_ids, name_ids
from services.gateway.config import GatewayConfig
from services.gateway.registry import (
    CREATE,
    LOST,
    RUNNING,
    TERMINATED,
    NoWorkerError,
    PoolFullError,
    Registry,
    SessionRecord,
)
from services.gateway.workers import WorkerPool
from zetta_wire.v1 import env_worker_pb2, gateway_pb2, gateway_pb2_grpc, types_pb2

log = logging.getLogger(__name__)
T = TypeVar("T")

_STATE_ENUM = {
    CREATE: types_pb2.SESSION_STATE_CREATE,
    RUNNING: types_pb2.SESSION_STATE_RUNNING,
    TERMINATED: types_pb2.SESSION_STATE_TERMINATED,
    LOST: types_pb2.SESSION_STATE_LOST,
}


def _timed(method: str):  # type: ignore[no-untyped-def]
    """Gateway hop latency and status code of every call (grpc_errors.timed_unary), after the
    caller is authenticated (auth.CALLER holds it for the call)."""
    timed = timed_unary("gateway", method, lambda m, code: metrics.REQUESTS.labels(m, code).inc())

    def deco(fn):  # type: ignore[no-untyped-def]
        @functools.wraps(fn)
        async def authenticated(self, request, context):  # type: ignore[no-untyped-def]
            self.auth.client(context)
            return await fn(self, request, context)

        return timed(authenticated)

    return deco


class GatewayServicer(gateway_pb2_grpc.GatewayServiceServicer):
    """The public API; all state is in the registry, so any number of these can run."""

    def __init__(self, registry: Registry, pool: WorkerPool, config: GatewayConfig,
                 auth: Authenticator | None = None) -> None:
        self.registry = registry
        self.pool = pool
        self.cfg = config
        self.auth = auth or Authenticator()

    # ---- validation and routing -------------------------------------------------------------

    async def _resolve(self, sids: Sequence[str]) -> list[SessionRecord]:
        """Records of a batch of RUNNING sessions, or the error that names the bad ones."""
        check_session_ids(sids, self.cfg.max_sessions_per_call)
        records = await self.registry.lookup(sids)
        unknown = [sid for sid, rec in zip(sids, records) if rec is None]
        if unknown:
            raise await self._unknown(unknown)
        recs = [r for r in records if r is not None]
        self._check_owner(recs)
        for state, make in (
            (LOST, lambda ids, why: ge.failed_precondition(
                f"session(s) {name_ids(ids)} LOST ({why}); create new sessions to continue", ids)),
            (TERMINATED, lambda ids, why: ge.not_found(f"session(s) {name_ids(ids)} closed ({why})", ids)),
            (CREATE, lambda ids, why: ge.failed_precondition(
                f"session(s) {name_ids(ids)} are still being created; retry when CreateSessions returns", ids)),
        ):
            bad = [r for r in recs if r.state == state]
            if bad:
                raise make([r.session_id for r in bad], bad[0].reason or state.lower())
        return recs

    @staticmethod
    def _check_owner(records: Sequence[SessionRecord]) -> None:
        """PERMISSION_DENIED for sessions another identity created."""
        caller = CALLER.get()
        foreign = [r.session_id for r in records if not caller.owns(r.owner)]
        if foreign:
            raise ge.permission_denied(
                f"session(s) {name_ids(foreign)} belong to another identity; {caller.name!r} may only use the "
                "sessions it created", foreign)

    async def _unknown(self, unknown: list[str]) -> ServiceError:
        """NOT_FOUND for ids the registry does not hold; LOST when the registry itself lost its state."""
        lost_state = await self.registry.lost_state()
        if lost_state:
            return ge.failed_precondition(
                f"session(s) {name_ids(unknown)} LOST: {lost_state}; create new sessions to continue", unknown)
        return ge.not_found(
            f"unknown session(s) {name_ids(unknown)}: never created, or closed more than "
            f"{self.cfg.tombstone_seconds} s ago",
            unknown,
        )

    async def _fan_out(
        self,
        records: Sequence[SessionRecord],
        call: Callable[[Any, list[int]], Awaitable[Sequence[T]]],
    ) -> list[T]:
        """Run ``call(stub, indices)`` once per worker, concurrently; results in request order."""
        by_worker: dict[str, list[int]] = {}
        for i, rec in enumerate(records):
            by_worker.setdefault(rec.worker_id, []).append(i)
        stubs = {w: await self.pool.stub(w) for w in by_worker}

        async def one(worker: str, idx: list[int]) -> Sequence[T]:
            try:
                return await call(stubs[worker], idx)
            except grpc.aio.AioRpcError as err:
                ids = [records[i].session_id for i in idx]
                if err.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED) and not ge.failed_component(err):
                    raise ge.unavailable(
                        f"env worker {worker} is unreachable ({err.details()}); its sessions become LOST if it "
                        f"does not heartbeat within {self.cfg.heartbeat_timeout_ms} ms",
                        ids,
                    ) from None
                raise ge.from_rpc_error(err, f"env worker {worker}") from None

        parts = await asyncio.gather(*(one(w, idx) for w, idx in by_worker.items()), return_exceptions=True)
        errors = [p for p in parts if isinstance(p, BaseException)]
        if errors:
            first = errors[0]
            if isinstance(first, ServiceError) and len(errors) > 1:
                failed = [s for e in errors if isinstance(e, ServiceError) for s in e.session_ids]
                first.session_ids = failed
            raise first
        out: list[Any] = [None] * len(records)
        for (worker, idx), part in zip(by_worker.items(), parts):
            for i, res in zip(idx, part):  # type: ignore[arg-type]
                out[i] = res
        return out

    def _specs_for(self, n: int, specs: Sequence[types_pb2.ResetSpec], what: str) -> list[types_pb2.ResetSpec]:
        for i, spec in enumerate(specs):
            check_reset_spec(spec, f"{what}[{i}]")
        if len(specs) == 1:
            return [specs[0]] * n
        if len(specs) != n:
            raise ge.invalid(f"{what}: give one spec for all sessions or one per session ({n}), got {len(specs)}")
        return list(specs)

    @staticmethod
    def _timeout(ms: int) -> float:
        return ms / 1000.0

    # ---- session management ---------------------------------------------------------------

    @_timed("CreateSessions")
    async def CreateSessions(self, request: gateway_pb2.CreateSessionsRequest, context) -> gateway_pb2.CreateSessionsResponse:
        family = request.env_family.strip()
        if not family:
            raise ge.invalid("env_family is empty; name a family such as 'libero' or 'robosuite'")
        if not 1 <= request.count <= self.cfg.max_sessions_per_call:
            raise ge.invalid(f"count must be between 1 and {self.cfg.max_sessions_per_call}, got {request.count}")
        if request.lease_seconds < 0 or request.lease_seconds > self.cfg.max_lease_seconds:
            raise ge.invalid(f"lease_seconds must be between 0 and {self.cfg.max_lease_seconds}, got {request.lease_seconds}")
        lease_ms = (request.lease_seconds or self.cfg.default_lease_seconds) * 1000
        try:
            config = json_format.MessageToDict(request.env_config)
        except (ValueError, json_format.Error) as exc:  # NaN and infinities have no JSON form
            raise ge.invalid(f"env_config cannot be read: {exc}; numbers must be finite") from None
        try:
            allocated = await self.registry.allocate(family, request.count, lease_ms, config,
                                                     hold_ms=self.cfg.create_timeout_ms, owner=CALLER.get().name)
        except NoWorkerError:
            workers = await self.registry.workers()
            silent = sorted(w.worker_id for w in workers if not w.alive and family in w.families)
            if silent:  # the family is served here, its workers are silent now: a retry may succeed
                metrics.REJECTED.labels(family, "no_live_worker").inc()
                raise ge.unavailable(
                    f"no live worker hosts env family {family!r} right now: {', '.join(silent)} host it but missed "
                    f"their heartbeats; retry in {self.cfg.retry_after_ms} ms", retry_after_ms=self.cfg.retry_after_ms,
                ) from None
            hosted = sorted({f for w in workers if w.alive for f in w.families})
            metrics.REJECTED.labels(family, "unknown_family").inc()
            raise ge.invalid(
                f"unknown env family {family!r}: no live worker hosts it; hosted families: {', '.join(hosted) or 'none'}"
            ) from None
        except PoolFullError as exc:
            metrics.REJECTED.labels(family, "pool_full").inc()
            raise ge.exhausted(
                f"pool full for family {family!r}: {request.count} sessions asked, {exc.free} slots free; "
                f"close sessions or retry in {self.cfg.retry_after_ms} ms",
                self.cfg.retry_after_ms,
            ) from None
        by_worker: dict[str, list[str]] = {}
        for sid, worker in allocated:
            by_worker.setdefault(worker, []).append(sid)

        async def open_on(worker: str, sids: list[str]) -> env_worker_pb2.OpenSlotsResponse:
            stub = await self.pool.stub(worker)
            req = env_worker_pb2.OpenSlotsRequest(session_ids=sids, env_family=family)
            req.env_config.CopyFrom(request.env_config)
            return await stub.OpenSlots(req, timeout=self._timeout(self.cfg.create_timeout_ms))

        results = await asyncio.gather(*(open_on(w, s) for w, s in by_worker.items()), return_exceptions=True)
        failure = next((r for r in results if isinstance(r, BaseException)), None)
        if failure is not None:
            await self._abandon(by_worker, results, "creation failed")
            if isinstance(failure, grpc.aio.AioRpcError):
                raise ge.from_rpc_error(failure, "cannot create sessions") from None
            raise failure
        sessions = []
        for (worker, sids), opened in zip(by_worker.items(), results):
            assert isinstance(opened, env_worker_pb2.OpenSlotsResponse)
            await self.registry.activate(
                sids,
                str(dtype_from_wire(opened.action_spec.dtype).newbyteorder("=")),
                list(opened.action_spec.shape),
                opened.SerializeToString(),
                (opened.action_spec.low if opened.action_spec.HasField("low") else None,
                 opened.action_spec.high if opened.action_spec.HasField("high") else None),
            )
            for sid in sids:
                info = types_pb2.SessionInfo(
                    session_id=sid,
                    env_family=family,
                    state=types_pb2.SESSION_STATE_RUNNING,
                    worker_id=worker,
                    observation_schema=opened.observation_schema,
                    action_spec=opened.action_spec,
                )
                sessions.append((sid, info))
        expiries = {r.session_id: r.expires_ms for r in await self.registry.lookup([s for s, _ in sessions]) if r}
        order = {sid: i for i, (sid, _) in enumerate(allocated)}
        sessions.sort(key=lambda p: order[p[0]])
        for sid, info in sessions:
            info.lease_expires_unix_ms = expiries.get(sid, 0)
        log.info("sessions created", extra={"fields": {"family": family, "count": len(sessions), "workers": list(by_worker)}})
        return gateway_pb2.CreateSessionsResponse(sessions=[i for _, i in sessions])

    async def _abandon(self, by_worker: dict[str, list[str]], results: Sequence[Any], reason: str) -> None:
        """Undo a partly failed creation: free every slot and close the ones that opened."""
        for (worker, sids), res in zip(by_worker.items(), results):
            for sid in sids:
                await self.registry.release(sid, TERMINATED, reason)
            if not isinstance(res, BaseException):
                try:
                    stub = await self.pool.stub(worker)
                    await stub.CloseSlots(env_worker_pb2.CloseSlotsRequest(session_ids=sids), timeout=10)
                except (grpc.aio.AioRpcError, ServiceError):
                    log.warning("could not close slots after a failed creation", extra={"fields": {"worker": worker}})

    @_timed("RenewSessions")
    async def RenewSessions(self, request, context) -> gateway_pb2.RenewSessionsResponse:
        records = await self._resolve(list(request.session_ids))
        if request.lease_seconds < 0 or request.lease_seconds > self.cfg.max_lease_seconds:
            raise ge.invalid(f"lease_seconds must be between 0 and {self.cfg.max_lease_seconds}, got {request.lease_seconds}")
        out = []
        for rec in records:
            ok, detail = await self.registry.renew(rec.session_id, request.lease_seconds * 1000)
            if not ok:
                raise ge.not_found(f"session {rec.session_id} closed while renewing ({detail})", [rec.session_id])
            out.append(
                types_pb2.SessionInfo(
                    session_id=rec.session_id,
                    env_family=rec.family,
                    state=types_pb2.SESSION_STATE_RUNNING,
                    worker_id=rec.worker_id,
                    lease_expires_unix_ms=int(detail),
                )
            )
        return gateway_pb2.RenewSessionsResponse(sessions=out)

    @_timed("CloseSessions")
    async def CloseSessions(self, request, context) -> gateway_pb2.CloseSessionsResponse:
        sids = list(dict.fromkeys(request.session_ids))
        if sids:
            check_session_ids(sids, self.cfg.max_sessions_per_call)
            self._check_owner([r for r in await self.registry.lookup(sids) if r is not None])
        closed, already = await self.close_sessions(sids, "closed by client")
        return gateway_pb2.CloseSessionsResponse(closed_session_ids=closed, already_closed_session_ids=already)

    async def close_sessions(self, sids: Sequence[str], reason: str) -> tuple[list[str], list[str]]:
        """Free slots in the registry first (the source of truth), then tell the workers."""
        closed: list[str] = []
        already: list[str] = []
        by_worker: dict[str, list[str]] = {}
        for sid in sids:
            changed, worker = await self.registry.release(sid, TERMINATED, reason)
            if changed:
                closed.append(sid)
                by_worker.setdefault(worker, []).append(sid)
            else:
                already.append(sid)
        for worker, ids in by_worker.items():
            try:
                stub = await self.pool.stub(worker)
                await stub.CloseSlots(env_worker_pb2.CloseSlotsRequest(session_ids=ids), timeout=10)
            except (grpc.aio.AioRpcError, ServiceError) as exc:
                log.warning("worker did not confirm slot close", extra={"fields": {"worker": worker, "error": str(exc)}})
        return closed, already

    # ---- environment control ----------------------------------------------------------------

    @_timed("Reset")
    async def Reset(self, request, context) -> gateway_pb2.ResetResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        specs = self._specs_for(len(sids), request.specs or [types_pb2.ResetSpec()], "specs")

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.ResetSlotsRequest(
                session_ids=[sids[i] for i in idx], specs=[specs[i] for i in idx]
            )
            return (await stub.ResetSlots(req, timeout=self._timeout(self.cfg.reset_timeout_ms))).results

        return gateway_pb2.ResetResponse(results=await self._fan_out(records, call))

    @_timed("Observe")
    async def Observe(self, request, context) -> gateway_pb2.ObserveResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.ObserveSlotsRequest(session_ids=[sids[i] for i in idx])
            return (await stub.ObserveSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.ObserveResponse(results=await self._fan_out(records, call))

    def _check_actions(self, records: Sequence[SessionRecord], actions: Sequence[types_pb2.Tensor]) -> None:
        if len(actions) != len(records):
            raise ge.invalid(f"actions: expected one per session ({len(records)}), got {len(actions)}")
        for rec, action in zip(records, actions):
            try:
                dtype = dtype_from_wire(action.dtype)
            except TensorDecodeError as exc:
                raise ge.invalid(f"action of session {rec.session_id}: {exc}", [rec.session_id]) from None
            want = rec.action_shape
            shape = tuple(action.shape)
            if str(dtype.newbyteorder("=")) != rec.action_dtype:
                raise ge.invalid(
                    f"action of session {rec.session_id}: expected dtype {rec.action_dtype}, got {dtype.newbyteorder('=')}",
                    [rec.session_id],
                )
            if shape != want and not (len(shape) == len(want) + 1 and shape[1:] == want and 1 <= shape[0] <= MAX_CHUNK):
                raise ge.invalid(
                    f"action of session {rec.session_id}: expected shape {list(want)} (or [n, {', '.join(map(str, want))}] "
                    f"for a chunk of n <= {MAX_CHUNK}), got {list(shape)}",
                    [rec.session_id],
                )
            if len(action.data) != int(np.prod(shape)) * dtype.itemsize:
                raise ge.invalid(
                    f"action of session {rec.session_id}: {len(action.data)} bytes do not match shape {list(shape)}",
                    [rec.session_id],
                )
            check_action_values(rec, np.frombuffer(action.data, dtype).reshape(shape))

    @_timed("ActionStep")
    async def ActionStep(self, request, context) -> gateway_pb2.ActionStepResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        self._check_actions(records, request.actions)
        actions = list(request.actions)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.StepSlotsRequest(session_ids=[sids[i] for i in idx], actions=[actions[i] for i in idx])
            return (await stub.StepSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.ActionStepResponse(results=await self._fan_out(records, call))

    # ---- the harness's tools ---------------------------------------------------------------

    @_timed("Perceive")
    async def Perceive(self, request, context) -> gateway_pb2.PerceiveResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        queries = check_queries(request.queries)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.PerceiveSlotsRequest(session_ids=[sids[i] for i in idx], queries=queries,
                                                      grasps=request.grasps)
            return (await stub.PerceiveSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.PerceiveResponse(results=await self._fan_out(records, call))

    @_timed("Move")
    async def Move(self, request, context) -> gateway_pb2.MoveResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        if len(request.motions) != len(sids):
            raise ge.invalid(f"motions: expected one per session ({len(sids)}), got {len(request.motions)}")
        for sid, motion in zip(sids, request.motions):
            check_motion(sid, motion)
        motions = list(request.motions)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.MoveSlotsRequest(session_ids=[sids[i] for i in idx], motions=[motions[i] for i in idx])
            return (await stub.MoveSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.MoveResponse(results=await self._fan_out(records, call))

    # ---- policy execution -----------------------------------------------------------------

    @_timed("PolicyStep")
    async def PolicyStep(self, request, context) -> gateway_pb2.PolicyStepResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        check_policy_spec(request.policy)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.PolicyStepSlotsRequest(session_ids=[sids[i] for i in idx], policy=request.policy)
            return (await stub.PolicyStepSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.PolicyStepResponse(results=await self._fan_out(records, call))

    @_timed("PolicyInfer")
    async def PolicyInfer(self, request, context) -> gateway_pb2.PolicyInferResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        check_policy_spec(request.policy)

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.InferSlotsRequest(session_ids=[sids[i] for i in idx], policy=request.policy)
            return (await stub.InferSlots(req, timeout=self._timeout(self.cfg.step_timeout_ms))).results

        return gateway_pb2.PolicyInferResponse(results=await self._fan_out(records, call))

    @_timed("RunEpisode")
    async def RunEpisode(self, request, context) -> gateway_pb2.RunEpisodeResponse:
        sids = list(request.session_ids)
        records = await self._resolve(sids)
        check_policy_spec(request.policy)
        specs = self._specs_for(len(sids), request.specs, "specs") if request.specs else []
        if request.max_steps < 0:
            raise ge.invalid(f"max_steps must be >= 0, got {request.max_steps}")

        async def call(stub, idx: list[int]):
            req = env_worker_pb2.RunEpisodesRequest(
                session_ids=[sids[i] for i in idx],
                specs=[specs[i] for i in idx] if specs else [],
                policy=request.policy,
                max_steps=request.max_steps,
            )
            return (await stub.RunEpisodes(req, timeout=self._timeout(self.cfg.episode_timeout_ms))).summaries

        return gateway_pb2.RunEpisodeResponse(summaries=await self._fan_out(records, call))

    async def StepStream(self, request_iterator, context):
        """One stream per session; every message is checked against the registry like a call."""
        bound = ""
        hist = HOP_LATENCY.labels("gateway", "StepStream")
        try:
            self.auth.client(context)
            async for req in request_iterator:
                start = time.perf_counter()
                sid = req.session_id or bound
                if not sid:
                    raise ge.invalid("the first StepStream message must name session_id")
                if bound and sid != bound:
                    raise ge.invalid(f"this stream drives session {bound}; open another stream for {sid}")
                bound = sid
                records = await self._resolve([sid])
                stub = await self.pool.stub(records[0].worker_id)
                op = req.WhichOneof("op")
                try:
                    if op == "reset":
                        check_reset_spec(req.reset, "reset")
                        res = await stub.ResetSlots(
                            env_worker_pb2.ResetSlotsRequest(session_ids=[sid], specs=[req.reset]),
                            timeout=self._timeout(self.cfg.reset_timeout_ms),
                        )
                        yield gateway_pb2.StepStreamResponse(reset=res.results[0])
                    elif op == "action":
                        self._check_actions(records, [req.action])
                        res = await stub.StepSlots(
                            env_worker_pb2.StepSlotsRequest(session_ids=[sid], actions=[req.action]),
                            timeout=self._timeout(self.cfg.step_timeout_ms),
                        )
                        yield gateway_pb2.StepStreamResponse(step=res.results[0])
                    elif op == "policy":
                        check_policy_spec(req.policy)
                        res = await stub.PolicyStepSlots(
                            env_worker_pb2.PolicyStepSlotsRequest(session_ids=[sid], policy=req.policy),
                            timeout=self._timeout(self.cfg.step_timeout_ms),
                        )
                        yield gateway_pb2.StepStreamResponse(step=res.results[0])
                    elif op == "observe":
                        res = await stub.ObserveSlots(
                            env_worker_pb2.ObserveSlotsRequest(session_ids=[sid]),
                            timeout=self._timeout(self.cfg.step_timeout_ms),
                        )
                        yield gateway_pb2.StepStreamResponse(observe=res.results[0])
                    else:
                        raise ge.invalid("StepStream message has no operation: set reset, action, policy or observe")
                except grpc.aio.AioRpcError as err:
                    raise ge.from_rpc_error(err, f"env worker {records[0].worker_id}") from None
                hist.observe(time.perf_counter() - start)
        except ge.STORE_ERRORS as exc:
            metrics.REQUESTS.labels("StepStream", "UNAVAILABLE").inc()
            await ge.store_unavailable(exc).abort(context)
        except ServiceError as exc:
            metrics.REQUESTS.labels("StepStream", exc.code.name).inc()
            await exc.abort(context)

    # ---- introspection ----------------------------------------------------------------------

    @_timed("ListSessions")
    async def ListSessions(self, request, context) -> gateway_pb2.ListSessionsResponse:
        wanted = set(request.states)
        caller = CALLER.get()
        sids = await self.registry.all_session_ids()
        out = []
        for sid, h in zip(sids, await self.registry.session_hashes(sids)):
            if not h or not caller.owns(h.get("owner", b"").decode()):
                continue
            text = {k: v.decode() for k, v in h.items() if k != "schema"}
            state = _STATE_ENUM.get(text.get("state", ""), types_pb2.SESSION_STATE_UNSPECIFIED)
            family = text.get("family", "")
            if (request.env_family and family != request.env_family) or (wanted and state not in wanted):
                continue
            info = types_pb2.SessionInfo(
                session_id=sid,
                env_family=family,
                state=state,
                worker_id=text.get("worker", ""),
                lease_expires_unix_ms=int(text.get("expires_ms") or 0),
                reason=text.get("reason", ""),
            )
            if h.get("schema"):
                opened = env_worker_pb2.OpenSlotsResponse.FromString(h["schema"])
                info.observation_schema.extend(opened.observation_schema)
                info.action_spec.CopyFrom(opened.action_spec)
            out.append(info)
        return gateway_pb2.ListSessionsResponse(sessions=out)

    @_timed("ListWorkers")
    async def ListWorkers(self, request, context) -> gateway_pb2.ListWorkersResponse:
        return gateway_pb2.ListWorkersResponse(
            workers=[
                gateway_pb2.WorkerInfo(
                    worker_id=w.worker_id,
                    address=w.address,
                    env_families=w.families,
                    slots=w.slots,
                    free_slots=w.free,
                    alive=w.alive,
                    last_heartbeat_unix_ms=w.last_hb_ms,
                )
                for w in await self.registry.workers()
            ]
        )

