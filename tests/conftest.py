"""Fixtures shared by the integration and fault tests: real stacks on loopback.

A stack is redis-server, the gateway, env workers and a policy worker, each its own OS process
(services.ops.local_stack.LocalStack). Starting one costs about 15 s on two cores, so tests that leave
the stack healthy share one session-wide stack; tests that kill or restart processes get their
own from ``stack_factory``. Every stack is stopped at teardown, also when the test failed, and the
service logs of a failed test are printed so a failure can be read without rerunning it.
Tests that need only the registry get a private redis-server from ``private_registry``.
"""

from __future__ import annotations

import asyncio
import contextlib
import subprocess
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from typing import Any

import pytest
import redis.asyncio as aioredis
import redis.exceptions

from zetta import Gateway
from services.gateway.registry import Registry
from services.ops.local_stack import HOST, LocalStack, free_port
from zetta_wire.v1 import gateway_pb2, types_pb2

#: Short heartbeats so LOST detection is fast in tests (production default: 1000 / 3000 ms).
HEARTBEAT_INTERVAL_MS = 250
HEARTBEAT_TIMEOUT_MS = 2000

#: The cheap environment most tests use (builds in about 3 s).
LIFT: dict[str, Any] = {"env_name": "Lift"}
#: A LIBERO-Goal task the scripted policy solves (builds in about 5 s).
LIBERO_CREAM: dict[str, Any] = {"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"}


def new_stack(**overrides: Any) -> LocalStack:
    """A LocalStack with the test defaults (2 env workers x 4 slots, robosuite and libero)."""
    settings: dict[str, Any] = {
        "env_workers": 2,
        "slots": 4,
        "heartbeat_interval_ms": HEARTBEAT_INTERVAL_MS,
        "heartbeat_timeout_ms": HEARTBEAT_TIMEOUT_MS,
        "extra_env": {"ZETTA_LOG_LEVEL": "INFO"},
        # Infrastructure tests drive Lift and LIBERO sessions without cameras: the scripted policy
        # reads state (the shipped default, the image VLA, is tested where it is the subject).
        "models": ("scripted-pick-place", "do-nothing"),
    }
    settings.update(overrides)
    return LocalStack(**settings)


def dump_logs(stack: LocalStack, lines: int = 40) -> str:
    """The last lines of every service log, for failure reports."""
    out = []
    for name, svc in stack.services.items():
        if svc.log.exists():
            tail = svc.log.read_text(errors="replace").splitlines()[-lines:]
            out.append(f"----- {name} ({svc.log}) -----\n" + "\n".join(tail))
    return "\n".join(out)


@pytest.hookimpl(hookwrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]):  # type: ignore[no-untyped-def]
    """Remember each phase's outcome on the item, so fixtures know whether their test failed."""
    outcome = yield
    rep = outcome.get_result()
    setattr(item, f"rep_{rep.when}", rep)


def _failed(request: pytest.FixtureRequest) -> bool:
    rep = getattr(request.node, "rep_call", None)
    return rep is not None and rep.failed


@pytest.fixture(scope="session")
def shared_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    """One healthy stack for every test that does not kill or restart a process."""
    # A looser heartbeat budget than the private stacks': nothing kills this stack's workers, and a
    # worker building LIBERO scenes on a busy 2-core machine can miss a 2 s budget (every session LOST).
    stack = new_stack(workdir=tmp_path_factory.mktemp("shared-stack"), heartbeat_timeout_ms=8000)
    stack.start()
    try:
        yield stack
    finally:
        stack.stop()


@pytest.fixture
def stack_factory(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[Callable[..., LocalStack]]:
    """Start private stacks (for kill/restart tests); all are stopped when the test ends."""
    stacks: list[LocalStack] = []

    def start(**overrides: Any) -> LocalStack:
        overrides.setdefault("workdir", tmp_path_factory.mktemp("stack"))
        stack = new_stack(**overrides)
        stacks.append(stack)
        stack.start()  # stops what it started if it fails
        return stack

    try:
        yield start
    finally:
        for stack in reversed(stacks):
            if _failed(request):
                print(dump_logs(stack))
            stack.stop()


@pytest.fixture
async def gw(shared_stack: LocalStack, request: pytest.FixtureRequest) -> AsyncIterator[Gateway]:
    """An SDK connection to the shared stack; sessions a test leaves open are closed afterwards."""
    gateway = Gateway(shared_stack.gateway_address)
    try:
        yield gateway
    finally:
        if _failed(request):
            print(dump_logs(shared_stack, lines=20))
        await close_all_sessions(gateway)
        await gateway.close()


@contextlib.asynccontextmanager
async def private_registry(server: str) -> AsyncIterator[Registry]:
    """A Registry (prefix "zt") on a private redis-server of its own (``server``: its path) on a
    free loopback port, no persistence; the server is stopped when the block ends."""
    port = free_port()
    proc = subprocess.Popen([server, "--bind", HOST, "--port", str(port), "--save", "", "--appendonly", "no"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    client = aioredis.Redis.from_url(f"redis://{HOST}:{port}/0")
    try:
        for _ in range(100):
            try:
                await client.ping()
                break
            except redis.exceptions.ConnectionError:
                await asyncio.sleep(0.05)
        yield Registry(client, "zt", 3600)
    finally:
        await client.aclose()
        proc.terminate()
        proc.wait(timeout=10)


async def close_all_sessions(gateway: Gateway) -> None:
    """Close every live session, so the next test sees all slots free."""
    live = [s.session_id for s in await gateway.list_sessions()
            if s.state in (types_pb2.SESSION_STATE_CREATE, types_pb2.SESSION_STATE_RUNNING)]
    if live:
        await gateway.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=live))


async def free_slots(gateway: Gateway) -> dict[str, int]:
    """Free slots per live worker, as the registry reports them."""
    return {w.worker_id: w.free_slots for w in await gateway.list_workers() if w.alive}


async def eventually(check: Callable[[], Awaitable[bool]], timeout: float, interval: float = 0.05) -> float:
    """Poll ``check`` until it is true; returns the seconds it took, fails the test on timeout."""
    start = time.monotonic()
    while True:
        if await check():
            return time.monotonic() - start
        if time.monotonic() - start > timeout:
            pytest.fail(f"condition not met within {timeout:.1f} s")
        await asyncio.sleep(interval)
