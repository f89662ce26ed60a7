"""The env worker's step bound: turns taken and handed over on the slot threads.

A slot's work goes to its own thread at once and waits there for a turn, so a finishing slot
wakes the next without the event loop; at most ``concurrency`` run at once; a call cancelled
before its turn came runs nothing.
"""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import cast

import pytest

from services.env_worker.families import EnvFamily
from services.env_worker.slots import BoundSlot, SlotActivity


def _slots(n: int, activity: SlotActivity) -> list[BoundSlot]:
    return [BoundSlot(f"s{i}", i, cast(EnvFamily, object()), "test", ThreadPoolExecutor(1), activity=activity)
            for i in range(n)]


async def test_at_most_concurrency_slots_run_at_once() -> None:
    activity = SlotActivity(concurrency=2)
    slots = _slots(6, activity)
    lock = threading.Lock()
    running, peak = 0, 0

    def work(i: int) -> int:
        nonlocal running, peak
        with lock:
            running += 1
            peak = max(peak, running)
        time.sleep(0.02)
        with lock:
            running -= 1
        return i

    try:
        assert await asyncio.gather(*(s.run(work, s.index) for s in slots)) == list(range(6))
    finally:
        for s in slots:
            s.executor.shutdown()
    assert peak == 2 and activity.busy == 0


async def test_the_turn_passes_between_threads_while_the_event_loop_is_blocked() -> None:
    """With one turn, slot 1 waits on its thread; when slot 0 finishes, slot 1 starts at once even
    though the event loop is stuck (a turn handed over by the loop would wait for it)."""
    activity = SlotActivity(concurrency=1)
    first, second = _slots(2, activity)
    release = threading.Event()
    started: dict[str, float] = {}

    def hold() -> None:
        release.wait(5)
        started["released"] = time.monotonic()

    def follow() -> None:
        started["second"] = time.monotonic()

    try:
        a = asyncio.ensure_future(first.run(hold))
        b = asyncio.ensure_future(second.run(follow))
        await asyncio.sleep(0.05)  # both submitted: slot 0 holds the turn, slot 1 waits on its thread
        assert "second" not in started
        release.set()
        time.sleep(0.3)  # the event loop is blocked here
        assert "second" in started and started["second"] - started["released"] < 0.25
        await asyncio.gather(a, b)
    finally:
        first.executor.shutdown()
        second.executor.shutdown()


async def test_a_call_cancelled_before_its_turn_runs_nothing() -> None:
    activity = SlotActivity(concurrency=1)
    first, second = _slots(2, activity)
    release = threading.Event()
    ran: list[str] = []
    try:
        holder = asyncio.ensure_future(first.run(release.wait, 5))
        await asyncio.sleep(0.05)
        waiting = asyncio.ensure_future(second.run(ran.append, "cancelled call"))
        await asyncio.sleep(0.05)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        release.set()
        await holder
        await second.run(ran.append, "later call")  # the slot and the turn are free again
    finally:
        first.executor.shutdown()
        second.executor.shutdown()
    assert ran == ["later call"] and activity.busy == 0


async def test_no_bound_runs_everything_at_once() -> None:
    activity = SlotActivity(concurrency=0)
    slots = _slots(3, activity)
    barrier = threading.Barrier(3, timeout=5)  # passes only if all three run at the same time
    try:
        await asyncio.gather(*(s.run(barrier.wait) for s in slots))
    finally:
        for s in slots:
            s.executor.shutdown()
