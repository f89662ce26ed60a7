"""Background duties of the gateway: dead-worker detection, lease expiry, session gauges.

A worker is dead when its heartbeat key expired: the key lives the heartbeat timeout after each
heartbeat, or until the end of the busy lease that heartbeat asked for when that is later
(services/env_worker/busy.py), so the judgment is max(last heartbeat + timeout, lease end).

Every gateway replica runs these loops; the Lua scripts they call re-check their condition
atomically, so two replicas racing on the same worker or lease do the work once.
"""

from __future__ import annotations

import asyncio
import logging
import time

from services.common.grpc_errors import STORE_ERRORS
from services.common.tasks import cancel_and_wait
from services.gateway import metrics
from services.gateway.config import GatewayConfig
from services.gateway.registry import CREATE, LOST, RUNNING, TERMINATED, Registry, WorkerRecord, now_ms
from services.gateway.servicer import GatewayServicer
from services.gateway.vantage import Vantage

log = logging.getLogger(__name__)

#: Sessions are counted for the gauges this often, not on every tick: it scans the registry.
GAUGE_PERIOD_S = 5.0


class Monitor:
    """Runs the periodic checks until stopped."""

    def __init__(self, registry: Registry, gateway: GatewayServicer, config: GatewayConfig,
                 vantage: Vantage | None = None) -> None:
        self.registry = registry
        self.gateway = gateway
        self.cfg = config
        self.vantage = vantage or Vantage()
        self._task: asyncio.Task[None] | None = None

    def start(self) -> None:
        """Start the loop in the background."""
        # Heartbeat keys also expire while no gateway runs to refresh them (a gateway restart):
        # give every worker one full timeout after this gateway started before declaring it dead.
        self.vantage.restart()
        self._task = asyncio.create_task(self._run())

    async def stop(self) -> None:
        """Stop the loop and wait for it."""
        await cancel_and_wait(self._task)

    async def _run(self) -> None:
        last_gauges = 0.0
        loop = asyncio.get_running_loop()
        interval_s = self.cfg.monitor_interval_ms / 1000
        slack_s = self._slack_ms() / 1000
        while True:
            woke = loop.time()
            try:
                await self.check_workers()
                await self.expire_leases()
                if loop.time() - last_gauges >= GAUGE_PERIOD_S:
                    await self.update_gauges()
                    last_gauges = loop.time()
            except STORE_ERRORS as exc:
                self.vantage.blind(f"redis: {type(exc).__name__}: {exc}")
            except Exception:
                log.exception("monitor tick failed")
            await asyncio.sleep(interval_s)
            late = loop.time() - woke - interval_s
            if late > slack_s:
                self.vantage.blind(f"stall: the monitor ran {late:.2f} s late (event loop or Redis busy)")

    def _slack_ms(self) -> int:
        """How long the gateway may be stalled or Redis slow before a heartbeat sent on time could
        have missed its key's expiry: the key lives a timeout and the worker writes it every interval."""
        return self.cfg.heartbeat_timeout_ms - self.cfg.heartbeat_interval_ms

    async def check_workers(self) -> list[str]:
        """Declare workers without a heartbeat dead; returns the sessions that became LOST."""
        lost_all: list[str] = []
        asked = time.monotonic()
        workers = await self.registry.workers()
        took_ms = (time.monotonic() - asked) * 1000
        if took_ms > self._slack_ms():
            self.vantage.blind(f"slow redis: reading the workers took {took_ms:.0f} ms")
        judging = self.vantage.may_judge(self.cfg.heartbeat_timeout_ms)
        now = now_ms()
        for w in workers:
            if w.alive:
                # Inside a busy lease silence is announced, not missed.
                if now - w.last_hb_ms > 1.5 * self.cfg.heartbeat_interval_ms and now >= w.busy_until_ms:
                    metrics.MISSED_HEARTBEATS.labels(w.worker_id).inc()
                continue
            if not judging:
                continue
            lost = await self.registry.mark_dead(w.worker_id, self.death_reason(w))
            if lost is None:
                continue
            metrics.WORKERS_DEAD.inc()
            metrics.SESSIONS_LOST.inc(len(lost))
            metrics.FREE_SLOTS.labels(w.worker_id).set(0)
            log.warning("worker declared dead", extra={"fields": {"worker": w.worker_id, "lost_sessions": lost}})
            lost_all.extend(lost)
        return lost_all

    def death_reason(self, w: WorkerRecord) -> str:
        """Why a silent worker's sessions are LOST (a busy lease that ran out is named)."""
        reason = f"env worker {w.worker_id} missed its heartbeats for {self.cfg.heartbeat_timeout_ms} ms"
        busy_ms = w.busy_until_ms - w.last_hb_ms
        if w.busy_until_ms and busy_ms > self.cfg.heartbeat_timeout_ms:
            reason = f"env worker {w.worker_id} sent no heartbeat within its busy lease of {busy_ms} ms"
        return reason

    async def expire_leases(self) -> list[str]:
        """Close every session whose lease ran out and free its slot."""
        expired = await self.registry.expired_leases()
        if not expired:
            return []
        closed, _ = await self.gateway.close_sessions(expired, "lease expired")
        if closed:
            metrics.LEASES_EXPIRED.inc(len(closed))
            log.info("leases expired", extra={"fields": {"sessions": closed}})
        return closed

    async def update_gauges(self) -> None:
        """Sessions by family and state, workers by health, free slots per worker."""
        tally = await self.registry.count_by_family_state()
        workers = await self.registry.workers()
        families = {f for f, _ in tally} | {f for w in workers for f in w.families}
        for fam in families:
            for state in (CREATE, RUNNING, TERMINATED, LOST):
                metrics.SESSIONS.labels(fam, state).set(tally.get((fam, state), 0))
        metrics.WORKERS.labels("alive").set(sum(w.alive for w in workers))
        metrics.WORKERS.labels("dead").set(sum(not w.alive for w in workers))
        for w in workers:
            metrics.FREE_SLOTS.labels(w.worker_id).set(w.free if w.alive else 0)

