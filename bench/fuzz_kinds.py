"""Malformed requests to the control plane, one kind per entry, each with the status it must get.

Used by bench/bench_fuzz.py (sent for a fixed time while good sessions run episodes) and by
tests/fault/test_fuzz.py (every kind once). docs/security.md lists the kinds ("Fuzzed requests").

A kind's request is built once (:func:`build`) and can be sent any number of times; each send
goes over a real channel to the gateway (a GatewayService, WorkerRegistryService or raw method
call) and its outcome is the gRPC status it got. A kind passes when the status is the expected
one and carries a message; UNKNOWN, INTERNAL, OK (the request was accepted) or an empty message
fail it. The fuzzer acts as its own identity (``user`` token), with one session of its own for
the kinds that need a valid id (bad actions, bad options) and a second one for the failing
resets, and knows one session id of another identity (``victim``).
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np
from google.protobuf import struct_pb2

from zetta_wire.channel import CHANNEL_OPTIONS
from zetta_wire.codec import encode
from zetta_wire.v1 import gateway_pb2, gateway_pb2_grpc, registry_pb2, registry_pb2_grpc, types_pb2

#: The gateway's defaults (ZETTA_MAX_SESSIONS_PER_CALL, ZETTA_MAX_REQUEST_BYTES).
MAX_IDS = 1024
MAX_REQUEST_BYTES = 16 * 1024 * 1024
#: Deadline of one fuzz call: a clear status comes back in well under it.
CALL_TIMEOUT_S = 20.0
#: The environment config of every session (the fuzzer's own and the good ones).
LIFT_CONFIG: dict[str, Any] = {"env_name": "Lift", "max_steps": 80}
#: The policy the stacks serve (state-based; the image VLA would need cameras).
MODEL = "scripted-pick-place"

ZEROS = np.zeros(7, np.float32)


@dataclass
class Ctx:
    """What a fuzzer holds: channels with and without its token, its own session, a foreign one."""

    address: str
    token: str
    worker_token: str
    own: str
    victim: str
    #: A second session of the fuzzer's for the kinds that fail a reset (which ends its episode),
    #: so that ``own`` keeps a running episode for the others; ``own`` when not given.
    scratch: str = ""
    channel: grpc.aio.Channel = field(init=False)

    def __post_init__(self) -> None:
        self.scratch = self.scratch or self.own
        self.channel = grpc.aio.insecure_channel(self.address, options=CHANNEL_OPTIONS)
        self.gw = gateway_pb2_grpc.GatewayServiceStub(self.channel)
        self.reg = registry_pb2_grpc.WorkerRegistryServiceStub(self.channel)

    def md(self, token: str | None = None) -> tuple[tuple[str, str], ...]:
        """Call metadata with ``token`` (the fuzzer's by default)."""
        return (("authorization", f"Bearer {token or self.token}"),)

    async def close(self) -> None:
        """Close the channel."""
        await self.channel.close()


#: Sends a prepared request; raises grpc.aio.AioRpcError with the status it got.
Send = Callable[[Ctx], Awaitable[Any]]


@dataclass(frozen=True)
class Kind:
    """One kind of malformed request: its name, the status it must get, what it is."""

    name: str
    expected: str
    what: str
    build: Callable[[Ctx], Send]


@dataclass(frozen=True)
class Outcome:
    """The status one send got."""

    kind: str
    expected: str
    code: str
    details: str
    seconds: float

    @property
    def ok(self) -> bool:
        """The expected status with a message."""
        return self.code == self.expected and bool(self.details.strip())


def _ids(n: int) -> list[str]:
    return [uuid.uuid4().hex for _ in range(n)]


def _tensor(values: np.ndarray) -> types_pb2.Tensor:
    return encode(values)


def _action(value: float, index: int = 3) -> types_pb2.Tensor:
    a = ZEROS.copy()
    a[index] = value
    return _tensor(a)


def _struct(values: dict[str, Any]) -> struct_pb2.Struct:
    s = struct_pb2.Struct()
    s.update(values)
    return s


def _call(method: str, request: Any, token: str | None = None, no_token: bool = False) -> Callable[[Ctx], Send]:
    """A GatewayService call of ``request`` with the fuzzer's token (or ``token``, or none)."""
    def build(ctx: Ctx) -> Send:
        md = () if no_token else ctx.md(token and getattr(ctx, token))
        fn = getattr(ctx.gw, method)
        return lambda c: fn(request(ctx) if callable(request) else request, timeout=CALL_TIMEOUT_S, metadata=md)
    return build


def _step(actions: Callable[[Ctx], Sequence[types_pb2.Tensor]], ids: Callable[[Ctx], Sequence[str]] | None = None
          ) -> Callable[[Ctx], Send]:
    """ActionStep on the fuzzer's own session with ``actions``."""
    def request(ctx: Ctx) -> gateway_pb2.ActionStepRequest:
        return gateway_pb2.ActionStepRequest(session_ids=ids(ctx) if ids else [ctx.own], actions=actions(ctx))
    return _call("ActionStep", request)


def _create(family: str, config: dict[str, Any], count: int = 1, lease: int = 0) -> Callable[[Ctx], Send]:
    return _call("CreateSessions", gateway_pb2.CreateSessionsRequest(
        env_family=family, count=count, lease_seconds=lease, env_config=_struct(config)))


def _reset(spec: types_pb2.ResetSpec) -> Callable[[Ctx], Send]:
    """A Reset that fails, on the fuzzer's scratch session."""
    return _call("Reset", lambda ctx: gateway_pb2.ResetRequest(session_ids=[ctx.scratch], specs=[spec]))


def _policy(spec: types_pb2.PolicySpec) -> Callable[[Ctx], Send]:
    return _call("PolicyStep", lambda ctx: gateway_pb2.PolicyStepRequest(session_ids=[ctx.own], policy=spec))


def _stream(messages: Callable[[Ctx], Sequence[gateway_pb2.StepStreamRequest]]) -> Callable[[Ctx], Send]:
    """A StepStream that sends ``messages`` and reads until the status."""
    def build(ctx: Ctx) -> Send:
        async def send(c: Ctx) -> None:
            call = c.gw.StepStream(timeout=CALL_TIMEOUT_S, metadata=c.md())
            for m in messages(c):
                await call.write(m)
            await call.done_writing()
            async for _ in call:
                pass
        return send
    return build


def _raw(method: str, payload: bytes, token: bool = True) -> Callable[[Ctx], Send]:
    """Bytes sent as the request of ``method`` (no protobuf encoding)."""
    def build(ctx: Ctx) -> Send:
        fn = ctx.channel.unary_unary(method)
        md = ctx.md() if token else ()
        return lambda c: fn(payload, timeout=CALL_TIMEOUT_S, metadata=md)
    return build


def _raw_stream() -> Callable[[Ctx], Send]:
    """A StepStream whose message is bytes that do not parse."""
    def build(ctx: Ctx) -> Send:
        async def send(c: Ctx) -> None:
            call = c.channel.stream_stream("/zetta.v1.GatewayService/StepStream")(timeout=CALL_TIMEOUT_S,
                                                                                  metadata=c.md())
            await call.write(b"\x0a\xff\xff\xff\xff\x0f")
            await call.done_writing()
            async for _ in call:
                pass
        return send
    return build


def _deep_struct_request(depth: int) -> bytes:
    """A serialized CreateSessionsRequest whose env_config nests ``depth`` Structs (built by hand:
    the protobuf library refuses to make it)."""
    inner = b""
    for _ in range(depth):
        # Struct.fields (1): map entry {key (1): "a", value (2): Value{struct_value (5): inner}}
        value = b"\x2a" + _varint(len(inner)) + inner
        entry = b"\x0a\x01a" + b"\x12" + _varint(len(value)) + value
        inner = b"\x0a" + _varint(len(entry)) + entry
    config = b"\x12" + _varint(len(inner)) + inner  # CreateSessionsRequest.env_config = 2
    return b"\x0a\x09robosuite" + config + b"\x20\x01"  # env_family = 1, count = 4


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _register(token: str | None) -> Callable[[Ctx], Send]:
    """RegisterWorker taking over the victim's worker id (a reroute), with ``token`` or none."""
    def build(ctx: Ctx) -> Send:
        md = () if token is None else ctx.md(getattr(ctx, token))
        req = registry_pb2.RegisterWorkerRequest(worker_id="env-0", address="127.0.0.1:1",
                                                 env_families=["robosuite"], slots=4)
        return lambda c: c.reg.RegisterWorker(req, timeout=CALL_TIMEOUT_S, metadata=md)
    return build


def _deregister(ctx: Ctx) -> Send:
    req = registry_pb2.DeregisterWorkerRequest(worker_id="env-0")
    return lambda c: c.reg.DeregisterWorker(req, timeout=CALL_TIMEOUT_S, metadata=c.md())


_DUP_15001 = [*_ids(15_000), "x"]
_DUP_15001[7] = _DUP_15001[8]
_IDS_1025 = _ids(MAX_IDS + 1)
_UNKNOWN_1000 = _ids(1000)
_BIG = b"\x00" * (MAX_REQUEST_BYTES + 1024 * 1024)
INVALID = "INVALID_ARGUMENT"

KINDS: list[Kind] = [
    # ---- session ids -------------------------------------------------------------------------
    Kind("empty-ids", INVALID, "PolicyStep naming no session",
         _call("PolicyStep", gateway_pb2.PolicyStepRequest())),
    Kind("duplicate-id", INVALID, "the same (own) session id twice in one call",
         _call("Observe", lambda ctx: gateway_pb2.ObserveRequest(session_ids=[ctx.own, ctx.own]))),
    Kind("unknown-id", "NOT_FOUND", "a well-formed id no session has",
         _call("Observe", gateway_pb2.ObserveRequest(session_ids=_ids(1)))),
    Kind("1000-unknown-ids", "NOT_FOUND", "1,000 unknown ids (their list would overflow the error metadata)",
         _call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=_UNKNOWN_1000))),
    Kind("too-many-ids", INVALID, f"{MAX_IDS + 1} ids, one over ZETTA_MAX_SESSIONS_PER_CALL",
         _call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=_IDS_1025))),
    Kind("15001-ids-duplicated", INVALID, "15,001 ids with a duplicate (about 510 KB; the issue's repro)",
         _call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=_DUP_15001))),
    Kind("long-id", INVALID, "a 65-character id",
         _call("Observe", gateway_pb2.ObserveRequest(session_ids=["a" * 65]))),
    Kind("non-ascii-id", INVALID, "a 3,000-character non-ASCII id",
         _call("ActionStep", gateway_pb2.ActionStepRequest(session_ids=["\u00e9" * 3000], actions=[_tensor(ZEROS)]))),
    Kind("control-char-id", INVALID, "ids with a NUL, a comma or a newline",
         _call("Observe", gateway_pb2.ObserveRequest(session_ids=["a\x00b", "a,b", "a\nb"]))),
    Kind("foreign-session", "PERMISSION_DENIED", "another identity's session (step)",
         _step(lambda ctx: [_tensor(ZEROS)], lambda ctx: [ctx.victim])),
    Kind("foreign-close", "PERMISSION_DENIED", "closing another identity's session",
         _call("CloseSessions", lambda ctx: gateway_pb2.CloseSessionsRequest(session_ids=[ctx.victim]))),
    # ---- credentials -------------------------------------------------------------------------
    Kind("no-token", "UNAUTHENTICATED", "a GatewayService call without a token (auth on)",
         _call("ListSessions", gateway_pb2.ListSessionsRequest(), no_token=True)),
    Kind("forged-token", "UNAUTHENTICATED", "a token nobody issued",
         lambda ctx: (lambda c: c.gw.ListWorkers(gateway_pb2.ListWorkersRequest(), timeout=CALL_TIMEOUT_S,
                                                  metadata=(("authorization", "Bearer forged-" + "x" * 40),)))),
    Kind("worker-token-as-client", "PERMISSION_DENIED", "the worker credential on GatewayService",
         _call("ListSessions", gateway_pb2.ListSessionsRequest(), token="worker_token")),
    Kind("register-without-credential", "UNAUTHENTICATED", "RegisterWorker rerouting a live worker, no token",
         _register(None)),
    Kind("register-as-user", "PERMISSION_DENIED", "RegisterWorker with a user token", _register("token")),
    Kind("deregister-as-user", "PERMISSION_DENIED", "DeregisterWorker of a live worker with a user token",
         _deregister),
    # ---- actions -----------------------------------------------------------------------------
    Kind("nan-action", INVALID, "an action element NaN", _step(lambda ctx: [_action(np.nan)])),
    Kind("inf-action", INVALID, "an action element +inf", _step(lambda ctx: [_action(np.inf)])),
    Kind("1e30-action", INVALID, "an action element 1e30 (spec [-1, 1])", _step(lambda ctx: [_action(1e30)])),
    Kind("out-of-range-chunk", INVALID, "a [5, 7] chunk with one element -1.5",
         _step(lambda ctx: [_tensor(np.full((5, 7), -1.5, np.float32))])),
    Kind("wrong-length-action", INVALID, "6 elements for a 7-element action",
         _step(lambda ctx: [_tensor(np.zeros(6, np.float32))])),
    Kind("too-long-chunk", INVALID, "a chunk of 257 actions (at most 256)",
         _step(lambda ctx: [_tensor(np.zeros((257, 7), np.float32))])),
    Kind("wrong-dtype", INVALID, "a float64 action for a float32 spec",
         _step(lambda ctx: [_tensor(np.zeros(7, np.float64))])),
    Kind("unknown-dtype", INVALID, "dtype enum value 99",
         _step(lambda ctx: [types_pb2.Tensor(dtype=99, shape=[7], data=b"\x00" * 28)])),
    Kind("bytes-mismatch", INVALID, "shape [7] with 3 bytes of data",
         _step(lambda ctx: [types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[7], data=b"\x00\x00\x00")])),
    Kind("huge-shape", INVALID, "shape [2^31, 2^31] with no data (a size overflow)",
         _step(lambda ctx: [types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[2**31, 2**31], data=b"")])),
    Kind("negative-shape", INVALID, "shape [-7]",
         _step(lambda ctx: [types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[-7], data=b"")])),
    Kind("action-count", INVALID, "two actions for one session", _step(lambda ctx: [_tensor(ZEROS)] * 2)),
    Kind("stream-nan-action", INVALID, "a NaN action on a StepStream",
         _stream(lambda ctx: [gateway_pb2.StepStreamRequest(session_id=ctx.own, action=_action(np.nan))])),
    # ---- policy specs and episodes -------------------------------------------------------------
    Kind("execute-steps-negative", INVALID, "PolicySpec.execute_steps = -3",
         _policy(types_pb2.PolicySpec(model=MODEL, execute_steps=-3))),
    Kind("execute-steps-huge", INVALID, "PolicySpec.execute_steps = 100000",
         _policy(types_pb2.PolicySpec(model=MODEL, execute_steps=100_000))),
    Kind("timeout-negative", INVALID, "PolicySpec.timeout_ms = -1",
         _call("PolicyInfer", lambda ctx: gateway_pb2.PolicyInferRequest(
             session_ids=[ctx.own], policy=types_pb2.PolicySpec(model=MODEL, timeout_ms=-1)))),
    Kind("max-steps-negative", INVALID, "RunEpisode.max_steps = -1",
         _call("RunEpisode", lambda ctx: gateway_pb2.RunEpisodeRequest(
             session_ids=[ctx.own], policy=types_pb2.PolicySpec(model=MODEL), max_steps=-1))),
    Kind("instruction-huge", INVALID, "a 100,000-character PolicySpec.instruction",
         _policy(types_pb2.PolicySpec(model=MODEL, instruction="x" * 100_000))),
    Kind("reset-instruction-huge", INVALID, "a 100,000-character ResetSpec.instruction",
         _reset(types_pb2.ResetSpec(instruction="y" * 100_000))),
    Kind("unknown-model", "NOT_FOUND", "PolicyStep with a model no policy worker serves",
         _policy(types_pb2.PolicySpec(model="no-such-model"))),
    Kind("unknown-task", INVALID, "Reset with a task the config does not hold",
         _reset(types_pb2.ResetSpec(task="no_such_task"))),
    Kind("unknown-harness", "NOT_FOUND", "Reset with a harness the registry does not hold",
         _reset(types_pb2.ResetSpec(harness="no-such-harness@7"))),
    Kind("reset-spec-count", INVALID, "three reset specs for one session",
         _call("Reset", lambda ctx: gateway_pb2.ResetRequest(session_ids=[ctx.own], specs=[types_pb2.ResetSpec()] * 3))),
    Kind("stream-no-op", INVALID, "a StepStream message with no operation",
         _stream(lambda ctx: [gateway_pb2.StepStreamRequest(session_id=ctx.own)])),
    Kind("stream-no-session", INVALID, "a StepStream whose first message names no session",
         _stream(lambda ctx: [gateway_pb2.StepStreamRequest(observe=gateway_pb2.ObserveOp())])),
    # ---- session creation and options ----------------------------------------------------------
    Kind("empty-family", INVALID, "CreateSessions without env_family",
         _create("", {})),
    Kind("unknown-family", INVALID, "CreateSessions of a family no worker hosts",
         _create("no-such-family", {})),
    Kind("unknown-suite", INVALID, "an env_name (suite) the family does not have",
         _create("robosuite", {"env_name": "NoSuchSuite"})),
    Kind("count-zero", INVALID, "CreateSessions.count = 0", _create("robosuite", LIFT_CONFIG, count=0)),
    Kind("count-huge", INVALID, "CreateSessions.count = 1,000,000", _create("robosuite", LIFT_CONFIG, count=1_000_000)),
    Kind("lease-negative", INVALID, "lease_seconds = -5", _create("robosuite", LIFT_CONFIG, lease=-5)),
    Kind("unknown-option", INVALID, "an env_config key the family does not know",
         _create("robosuite", {"env_name": "Lift", "bogus": 1})),
    Kind("option-wrong-type", INVALID, "camera_size as a string, a nested Struct for max_steps",
         _create("robosuite", {"env_name": "Lift", "camera_size": "big", "max_steps": {"a": [1, None]}})),
    Kind("option-huge", INVALID, "camera_size 1e6 with a camera (a terabyte frame)",
         _create("robosuite", {"env_name": "Lift", "cameras": ["agentview"], "camera_size": 1e6})),
    Kind("option-non-finite", INVALID, "max_steps = NaN",
         _create("robosuite", {"env_name": "Lift", "max_steps": float("nan")})),
    # ---- the wire --------------------------------------------------------------------------------
    Kind("oversized-message", "RESOURCE_EXHAUSTED", "a 17 MiB ActionStep (over ZETTA_MAX_REQUEST_BYTES)",
         _step(lambda ctx: [types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[7], data=_BIG)])),
    Kind("garbage-bytes", INVALID, "bytes that are not a protobuf message",
         _raw("/zetta.v1.GatewayService/PolicyStep", b"\xff\xff\xff\xff\x0f\x0a\xff")),
    Kind("stream-garbage-bytes", INVALID, "a StepStream message that is not protobuf", _raw_stream()),
    Kind("deep-struct", INVALID, "an env_config Struct nested 200 deep (over protobuf's recursion limit)",
         _raw("/zetta.v1.GatewayService/CreateSessions", _deep_struct_request(200))),
    Kind("oversized-metadata", "RESOURCE_EXHAUSTED", "a 20 KB authorization header (over the metadata limit)",
         lambda ctx: (lambda c: c.gw.ListWorkers(gateway_pb2.ListWorkersRequest(), timeout=CALL_TIMEOUT_S,
                                                  metadata=(("authorization", "Bearer " + "y" * 20_000),)))),
    Kind("unknown-method", "UNIMPLEMENTED", "a method the gateway does not have",
         _raw("/zetta.v1.GatewayService/NoSuchMethod", b"")),
]


def kind(name: str) -> Kind:
    """The kind called ``name``."""
    return next(k for k in KINDS if k.name == name)


async def send(ctx: Ctx, k: Kind, prepared: Send | None = None) -> Outcome:
    """Send one request of kind ``k`` and return the status it got."""
    fn = prepared or k.build(ctx)
    start = time.perf_counter()
    try:
        await fn(ctx)
    except grpc.aio.AioRpcError as err:
        return Outcome(k.name, k.expected, err.code().name, err.details() or "", time.perf_counter() - start)
    return Outcome(k.name, k.expected, "OK", "", time.perf_counter() - start)
