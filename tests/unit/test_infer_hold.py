"""The env worker's inference hold: requests wait for each other while the worker's slots are busy.

A real policy worker servicer (its batching scheduler, the scripted policy) serves on loopback; the
env worker's real PolicyClient sends to it, and a SlotActivity stands for the worker's slots.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator

import grpc
import numpy as np
import pytest

from services.env_worker.policy_client import InferHold, PolicyClient
from services.env_worker.slots import SlotActivity
from services.policy_worker.models.base import load_model
from services.policy_worker.scheduler import BatchScheduler, NullObserver, SchedulerConfig
from services.policy_worker.servicer import PolicyWorkerServicer
from zetta_wire.v1 import policy_worker_pb2_grpc

MODEL = "scripted-pick-place"
OBS = {
    "robot0_eef_pos": np.array([0.0, 0.0, 1.0], np.float32),
    "robot0_gripper_qpos": np.array([0.04, -0.04], np.float32),
    "task_object_bbox": np.array([0.1, 0.0, 0.9, 0.12, 0.02, 0.95], np.float32),
    "task_target_bbox": np.array([0.3, 0.0, 0.9, 0.35, 0.05, 0.92], np.float32),
    "task_grasped": np.zeros(1, np.float32),
}


class Batches(NullObserver):
    """The scheduler's observer: the size of every batch the policy ran."""

    def __init__(self) -> None:
        self.sizes: list[int] = []

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        self.sizes.append(size)


@pytest.fixture
async def policy_worker() -> AsyncIterator[tuple[str, Batches]]:
    models = {MODEL: load_model(MODEL)}
    batches = Batches()
    # A long queue delay and no early dispatch: a batch holds exactly what one Infer call brought.
    config = SchedulerConfig(max_batch=32, max_queue_delay=0.0, early_dispatch=False)
    scheduler = BatchScheduler(lambda m, inputs, instr: models[m].infer(inputs, instr), config, batches)
    server = grpc.aio.server()
    policy_worker_pb2_grpc.add_PolicyWorkerServiceServicer_to_server(
        PolicyWorkerServicer(models, MODEL, scheduler, 5000), server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        yield f"127.0.0.1:{port}", batches
    finally:
        await server.stop(None)
        await scheduler.drain()


def _client(address: str, hold: InferHold, activity: SlotActivity) -> PolicyClient:
    client = PolicyClient([address], 5000, hold, busy=lambda: activity.busy)
    activity.listen(client.slot_finished)
    return client


@contextlib.asynccontextmanager
async def _busy_worker(address: str, hold: InferHold, busy: int) -> AsyncIterator[tuple[PolicyClient, SlotActivity]]:
    """A policy client of a worker whose other ``busy`` slots are stepping (until the test says)."""
    activity = SlotActivity()
    for _ in range(busy):
        activity.enter()
    client = _client(address, hold, activity)
    try:
        yield client, activity
    finally:
        await client.close()


async def _ask_apart(client: PolicyClient, n: int, gap: float) -> list[asyncio.Task]:
    """``n`` requests, one every ``gap`` seconds (each in its own loop turn), as slots finishing
    their chunks at different times ask."""
    tasks = []
    for i in range(n):
        tasks.append(asyncio.ensure_future(client.infer(f"slot-{i}", MODEL, OBS, "put it in", 5000)))
        await asyncio.sleep(gap)
    return tasks


async def test_held_requests_leave_together_when_the_slots_are_done(policy_worker) -> None:
    address, batches = policy_worker
    async with _busy_worker(address, InferHold(max_ms=5000, min_busy=2), busy=3) as (client, activity):
        tasks = await _ask_apart(client, 4, 0.01)
        await asyncio.sleep(0.05)
        assert not any(t.done() for t in tasks) and batches.sizes == [], "held while 3 slots are busy"
        activity.leave()  # 2 busy: still enough to keep the cores working
        await asyncio.sleep(0.05)
        assert batches.sizes == []
        activity.leave()  # 1 busy: the held requests go, in one call, as one batch
        outputs = await asyncio.wait_for(asyncio.gather(*tasks), 5)
        assert batches.sizes == [4]
        assert [o.token for o in outputs] == [f"slot-{i}" for i in range(4)]
        assert all(o.actions.shape for o in outputs)


async def test_a_request_is_held_at_most_max_ms(policy_worker) -> None:
    address, batches = policy_worker
    # These five slots never finish within the test.
    async with _busy_worker(address, InferHold(max_ms=150, min_busy=2), busy=5) as (client, _):
        start = time.monotonic()
        tasks = await _ask_apart(client, 3, 0.02)
        await asyncio.wait_for(asyncio.gather(*tasks), 5)
        waited = time.monotonic() - start
        assert batches.sizes == [3]
        assert 0.14 <= waited < 1.0, waited


async def test_a_request_is_held_at_most_half_its_timeout(policy_worker) -> None:
    """A request with a short budget cuts the hold of every request waiting with it."""
    address, batches = policy_worker
    async with _busy_worker(address, InferHold(max_ms=5000, min_busy=2), busy=5) as (client, _):
        start = time.monotonic()
        patient = asyncio.ensure_future(client.infer("patient", MODEL, OBS, "put it in", 5000))
        await asyncio.sleep(0.02)
        hurried = asyncio.ensure_future(client.infer("hurried", MODEL, OBS, "put it in", 200))  # held <= 100 ms
        await asyncio.wait_for(asyncio.gather(patient, hurried), 5)
        # Both left when the hurried one had to, not after the patient one's 2.5 s. They go in a call
        # per budget (test_a_too_short_budget_...), which the policy worker may run as one batch
        # when both arrive together (on a loaded machine they do).
        assert time.monotonic() - start < 1.0 and sum(batches.sizes) == 2 and batches.sizes in ([1, 1], [2])


async def test_no_hold_when_few_slots_are_busy_or_holding_is_off(policy_worker) -> None:
    address, batches = policy_worker
    # One other slot stepping: fewer than min_busy.
    async with _busy_worker(address, InferHold(max_ms=5000, min_busy=2), busy=1) as (lone, activity):
        start = time.monotonic()
        await asyncio.wait_for(lone.infer("lone", MODEL, OBS, "put it in", 5000), 5)
        assert time.monotonic() - start < 1.0 and batches.sizes == [1]
        for _ in range(4):
            activity.enter()
        off = _client(address, InferHold(max_ms=0), activity)
        tasks = await _ask_apart(off, 3, 0.02)
        await asyncio.wait_for(asyncio.gather(*tasks), 5)
        assert batches.sizes == [1, 1, 1, 1], "holding off: each request leaves in its own loop turn"
        await off.close()


async def test_step_concurrency_bounds_the_slots_working_at_once() -> None:
    """SlotTable(step_concurrency=2): of 6 slots asked to work together, 2 run at a time, all finish,
    and every one counts as busy (the hold's measure) while it waits for its turn."""
    import threading

    from services.env_worker.slots import SlotTable

    table = SlotTable(6, ["robosuite"], step_concurrency=2)
    running, most, lock = [0], [0], threading.Lock()

    def work() -> None:
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.05)
        with lock:
            running[0] -= 1

    try:
        slots = table.bind([f"s{i}" for i in range(6)], "robosuite", None)  # family unused by run()
        jobs = asyncio.gather(*(s.run(work) for s in slots))
        await asyncio.sleep(0.01)
        assert table.activity.busy == 6
        await asyncio.wait_for(jobs, 5)
        assert most[0] == 2 and table.activity.busy == 0
        unbounded = SlotTable(6, ["robosuite"])
        most[0] = 0
        free = unbounded.bind([f"u{i}" for i in range(6)], "robosuite", None)
        await asyncio.wait_for(asyncio.gather(*(s.run(work) for s in free)), 5)
        assert most[0] == 6
        unbounded.shutdown()
    finally:
        table.shutdown()


async def test_a_bad_item_fails_only_its_own_session(policy_worker) -> None:
    """Items of one loop turn travel together, but one that cannot succeed (a model the policy
    worker does not serve, a wrong observation) fails alone: the policy worker fails a call whole,
    and it used to fail every session coalesced with the bad one (found by bench/bench_fuzz.py:
    a fuzzer's unknown model reached a good session as NOT_FOUND)."""
    from services.common.grpc_errors import ServiceError

    address, batches = policy_worker
    bad_obs = {**OBS, "robot0_eef_pos": np.zeros(5, np.float32)}
    async with _busy_worker(address, InferHold(max_ms=5000, min_busy=2), busy=3) as (client, activity):
        tasks = [asyncio.ensure_future(client.infer(token, model, obs, "put it in", 5000)) for token, model, obs in (
            ("good-0", MODEL, OBS), ("unknown-model", "no-such-model", OBS), ("good-1", MODEL, OBS),
            ("bad-observation", MODEL, bad_obs))]
        await asyncio.sleep(0.1)
        assert not any(t.done() for t in tasks), "held together while the slots are busy"
        activity.leave()
        activity.leave()  # they leave in one turn
        results = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 5)
    assert [r.token for r in results if not isinstance(r, BaseException)] == ["good-0", "good-1"]
    unknown, bad = results[1], results[3]
    assert isinstance(unknown, ServiceError) and unknown.code == grpc.StatusCode.NOT_FOUND
    assert "no-such-model" in unknown.message
    assert isinstance(bad, ServiceError) and bad.code == grpc.StatusCode.INVALID_ARGUMENT


@pytest.fixture
async def slow_policy_worker() -> AsyncIterator[str]:
    """The scripted policy taking 30 ms a batch, so the scheduler's estimate rejects a 1 ms budget."""
    models = {MODEL: load_model(MODEL)}

    def run_batch(m, inputs, instr):  # type: ignore[no-untyped-def]
        time.sleep(0.03)
        return models[m].infer(inputs, instr)

    scheduler = BatchScheduler(run_batch, SchedulerConfig(max_batch=32, max_queue_delay=0.0, early_dispatch=False),
                               NullObserver())
    server = grpc.aio.server()
    policy_worker_pb2_grpc.add_PolicyWorkerServiceServicer_to_server(
        PolicyWorkerServicer(models, MODEL, scheduler, 5000), server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        await server.stop(None)
        await scheduler.drain()


async def test_a_too_short_budget_fails_only_its_own_session(slow_policy_worker: str) -> None:
    """An item whose timeout cannot be met (1 ms against 30 ms batches) makes the policy worker
    fail the call with DEADLINE_EXCEEDED; the items with a normal budget that travelled with it are
    answered (they used to fail with it)."""
    from services.common.grpc_errors import ServiceError

    async with _busy_worker(slow_policy_worker, InferHold(max_ms=5000, min_busy=2), busy=3) as (client, activity):
        await client.infer("warm-up", MODEL, OBS, "put it in", 5000)  # the scheduler's batch-time estimate
        tasks = [asyncio.ensure_future(client.infer(token, MODEL, OBS, "put it in", timeout)) for token, timeout in (
            ("good-0", 5000), ("hurried", 1), ("good-1", 5000))]
        results = await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 5)
    assert [r.token for r in results if not isinstance(r, BaseException)] == ["good-0", "good-1"]
    assert isinstance(results[1], ServiceError) and results[1].code == grpc.StatusCode.DEADLINE_EXCEEDED
