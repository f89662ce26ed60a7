"""Redis stalls and restarts are the gateway's trouble, not the workers' (issue #21, item 4).

The repros: SIGSTOP of Redis for 8 s used to get both healthy workers declared dead and every
session LOST, clients saw UNKNOWN "Unexpected <class 'redis.exceptions.TimeoutError'>", and after
a Redis restart every session was NOT_FOUND "never created", which was false.
"""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import Callable
from typing import Any

import pytest

from tests.conftest import HEARTBEAT_TIMEOUT_MS, LIFT, eventually
from tests.fault.test_faults import ZEROS, episode_steps, expect_error, states
from zetta import Gateway, SessionGroup, ZettaError
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import types_pb2


async def running_group(gw: Gateway, n: int = 4) -> SessionGroup:
    """``n`` reset sessions spread over both workers, one step taken."""
    group = await gw.create_sessions("robosuite", n=n, env_config=LIFT)
    await group.reset(seed=list(range(n)))
    await group.action_step([ZEROS] * n)
    assert len({i.worker_id for i in group.infos}) == 2
    return group


async def retried(call: Callable[[], Any]) -> Any:
    """``call()``, retried as the error contract says: a pooled Redis connection the restart closed
    answers UNAVAILABLE with a retry hint once, the next connection serves."""
    for _ in range(5):
        try:
            return await call()
        except ZettaError as err:
            if err.code.name != "UNAVAILABLE" or err.retry_after_ms is None:
                raise
            await asyncio.sleep(err.retry_after_ms / 1000)
    return await call()


async def answering(gw: Gateway) -> bool:
    """True once the gateway answers a registry read again."""
    try:
        await gw.list_workers()
        return True
    except ZettaError:
        return False


@pytest.mark.parametrize("stall_s", [3.0, 10.0])
async def test_redis_stall_loses_no_session(stack_factory: Callable[..., LocalStack], stall_s: float) -> None:
    """SIGSTOP the stack's own redis-server for ``stall_s`` (3 s: slower than every heartbeat
    timeout; 10 s: beyond the client's socket timeout too), then SIGCONT: every worker stays
    alive, every session RUNNING, and calls during the stall answer UNAVAILABLE with a retry hint."""
    stack: LocalStack = stack_factory()
    assert stack.redis_proc is not None
    async with Gateway(stack.gateway_address) as gw:
        group = await running_group(gw)
        os.kill(stack.redis_proc.pid, signal.SIGSTOP)
        try:
            during = asyncio.ensure_future(group.action_step([ZEROS] * len(group)))
            await asyncio.sleep(stall_s)
        finally:
            os.kill(stack.redis_proc.pid, signal.SIGCONT)
        try:
            await during  # it may also complete once Redis is back
        except ZettaError as err:
            assert err.code.name == "UNAVAILABLE", err
            assert err.retry_after_ms and err.retry_after_ms > 0
            assert "Redis" in err.details and "retry" in err.details
        await eventually(lambda: answering(gw), timeout=10)
        # Long enough for a dead-worker verdict, had the gateway blamed the workers.
        await asyncio.sleep(2 * HEARTBEAT_TIMEOUT_MS / 1000 + 1.0)
        now = await states(gw)
        assert [now[s].state for s in group.ids] == [types_pb2.SESSION_STATE_RUNNING] * len(group), \
            [now[s].reason for s in group.ids]
        assert all(w.alive for w in await gw.list_workers())
        before = await episode_steps(gw, group.ids)
        after = await group.action_step([ZEROS] * len(group))
        assert [r.episode_step for r in after] == [b + 1 for b in before]
        gateway_log = stack.services["gateway"].log.read_text()
        assert "worker declared dead" not in gateway_log


async def test_redis_restart_with_persistence_keeps_sessions(stack_factory: Callable[..., LocalStack]) -> None:
    """With append-only persistence (as in deploy/compose and deploy/k8s) sessions come back."""
    stack: LocalStack = stack_factory(redis_appendonly=True)
    async with Gateway(stack.gateway_address) as gw:
        group = await running_group(gw)
        await asyncio.sleep(1.2)  # appendfsync everysec
        stack.restart_redis(signal.SIGTERM)
        await eventually(lambda: answering(gw), timeout=15)
        await asyncio.sleep(2 * HEARTBEAT_TIMEOUT_MS / 1000 + 1.0)
        now = await states(gw)
        assert [now[s].state for s in group.ids] == [types_pb2.SESSION_STATE_RUNNING] * len(group)
        assert all(w.alive for w in await retried(gw.list_workers))
        assert [r.episode_step for r in await retried(lambda: group.action_step([ZEROS] * len(group)))] == [2] * len(group)


async def test_redis_restart_without_persistence_says_what_happened(
        stack_factory: Callable[..., LocalStack]) -> None:
    """Without persistence the sessions are gone: calls say LOST because the registry lost its
    state (never "never created"), and the workers come back with free slots for new sessions."""
    stack: LocalStack = stack_factory()
    async with Gateway(stack.gateway_address) as gw:
        group = await running_group(gw)
        stack.restart_redis(signal.SIGKILL)
        await eventually(lambda: answering(gw), timeout=15)
        err = await expect_error(group.action_step([ZEROS] * len(group)), "FAILED_PRECONDITION")
        assert "LOST" in err.details and "Redis" in err.details and "never created" not in err.details
        assert err.session_ids and set(err.session_ids) <= set(group.ids)

        async def registered() -> bool:
            return sum(w.alive for w in await gw.list_workers()) == 2

        await eventually(registered, timeout=15)
        # Once the workers re-registered, the registry holds a LOST record for what they dropped.
        now = await states(gw)
        for sid in group.ids:
            assert now[sid].state == types_pb2.SESSION_STATE_LOST
            assert "lost this session's record" in now[sid].reason
        err = await expect_error(group.policy_step(), "FAILED_PRECONDITION")
        assert "Redis" in err.details
        fresh = await gw.create_sessions("robosuite", n=8, env_config=LIFT)
        await fresh.close()
