"""Turning failures into gRPC statuses a person can act on.

Every error a service returns goes through :class:`ServiceError`, so the status code, the message
and the trailing metadata (which sessions failed, when to retry) are set in one place.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Sequence
from typing import Any

import grpc
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError

from zetta_wire.errors import FAILED_SESSIONS_KEY, FAILED_SESSIONS_MORE_KEY, RETRY_AFTER_KEY, parse_error_metadata

#: A Redis outage (refused, reset, timed out, still loading its data) as seen by redis-py.
STORE_ERRORS = (RedisConnectionError, RedisTimeoutError)
#: When a client should retry a call that failed because Redis did not answer.
STORE_RETRY_AFTER_MS = 1000

#: Failed-session ids carried in trailing metadata at most, and their bytes at most: a status must
#: fit the peer's metadata limit (8 KiB by default), or the client sees RESOURCE_EXHAUSTED instead.
MAX_FAILED_IDS = 100
MAX_FAILED_IDS_BYTES = 4096
#: Longest status message; longer ones are cut (they travel as metadata too).
MAX_MESSAGE_CHARS = 2000


def _printable(value: str) -> bool:
    return value.isascii() and value.isprintable() and "," not in value

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
        component: str = "",
    ) -> None:
        if len(message) > MAX_MESSAGE_CHARS:
            message = message[: MAX_MESSAGE_CHARS - 40] + f" ... (cut from {len(message)} characters)"
        super().__init__(message)
        self.code = code
        self.message = message
        self.session_ids = list(session_ids)
        self.retry_after_ms = retry_after_ms
        #: The service that failed when it is not the one answering (``zetta-failed-component``).
        self.component = component

    def trailing_metadata(self) -> tuple[tuple[str, str], ...]:
        """Machine-readable details: failed sessions (bounded; ``zetta-failed-sessions-more`` counts
        the ones left out) and a retry hint."""
        md: list[tuple[str, str]] = []
        if self.session_ids:
            kept: list[str] = []
            size = 0
            for sid in self.session_ids:
                if len(kept) == MAX_FAILED_IDS or size + len(sid) + 1 > MAX_FAILED_IDS_BYTES:
                    break
                if _printable(sid):
                    kept.append(sid)
                    size += len(sid) + 1
            if kept:
                md.append((FAILED_SESSIONS_KEY, ",".join(kept)))
            if len(kept) < len(self.session_ids):
                md.append((FAILED_SESSIONS_MORE_KEY, str(len(self.session_ids) - len(kept))))
        if self.retry_after_ms is not None:
            md.append((RETRY_AFTER_KEY, str(self.retry_after_ms)))
        if self.component:
            md.append(("zetta-failed-component", self.component))
        return tuple(md)

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


def unavailable(message: str, session_ids: Sequence[str] = (), retry_after_ms: int | None = None) -> ServiceError:
    """UNAVAILABLE (with a retry hint when the caller knows when to come back)."""
    return ServiceError(grpc.StatusCode.UNAVAILABLE, message, session_ids, retry_after_ms=retry_after_ms)


def store_unavailable(exc: BaseException) -> ServiceError:
    """A Redis outage as UNAVAILABLE with a retry hint: the call did nothing and may be retried."""
    return ServiceError(
        grpc.StatusCode.UNAVAILABLE,
        f"the session registry (Redis) did not answer ({type(exc).__name__}: {exc}); nothing was done, "
        f"retry in {STORE_RETRY_AFTER_MS} ms",
        retry_after_ms=STORE_RETRY_AFTER_MS,
    )


def failed_component(err: grpc.aio.AioRpcError) -> str:
    """The component a peer's error blames (``zetta-failed-component``); "" when the peer itself failed."""
    return next((v for k, v in err.trailing_metadata() or () if k == "zetta-failed-component"), "")


def from_rpc_error(err: grpc.aio.AioRpcError, what: str, component: str = "") -> ServiceError:
    """Re-raise a downstream error with context, keeping its code, failed sessions and the failed
    component (the peer's own, else ``component``)."""
    details = parse_error_metadata(err.trailing_metadata())
    return ServiceError(err.code(), f"{what}: {err.details()}", details.session_ids, details.retry_after_ms,
                        failed_component(err) or component)


def error_boundary(method: _Handler) -> _Handler:
    """Decorator for async servicer methods: a ServiceError becomes its status, nothing else leaks."""
    import functools

    @functools.wraps(method)
    async def wrapper(self: Any, request: Any, context: Any) -> Any:
        try:
            return await method(self, request, context)
        except ServiceError as exc:
            await exc.abort(context)
        except STORE_ERRORS as exc:
            await store_unavailable(exc).abort(context)

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
            except STORE_ERRORS:
                code = grpc.StatusCode.UNAVAILABLE.name
                raise
            finally:
                hist.observe(time.perf_counter() - start)
                if on_code is not None:
                    on_code(method, code)

        return error_boundary(wrapper)

    return deco


def unauthenticated(message: str) -> ServiceError:
    """UNAUTHENTICATED: no credential, or one nobody issued."""
    return ServiceError(grpc.StatusCode.UNAUTHENTICATED, message)


def permission_denied(message: str, session_ids: Sequence[str] = ()) -> ServiceError:
    """PERMISSION_DENIED: a known caller asking for what is not theirs."""
    return ServiceError(grpc.StatusCode.PERMISSION_DENIED, message, session_ids)
