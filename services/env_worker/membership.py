"""Registration and heartbeats of an env worker with the gateway.

The gateway is the only writer of the registry; the worker tells it who it is, which sessions it
still holds (after a gateway restart) and that it is alive. When the registry says it no longer
knows the worker (it was declared dead), the worker registers again and drops every slot the
registry did not let it keep: those sessions are LOST for their clients already.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Sequence

import grpc

from services.common.tasks import cancel_and_wait
from services.common.tls import aio_channel
from zetta_wire.channel import CHANNEL_OPTIONS
from services.env_worker.config import EnvWorkerConfig
from zetta_wire.v1 import registry_pb2, registry_pb2_grpc

log = logging.getLogger(__name__)


class Membership:
    """Keeps this worker registered until stopped."""

    def __init__(
        self,
        config: EnvWorkerConfig,
        held_sessions: Callable[[], Sequence[str]],
        drop_others: Callable[[Sequence[str]], Sequence[str]],
    ) -> None:
        self.cfg = config
        self._held = held_sessions
        self._drop_others = drop_others
        # Reconnect quickly after a gateway restart: gRPC's default backoff (1 s growing to 120 s)
        # would outlast the heartbeat timeout and get this worker's sessions declared LOST.
        self._channel = aio_channel(
            config.gateway_address,
            options=[*CHANNEL_OPTIONS, ("grpc.initial_reconnect_backoff_ms", 100), ("grpc.max_reconnect_backoff_ms", 500)],
        )
        self._stub = registry_pb2_grpc.WorkerRegistryServiceStub(self._channel)
        self._md = (("authorization", f"Bearer {config.worker_token}"),) if config.worker_token else ()
        self._interval_s = 1.0
        self._task: asyncio.Task[None] | None = None

    async def register(self) -> None:
        """Register, retrying with back-off until the gateway answers."""
        delay = 0.1
        while True:
            try:
                resp = await self._stub.RegisterWorker(
                    registry_pb2.RegisterWorkerRequest(
                        worker_id=self.cfg.worker_id,
                        address=self.cfg.advertise_address,
                        env_families=list(self.cfg.families),
                        slots=self.cfg.slots,
                        session_ids=list(self._held()),
                    ),
                    timeout=5,
                    metadata=self._md,
                )
            except grpc.aio.AioRpcError as err:
                if err.code() in (grpc.StatusCode.UNAUTHENTICATED, grpc.StatusCode.PERMISSION_DENIED):
                    log.error("the gateway refused this worker's credential (ZETTA_WORKER_TOKEN); retrying",
                              extra={"fields": {"gateway": self.cfg.gateway_address, "error": err.details()}})
                    await asyncio.sleep(2.0)
                    continue
                log.warning(
                    "gateway not reachable, retrying",
                    extra={"fields": {"gateway": self.cfg.gateway_address, "error": err.code().name, "retry_s": delay}},
                )
                await asyncio.sleep(delay)
                delay = min(delay * 2, 2.0)
                continue
            self._interval_s = resp.heartbeat_interval_ms / 1000.0
            dropped = self._drop_others(list(resp.session_ids))
            log.info(
                "registered",
                extra={"fields": {"worker": self.cfg.worker_id, "address": self.cfg.advertise_address,
                                  "kept": len(resp.session_ids), "dropped": len(dropped)}},
            )
            return

    def start(self) -> None:
        """Heartbeat in the background."""
        self._task = asyncio.create_task(self._beat())

    async def _beat(self) -> None:
        while True:
            await asyncio.sleep(self._interval_s)
            try:
                resp = await self._stub.Heartbeat(
                    registry_pb2.HeartbeatRequest(worker_id=self.cfg.worker_id), timeout=max(self._interval_s, 0.5),
                    metadata=self._md,
                )
            except grpc.aio.AioRpcError as err:
                log.warning("heartbeat failed", extra={"fields": {"error": err.code().name}})
                continue
            if not resp.known:
                log.warning("registry declared this worker dead; registering again")
                await self.register()

    async def stop(self, deregister: bool) -> None:
        """Stop heartbeating; deregister so the gateway stops routing here at once."""
        await cancel_and_wait(self._task)
        if deregister:
            try:
                await self._stub.DeregisterWorker(
                    registry_pb2.DeregisterWorkerRequest(worker_id=self.cfg.worker_id), timeout=2, metadata=self._md
                )
            except grpc.aio.AioRpcError as err:
                log.warning("deregistration failed", extra={"fields": {"error": err.code().name}})
        await self._channel.close()
