"""Critic service process: `python -m services.critic.main` (configuration in ZETTA_* variables).

Serves the harness registry (HarnessRegistryService) and the Evaluate stream (CriticService).
"""

from __future__ import annotations

import asyncio
import logging

import redis.asyncio as aioredis

from services.common.config import ConfigError
from services.common.logs import setup_logging
from services.common.server import Registration, ServiceRunner, run_service
from services.harness.runtime.budget import PlatformLimits
from services.harness.sandbox import client as sandbox
from services.harness.sandbox.client import SandboxLimits
from services.critic.config import CriticConfig
from services.harness.package.probe import start_fork_server
from services.harness.package.store import PackageStore
from services.critic.registry import HarnessRegistry
from services.critic.servicer import CriticServicer, HarnessRegistryServicer, PackageCache
from zetta_wire.v1 import critic_pb2, critic_pb2_grpc


async def main() -> None:
    """Open the store and Redis (fail fast if either is unusable), restore pointers, serve."""
    logger = setup_logging("critic")
    cfg = CriticConfig.from_env()
    PlatformLimits.from_env()  # the harness time limits fail fast here, not at the first reset
    SandboxLimits.from_env()
    if not sandbox.enabled():
        logger.warning("ZETTA_HARNESS_SANDBOX=off: harness package code runs inside this process (trusted code only)")
    try:
        store = PackageStore(cfg.store)
        store.check_writable()
    except OSError as exc:
        raise ConfigError(f"critic: ZETTA_CRITIC_STORE={cfg.store} is not a writable directory: {exc}") from None
    client = aioredis.Redis.from_url(cfg.redis_url, socket_timeout=5, socket_connect_timeout=5)
    try:
        await client.ping()
    except Exception as exc:  # noqa: BLE001 - any connection failure is fatal at start-up
        raise ConfigError(f"critic: cannot reach Redis at ZETTA_REDIS_URL={cfg.redis_url}: {exc}") from None
    registry = HarnessRegistry(client, cfg.redis_prefix, store)
    restored = await registry.restore()
    if restored:
        logger.warning("restored registry pointers from the package store", extra={"fields": {"versions": restored}})
    service = critic_pb2.DESCRIPTOR.services_by_name
    runner = ServiceRunner(
        name="critic",
        host=cfg.host,
        port=cfg.port,
        metrics_port=cfg.metrics_port,
        registrations=[
            Registration(
                critic_pb2_grpc.add_HarnessRegistryServiceServicer_to_server,
                HarnessRegistryServicer(registry, cfg),
                service["HarnessRegistryService"].full_name,
            ),
            Registration(
                critic_pb2_grpc.add_CriticServiceServicer_to_server,
                CriticServicer(registry, PackageCache(registry, cfg.package_cache, cfg.max_package_bytes)),
                service["CriticService"].full_name,
            ),
        ],
        grace_seconds=cfg.grace_seconds,
    )
    await runner.start()
    await asyncio.to_thread(start_fork_server)
    logging.getLogger("critic").info(
        "ready", extra={"fields": {"redis": cfg.redis_url, "prefix": cfg.redis_prefix, "store": cfg.store}}
    )
    try:
        await runner.run_until_signalled()
    finally:
        await client.aclose()


if __name__ == "__main__":
    run_service(main, "critic")
