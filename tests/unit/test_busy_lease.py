"""Busy leases (issue #21 item 4): a worker is declared dead only on evidence about the worker.

The gateway side: a heartbeat's busy lease keeps a silent worker alive until the lease ends, is
capped at ZETTA_HEARTBEAT_MAX_BUSY_MS, refused when negative, and ended by the next heartbeat
without one. The judgment is the registry's heartbeat key (Redis TTLs), so it runs against a
private redis-server with short timeouts. The worker side: the context manager announces, waits
briefly for the acknowledgement and never blocks when nothing can answer.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import shutil
import threading
import time
from collections.abc import AsyncIterator, Iterator
from typing import Any

import grpc
import pytest

from services.env_worker import busy as busy_mod
from services.env_worker.busy import BusyLeases
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.membership import Membership
from services.gateway.config import GatewayConfig
from services.gateway.monitor import Monitor
from services.gateway.registry import Registry
from services.gateway.registry_servicer import WorkerRegistryServicer
from services.gateway.vantage import Vantage
from tests.conftest import private_registry
from zetta_wire.v1 import registry_pb2

TIMEOUT_MS = 300


def gateway_config(**env: str) -> GatewayConfig:
    return GatewayConfig.from_env({"ZETTA_REDIS_URL": "redis://x:1", "ZETTA_HEARTBEAT_INTERVAL_MS": "100",
                                   "ZETTA_HEARTBEAT_TIMEOUT_MS": str(TIMEOUT_MS), **env})


# ---------------------------------------------------------------------------------------------
# Gateway: the judgment


@pytest.fixture
async def registry() -> AsyncIterator[Registry]:
    server = shutil.which("redis-server")
    if server is None:
        pytest.skip("redis-server is not installed")
    async with private_registry(server) as reg:
        yield reg


class _Sighted(Vantage):
    """A gateway that has been able to judge for a long time (no restart, no Redis trouble)."""

    def may_judge(self, heartbeat_timeout_ms: int) -> bool:
        return True


async def _worker_with_session(registry: Registry, worker: str = "env-0") -> str:
    await registry.register_worker(worker, "127.0.0.1:1", ["robosuite"], 2, [], TIMEOUT_MS)
    [(sid, where)] = await registry.allocate("robosuite", 1, 60_000, {})
    assert where == worker
    return sid


async def test_a_silent_worker_inside_its_lease_is_alive_and_dead_after_it(registry: Registry) -> None:
    cfg = gateway_config()
    monitor = Monitor(registry, gateway=None, config=cfg, vantage=_Sighted())  # type: ignore[arg-type]
    sid = await _worker_with_session(registry)
    assert await registry.heartbeat("env-0", TIMEOUT_MS, busy_ms=1200)
    started = time.monotonic()
    # Silent for twice the heartbeat timeout, but inside the lease: alive, its session untouched.
    await asyncio.sleep(2 * TIMEOUT_MS / 1000)
    assert await monitor.check_workers() == []
    [w] = await registry.workers()
    assert w.alive and w.busy_until_ms - w.last_hb_ms == 1200
    [rec] = await registry.lookup([sid])
    assert rec is not None and rec.state == "CREATE"
    # Still silent when the lease ends: dead, the session LOST, the reason names the lease.
    await asyncio.sleep(max(0.0, 1.2 - (time.monotonic() - started)) + 0.15)
    assert await monitor.check_workers() == [sid]
    [rec] = await registry.lookup([sid])
    assert rec is not None and rec.state == "LOST"
    assert "busy lease of 1200 ms" in rec.reason and "heartbeat" in rec.reason


async def test_a_heartbeat_without_a_lease_ends_it(registry: Registry) -> None:
    monitor = Monitor(registry, gateway=None, config=gateway_config(), vantage=_Sighted())  # type: ignore[arg-type]
    sid = await _worker_with_session(registry)
    assert await registry.heartbeat("env-0", TIMEOUT_MS, busy_ms=5000)
    assert await registry.heartbeat("env-0", TIMEOUT_MS)  # the stall is over
    [w] = await registry.workers()
    assert w.busy_until_ms == 0
    await asyncio.sleep(TIMEOUT_MS / 1000 + 0.15)
    assert await monitor.check_workers() == [sid]
    [rec] = await registry.lookup([sid])
    assert rec is not None and "missed its heartbeats for 300 ms" in rec.reason


async def test_a_lease_shorter_than_the_timeout_changes_nothing(registry: Registry) -> None:
    monitor = Monitor(registry, gateway=None, config=gateway_config(), vantage=_Sighted())  # type: ignore[arg-type]
    await _worker_with_session(registry)
    assert await registry.heartbeat("env-0", TIMEOUT_MS, busy_ms=50)
    await asyncio.sleep(0.2)
    assert await monitor.check_workers() == []
    assert (await registry.workers())[0].alive
    with pytest.raises(ValueError):
        await registry.heartbeat("env-0", TIMEOUT_MS, busy_ms=-1)


# ---------------------------------------------------------------------------------------------
# Gateway: the bounds, through the servicer


class _Abort(Exception):
    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self.code = code


class _Context:
    def set_trailing_metadata(self, md: Any) -> None:
        pass

    def invocation_metadata(self) -> tuple[()]:
        return ()

    async def abort(self, code: grpc.StatusCode, details: str) -> None:
        raise _Abort(code, details)


class _RecordingRegistry:
    def __init__(self) -> None:
        self.calls: list[tuple[str, int, int]] = []

    async def heartbeat(self, worker_id: str, hb_ttl_ms: int, busy_ms: int = 0) -> bool:
        self.calls.append((worker_id, hb_ttl_ms, busy_ms))
        return True


async def test_the_servicer_caps_a_long_lease_and_refuses_a_negative_one() -> None:
    reg = _RecordingRegistry()
    servicer = WorkerRegistryServicer(reg, pool=None, config=gateway_config(ZETTA_HEARTBEAT_MAX_BUSY_MS="4000"))  # type: ignore[arg-type]
    ask = registry_pb2.HeartbeatRequest
    assert (await servicer.Heartbeat(ask(worker_id="w", busy_ms=2500), _Context())).busy_ms == 2500
    assert (await servicer.Heartbeat(ask(worker_id="w", busy_ms=90_000), _Context())).busy_ms == 4000
    assert (await servicer.Heartbeat(ask(worker_id="w"), _Context())).busy_ms == 0
    assert reg.calls == [("w", TIMEOUT_MS, 2500), ("w", TIMEOUT_MS, 4000), ("w", TIMEOUT_MS, 0)]
    with pytest.raises(_Abort) as info:
        await servicer.Heartbeat(ask(worker_id="w", busy_ms=-5), _Context())
    assert info.value.code == grpc.StatusCode.INVALID_ARGUMENT and "busy_ms" in str(info.value)
    assert len(reg.calls) == 3  # nothing written


def test_max_busy_default_and_bounds() -> None:
    assert gateway_config().heartbeat_max_busy_ms == 30_000
    assert gateway_config(ZETTA_HEARTBEAT_MAX_BUSY_MS="0").heartbeat_max_busy_ms == 0
    with pytest.raises(Exception, match="ZETTA_HEARTBEAT_MAX_BUSY_MS"):
        gateway_config(ZETTA_HEARTBEAT_MAX_BUSY_MS="-1")


# ---------------------------------------------------------------------------------------------
# Worker: the context manager


class _Announcer:
    def __init__(self, answer: concurrent.futures.Future[int] | None | Exception) -> None:
        self.answer = answer
        self.announced = 0
        self.woken = 0

    def announce(self) -> concurrent.futures.Future[int] | None:
        self.announced += 1
        if isinstance(self.answer, Exception):
            raise self.answer
        return self.answer

    def wake(self) -> None:
        self.woken += 1


def _done(value: int) -> concurrent.futures.Future[int]:
    fut: concurrent.futures.Future[int] = concurrent.futures.Future()
    fut.set_result(value)
    return fut


def test_lease_without_a_membership_just_runs() -> None:
    leases = BusyLeases()
    with leases.hold(1000, "test"):
        assert leases.held() == 1 and 900 < leases.remaining_ms() <= 1001
    assert leases.held() == 0 and leases.remaining_ms() == 0
    with pytest.raises(ValueError):
        with leases.hold(0, "test"):
            pass


@pytest.mark.parametrize("answer", [_done(1000), _done(0), None, RuntimeError("Event loop is closed"),
                                    concurrent.futures.Future()])
def test_lease_waits_briefly_and_never_blocks(answer: Any) -> None:
    """Granted, refused, not awaitable, loop gone, never answered: the block runs within the wait."""
    leases = BusyLeases()
    announcer = _Announcer(answer)
    leases.install(announcer)
    ran = False
    start = time.monotonic()
    with leases.hold(1000, "test", ack_wait_s=0.3):
        ran = True
    assert ran and time.monotonic() - start < 1.0
    assert announcer.announced == 1 and announcer.woken == 1  # the end is announced too
    assert leases.held() == 0


def test_remaining_is_the_longest_lease() -> None:
    now = [100.0]
    leases = BusyLeases(clock=lambda: now[0])
    with leases.hold(1000, "a"):
        now[0] += 0.5
        with leases.hold(3000, "b"):
            assert leases.remaining_ms() == 3001
        assert leases.remaining_ms() == 501
        now[0] += 2.0
        assert leases.remaining_ms() == 0  # overrun: nothing left to ask for


# ---------------------------------------------------------------------------------------------
# Worker: the membership sends the lease and ends it


class _Stub:
    """WorkerRegistryService in-process: records heartbeats, grants what they ask."""

    def __init__(self) -> None:
        self.beats: list[tuple[float, int]] = []

    async def Heartbeat(self, request: registry_pb2.HeartbeatRequest, timeout: float,
                        metadata: Any) -> registry_pb2.HeartbeatResponse:
        self.beats.append((time.monotonic(), request.busy_ms))
        return registry_pb2.HeartbeatResponse(known=True, busy_ms=request.busy_ms)


@pytest.fixture
def loop_thread() -> Iterator[asyncio.AbstractEventLoop]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    try:
        yield loop
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=5)
        loop.close()


def test_membership_announces_the_lease_and_its_end(loop_thread: asyncio.AbstractEventLoop,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    cfg = EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "127.0.0.1:1", "ZETTA_ENV_WORKER_PORT": "0"})
    leases = BusyLeases()
    monkeypatch.setattr(busy_mod, "LEASES", leases)
    stub = _Stub()

    async def start() -> Membership:
        m = Membership(cfg, lambda: [], lambda kept: [], leases=leases)
        m._stub = stub  # type: ignore[assignment]
        m._interval_s = 30.0  # no periodic heartbeat during the test: every one seen is announced
        m.start()
        return m

    membership = asyncio.run_coroutine_threadsafe(start(), loop_thread).result(5)
    try:
        with busy_mod.busy(4000, "test"):
            # Acknowledged before the block runs: one heartbeat carrying the lease.
            assert len(stub.beats) == 1 and 3900 < stub.beats[0][1] <= 4001
        ended = time.monotonic()
        deadline = ended + 2
        while len(stub.beats) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        # The end is sent at once, without a lease.
        assert len(stub.beats) == 2 and stub.beats[1][1] == 0 and stub.beats[1][0] - ended < 1.0
    finally:
        asyncio.run_coroutine_threadsafe(membership.stop(deregister=False), loop_thread).result(5)
    # Stopped: leases are no longer announced, and nothing waits.
    with busy_mod.busy(4000, "test"):
        pass
    assert len(stub.beats) == 2
