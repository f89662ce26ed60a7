"""Turning failures into gRPC statuses a person can act on.

Every error a service returns goes through :class:`ServiceError`, so the status code, the message
and the trailing metadata (which sessions failed, when to retry) are set in one place.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import grpc

from zetta_wire.errors import error_metadata, parse_error_metadata

#: An async servicer method: (self, request, context) -> response.
_Handler = Callable[[Any, Any, Any], Awaitable[Any]]


class ServiceError(Exception):
    """An error with its gRPC status code and the sessions it concerns."""

    def __init__(
        self,
        code: grpc.StatusCode,
        message: str,
        session_ids: Sequence[str] = (),
        retry_after_ms: int | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.session_ids = list(session_ids)
        self.retry_after_ms = retry_after_ms

    def trailing_metadata(self) -> tuple[tuple[str, str], ...]:
        """Machine-readable details: failed sessions and a retry hint."""
        return error_metadata(self.session_ids, self.retry_after_ms)

    async def abort(self, context: grpc.aio.ServicerContext) -> None:
        """End the call with this error."""
        context.set_trailing_metadata(self.trailing_metadata())
        await context.abort(self.code, self.message)


def invalid(message: str, session_ids: Sequence[str] = ()) -> ServiceError:
    """INVALID_ARGUMENT."""
    return ServiceError(grpc.StatusCode.INVALID_ARGUMENT, message, session_ids)


def not_found(message: str, session_ids: Sequence[str] = ()) -> ServiceError:
    """NOT_FOUND."""
    return ServiceError(grpc.StatusCode.NOT_FOUND, message, session_ids)


def failed_precondition(message: str, session_ids: Sequence[str] = ()) -> ServiceError:
    """FAILED_PRECONDITION."""
    return ServiceError(grpc.StatusCode.FAILED_PRECONDITION, message, session_ids)


def exhausted(message: str, retry_after_ms: int) -> ServiceError:
    """RESOURCE_EXHAUSTED with a retry hint."""
    return ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED, message, retry_after_ms=retry_after_ms)


def unavailable(message: str, session_ids: Sequence[str] = ()) -> ServiceError:
    """UNAVAILABLE."""
    return ServiceError(grpc.StatusCode.UNAVAILABLE, message, session_ids)


def from_rpc_error(err: grpc.aio.AioRpcError, what: str) -> ServiceError:
    """Re-raise a downstream error with context, keeping its code and failed sessions."""
    details = parse_error_metadata(err.trailing_metadata())
    return ServiceError(err.code(), f"{what}: {err.details()}", details.session_ids, details.retry_after_ms)


def error_boundary(method: _Handler) -> _Handler:
    """Decorator for async servicer methods: a ServiceError becomes its status, nothing else leaks."""
    import functools

    @functools.wraps(method)
    async def wrapper(self: Any, request: Any, context: Any) -> Any:
        try:
            return await method(self, request, context)
        except ServiceError as exc:
            await exc.abort(context)

    return wrapper


def timed_unary(service: str, method: str,
                on_code: Callable[[str, str], None] | None = None) -> Callable[[_Handler], _Handler]:
    """Decorator for unary async servicer methods: the hop latency (zetta_hop_latency_seconds) of
    every call, the status code handed to ``on_code`` (a per-service request counter), and the
    :func:`error_boundary` around it, so every service records its hop the same way."""
    import functools
    import time

    from services.common.metrics import HOP_LATENCY

    hist = HOP_LATENCY.labels(service, method)

    def deco(fn: _Handler) -> _Handler:
        @functools.wraps(fn)
        async def wrapper(self: Any, request: Any, context: Any) -> Any:
            start = time.perf_counter()
            code = "OK"
            try:
                return await fn(self, request, context)
            except ServiceError as exc:
                code = exc.code.name
                raise
            finally:
                hist.observe(time.perf_counter() - start)
                if on_code is not None:
                    on_code(method, code)

        return error_boundary(wrapper)

    return deco
