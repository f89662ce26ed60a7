"""Gateway process: `python -m services.gateway.main` (configuration in ZETTA_* variables)."""

from __future__ import annotations

import logging

import redis.asyncio as aioredis

from services.common.config import ConfigError
from services.common.logs import setup_logging
from services.common.server import Registration, ServiceRunner, run_service
from services.gateway.auth import Authenticator, read_tokens_file
from services.gateway.config import GatewayConfig
from services.gateway.monitor import Monitor
from services.gateway.registry import Registry
from services.gateway.registry_servicer import WorkerRegistryServicer
from services.gateway.servicer import GatewayServicer
from services.gateway.vantage import Vantage
from services.gateway.workers import WorkerPool
from zetta_wire.v1 import gateway_pb2, gateway_pb2_grpc, registry_pb2, registry_pb2_grpc


def redact(url: str) -> str:
    """A Redis URL without its password, for logs."""
    head, at, tail = url.rpartition("@")
    if not at:
        return url
    scheme, _, _ = head.partition("//")
    return f"{scheme}//***@{tail}"


async def main() -> None:
    """Connect to Redis (fail fast if it is not there), serve, and run the monitor."""
    setup_logging("gateway")
    cfg = GatewayConfig.from_env()
    client = aioredis.Redis.from_url(cfg.redis_url, socket_timeout=5, socket_connect_timeout=5)
    try:
        await client.ping()
    except Exception as exc:  # noqa: BLE001 - any connection failure is fatal at start-up
        raise ConfigError(f"gateway: cannot reach Redis at ZETTA_REDIS_URL={redact(cfg.redis_url)}: {exc}") from None
    registry = Registry(client, cfg.redis_prefix, cfg.tombstone_seconds)
    await registry.start_epoch()
    pool = WorkerPool(registry)
    auth = Authenticator(read_tokens_file(cfg.auth_tokens_file) if cfg.auth_tokens_file else None)
    gateway = GatewayServicer(registry, pool, cfg, auth)
    vantage = Vantage()
    monitor = Monitor(registry, gateway, cfg, vantage)

    async def drain() -> None:
        await monitor.stop()

    runner = ServiceRunner(
        name="gateway",
        host=cfg.host,
        port=cfg.port,
        metrics_port=cfg.metrics_port,
        registrations=[
            Registration(
                gateway_pb2_grpc.add_GatewayServiceServicer_to_server,
                gateway,
                gateway_pb2.DESCRIPTOR.services_by_name["GatewayService"].full_name,
            ),
            Registration(
                registry_pb2_grpc.add_WorkerRegistryServiceServicer_to_server,
                WorkerRegistryServicer(registry, pool, cfg, vantage, auth),
                registry_pb2.DESCRIPTOR.services_by_name["WorkerRegistryService"].full_name,
            ),
        ],
        grace_seconds=cfg.grace_seconds,
        max_receive_bytes=cfg.max_request_bytes,
        client_auth_default=False,
        on_drain=drain,
    )
    await runner.start()
    monitor.start()
    logger = logging.getLogger("gateway")
    logger.info("ready", extra={"fields": {"redis": redact(cfg.redis_url), "prefix": cfg.redis_prefix,
                                           "auth": "tokens" if auth.enabled else "off"}})
    if not auth.enabled:
        logger.warning("auth is off (ZETTA_AUTH_TOKENS_FILE unset): any caller that reaches %s:%s may use, close "
                       "and list every session and register workers; keep it on loopback (docs/security.md)",
                       cfg.host, runner.bound_port)
    try:
        await runner.run_until_signalled()
    finally:
        await pool.close()
        await client.aclose()


if __name__ == "__main__":
    run_service(main, "gateway")
