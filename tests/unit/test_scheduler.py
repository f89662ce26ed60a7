"""Unit tests of the policy worker's batching scheduler (pure asyncio, no gRPC)."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from services.policy_worker.scheduler import (
    BatchScheduler,
    DeadlineExceededError,
    InferItem,
    QueueFullError,
    SchedulerClosedError,
    SchedulerConfig,
    compatibility_key,
)

# Upper bound on any single wait, so a scheduler bug fails the test instead of hanging it.
GUARD = 3.0


def make_item(
    token: str,
    value: float = 0.0,
    *,
    shape: tuple[int, ...] = (3,),
    dtype: type = np.float32,
    model: str = "pi",
    deadline: float | None = None,
) -> InferItem:
    return InferItem(
        token=token,
        model=model,
        inputs={"x": np.full(shape, value, dtype=dtype)},
        instruction=token,
        deadline=deadline,
    )


class FakeModel:
    """run_batch double: records each batch, returns x * 2.

    A batch whose instructions include "gate" blocks its worker thread until ``release`` is set,
    which lets a test build up queues behind a busy worker deterministically.
    """

    def __init__(self, cost: float = 0.0) -> None:
        self.cost = cost
        self.calls: list[tuple[str, dict[str, tuple[np.dtype, tuple[int, ...]]], list[str]]] = []
        self.started = threading.Event()
        self.release = threading.Event()

    def __call__(self, model: str, inputs: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        self.calls.append((model, {k: (v.dtype, v.shape) for k, v in inputs.items()}, list(instructions)))
        if "gate" in instructions:
            self.started.set()
            self.release.wait(GUARD)
        if "bad" in instructions:
            raise RuntimeError("boom")
        if self.cost:
            time.sleep(self.cost)
        return inputs["x"] * 2

    @property
    def sizes(self) -> list[int]:
        return [len(instructions) for _, _, instructions in self.calls]

    def batches(self) -> list[list[str]]:
        return [instructions for _, _, instructions in self.calls]

    def seen(self) -> set[str]:
        return {token for _, _, instructions in self.calls for token in instructions}


class RecordingObserver:
    def __init__(self) -> None:
        self.batches: list[tuple[str, int, float]] = []
        self.waits: list[tuple[str, float]] = []
        self.depths: list[tuple[str, int]] = []
        self.rejects: list[tuple[str, str]] = []

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        self.batches.append((model, size, compute_seconds))

    def on_queue_wait(self, model: str, seconds: float) -> None:
        self.waits.append((model, seconds))

    def on_queue_depth(self, model: str, depth: int) -> None:
        self.depths.append((model, depth))

    def on_reject(self, model: str, reason: str) -> None:
        self.rejects.append((model, reason))


async def wait_until(predicate, timeout: float = GUARD) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.001)


async def occupy_worker(scheduler: BatchScheduler, model: FakeModel, size: int = 1) -> asyncio.Future:
    """Start a batch of ``size`` that holds the only worker thread until ``model.release`` is set."""
    tokens = ["gate"] + [f"gate{i}" for i in range(1, size)]
    task = asyncio.gather(*(scheduler.submit(make_item(token, model="gate")) for token in tokens))
    await wait_until(model.started.is_set)
    return task


@pytest.mark.asyncio
async def test_concurrent_submits_form_full_batches() -> None:
    model = FakeModel()
    # A delay far longer than the test: only "batch is full" can explain a fast completion.
    config = SchedulerConfig(max_batch=4, max_queue_delay=10.0, max_queue=64)
    async with BatchScheduler(model, config) as scheduler:
        start = time.monotonic()
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"t{i}", i)) for i in range(12))), GUARD)
        assert time.monotonic() - start < 1.0
    assert model.sizes == [4, 4, 4]


@pytest.mark.asyncio
async def test_max_queue_delay_dispatches_partial_batch() -> None:
    model = FakeModel()
    config = SchedulerConfig(max_batch=8, max_queue_delay=0.05)
    async with BatchScheduler(model, config) as scheduler:
        # 64 requesters seen at once, at a rate that brings more within the delay: three waiting
        # can still be joined by others, so they wait for them.
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"w{i}")) for i in range(64))), GUARD)
        start = time.monotonic()
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"t{i}")) for i in range(3))), GUARD)
        elapsed = time.monotonic() - start
    assert model.sizes == [8] * 8 + [3]
    assert 0.04 <= elapsed < 1.0


@pytest.mark.asyncio
async def test_rare_requests_do_not_wait_for_company() -> None:
    """Sixteen requesters were seen at once, but over the window requests come about 8 per second:
    fewer than one is expected within a 50 ms delay, so a lone request goes out at once."""
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=32, max_queue_delay=0.05)) as scheduler:
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"w{i}")) for i in range(16))), GUARD)
        start = time.monotonic()
        await asyncio.wait_for(scheduler.submit(make_item("lone")), GUARD)
        assert time.monotonic() - start < 0.04
    assert model.sizes == [16, 1]


@pytest.mark.asyncio
async def test_lone_closed_loop_requester_does_not_wait_out_the_delay() -> None:
    """One session asks, waits for its answer, asks again: no second request can join its batch,
    so the scheduler must not hold it for max_queue_delay (which used to cost every action chunk)."""
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=8, max_queue_delay=10.0)) as scheduler:
        start = time.monotonic()
        for i in range(5):
            await asyncio.wait_for(scheduler.submit(make_item(f"t{i}", i)), GUARD)
        assert time.monotonic() - start < 1.0
    assert model.sizes == [1, 1, 1, 1, 1]


@pytest.mark.asyncio
async def test_closed_loop_requesters_wait_only_while_one_is_missing() -> None:
    """Four requesters seen at once: three waiting hold for the fourth (not for the delay once it
    comes), and once all four wait the batch goes at once."""
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=8, max_queue_delay=10.0)) as scheduler:
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"w{i}")) for i in range(4))), GUARD)
        first = [asyncio.create_task(scheduler.submit(make_item(f"a{i}"))) for i in range(3)]
        await asyncio.sleep(0.05)
        assert not any(t.done() for t in first)  # a fourth requester may still come
        start = time.monotonic()
        last = asyncio.create_task(scheduler.submit(make_item("a3")))
        await asyncio.wait_for(asyncio.gather(*first, last), GUARD)
        assert time.monotonic() - start < 1.0
    assert model.sizes == [4, 4]


@pytest.mark.asyncio
async def test_without_early_dispatch_a_lone_requester_waits_out_the_delay() -> None:
    model = FakeModel()
    config = SchedulerConfig(max_batch=8, max_queue_delay=0.05, early_dispatch=False)
    async with BatchScheduler(model, config) as scheduler:
        start = time.monotonic()
        await asyncio.wait_for(scheduler.submit(make_item("t")), GUARD)
        assert time.monotonic() - start >= 0.04
    assert model.sizes == [1]


@pytest.mark.asyncio
async def test_requesters_peak_is_forgotten_after_the_window(monkeypatch: pytest.MonkeyPatch) -> None:
    """A burst long gone does not make a lone requester wait: the peak lasts one to two windows."""
    from services.policy_worker import scheduler as sched

    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=8, max_queue_delay=10.0)) as scheduler:
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"w{i}")) for i in range(6))), GUARD)
        pending = asyncio.create_task(scheduler.submit(make_item("held")))
        await asyncio.sleep(0.05)
        assert not pending.done()  # six were seen at once: this one waits for company
        pending.cancel()
        monkeypatch.setattr(sched, "PEAK_WINDOW_SECONDS", 0.01)
        await asyncio.sleep(0.03)  # two windows without a request
        await asyncio.wait_for(scheduler.submit(make_item("alone")), 1.0)
    assert model.sizes == [6, 1]


@pytest.mark.asyncio
async def test_incompatible_requests_are_not_batched_together() -> None:
    model = FakeModel()
    variants = [
        {"shape": (3,)},
        {"shape": (4,)},
        {"shape": (3,), "dtype": np.float64},
        {"shape": (3,), "model": "other"},
    ]
    items = [make_item(f"t{i}", i, **variants[i % 4]) for i in range(16)]
    assert len({compatibility_key(item) for item in items}) == 4
    async with BatchScheduler(model, SchedulerConfig(max_batch=16, max_queue_delay=0.01)) as scheduler:
        results = await asyncio.wait_for(asyncio.gather(*(scheduler.submit(item) for item in items)), GUARD)
    assert sorted(model.sizes) == [4, 4, 4, 4]
    for name, signature, instructions in model.calls:
        members = [item for item in items if item.token in instructions]
        assert {compatibility_key(item) for item in members} == {compatibility_key(members[0])}
        assert name == members[0].model
        assert signature["x"] == (members[0].inputs["x"].dtype, (len(members), *members[0].inputs["x"].shape))
    for item, result in zip(items, results, strict=True):
        np.testing.assert_array_equal(result, item.inputs["x"] * 2)


@pytest.mark.asyncio
async def test_fcfs_within_a_group() -> None:
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=2, max_queue_delay=0.0)) as scheduler:
        gate = await occupy_worker(scheduler, model)
        tasks = [asyncio.create_task(scheduler.submit(make_item(f"t{i}"))) for i in range(6)]
        await asyncio.sleep(0.01)
        model.release.set()
        await asyncio.wait_for(asyncio.gather(gate, *tasks), GUARD)
    assert model.batches() == [["gate"], ["t0", "t1"], ["t2", "t3"], ["t4", "t5"]]


@pytest.mark.asyncio
async def test_fcfs_across_groups_by_oldest_item() -> None:
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=2, max_queue_delay=0.001)) as scheduler:
        gate = await occupy_worker(scheduler, model)
        # Submitted in this order: each time the worker frees, the group whose head arrived first
        # goes next (neither round-robin nor group creation order).
        order = [
            ("b0", (4,)), ("a0", (3,)), ("c0", (2,)), ("a1", (3,)),
            ("a2", (3,)), ("a3", (3,)), ("b1", (4,)), ("b2", (4,)),
        ]  # fmt: skip
        tasks = [asyncio.create_task(scheduler.submit(make_item(token, shape=shape))) for token, shape in order]
        await asyncio.sleep(0.02)
        model.release.set()
        await asyncio.wait_for(asyncio.gather(gate, *tasks), GUARD)
    assert model.batches() == [["gate"], ["b0", "b1"], ["a0", "a1"], ["c0"], ["a2", "a3"], ["b2"]]


@pytest.mark.asyncio
async def test_workers_run_batches_in_parallel() -> None:
    model = FakeModel(cost=0.1)
    config = SchedulerConfig(max_batch=2, max_queue_delay=10.0, workers=2)
    async with BatchScheduler(model, config) as scheduler:
        start = time.monotonic()
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"t{i}")) for i in range(4))), GUARD)
        elapsed = time.monotonic() - start
    assert model.sizes == [2, 2]
    assert elapsed < 0.18


@pytest.mark.asyncio
async def test_expired_deadline_fails_without_running() -> None:
    model = FakeModel()
    observer = RecordingObserver()
    async with BatchScheduler(model, observer=observer) as scheduler:
        with pytest.raises(DeadlineExceededError):
            await scheduler.submit(make_item("late", deadline=time.monotonic() - 0.001))
    assert model.calls == []
    assert observer.rejects == [("pi", "deadline_expired")]


@pytest.mark.asyncio
async def test_deadline_passing_in_queue_fails_at_dispatch() -> None:
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=4, max_queue_delay=0.0)) as scheduler:
        gate = await occupy_worker(scheduler, model)
        late = asyncio.create_task(scheduler.submit(make_item("late", deadline=time.monotonic() + 0.02)))
        on_time = asyncio.create_task(scheduler.submit(make_item("on_time", 1.0)))
        await asyncio.sleep(0.05)
        model.release.set()
        with pytest.raises(DeadlineExceededError):
            await asyncio.wait_for(late, GUARD)
        np.testing.assert_array_equal(await asyncio.wait_for(on_time, GUARD), np.full(3, 2.0, np.float32))
        await gate
    assert "late" not in model.seen()
    assert model.batches()[-1] == ["on_time"]


@pytest.mark.asyncio
async def test_unreachable_deadline_is_rejected_early() -> None:
    model = FakeModel(cost=0.05)
    observer = RecordingObserver()
    async with BatchScheduler(model, observer=observer) as scheduler:
        await asyncio.wait_for(scheduler.submit(make_item("warmup")), GUARD)
        assert scheduler.compute_estimate(compatibility_key(make_item("probe"))) >= 0.04
        start = time.monotonic()
        with pytest.raises(DeadlineExceededError):
            await scheduler.submit(make_item("tight", deadline=time.monotonic() + 0.01))
        assert time.monotonic() - start < 0.04  # rejected up front, not after running
        await asyncio.wait_for(scheduler.submit(make_item("loose", deadline=time.monotonic() + 2.0)), GUARD)
    assert "tight" not in model.seen()
    assert observer.rejects == [("pi", "deadline_unreachable")]


@pytest.mark.asyncio
async def test_stale_estimate_stops_rejecting(monkeypatch: pytest.MonkeyPatch) -> None:
    """One slow spell must not refuse tight deadlines forever: a stale estimate lets a request run."""
    from services.policy_worker import scheduler as sched

    model = FakeModel(cost=0.05)
    async with BatchScheduler(model) as scheduler:
        await asyncio.wait_for(scheduler.submit(make_item("slow")), GUARD)
        with pytest.raises(DeadlineExceededError):
            await scheduler.submit(make_item("refused", deadline=time.monotonic() + 0.03))
        monkeypatch.setattr(sched, "ESTIMATE_TTL_SECONDS", 0.0)
        model.cost = 0.0
        await asyncio.wait_for(scheduler.submit(make_item("runs", deadline=time.monotonic() + 0.03)), GUARD)
    assert "runs" in model.seen() and "refused" not in model.seen()


@pytest.mark.asyncio
async def test_full_queue_rejects_with_retry_hint() -> None:
    model = FakeModel(cost=0.02)
    observer = RecordingObserver()
    config = SchedulerConfig(max_batch=2, max_queue=2, max_queue_delay=0.0)
    async with BatchScheduler(model, config, observer) as scheduler:
        await asyncio.wait_for(scheduler.submit(make_item("warmup")), GUARD)
        gate = await occupy_worker(scheduler, model)
        queued = [asyncio.create_task(scheduler.submit(make_item(f"q{i}"))) for i in range(2)]
        await asyncio.sleep(0.01)
        with pytest.raises(QueueFullError) as excinfo:
            await scheduler.submit(make_item("overflow"))
        # One full batch ahead at ~20 ms each.
        assert excinfo.value.retry_after >= 0.015
        assert ("pi", "queue_full") in observer.rejects
        model.release.set()
        await asyncio.wait_for(asyncio.gather(gate, *queued), GUARD)
    assert "overflow" not in model.seen()


@pytest.mark.asyncio
async def test_run_batch_error_fails_its_batch_and_scheduler_keeps_serving() -> None:
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_batch=2, max_queue_delay=10.0)) as scheduler:
        outcomes = await asyncio.wait_for(
            asyncio.gather(
                scheduler.submit(make_item("ok")), scheduler.submit(make_item("bad")), return_exceptions=True
            ),
            GUARD,
        )
        assert all(isinstance(outcome, RuntimeError) and str(outcome) == "boom" for outcome in outcomes)
        results = await asyncio.wait_for(
            asyncio.gather(scheduler.submit(make_item("c", 1.0)), scheduler.submit(make_item("d", 2.0))), GUARD
        )
    np.testing.assert_array_equal(results[0], np.full(3, 2.0, np.float32))
    np.testing.assert_array_equal(results[1], np.full(3, 4.0, np.float32))


@pytest.mark.asyncio
async def test_wrong_output_batch_size_fails_the_batch() -> None:
    def run_batch(model: str, inputs: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        return np.zeros((len(instructions) + 1, 2))

    async with BatchScheduler(run_batch, SchedulerConfig(max_queue_delay=0.0)) as scheduler:
        with pytest.raises(ValueError, match="batch of 1"):
            await asyncio.wait_for(scheduler.submit(make_item("t")), GUARD)


@pytest.mark.asyncio
async def test_drain_finishes_queued_work_and_rejects_new_submits() -> None:
    model = FakeModel()
    # The delay would hold the partial last batch for 10 s: drain must not wait it out.
    scheduler = BatchScheduler(model, SchedulerConfig(max_batch=2, max_queue_delay=10.0))
    gate = await occupy_worker(scheduler, model, size=2)
    tasks = [asyncio.create_task(scheduler.submit(make_item(f"t{i}", i))) for i in range(5)]
    await asyncio.sleep(0.01)
    start = time.monotonic()
    draining = asyncio.create_task(scheduler.drain())
    await asyncio.sleep(0)
    assert scheduler.closed
    with pytest.raises(SchedulerClosedError):
        await scheduler.submit(make_item("too_late"))
    model.release.set()
    await asyncio.wait_for(draining, GUARD)
    assert time.monotonic() - start < 1.0
    assert all(task.done() for task in tasks)
    for i, task in enumerate(tasks):
        np.testing.assert_array_equal(task.result(), np.full(3, 2.0 * i, np.float32))
    await gate
    assert model.sizes == [2, 2, 2, 1]


@pytest.mark.asyncio
async def test_results_are_routed_to_their_own_tokens() -> None:
    model = FakeModel()
    items = [make_item(f"t{i}", float(i)) for i in range(40)]
    async with BatchScheduler(model, SchedulerConfig(max_batch=8, max_queue_delay=0.001)) as scheduler:
        results = await asyncio.wait_for(asyncio.gather(*(scheduler.submit(item) for item in items)), GUARD)
    assert max(model.sizes) > 1
    for item, result in zip(items, results, strict=True):
        assert result.shape == (3,)
        np.testing.assert_array_equal(result, item.inputs["x"] * 2)


@pytest.mark.asyncio
async def test_cancelled_queued_request_is_withdrawn() -> None:
    model = FakeModel()
    observer = RecordingObserver()
    async with BatchScheduler(model, SchedulerConfig(max_queue_delay=0.0), observer) as scheduler:
        gate = await occupy_worker(scheduler, model)
        doomed = asyncio.create_task(scheduler.submit(make_item("t")))
        await asyncio.sleep(0.01)
        doomed.cancel()
        with pytest.raises(asyncio.CancelledError):
            await doomed
        assert observer.depths[-1] == ("pi", 0)
        # The token is free again once its request is withdrawn.
        retry = asyncio.create_task(scheduler.submit(make_item("t", 5.0)))
        model.release.set()
        np.testing.assert_array_equal(await asyncio.wait_for(retry, GUARD), np.full(3, 10.0, np.float32))
        await gate
    assert model.batches() == [["gate"], ["t"]]


@pytest.mark.asyncio
async def test_duplicate_in_flight_token_is_rejected() -> None:
    model = FakeModel()
    async with BatchScheduler(model, SchedulerConfig(max_queue_delay=0.05)) as scheduler:
        first = asyncio.create_task(scheduler.submit(make_item("same")))
        await asyncio.sleep(0)
        with pytest.raises(ValueError, match="already in flight"):
            await scheduler.submit(make_item("same"))
        await asyncio.wait_for(first, GUARD)


@pytest.mark.asyncio
async def test_observer_sees_batches_waits_and_depth() -> None:
    model = FakeModel()
    observer = RecordingObserver()
    async with BatchScheduler(model, SchedulerConfig(max_batch=4, max_queue_delay=0.001), observer) as scheduler:
        await asyncio.wait_for(asyncio.gather(*(scheduler.submit(make_item(f"t{i}")) for i in range(10))), GUARD)
    assert sum(size for _, size, _ in observer.batches) == 10
    assert all(model_name == "pi" and seconds >= 0 for model_name, _, seconds in observer.batches)
    assert len(observer.waits) == 10 and all(seconds >= 0 for _, seconds in observer.waits)
    assert max(depth for _, depth in observer.depths) >= 4
    assert observer.depths[-1] == ("pi", 0)


@pytest.mark.asyncio
async def test_raising_observer_does_not_stall_inference() -> None:
    class Broken(RecordingObserver):
        def on_queue_wait(self, model: str, seconds: float) -> None:
            raise RuntimeError("exporter down")

    async with BatchScheduler(FakeModel(), SchedulerConfig(max_queue_delay=0.0), Broken()) as scheduler:
        result = await asyncio.wait_for(scheduler.submit(make_item("t", 1.0)), GUARD)
    np.testing.assert_array_equal(result, np.full(3, 2.0, np.float32))


@pytest.mark.asyncio
async def test_non_array_input_is_rejected_alone() -> None:
    async with BatchScheduler(FakeModel()) as scheduler:
        with pytest.raises(TypeError, match=r"not numpy\.ndarray"):
            await scheduler.submit(InferItem(token="t", model="pi", inputs={"x": [1.0, 2.0]}))


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"max_batch": 0}, "max_batch"),
        ({"max_batch": 2.5}, "max_batch"),
        ({"max_queue": 0}, "max_queue"),
        ({"workers": 0}, "workers"),
        ({"max_queue_delay": -0.001}, "max_queue_delay"),
        ({"max_queue_delay": float("nan")}, "max_queue_delay"),
        ({"max_batch": 64, "max_queue": 32}, "max_queue"),
        ({"early_dispatch": 1}, "early_dispatch"),
    ],
)
def test_config_validation(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SchedulerConfig(**kwargs)
