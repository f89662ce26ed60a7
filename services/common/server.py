"""The shell every service runs in: gRPC with health and reflection, /metrics, graceful stop.

A service hands over its servicers and a drain hook; this module owns the signal handling so that
every service stops the same way: health turns NOT_SERVING (load balancers stop sending), the
drain hook runs (deregister, finish in-flight episodes), then the server stops with a grace period.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import sys
from collections.abc import Awaitable, Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_health.v1._async import HealthServicer
from grpc_reflection.v1alpha import reflection
from prometheus_client import start_http_server

from services.common.decode_guard import DecodeGuard
from services.common.tls import read_tls, server_credentials
from zetta_wire.channel import MAX_MESSAGE_BYTES

log = logging.getLogger(__name__)


@dataclass
class Registration:
    """A servicer and the function that adds it to a server, with its full service name."""

    add_to_server: Callable[[Any, grpc.aio.Server], None]
    servicer: Any
    service_name: str


@dataclass
class ServiceRunner:
    """Runs one service process until SIGTERM or SIGINT, then drains and stops."""

    name: str
    host: str
    port: int
    metrics_port: int
    registrations: Sequence[Registration]
    grace_seconds: float = 5.0
    #: Largest request this server accepts; a bigger one is refused by gRPC (RESOURCE_EXHAUSTED)
    #: before any handler runs.
    max_receive_bytes: int = MAX_MESSAGE_BYTES
    #: Whether this server requires client certificates when TLS is on (ZETTA_TLS_CLIENT_AUTH
    #: overrides); every service but the gateway, whose clients present tokens instead.
    client_auth_default: bool = True
    on_drain: Callable[[], Awaitable[None]] | None = None
    server: grpc.aio.Server = field(init=False)
    health: HealthServicer = field(init=False)
    bound_port: int = field(init=False, default=0)

    async def start(self) -> None:
        """Bind, start serving and mark every service SERVING."""
        self.server = grpc.aio.server(
            # Undecodable requests: INVALID_ARGUMENT naming the method, not UNKNOWN.
            interceptors=[DecodeGuard()],
            options=[
                ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
                ("grpc.max_receive_message_length", self.max_receive_bytes),
                ("grpc.so_reuseport", 0),
                ("grpc.keepalive_permit_without_calls", 1),
                ("grpc.http2.min_ping_interval_without_data_ms", 5_000),
            ]
        )
        self.health = HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
        names = [health_pb2.DESCRIPTOR.services_by_name["Health"].full_name, reflection.SERVICE_NAME]
        for reg in self.registrations:
            reg.add_to_server(reg.servicer, self.server)
            names.append(reg.service_name)
        reflection.enable_server_reflection(names, self.server)
        tls = read_tls(client_auth_default=self.client_auth_default)
        address = f"{self.host}:{self.port}"
        if tls is None:
            self.bound_port = self.server.add_insecure_port(address)
        else:
            self.bound_port = self.server.add_secure_port(address, server_credentials(tls))
        if self.bound_port == 0:
            raise RuntimeError(f"{self.name}: cannot bind {self.host}:{self.port}")
        if self.metrics_port >= 0:
            start_http_server(self.metrics_port, addr=self.host)
        await self.server.start()
        await self.health.set("", health_pb2.HealthCheckResponse.SERVING)
        for reg in self.registrations:
            await self.health.set(reg.service_name, health_pb2.HealthCheckResponse.SERVING)
        log.info(
            "serving",
            extra={"fields": {"grpc": f"{self.host}:{self.bound_port}", "metrics_port": self.metrics_port,
                              "tls": "off" if tls is None else ("mutual" if tls.client_auth else "server")}},
        )

    async def run_until_signalled(self) -> None:
        """Serve until SIGTERM/SIGINT, then drain and stop."""
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await stop.wait()
        await self.shutdown()

    async def shutdown(self) -> None:
        """NOT_SERVING first, then the drain hook, then stop with the grace period."""
        log.info("draining", extra={"fields": {"grace_seconds": self.grace_seconds}})
        await self.health.enter_graceful_shutdown()
        if self.on_drain is not None:
            try:
                await asyncio.wait_for(self.on_drain(), timeout=self.grace_seconds)
            except Exception:  # a failing drain hook must not block the stop
                log.exception("drain hook failed")
        await self.server.stop(self.grace_seconds)
        log.info("stopped")


def run_service(main: Callable[[], Coroutine[Any, Any, None]], service: str) -> None:
    """Entry point wrapper: configuration errors exit 2 with the message, not a traceback."""
    from services.common.config import ConfigError

    try:
        asyncio.run(main())
    except ConfigError as exc:
        print(f"{service}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        pass
