"""WorkerRegistryService: env workers register and heartbeat through the gateway."""

from __future__ import annotations

import logging

from services.common import grpc_errors as ge
from services.common.grpc_errors import error_boundary
from services.gateway import metrics
from services.gateway.auth import Authenticator
from services.gateway.config import GatewayConfig
from services.gateway.registry import Registry
from services.gateway.vantage import Vantage
from services.gateway.workers import WorkerPool
from zetta_wire.v1 import registry_pb2, registry_pb2_grpc

log = logging.getLogger(__name__)


class WorkerRegistryServicer(registry_pb2_grpc.WorkerRegistryServiceServicer):
    """Writes worker records and heartbeat keys; the monitor reads them."""

    def __init__(self, registry: Registry, pool: WorkerPool, config: GatewayConfig,
                 vantage: Vantage | None = None, auth: Authenticator | None = None) -> None:
        self.registry = registry
        self.pool = pool
        self.cfg = config
        self.vantage = vantage or Vantage()
        self.auth = auth or Authenticator()

    @error_boundary
    async def RegisterWorker(self, request, context) -> registry_pb2.RegisterWorkerResponse:
        self.auth.worker(context)
        if not request.worker_id or not request.address:
            raise ge.invalid("worker_id and address are required")
        if request.slots < 1:
            raise ge.invalid(f"slots must be >= 1, got {request.slots}")
        if not request.env_families:
            raise ge.invalid("env_families is empty: a worker must host at least one family")
        await self.pool.update(request.worker_id, request.address)
        kept = await self.registry.register_worker(
            request.worker_id,
            request.address,
            list(request.env_families),
            request.slots,
            list(request.session_ids),
            self.cfg.heartbeat_timeout_ms,
        )
        log.info(
            "worker registered",
            extra={"fields": {"worker": request.worker_id, "address": request.address, "slots": request.slots,
                              "kept_sessions": len(kept), "held_sessions": len(request.session_ids)}},
        )
        return registry_pb2.RegisterWorkerResponse(heartbeat_interval_ms=self.cfg.heartbeat_interval_ms, session_ids=kept)

    @error_boundary
    async def Heartbeat(self, request, context) -> registry_pb2.HeartbeatResponse:
        self.auth.worker(context)
        busy_ms = self.busy_lease_ms(request.busy_ms)
        try:
            known = await self.registry.heartbeat(request.worker_id, self.cfg.heartbeat_timeout_ms, busy_ms)
        except ge.STORE_ERRORS as exc:
            self.vantage.blind(f"redis: a heartbeat of {request.worker_id} could not be written: {exc}")
            raise
        if busy_ms and known:
            metrics.BUSY_LEASES.labels("capped" if busy_ms < request.busy_ms else "granted").inc()
            log.debug("busy lease", extra={"fields": {"worker": request.worker_id, "busy_ms": busy_ms,
                                                      "asked_ms": request.busy_ms}})
        return registry_pb2.HeartbeatResponse(known=known, busy_ms=busy_ms if known else 0)

    def busy_lease_ms(self, asked_ms: int) -> int:
        """The busy lease a heartbeat gets: the one it asked for, at most ZETTA_HEARTBEAT_MAX_BUSY_MS.

        A lease shorter than the heartbeat timeout changes nothing and is kept as asked (the key
        lives the longer of the two); a negative one is refused.
        """
        if asked_ms < 0:
            raise ge.invalid(f"busy_ms must be >= 0, got {asked_ms}")
        return min(asked_ms, self.cfg.heartbeat_max_busy_ms)

    @error_boundary
    async def DeregisterWorker(self, request, context) -> registry_pb2.DeregisterWorkerResponse:
        self.auth.worker(context)
        lost = await self.registry.deregister(request.worker_id)
        log.info("worker deregistered", extra={"fields": {"worker": request.worker_id, "lost_sessions": len(lost)}})
        return registry_pb2.DeregisterWorkerResponse()
