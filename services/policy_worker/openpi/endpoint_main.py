"""openpi endpoint process: `python -m services.policy_worker.openpi.endpoint_main` (ZETTA_* variables).

ZETTA_OPENPI_PORT (8000, openpi's default), ZETTA_BIND_HOST (127.0.0.1), ZETTA_POLICY_ADDRESSES
(policy workers, host:port,...; required), ZETTA_OPENPI_MODEL (the worker's default model when
empty), ZETTA_POLICY_TIMEOUT_MS (10000), ZETTA_METRICS_PORT (9105; -1 off). Health: GET /healthz
on the openpi port. Stops on SIGTERM/SIGINT.
"""

from __future__ import annotations

import asyncio
import logging
import signal

from prometheus_client import start_http_server

from services.common.config import ConfigError, EnvReader
from services.common.logs import setup_logging
from services.common.server import run_service
from services.policy_worker.openpi.endpoint import OpenPIEndpoint


async def main() -> None:
    """Serve until signalled."""
    setup_logging("openpi_endpoint")
    env = EnvReader()
    host = env.str("ZETTA_BIND_HOST", "127.0.0.1")
    port = env.int("ZETTA_OPENPI_PORT", 8000, minimum=0, maximum=65535)
    addresses = [a.strip() for a in env.str("ZETTA_POLICY_ADDRESSES", required=True).split(",") if a.strip()]
    model = env.str("ZETTA_OPENPI_MODEL", "")
    timeout = env.int("ZETTA_POLICY_TIMEOUT_MS", 10_000, minimum=1)
    metrics_port = env.int("ZETTA_METRICS_PORT", 9105, minimum=-1, maximum=65535)
    env.finish("openpi endpoint")
    if metrics_port >= 0:
        start_http_server(metrics_port, addr=host)
    endpoint = OpenPIEndpoint(addresses, model, timeout)
    try:
        bound = await endpoint.start(host, port)
    except ValueError as exc:
        raise ConfigError(f"openpi endpoint: {exc}") from None
    logging.getLogger("openpi_endpoint").info("serving openpi clients", extra={"fields": {
        "address": f"{host}:{bound}", "model": endpoint.model, "policy_workers": addresses}})
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    await endpoint.close()


if __name__ == "__main__":
    run_service(main, "openpi_endpoint")
