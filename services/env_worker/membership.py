"""Registration and heartbeats of an env worker with the gateway.

The gateway is the only writer of the registry; the worker tells it who it is, which sessions it
still holds (after a gateway restart) and that it is alive. When the registry says it no longer
knows the worker (it was declared dead), the worker registers again and drops every slot the
registry did not let it keep: those sessions are LOST for their clients already.

Heartbeats carry the busy lease the worker's slots hold (services/env_worker/busy.py): a slot
about to hold the GIL has a heartbeat sent at once (:meth:`Membership.announce`), and one more
when it is done (:meth:`Membership.wake`). Heartbeats are sent one at a time, each with the
leases held when it leaves, so an older heartbeat without the lease never lands after the one
that announced it.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
from collections.abc import Callable, Sequence

import grpc

from services.common.tasks import cancel_and_wait
from services.common.tls import aio_channel
from zetta_wire.channel import CHANNEL_OPTIONS
from services.env_worker.busy import ACK_WAIT_S, LEASES, BusyLeases
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
        leases: BusyLeases = LEASES,
    ) -> None:
        self.cfg = config
        self.leases = leases
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
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._wake: asyncio.Event | None = None
        self._sending: asyncio.Lock | None = None

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
        """Heartbeat in the background; from now on busy leases are announced through this worker."""
        self._loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self._wake = asyncio.Event()
        self._sending = asyncio.Lock()
        self._task = asyncio.create_task(self._beat())
        self.leases.install(self)

    async def _beat(self) -> None:
        assert self._wake is not None
        while True:
            try:
                await asyncio.wait_for(self._wake.wait(), self._interval_s)
            except TimeoutError:
                pass
            self._wake.clear()
            resp = await self._heartbeat()
            if resp is not None and not resp.known:
                log.warning("registry declared this worker dead; registering again")
                await self.register()

    async def _heartbeat(self, timeout_s: float = 0.0) -> registry_pb2.HeartbeatResponse | None:
        """One heartbeat with the busy lease held now; None when it failed."""
        assert self._sending is not None
        async with self._sending:
            busy_ms = self.leases.remaining_ms()
            try:
                return await self._stub.Heartbeat(
                    registry_pb2.HeartbeatRequest(worker_id=self.cfg.worker_id, busy_ms=busy_ms),
                    timeout=max(self._interval_s, 0.5, timeout_s), metadata=self._md,
                )
            except grpc.aio.AioRpcError as err:
                log.warning("heartbeat failed", extra={"fields": {"error": err.code().name, "busy_ms": busy_ms}})
                return None

    async def _announce(self) -> int:
        resp = await self._heartbeat(ACK_WAIT_S)
        if resp is None:
            return 0
        if not resp.known and self._wake is not None:
            self._wake.set()  # the beat loop registers again
        return resp.busy_ms

    def announce(self) -> concurrent.futures.Future[int] | None:
        """From a slot thread: send a heartbeat with the current busy lease now (busy.Announcer)."""
        if self._loop is None or threading.get_ident() == self._loop_thread:
            return None
        return asyncio.run_coroutine_threadsafe(self._announce(), self._loop)

    def wake(self) -> None:
        """From any thread: heartbeat soon (a lease ended, so the gateway learns it at once)."""
        if self._loop is None or self._wake is None:
            return
        if threading.get_ident() == self._loop_thread:
            self._wake.set()
        else:
            self._loop.call_soon_threadsafe(self._wake.set)

    async def stop(self, deregister: bool) -> None:
        """Stop heartbeating; deregister so the gateway stops routing here at once."""
        self.leases.install(None)
        await cancel_and_wait(self._task)
        if deregister:
            try:
                await self._stub.DeregisterWorker(
                    registry_pb2.DeregisterWorkerRequest(worker_id=self.cfg.worker_id), timeout=2, metadata=self._md
                )
            except grpc.aio.AioRpcError as err:
                log.warning("deregistration failed", extra={"fields": {"error": err.code().name}})
        await self._channel.close()
