"""Evolver service process: `python -m services.evolver.main` (configuration in ZETTA_* variables).

Runs evolution jobs (services/evolver/jobs.py) against the stack's gateway and critic service,
serving EvolverService with health, reflection, /metrics and a graceful drain that cancels running
jobs after their finished rollouts are filed.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import grpc

from services.common.config import ConfigError
from services.common.logs import setup_logging
from services.common.server import Registration, ServiceRunner, run_service
from services.common.tls import sync_channel
from services.evolver.config import EvolverConfig
from services.evolver.jobs import JobManager
from services.evolver.servicer import EvolverServicer
from zetta_wire.v1 import evolver_pb2, evolver_pb2_grpc


def _reachable(address: str, what: str, variable: str) -> None:
    """Fail fast when a dependency does not answer: a job would only fail later, less clearly."""
    try:
        with sync_channel(address) as ch:
            grpc.channel_ready_future(ch).result(timeout=10)
    except grpc.FutureTimeoutError:
        raise ConfigError(f"evolver: the {what} at {variable}={address} does not answer") from None


async def main() -> None:
    """Check configuration and dependencies, then serve until SIGTERM/SIGINT and drain."""
    setup_logging("evolver")
    cfg = EvolverConfig.from_env()
    store = Path(cfg.store)
    try:
        store.mkdir(parents=True, exist_ok=True)
        probe = store / ".write-probe"
        probe.write_text("ok")
        probe.unlink()
    except OSError as exc:
        raise ConfigError(f"evolver: ZETTA_EVOLVER_STORE={cfg.store} is not a writable directory: {exc}") from None
    await asyncio.to_thread(_reachable, cfg.gateway, "gateway", "ZETTA_GATEWAY_ADDRESS")
    await asyncio.to_thread(_reachable, cfg.registry, "critic service", "ZETTA_CRITIC_ADDR")
    jobs = JobManager(store, cfg.gateway, cfg.registry, cfg.max_jobs, cfg.policy_worker)

    async def drain() -> None:
        await asyncio.to_thread(jobs.drain, max(0.0, cfg.grace_seconds - 1.0))

    runner = ServiceRunner(
        name="evolver", host=cfg.host, port=cfg.port, metrics_port=cfg.metrics_port,
        registrations=[Registration(evolver_pb2_grpc.add_EvolverServiceServicer_to_server, EvolverServicer(jobs),
                                    evolver_pb2.DESCRIPTOR.services_by_name["EvolverService"].full_name)],
        grace_seconds=cfg.grace_seconds, on_drain=drain,
    )
    await runner.start()
    logging.getLogger("evolver").info("ready", extra={"fields": {"gateway": cfg.gateway, "registry": cfg.registry,
                                                                  "store": cfg.store, "jobs": len(jobs.jobs)}})
    await runner.run_until_signalled()


if __name__ == "__main__":
    run_service(main, "evolver")
