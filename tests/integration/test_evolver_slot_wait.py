"""A rollout waits for an env slot as long as RunConfig.open_timeout_s allows, on a real gateway:
a full pool is waited out, and a pool with no live worker ends in an error a person can act on.

An experiment of hours died when a loaded machine's workers missed heartbeats for longer than the
old fixed 60 tries (about 30 s); the wait is now a time budget.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest

from services.evolver.rollout import InfrastructureError, RunConfig, Runner
from services.evolver.store import RolloutStore
from services.ops.local_stack import LocalStack
from tests.conftest import LIBERO_CREAM, LIFT, free_slots
from zetta import Gateway


async def test_a_full_pool_is_waited_out(gw: Gateway, shared_stack: LocalStack, tmp_path: Path) -> None:
    """Every slot held: the runner waits (the gateway's retry-after) and gets the slot freed later."""
    total = sum((await free_slots(gw)).values())
    held = await gw.create_sessions("robosuite", n=total, env_config=LIFT)
    runner = Runner(RolloutStore(tmp_path / "store"), RunConfig(gateway=shared_stack.gateway_address,
                                                                open_timeout_s=120.0), LIBERO_CREAM)
    opening = asyncio.create_task(runner._open(gw))
    await asyncio.sleep(2.0)
    assert not opening.done(), "a full pool must be waited out, not answered with a session"
    await held.subset(held.ids[:1]).close()
    session = await asyncio.wait_for(opening, 90.0)
    assert len(session.ids) == 1
    await session.close()
    await held.subset(held.ids[1:]).close()


async def test_silent_workers_end_the_wait_with_the_gateways_reason(stack_factory, tmp_path: Path) -> None:
    """The only worker hosting the family stopped heartbeating: the gateway says UNAVAILABLE with a
    retry-after; the wait ends at the budget with that reason and what to do next."""
    stack = stack_factory(env_workers=1, policy_workers=0, critic=False)
    stack.kill("env-0")
    gateway = Gateway(stack.gateway_address)
    try:
        runner = Runner(RolloutStore(tmp_path / "store"), RunConfig(gateway=stack.gateway_address,
                                                                    open_timeout_s=4.0), LIBERO_CREAM)
        start = time.monotonic()
        with pytest.raises(InfrastructureError, match=r"no env slot could be opened in 4 s \((?:[2-9]|\d\d+) tries\); "
                                                      r"the gateway last said UNAVAILABLE: .*missed their heartbeats.*"
                                                      r"run the same command again"):
            await runner._open(gateway)
        assert time.monotonic() - start <= 4.0 + 5.0  # it stops before a wait that would overrun the budget
    finally:
        await gateway.close()
