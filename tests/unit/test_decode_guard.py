"""A request that is not valid protobuf gets INVALID_ARGUMENT naming the method (found by the
control-plane fuzz, bench/bench_fuzz.py: grpc.aio answered UNKNOWN "Unexpected <class
'DecodeError'>"), on unary calls and on streams, and valid requests pass unchanged."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Any

import grpc
import pytest

from services.common.decode_guard import DecodeGuard
from zetta_wire.v1 import gateway_pb2

GARBAGE = b"\xff\xff\xff\xff\x0f\x0a\xff"


async def _unary(request: gateway_pb2.ObserveRequest, context: Any) -> gateway_pb2.ObserveResponse:
    return gateway_pb2.ObserveResponse()


async def _stream(requests: AsyncIterator[gateway_pb2.StepStreamRequest], context: Any
                  ) -> AsyncIterator[gateway_pb2.StepStreamResponse]:
    async for _ in requests:
        yield gateway_pb2.StepStreamResponse()


@pytest.fixture
async def address() -> AsyncIterator[str]:
    server = grpc.aio.server(interceptors=[DecodeGuard()])
    server.add_generic_rpc_handlers([grpc.method_handlers_generic_handler("t.S", {
        "U": grpc.unary_unary_rpc_method_handler(_unary, gateway_pb2.ObserveRequest.FromString,
                                                 gateway_pb2.ObserveResponse.SerializeToString),
        "B": grpc.stream_stream_rpc_method_handler(_stream, gateway_pb2.StepStreamRequest.FromString,
                                                   gateway_pb2.StepStreamResponse.SerializeToString),
    })])
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        await server.stop(0)


async def test_unary_garbage_is_invalid_argument(address: str) -> None:
    async with grpc.aio.insecure_channel(address) as channel:
        call = channel.unary_unary("/t.S/U")
        assert await call(gateway_pb2.ObserveRequest(session_ids=["a"]).SerializeToString(), timeout=5) == b""
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await call(GARBAGE, timeout=5)
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "/t.S/U" in (err.value.details() or "") and "ObserveRequest" in (err.value.details() or "")


async def test_stream_garbage_is_invalid_argument_at_that_message(address: str) -> None:
    async with grpc.aio.insecure_channel(address) as channel:
        call = channel.stream_stream("/t.S/B")(timeout=5)
        await call.write(gateway_pb2.StepStreamRequest(session_id="a").SerializeToString())
        assert await call.read() == b""
        await call.write(GARBAGE)
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await call.read()
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "StepStreamRequest" in (err.value.details() or "")
