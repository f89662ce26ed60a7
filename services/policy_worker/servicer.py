"""PolicyWorkerService: decodes items, hands them to the batching scheduler, routes answers.

Every item of a call is checked before any is queued (known model, every input present with the
declared dtype and shape), so a malformed call fails whole with INVALID_ARGUMENT or NOT_FOUND.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Mapping

import grpc
import numpy as np

from services.common import grpc_errors as ge
from services.common.grpc_errors import ServiceError, error_boundary
from services.common.metrics import HOP_LATENCY
from services.common.specs import SpecError
from services.common.spec_codec import spec_to_wire
from zetta_wire.codec import TensorDecodeError, decode, encode
from services.policy_worker.models.base import ACTION_SPEC, PolicyModel
from services.policy_worker.scheduler import (
    BatchScheduler,
    DeadlineExceededError,
    InferItem,
    QueueFullError,
    SchedulerClosedError,
)
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc


class PolicyWorkerServicer(policy_worker_pb2_grpc.PolicyWorkerServiceServicer):
    """Serves a fixed set of models through one scheduler."""

    def __init__(self, models: Mapping[str, PolicyModel], default_model: str, scheduler: BatchScheduler,
                 default_timeout_ms: int) -> None:
        self.models = dict(models)
        self.default_model = default_model
        self.scheduler = scheduler
        self.default_timeout_ms = default_timeout_ms
        self._specs = {name: {s.name: s for s in m.input_specs()} for name, m in self.models.items()}
        self._hop = HOP_LATENCY.labels("policy_worker", "Infer")

    def _prepare(self, item: policy_worker_pb2.InferItem, now: float) -> InferItem:
        model = item.model or self.default_model
        specs = self._specs.get(model)
        if specs is None:
            raise ge.not_found(f"unknown model {model!r}; this worker serves {', '.join(sorted(self.models))}")
        inputs: dict[str, np.ndarray] = {}
        missing = [n for n in specs if n not in item.observation.tensors]
        if missing:
            raise ge.invalid(
                f"item {item.token}: model {model!r} needs tensors {', '.join(missing)} which the observation lacks"
            )
        for name, spec in specs.items():
            try:
                array = decode(item.observation.tensors[name])
                spec.check(array)
            except (TensorDecodeError, SpecError) as exc:
                raise ge.invalid(f"item {item.token}: {exc}") from None
            inputs[name] = array
        if item.timeout_ms < 0:
            raise ge.invalid(f"item {item.token}: timeout_ms must be >= 0")
        budget = (item.timeout_ms or self.default_timeout_ms) / 1000.0
        return InferItem(token=item.token, model=model, inputs=inputs, instruction=item.instruction,
                         deadline=now + budget, arrival=now)

    async def _run(self, item: InferItem) -> policy_worker_pb2.InferOutput:
        try:
            actions = await self.scheduler.submit(item)
        except QueueFullError as exc:
            raise ge.exhausted(str(exc), retry_after_ms=max(1, int(exc.retry_after * 1000))) from None
        except DeadlineExceededError as exc:
            raise ServiceError(grpc.StatusCode.DEADLINE_EXCEEDED, f"item {item.token}: {exc}") from None
        except SchedulerClosedError as exc:
            raise ge.unavailable(f"policy worker is shutting down: {exc}") from None
        except ValueError as exc:
            raise ge.invalid(f"item {item.token}: {exc}") from None
        except Exception as exc:  # a model failure is the caller's INTERNAL error
            raise ServiceError(grpc.StatusCode.INTERNAL, f"model {item.model!r} failed: {exc}") from exc
        return policy_worker_pb2.InferOutput(token=item.token, actions=encode(actions), model=item.model)

    @error_boundary
    async def Infer(self, request, context) -> policy_worker_pb2.InferResponse:
        start = time.perf_counter()
        if not request.items:
            raise ge.invalid("items is empty")
        now = time.monotonic()
        items = [self._prepare(item, now) for item in request.items]
        tasks = [asyncio.ensure_future(self._run(i)) for i in items]
        try:
            outputs = await asyncio.gather(*tasks)
        except BaseException:
            for t in tasks:
                t.cancel()
            raise
        self._hop.observe(time.perf_counter() - start)
        return policy_worker_pb2.InferResponse(outputs=outputs)

    @error_boundary
    async def ListModels(self, request, context) -> policy_worker_pb2.ListModelsResponse:
        resp = policy_worker_pb2.ListModelsResponse()
        for name, model in self.models.items():
            info = resp.models.add(name=name, chunk_size=model.chunk_size, is_default=name == self.default_model,
                                   instructions=getattr(model, "instructions", ()))
            for spec in model.input_specs():
                spec_to_wire(spec, info.inputs.add())
            spec_to_wire(ACTION_SPEC, info.action)
        return resp
