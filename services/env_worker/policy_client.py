"""Env worker -> policy worker: one reused channel per policy worker, requests coalesced.

Every inference request a worker's slots make in the same event-loop turn travels in one Infer
call; the policy worker then batches those with other workers' requests. Observations are cut
down to the tensors the model reads (learned once from ListModels) before they are encoded, so
images a state-based policy ignores are neither serialized nor sent.

Holding (:class:`InferHold`): a policy answers a batch of many requests for little more than the
cost of one on a CPU (and on a GPU), but slots in a closed loop ask one at a time, a few
milliseconds apart, so requests sent as they come make batches of one or two. While at least
``min_busy`` of this worker's slots are still stepping, the worker's cores are busy anyway, and a
request that waits for company costs no throughput: it is held until fewer slots are busy (they
have finished their chunks and asked too), or for ``max_ms`` at most (and never more than half
of a request's own timeout), and the held requests leave in one call. A lone session (fewer busy
slots than ``min_busy``) is never held.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import grpc
import numpy as np

from services.common import grpc_errors as ge
from services.common.metrics import HOP_LATENCY
from services.common.tls import aio_channel
from zetta_wire.channel import CHANNEL_OPTIONS
from services.env_worker import metrics
from zetta_wire.codec import encode
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc


#: Statuses of an Infer call that one item can cause while the others were fine: the call is
#: retried item by item. The policy worker checks every item (model, tensors, budget) before it
#: runs any, so a refusal of those costs no inference twice.
_ITEM_ERRORS = frozenset({grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND})


@dataclass(frozen=True)
class InferHold:
    """When requests wait for each other (module doc); ``max_ms`` 0 sends each loop turn's at once."""

    max_ms: float = 0.0
    min_busy: int = 2


@dataclass
class _Pending:
    item: policy_worker_pb2.InferItem
    future: asyncio.Future[policy_worker_pb2.InferOutput]
    arrival: float
    #: Loop time after which holding it longer is not allowed.
    hold_until: float


class PolicyClient:
    """Sends inference items to the policy workers and routes answers back by token."""

    def __init__(self, addresses: Sequence[str], default_timeout_ms: int, hold: InferHold = InferHold(),
                 busy: Callable[[], int] = lambda: 0) -> None:
        """``busy``: how many of the worker's slots have work on their threads now; call
        :meth:`slot_finished` whenever one finishes, so held requests can leave."""
        # round_robin spreads calls over every address a name resolves to (dns:///policy:50071 in
        # Kubernetes), so policy pods added by the autoscaler take load from existing env workers.
        options = [*CHANNEL_OPTIONS, ("grpc.lb_policy_name", "round_robin")]
        self._channels = [aio_channel(a, options) for a in addresses]
        self._stubs = [policy_worker_pb2_grpc.PolicyWorkerServiceStub(c) for c in self._channels]
        self._rr = itertools.cycle(range(len(self._stubs))) if self._stubs else None
        self._pending: list[_Pending] = []
        self._flush_scheduled = False
        self._hold = hold
        self._busy = busy
        self._hold_timer: asyncio.TimerHandle | None = None
        self._inputs: dict[str, frozenset[str]] = {}
        self._instructions: dict[str, tuple[str, ...]] = {}
        self._default_timeout_ms = default_timeout_ms
        self._hop = HOP_LATENCY.labels("env_worker", "policy_infer")

    async def model_inputs(self, model: str) -> frozenset[str] | None:
        """Input names of a model (None when the policy workers do not know it)."""
        if model not in self._inputs and self._stubs:
            listing = await self._stubs[0].ListModels(policy_worker_pb2.ListModelsRequest(), timeout=10)
            for m in listing.models:
                self._inputs[m.name] = frozenset(s.name for s in m.inputs)
                self._instructions[m.name] = tuple(m.instructions)
                if m.is_default:
                    self._inputs[""] = self._inputs[m.name]
                    self._instructions[""] = self._instructions[m.name]
        return self._inputs.get(model)

    async def model_instructions(self, model: str) -> tuple[str, ...]:
        """The instructions a model was trained on (ModelInfo.instructions; empty when it lists
        none or the policy workers do not know it)."""
        await self.model_inputs(model)
        return self._instructions.get(model, ())

    async def infer(
        self, token: str, model: str, observation: Mapping[str, np.ndarray], instruction: str, timeout_ms: int
    ) -> policy_worker_pb2.InferOutput:
        """One item; it leaves with every other item submitted in the same loop turn. Only the
        tensors the model reads are encoded."""
        if not self._stubs:
            raise ge.failed_precondition(
                "this env worker has no policy worker configured (set ZETTA_POLICY_ADDRESSES)"
            )
        try:
            wanted = await self.model_inputs(model)
        except grpc.aio.AioRpcError as err:
            raise ge.from_rpc_error(err, "policy worker", component="policy worker") from None
        item = policy_worker_pb2.InferItem(
            token=token, model=model, instruction=instruction, timeout_ms=timeout_ms or self._default_timeout_ms
        )
        for name, array in observation.items():
            if wanted is None or name in wanted:
                encode(array, item.observation.tensors[name])
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[policy_worker_pb2.InferOutput] = loop.create_future()
        now = loop.time()
        self._pending.append(_Pending(item, fut, now, now + min(self._hold.max_ms, item.timeout_ms / 2) / 1000.0))
        self._check_soon()
        return await fut

    def slot_finished(self) -> None:
        """A slot of this worker finished its work: held requests may leave now."""
        if self._pending:
            self._check_soon()

    def _check_soon(self) -> None:
        # At the end of this loop turn, so every request made in it (also by the slot that just
        # finished a chunk and asks for the next) leaves in the same call.
        if not self._flush_scheduled:
            self._flush_scheduled = True
            asyncio.get_running_loop().call_soon(self._check)

    def _check(self) -> None:
        self._flush_scheduled = False
        if not self._pending:
            return
        hold = self._hold
        if hold.max_ms > 0 and self._busy() >= hold.min_busy:
            due = min(p.hold_until for p in self._pending)
            if self._hold_timer is None or self._hold_timer.when() > due:
                if self._hold_timer is not None:
                    self._hold_timer.cancel()
                self._hold_timer = asyncio.get_running_loop().call_at(due, self._flush)
            return
        self._flush()

    def _flush(self) -> None:
        if self._hold_timer is not None:
            self._hold_timer.cancel()
            self._hold_timer = None
        pending, self._pending = self._pending, []
        # One call per (model, budget): the policy worker fails a call whole, so an item asking for
        # a model it does not serve, or with a budget too short to meet (a client's timeout_ms of
        # 1), must not share a call with other sessions' items. Items of different models never
        # share a policy batch anyway, and the policy worker batches items of different calls
        # that arrive together.
        calls: dict[tuple[str, int], list[_Pending]] = {}
        for p in pending:
            calls.setdefault((p.item.model, p.item.timeout_ms), []).append(p)
        for batch in calls.values():
            metrics.INFER_CALL_ITEMS.observe(len(batch))
            metrics.INFER_HOLD_SECONDS.observe(asyncio.get_running_loop().time() - batch[0].arrival)
            asyncio.ensure_future(self._send(batch))

    async def _send(self, batch: list[_Pending]) -> None:
        assert self._rr is not None
        stub = self._stubs[next(self._rr)]
        budget = max(p.item.timeout_ms for p in batch) / 1000.0 + 1.0
        start = time.perf_counter()
        try:
            resp = await stub.Infer(policy_worker_pb2.InferRequest(items=[p.item for p in batch]), timeout=budget)
        except grpc.aio.AioRpcError as err:
            metrics.POLICY_ERRORS.labels(err.code().name).inc()
            if len(batch) > 1 and err.code() in _ITEM_ERRORS:
                # One item's fault (its instruction, its observation) failed the call: each item
                # again on its own, so only the faulty one fails.
                await asyncio.gather(*(self._send([p]) for p in batch))
                return
            error = ge.from_rpc_error(err, "policy worker", component="policy worker")
            for p in batch:
                if not p.future.done():
                    p.future.set_exception(error)
            return
        self._hop.observe(time.perf_counter() - start)
        by_token = {out.token: out for out in resp.outputs}
        for p in batch:
            if p.future.done():
                continue
            out = by_token.get(p.item.token)
            if out is None:
                p.future.set_exception(ge.ServiceError(grpc.StatusCode.INTERNAL, f"no answer for token {p.item.token}"))
            else:
                p.future.set_result(out)

    async def close(self) -> None:
        """Close the channels."""
        for c in self._channels:
            await c.close()
