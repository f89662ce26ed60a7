"""Requests that are not valid protobuf get INVALID_ARGUMENT, not UNKNOWN.

gRPC deserializes a request before any handler runs; when the bytes do not parse (a fuzzer, a
client with mismatched stubs), grpc.aio answers UNKNOWN "Unexpected <class 'DecodeError'>", which
tells the caller nothing it can act on. :class:`DecodeGuard`, a server interceptor every service
installs (services/common/server.py), wraps each method's deserializer: an undecodable message
becomes a marker, and the wrapped handler aborts with INVALID_ARGUMENT naming the method and the
message type before the servicer sees it (for streams: at the message that did not parse).
"""

from __future__ import annotations

import inspect
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import grpc
from google.protobuf.message import DecodeError


class _Undecodable:
    """Stands for a request message that did not parse."""

    __slots__ = ("message",)

    def __init__(self, message: str) -> None:
        self.message = message


def _safe(deserializer: Callable[[bytes], Any], method: str) -> Callable[[bytes], Any]:
    def deserialize(data: bytes) -> Any:
        try:
            return deserializer(data)
        except (DecodeError, RecursionError, ValueError) as exc:  # a corrupt or too deeply nested message
            what = getattr(getattr(deserializer, "__self__", None), "__name__", "request")
            return _Undecodable(f"{method}: the request is not a valid {what} message "
                                f"({type(exc).__name__}: {str(exc)[:200]}); check that client and server use "
                                "the same proto/ definitions")
    return deserialize


async def _checked(requests: AsyncIterator[Any], context: grpc.aio.ServicerContext) -> AsyncIterator[Any]:
    async for request in requests:
        if isinstance(request, _Undecodable):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)
        yield request


def _guard(handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
    """The handler with a safe deserializer and a behaviour that refuses the marker; handlers of a
    kind this cannot wrap without changing how gRPC calls them (synchronous ones) are left as they are."""
    safe = _safe(handler.request_deserializer, method)
    if handler.unary_unary is not None and inspect.iscoroutinefunction(handler.unary_unary):
        uu = handler.unary_unary

        async def unary_unary(request: Any, context: grpc.aio.ServicerContext) -> Any:
            if isinstance(request, _Undecodable):
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)
            return await uu(request, context)

        return handler._replace(request_deserializer=safe, unary_unary=unary_unary)
    if handler.unary_stream is not None and inspect.isasyncgenfunction(handler.unary_stream):
        us = handler.unary_stream

        async def unary_stream(request: Any, context: grpc.aio.ServicerContext) -> AsyncIterator[Any]:
            if isinstance(request, _Undecodable):
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.message)
            async for response in us(request, context):
                yield response

        return handler._replace(request_deserializer=safe, unary_stream=unary_stream)
    for attr in ("stream_unary", "stream_stream"):
        behaviour = getattr(handler, attr)
        if behaviour is None:
            continue
        if inspect.iscoroutinefunction(behaviour):
            async def coro(requests: AsyncIterator[Any], context: grpc.aio.ServicerContext,
                           _b: Callable[..., Awaitable[Any]] = behaviour) -> Any:
                return await _b(_checked(requests, context), context)
            return handler._replace(request_deserializer=safe, **{attr: coro})
        if inspect.isasyncgenfunction(behaviour):
            async def agen(requests: AsyncIterator[Any], context: grpc.aio.ServicerContext,
                           _b: Callable[..., AsyncIterator[Any]] = behaviour) -> AsyncIterator[Any]:
                async for response in _b(_checked(requests, context), context):
                    yield response
            return handler._replace(request_deserializer=safe, **{attr: agen})
    return handler


class DecodeGuard(grpc.aio.ServerInterceptor):  # type: ignore[misc]
    """Server interceptor: undecodable requests get INVALID_ARGUMENT (wrapped handlers are cached)."""

    def __init__(self) -> None:
        self._cache: dict[str, tuple[grpc.RpcMethodHandler, grpc.RpcMethodHandler]] = {}

    async def intercept_service(
        self,
        continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        handler_call_details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(handler_call_details)
        if handler is None or handler.request_deserializer is None:
            return handler
        method = handler_call_details.method
        cached = self._cache.get(method)
        if cached is not None and cached[0] is handler:
            return cached[1]
        guarded = _guard(handler, method)
        self._cache[method] = (handler, guarded)
        return guarded
