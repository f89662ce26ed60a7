"""HarnessRegistryService (publish, get, list, diff, pin) and CriticService (Evaluate).

Publishing checks a package before anything is stored: the static checks in this process
(layout, SKILL.md, TOML, the code rules), then, in a child process with a deadline, the import
of its tools and the construction of a harness runtime from it; a package that fails is
INVALID_ARGUMENT with every reason. Content already published skips the checks and returns its
version. Evaluate runs the harness runtime beside a control loop the client owns, one episode
per stream.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Mapping, Sequence
from typing import Any

import grpc
import numpy as np

from services.common import grpc_errors as ge
from services.common.grpc_errors import ServiceError, timed_unary
from services.common.metrics import HOP_LATENCY
from services.critic import metrics
from services.critic.config import CriticConfig
from services.harness.package import diff as pkg_diff
from services.harness.package import format as fmt
from services.harness.package.errors import PackageRejected
from services.harness.package.loader import check_files, load_files, unload
from services.harness.package.model import LoadedPackage
from services.harness.package.probe import probe_import
from services.harness.report_proto import report_to_proto
from services.critic.registry import HarnessRegistry, Resolved, parse_json
from services.harness.runtime.engine import HarnessError, HarnessRuntime
from services.harness.sandbox import client as sandbox
from zetta_wire.codec import TensorDecodeError, decode, decode_observation, encode
from zetta_wire.v1 import critic_pb2, critic_pb2_grpc

log = logging.getLogger(__name__)

#: Bounds on EvaluateStart.policy_instructions: a model's training instructions (LIBERO-90 has 90),
#: each a sentence; a redirection scans them all, so a client cannot make that scan unbounded.
MAX_POLICY_INSTRUCTIONS = 1024
MAX_INSTRUCTION_CHARS = 1024
_FILE_CHANGE = {
    "added": critic_pb2.FILE_CHANGE_ADDED,
    "removed": critic_pb2.FILE_CHANGE_REMOVED,
    "modified": critic_pb2.FILE_CHANGE_MODIFIED,
}


def _timed(method: str):
    """Hop latency and status code of every unary call (services/common/grpc_errors.timed_unary)."""
    return timed_unary("critic", method, lambda m, code: metrics.REQUESTS.labels(m, code).inc())


def _json_or_empty(value: Any) -> str:
    return "" if value is None else json.dumps(value, sort_keys=True)


def manifest_message(manifest: Mapping[str, Any]) -> critic_pb2.HarnessManifest:
    """The stored manifest.json as its proto message."""
    return critic_pb2.HarnessManifest(
        name=manifest["name"],
        version=int(manifest["version"]),
        parent=manifest.get("parent") or "",
        content_hash=manifest["content_hash"],
        lineage=list(manifest.get("lineage") or []),
        evidence_json=_json_or_empty(manifest.get("evidence")),
        validation_json=_json_or_empty(manifest.get("validation")),
        created_at=manifest.get("created_at", ""),
    )


class HarnessRegistryServicer(critic_pb2_grpc.HarnessRegistryServiceServicer):
    """The registry's gRPC face; state lives in Redis and the package store."""

    def __init__(self, registry: HarnessRegistry, config: CriticConfig) -> None:
        self.registry = registry
        self.config = config

    @_timed("Publish")
    async def Publish(self, request: critic_pb2.PublishRequest, context: grpc.aio.ServicerContext) -> critic_pb2.PublishResponse:
        files = {path: data for path, data in request.files.items() if path != fmt.MANIFEST}
        evidence = parse_json("evidence_json", request.evidence_json)
        validation = parse_json("validation_json", request.validation_json)
        try:
            checked = await asyncio.to_thread(check_files, files, self.config.max_package_bytes)
        except PackageRejected as exc:
            metrics.REJECTED.inc()
            raise ge.invalid(str(exc)) from None
        digest = fmt.content_hash(files)
        existing = await self.registry.published(digest)
        if existing is not None:
            metrics.PUBLISHED.labels("false").inc()
            return critic_pb2.PublishResponse(manifest=manifest_message(existing), created=False)
        try:
            await probe_import(files, self.config.import_timeout_s, self.config.max_package_bytes)
        except PackageRejected as exc:
            metrics.REJECTED.inc()
            raise ge.invalid(str(exc)) from None
        manifest, created = await self.registry.publish(
            files, checked.skill["name"], digest, request.parent, evidence, validation
        )
        metrics.PUBLISHED.labels(str(created).lower()).inc()
        log.info(
            "published" if created else "already published",
            extra={"fields": {"ref": f"{manifest['name']}@{manifest['version']}", "content_hash": digest}},
        )
        return critic_pb2.PublishResponse(manifest=manifest_message(manifest), created=created)

    @_timed("Get")
    async def Get(self, request: critic_pb2.GetRequest, context: grpc.aio.ServicerContext) -> critic_pb2.GetResponse:
        resolved = await self.registry.resolve(request.ref, request.task)
        response = critic_pb2.GetResponse(manifest=manifest_message(self.registry.manifest(resolved)))
        if not request.manifest_only:
            for path, data in (await self.registry.files(resolved)).items():
                response.files[path] = data
        return response

    @_timed("List")
    async def List(self, request: critic_pb2.ListRequest, context: grpc.aio.ServicerContext) -> critic_pb2.ListResponse:
        response = critic_pb2.ListResponse()
        for resolved in await self.registry.list(request.name):
            response.versions.append(manifest_message(self.registry.manifest(resolved)))
        for task, ref in sorted((await self.registry.pins()).items()):
            if not request.name or ref.split("@", 1)[0] == request.name:
                response.pins.append(critic_pb2.HarnessPin(task=task, ref=ref))
        return response

    @_timed("Diff")
    async def Diff(self, request: critic_pb2.DiffRequest, context: grpc.aio.ServicerContext) -> critic_pb2.DiffResponse:
        if not request.base or not request.head:
            raise ge.invalid("Diff needs both base and head references")
        base = await self.registry.resolve(request.base)
        head = await self.registry.resolve(request.head)
        base_files, head_files = await self.registry.files(base), await self.registry.files(head)
        response = critic_pb2.DiffResponse(
            base=manifest_message(self.registry.manifest(base)), head=manifest_message(self.registry.manifest(head))
        )
        for change in pkg_diff.file_changes(base_files, head_files, base.ref, head.ref):
            response.files.append(
                critic_pb2.FileDiff(path=change.path, change=_FILE_CHANGE[change.change], unified_diff=change.unified_diff)
            )
        for param in pkg_diff.param_changes(base_files, head_files):
            response.params.append(
                critic_pb2.ParamChange(
                    file=param.file, key=param.key, base_json=param.base_json or "", head_json=param.head_json or ""
                )
            )
        return response

    @_timed("Pin")
    async def Pin(self, request: critic_pb2.PinRequest, context: grpc.aio.ServicerContext) -> critic_pb2.PinResponse:
        resolved, previous = await self.registry.pin(request.task, request.ref)
        log.info("pinned", extra={"fields": {"task": request.task, "ref": resolved.ref, "previous": previous}})
        return critic_pb2.PinResponse(ref=resolved.ref, previous=previous)

    @_timed("GetPin")
    async def GetPin(self, request: critic_pb2.GetPinRequest, context: grpc.aio.ServicerContext) -> critic_pb2.GetPinResponse:
        return critic_pb2.GetPinResponse(ref=await self.registry.get_pin(request.task))


class PackageCache:
    """Loaded harness versions by content hash, least recently used evicted first: loading
    imports the tools, which Evaluate streams of the same version can share."""

    def __init__(self, registry: HarnessRegistry, size: int, max_bytes: int, sandboxed: bool | None = None) -> None:
        self._registry = registry
        #: Package code runs in sandbox children (ZETTA_HARNESS_SANDBOX, default on): the tools are
        #: checked here but never imported into this process; each Evaluate stream gets a child.
        self.sandboxed = sandbox.enabled() if sandboxed is None else sandboxed
        self._size = size
        self._max_bytes = max_bytes
        self._loaded: OrderedDict[str, LoadedPackage] = OrderedDict()
        self._lock = asyncio.Lock()

    async def get(self, resolved: Resolved) -> LoadedPackage:
        """The loaded package of a stored version."""
        async with self._lock:
            package = self._loaded.get(resolved.content_hash)
            if package is None:
                files = await self._registry.files(resolved)
                try:
                    package = await asyncio.to_thread(load_files, files, self._max_bytes, not self.sandboxed)
                except PackageRejected as exc:  # stored packages passed this check at publish
                    raise ge.failed_precondition(f"{resolved.ref} no longer loads: {exc}") from None
                self._loaded[resolved.content_hash] = package
                while len(self._loaded) > self._size:
                    unload(self._loaded.popitem(last=False)[1])
            self._loaded.move_to_end(resolved.content_hash)
            metrics.LOADED.set(len(self._loaded))
            return package


def decision_message(step: int, decision: Any) -> critic_pb2.EvaluateResponse:
    """The runtime's Decision as an EvaluateResponse."""
    out = critic_pb2.EvaluateDecision(step=step, mode=decision.mode, intervention_id=decision.intervention_id or "",
                                      instruction=decision.instruction)
    for p in decision.proposals:
        proposal = out.proposals.add(critic=p.critic, evidence=p.evidence, suggested_mode=p.suggested_mode)
        for key, value in p.details.items():
            proposal.details[key] = float(value)
        metrics.PROPOSALS.labels(p.evidence).inc()
    if decision.action is not None:
        encode(np.asarray(decision.action), out.action)
    metrics.DECISIONS.labels(decision.mode).inc()
    return critic_pb2.EvaluateResponse(decision=out)


class CriticServicer(critic_pb2_grpc.CriticServiceServicer):
    """Evaluate: one harness runtime per stream, fed by the client's env steps."""

    def __init__(self, registry: HarnessRegistry, cache: PackageCache) -> None:
        self.registry = registry
        self.cache = cache
        self._hop = HOP_LATENCY.labels("critic", "EvaluateStep")

    async def Evaluate(
        self, request_iterator: AsyncIterator[critic_pb2.EvaluateRequest], context: grpc.aio.ServicerContext
    ) -> AsyncIterator[critic_pb2.EvaluateResponse]:
        code = "OK"
        metrics.STREAMS.inc()
        try:
            async for response in self._evaluate(request_iterator):
                yield response
        except ServiceError as exc:
            code = exc.code.name
            await exc.abort(context)
        finally:
            metrics.STREAMS.dec()
            metrics.REQUESTS.labels("Evaluate", code).inc()

    async def _evaluate(
        self, requests: AsyncIterator[critic_pb2.EvaluateRequest]
    ) -> AsyncIterator[critic_pb2.EvaluateResponse]:
        first = await anext(requests, None)
        if first is None:
            return
        if first.WhichOneof("kind") != "start":
            raise ge.invalid("the first Evaluate message must be a start naming the harness")
        start = first.start
        _check_policy_instructions(start.policy_instructions)
        resolved = await self.registry.resolve(start.harness, start.task)
        package = await self.cache.get(resolved)
        try:
            runtime = await asyncio.to_thread(HarnessRuntime, package)  # spawns its sandbox child
        except HarnessError as exc:  # published packages passed this check; the runtime changed since
            raise ge.failed_precondition(f"{resolved.ref} does not make a runnable harness: {exc}") from None
        try:
            async for response in self._run(runtime, start, resolved, requests):
                yield response
        finally:
            runtime.close()  # its sandbox child, if any

    async def _run(self, runtime: HarnessRuntime, start: Any, resolved: Resolved,
                   requests: AsyncIterator[critic_pb2.EvaluateRequest]) -> AsyncIterator[critic_pb2.EvaluateResponse]:
        runtime.policy_instructions = tuple(start.policy_instructions)
        runtime.start(start.instruction, list(start.milestone_names))
        yield critic_pb2.EvaluateResponse(
            started=critic_pb2.EvaluateStarted(manifest=manifest_message(self.registry.manifest(resolved)))
        )
        step = 0
        async for request in requests:
            kind = request.WhichOneof("kind")
            if kind == "end":
                report = critic_pb2.EvaluateResponse()
                report_to_proto(runtime.finish(request.end.success), report.report)
                yield report
                return
            if kind != "step":
                raise ge.invalid(f"message {step + 1} after the start must be a step or an end; one stream runs one episode")
            t0 = time.perf_counter()
            try:
                obs = decode_observation(request.step.observation)
                action = decode(request.step.action) if request.step.HasField("action") else None
            except TensorDecodeError as exc:
                raise ge.invalid(f"step {step}: {exc}") from None
            try:
                decision = await asyncio.to_thread(runtime.step, obs, action, frozenset(request.step.milestones))
            except Exception as exc:  # the runtime contains critic failures; anything else ends the stream
                log.exception("harness runtime failed", extra={"fields": {"ref": resolved.ref, "step": step}})
                raise ServiceError(grpc.StatusCode.INTERNAL, f"{resolved.ref}: runtime failed at step {step}: {exc}") from None
            response = decision_message(step, decision)
            self._hop.observe(time.perf_counter() - t0)
            yield response
            step += 1


def _check_policy_instructions(instructions: Sequence[str]) -> None:
    """INVALID_ARGUMENT for more than MAX_POLICY_INSTRUCTIONS, or one longer than MAX_INSTRUCTION_CHARS."""
    if len(instructions) > MAX_POLICY_INSTRUCTIONS:
        raise ge.invalid(f"EvaluateStart.policy_instructions has {len(instructions)} entries; at most "
                         f"{MAX_POLICY_INSTRUCTIONS} (the instructions your policy was trained on)")
    for i, text in enumerate(instructions):
        if len(text) > MAX_INSTRUCTION_CHARS:
            raise ge.invalid(f"EvaluateStart.policy_instructions[{i}] is {len(text)} characters long; at most "
                             f"{MAX_INSTRUCTION_CHARS}")
