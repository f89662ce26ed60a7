"""Batching scheduler of the policy worker (the paper's Rollout Worker Scheduler).

Many env-worker sessions each ask for one action at a time; a policy amortises its kernel and
Python overhead only when those requests run together. The scheduler sits between the
per-request RPCs and the model: it sorts requests into compatibility groups (same model, same
input names, dtypes and shapes, the only ones that can be stacked), holds each group in a bounded
first-come-first-served queue, and hands whole batches to a thread pool running the user's
``run_batch`` so the event loop keeps accepting requests while the model computes.

When a batch is dispatched:
  * a group's batch goes out as soon as it holds ``max_batch`` items, or once its oldest item
    has waited ``max_queue_delay`` seconds, whichever comes first; while every worker thread is
    busy nothing goes out, so queues keep filling and the next batches are larger: under load
    batch size adapts to compute time without tuning;
  * when several groups are ready, the one whose oldest item arrived first is served first;
  * a group is also ready at once when waiting is not expected to grow its batch (early
    dispatch): when its queued and running items together are as many as it ever held at one
    time over the last ``PEAK_WINDOW_SECONDS`` (requesters in a closed loop, such as an env
    worker's slot that asks, waits for the answer, steps and asks again, cannot send a second
    request before the first is answered, so once every requester seen lately is waiting, no one
    is left to join), or when its requests arrive so rarely that fewer than one is expected over
    a whole ``max_queue_delay`` (the rate counted over the same windows). Without it a lone
    session paid ``max_queue_delay`` on every action chunk, and on a machine that steps a few
    hundred env steps per second every request waited about that long for nothing. A group with
    no history goes out at once for the same reasons; the estimates follow the load up at once
    and down within two windows.

Deadline rule: a request is failed with :class:`DeadlineExceededError`, without running, when at
submit or at dispatch its deadline has passed, or when it is earlier than ``now`` plus the
group's estimated batch compute time (an exponential moving average of recent batches; no
estimate exists before the group's first batch, so then only passed deadlines are rejected). The
estimate is that of running at once, so an item is rejected early only when even immediate
dispatch would very likely miss; time still to be spent in the queue is not charged against it.
Results that arrive after their deadline are still delivered: the caller decides what a late
action is worth.

The scheduler is pure asyncio and knows nothing of gRPC or Prometheus: the server wraps
:meth:`BatchScheduler.submit` and passes a :class:`SchedulerObserver` to export metrics.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

logger = logging.getLogger(__name__)

#: ``run_batch(model, stacked_inputs, instructions) -> outputs`` with the batch as first dim.
RunBatch = Callable[[str, dict[str, np.ndarray], list[str]], np.ndarray]

#: (model, sorted ((input name, dtype, shape), ...)): requests batch together only on equal keys.
GroupKey = tuple[str, tuple[tuple[str, np.dtype, tuple[int, ...]], ...]]

# Weight of the newest batch in the compute-time estimate: recent enough to follow load changes,
# smooth enough that one slow batch does not start rejecting deadlines.
_ESTIMATE_WEIGHT = 0.2
#: An estimate older than this no longer rejects requests early: the estimate only moves when a
#: batch runs, so after one slow spell it would otherwise refuse every request forever.
ESTIMATE_TTL_SECONDS = 5.0
# A retry hint of zero would invite a busy loop of retries against a full queue.
_MIN_RETRY_AFTER = 0.001
#: How long the most items a group held at once is remembered (see the module doc): long enough
#: to span many request cycles of a closed-loop client (tens of ms), short enough that a group
#: whose load fell stops waiting for requesters that left within a few seconds.
PEAK_WINDOW_SECONDS = 2.0


class SchedulerError(Exception):
    """Base of the errors a request can get from the scheduler rather than from the model."""


class QueueFullError(SchedulerError):
    """The request's group queue is at ``max_queue``; the caller should back off.

    ``retry_after`` (seconds) estimates when the queue will have drained enough to take it, so
    the server can pass it on as a back-pressure hint instead of letting clients retry blindly.
    """

    def __init__(self, message: str, retry_after: float) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class DeadlineExceededError(SchedulerError):
    """The request's deadline passed, or could not be met, before it ran; the model never saw it."""


class SchedulerClosedError(SchedulerError):
    """The scheduler is draining or drained and takes no new requests."""


@dataclass(eq=False, slots=True)
class InferItem:
    """One inference request: a single sample, no batch dimension.

    ``deadline`` is absolute ``time.monotonic()`` seconds. ``arrival`` defaults to construction
    time; the server should stamp it when the request is received, so that ``max_queue_delay``
    and FCFS order count the time the request has already spent before reaching the scheduler.
    Identity equality (``eq=False``) because ndarray fields make value equality ambiguous.
    """

    token: str
    model: str
    inputs: dict[str, np.ndarray]
    instruction: str = ""
    deadline: float | None = None
    arrival: float = field(default_factory=time.monotonic)


@dataclass(frozen=True)
class SchedulerConfig:
    """Batching limits; checked at construction so a bad deployment value fails at start-up."""

    #: Defaults from `bench/bench_policy.py` (docs/configuration.md cites the run): at 400 req/s on
    #: the shipped VLA, max_batch 32 had the highest goodput of 1..64 and a 5 ms delay beat 0-2 ms.
    max_batch: int = 32
    max_queue_delay: float = 0.005
    max_queue: int = 1024
    workers: int = 1
    #: Dispatch a partial batch at once when every requester seen lately is waiting (module doc);
    #: False waits out ``max_queue_delay`` regardless (what bench/bench_scheduler.py compares).
    early_dispatch: bool = True

    def __post_init__(self) -> None:
        for name in ("max_batch", "max_queue", "workers"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"SchedulerConfig.{name} must be an integer >= 1, got {value!r}")
        delay = self.max_queue_delay
        if isinstance(delay, bool) or not isinstance(delay, (int, float)) or not math.isfinite(delay) or delay < 0:
            raise ValueError(f"SchedulerConfig.max_queue_delay must be a finite number of seconds >= 0, got {delay!r}")
        if not isinstance(self.early_dispatch, bool):
            raise ValueError(f"SchedulerConfig.early_dispatch must be a bool, got {self.early_dispatch!r}")
        if self.max_queue < self.max_batch:
            raise ValueError(
                f"SchedulerConfig.max_queue ({self.max_queue}) must be >= max_batch ({self.max_batch}), "
                "otherwise a full batch can never form"
            )


class SchedulerObserver(Protocol):
    """Metrics hooks, so the server can export Prometheus metrics without the scheduler
    depending on it. Called on the event loop, several times per request: keep them cheap.

    ``on_reject`` reasons: ``"closed"``, ``"queue_full"``, ``"deadline_expired"``,
    ``"deadline_unreachable"``. ``on_queue_depth`` reports the model's queued requests summed
    over its compatibility groups.
    """

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None: ...

    def on_queue_wait(self, model: str, seconds: float) -> None: ...

    def on_queue_depth(self, model: str, depth: int) -> None: ...

    def on_reject(self, model: str, reason: str) -> None: ...


class NullObserver:
    """Every hook a no-op: what the scheduler calls without an observer (so the hot path calls hooks
    unconditionally instead of testing for one), and the base of observers that need only some."""

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        pass

    def on_queue_wait(self, model: str, seconds: float) -> None:
        pass

    def on_queue_depth(self, model: str, depth: int) -> None:
        pass

    def on_reject(self, model: str, reason: str) -> None:
        pass


class _GuardedObserver:
    """A raising metrics exporter must not kill the dispatcher and strand every waiting request.

    Only the first failure is logged: an observer that fails once usually fails on every call,
    and logging each would put logging back on the per-request path.
    """

    __slots__ = ("_inner", "_logged")

    def __init__(self, inner: SchedulerObserver) -> None:
        self._inner = inner
        self._logged = False

    def _failed(self, hook: str) -> None:
        if not self._logged:
            self._logged = True
            logger.exception("scheduler observer %s raised; further observer errors are not logged", hook)

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        try:
            self._inner.on_batch(model, size, compute_seconds)
        except Exception:  # noqa: BLE001 - an observer must never fail a batch
            self._failed("on_batch")

    def on_queue_wait(self, model: str, seconds: float) -> None:
        try:
            self._inner.on_queue_wait(model, seconds)
        except Exception:  # noqa: BLE001 - an observer must never fail a batch
            self._failed("on_queue_wait")

    def on_queue_depth(self, model: str, depth: int) -> None:
        try:
            self._inner.on_queue_depth(model, depth)
        except Exception:  # noqa: BLE001 - an observer must never fail a batch
            self._failed("on_queue_depth")

    def on_reject(self, model: str, reason: str) -> None:
        try:
            self._inner.on_reject(model, reason)
        except Exception:  # noqa: BLE001 - an observer must never fail a batch
            self._failed("on_reject")


def compatibility_key(item: InferItem) -> GroupKey:
    """Group key of ``item``; raises TypeError for inputs that are not numpy arrays.

    Checked at submit rather than at stacking time, so one malformed request fails alone instead
    of failing the batch it would have joined.
    """
    entries = []
    for name, array in item.inputs.items():
        if not isinstance(array, np.ndarray):
            raise TypeError(f"request {item.token!r}: input {name!r} is {type(array).__name__}, not numpy.ndarray")
        entries.append((name, array.dtype, array.shape))
    entries.sort(key=lambda entry: entry[0])
    return item.model, tuple(entries)


class _Group:
    __slots__ = ("model", "queue")

    def __init__(self, model: str) -> None:
        self.model = model
        self.queue: deque[InferItem] = deque()


class _Occupancy:
    """Items of one group in the scheduler (queued or running), the most it held at once lately,
    and how often its items arrive.

    Both are kept over two consecutive windows of ``PEAK_WINDOW_SECONDS`` (the current one and the
    one before), so a burst is forgotten between one and two windows after it ended.
    """

    __slots__ = ("running", "peak_now", "peak_before", "count_now", "count_before", "window_start")

    def __init__(self, now: float) -> None:
        self.running = 0
        self.peak_now = self.peak_before = 0
        self.count_now = self.count_before = 0
        self.window_start = now

    def _roll(self, now: float) -> None:
        elapsed = now - self.window_start
        if elapsed >= PEAK_WINDOW_SECONDS:
            recent = elapsed < 2 * PEAK_WINDOW_SECONDS
            self.peak_before = self.peak_now if recent else 0
            self.count_before = self.count_now if recent else 0
            self.peak_now = self.count_now = 0
            self.window_start = now

    def arrived(self, in_system: int, now: float) -> None:
        """Record an arrival, after which the group holds ``in_system`` items."""
        self._roll(now)
        self.count_now += 1
        if in_system > self.peak_now:
            self.peak_now = in_system

    def peak(self, now: float) -> int:
        """The most items the group held at once over the last one to two windows."""
        self._roll(now)
        return max(self.peak_now, self.peak_before)

    def rate(self, now: float) -> float:
        """Arrivals per second over the last one to two windows (counted over at least a whole
        window, so a group with little history has a low rate rather than a noisy one)."""
        self._roll(now)
        return (self.count_before + self.count_now) / (PEAK_WINDOW_SECONDS + (now - self.window_start))


class BatchScheduler:
    """Dynamic batcher: ``await submit(item)`` returns the item's row of its batch's output.

    Bound to the event loop of its first :meth:`submit`; its dispatcher task starts then.
    Results are routed back by token, so a token may have only one request in flight
    (a second submit with it raises ValueError until the first has completed or been withdrawn).
    """

    def __init__(
        self,
        run_batch: RunBatch,
        config: SchedulerConfig | None = None,
        observer: SchedulerObserver | None = None,
    ) -> None:
        self._run_batch = run_batch
        self._config = config or SchedulerConfig()
        self._observer: SchedulerObserver = _GuardedObserver(observer) if observer is not None else NullObserver()
        self._executor = ThreadPoolExecutor(max_workers=self._config.workers, thread_name_prefix="policy-batch")
        # Insertion-ordered; a group is removed as soon as its queue empties, so the dispatcher
        # scans only groups with work.
        self._groups: dict[GroupKey, _Group] = {}
        self._waiters: dict[str, asyncio.Future[np.ndarray]] = {}
        self._depth: dict[str, int] = {}
        self._estimates: dict[GroupKey, float] = {}
        self._estimated_at: dict[GroupKey, float] = {}
        self._occupancy: dict[GroupKey, _Occupancy] = {}
        self._busy = 0
        self._closing = False
        self._dispatcher: asyncio.Task[None] | None = None
        self._wake: asyncio.Future[None] | None = None

    @property
    def closed(self) -> bool:
        """Lets the server report not-serving to health checks as soon as a drain starts."""
        return self._closing

    def compute_estimate(self, key: GroupKey) -> float | None:
        """The moving average of batch compute seconds behind the deadline and retry-after
        estimates (None before the group's first batch), exposed so callers can reason with the
        same number the scheduler uses."""
        return self._estimates.get(key)

    async def __aenter__(self) -> BatchScheduler:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.drain()

    async def submit(self, item: InferItem) -> np.ndarray:
        """Queue ``item`` and wait for its result (``run_batch`` output row for this item).

        Raises SchedulerClosedError, QueueFullError, DeadlineExceededError, TypeError/ValueError
        for a malformed request, or whatever ``run_batch`` raised for the item's batch.
        Cancelling the caller withdraws the item if it has not been dispatched yet.
        """
        model = item.model
        if self._closing:
            self._observer.on_reject(model, "closed")
            raise SchedulerClosedError("scheduler is draining; not accepting requests")
        key = compatibility_key(item)
        token = item.token
        if token in self._waiters:
            raise ValueError(f"request token {token!r} is already in flight")
        if item.deadline is not None:
            self._check_deadline(key, item, item.deadline, time.monotonic())
        config = self._config
        group = self._groups.get(key)
        if group is None:
            group = self._groups[key] = _Group(model)
        elif len(group.queue) >= config.max_queue:
            self._observer.on_reject(model, "queue_full")
            retry_after = self._retry_after(key, len(group.queue))
            raise QueueFullError(
                f"queue of model {model!r} is full ({config.max_queue} requests); retry in {retry_after:.3f}s",
                retry_after,
            )

        loop = asyncio.get_running_loop()
        future: asyncio.Future[np.ndarray] = loop.create_future()
        self._waiters[token] = future
        queue = group.queue
        queue.append(item)
        occupancy = self._occupancy.get(key)
        if occupancy is None:
            occupancy = self._occupancy[key] = _Occupancy(item.arrival)
        occupancy.arrived(len(queue) + occupancy.running, time.monotonic())
        depth = self._depth[model] = self._depth.get(model, 0) + 1
        self._observer.on_queue_depth(model, depth)
        if self._dispatcher is None:
            self._dispatcher = loop.create_task(self._dispatch_loop(), name="policy-batch-dispatcher")
        elif (len(queue) == 1 or len(queue) == config.max_batch
              or self._all_waiting(occupancy, len(queue), time.monotonic())):
            # A new head arms a new delay timer, a full queue is ready now, and so is a group
            # whose requesters are all waiting; any other arrival does not change when the next
            # dispatch is due.
            self._kick()
        try:
            return await future
        except asyncio.CancelledError:
            self._withdraw(key, item)
            raise

    async def drain(self) -> None:
        """Stop taking requests, run everything already queued (without waiting out
        ``max_queue_delay``), wait for running batches, then release the worker threads."""
        self._closing = True
        if self._dispatcher is not None:
            self._kick()
            # Shielded: a caller giving up on drain must not kill the dispatcher mid-shutdown.
            await asyncio.shield(self._dispatcher)
        self._executor.shutdown(wait=False)

    def _check_deadline(self, key: GroupKey, item: InferItem, deadline: float, now: float) -> None:
        if deadline <= now:
            self._observer.on_reject(item.model, "deadline_expired")
            raise DeadlineExceededError(f"request {item.token!r}: deadline passed {now - deadline:.4f}s ago")
        estimate = self._estimates.get(key)
        fresh = now - self._estimated_at.get(key, now) < ESTIMATE_TTL_SECONDS
        if estimate is not None and fresh and now + estimate > deadline:
            self._observer.on_reject(item.model, "deadline_unreachable")
            raise DeadlineExceededError(
                f"request {item.token!r}: {deadline - now:.4f}s left, a batch takes about {estimate:.4f}s"
            )

    def _retry_after(self, key: GroupKey, depth: int) -> float:
        config = self._config
        per_batch = self._estimates.get(key, config.max_queue_delay)
        batches_ahead = -(-depth // config.max_batch)
        return max(batches_ahead * per_batch / config.workers, config.max_queue_delay, _MIN_RETRY_AFTER)

    def _withdraw(self, key: GroupKey, item: InferItem) -> None:
        """Drop a cancelled request that is still queued; one already dispatched just runs and
        its result is discarded."""
        group = self._groups.get(key)
        if group is None:
            return
        try:
            group.queue.remove(item)
        except ValueError:
            return
        del self._waiters[item.token]
        if not group.queue:
            del self._groups[key]
        depth = self._depth[item.model] = self._depth[item.model] - 1
        self._observer.on_queue_depth(item.model, depth)

    def _kick(self) -> None:
        wake = self._wake
        if wake is not None and not wake.done():
            wake.set_result(None)

    async def _dispatch_loop(self) -> None:
        """Owns the max_queue_delay timer; batches that are ready at once go out from _pump."""
        loop = asyncio.get_running_loop()
        while True:
            timeout = self._pump()
            if self._closing and not self._groups and self._busy == 0:
                return
            self._wake = wake = loop.create_future()
            timer = loop.call_later(timeout, self._kick) if timeout is not None else None
            await wake
            if timer is not None:
                timer.cancel()

    def _pump(self) -> float | None:
        """Dispatch ready batches while a worker is free; return seconds until the next is due
        (None: nothing queued, or every worker busy, so only a completion can change that)."""
        workers = self._config.workers
        while self._busy < workers:
            now = time.monotonic()
            key, timeout = self._ready_group(now)
            if key is None:
                return timeout
            self._dispatch(key, now)
        return None

    def _ready_group(self, now: float) -> tuple[GroupKey | None, float | None]:
        """The ready group whose oldest item arrived first, else how long until one is due.

        Groups not yet ready are not served ahead of ready ones even if older: dispatching them
        early would only shrink their batch while a full one waits. A group is ready when full,
        when its head waited ``max_queue_delay``, or when no other requester is expected (see the
        module doc).
        """
        config = self._config
        delay = config.max_queue_delay
        max_batch = config.max_batch
        closing = self._closing
        best: GroupKey | None = None
        best_arrival = math.inf
        timeout: float | None = None
        for key, group in self._groups.items():
            queue = group.queue
            head_arrival = queue[0].arrival
            due_in = head_arrival + delay - now
            if (closing or due_in <= 0 or len(queue) >= max_batch
                    or self._all_waiting(self._occupancy[key], len(queue), now)):
                if head_arrival < best_arrival:
                    best, best_arrival = key, head_arrival
            elif timeout is None or due_in < timeout:
                timeout = due_in
        return best, timeout

    def _all_waiting(self, occupancy: _Occupancy, queued: int, now: float) -> bool:
        """Whether waiting is not expected to add a request: the group holds as many items as it
        ever did lately, or fewer than one arrival is expected over a whole ``max_queue_delay``."""
        config = self._config
        return config.early_dispatch and (queued + occupancy.running >= occupancy.peak(now)
                                          or occupancy.rate(now) * config.max_queue_delay < 1.0)

    def _dispatch(self, key: GroupKey, now: float) -> None:
        group = self._groups[key]
        queue = group.queue
        model = group.model
        observer = self._observer
        waiters = self._waiters
        max_batch = self._config.max_batch
        batch: list[InferItem] = []
        taken = 0
        while queue and len(batch) < max_batch:
            item = queue.popleft()
            taken += 1
            future = waiters[item.token]
            if future.done():  # cancelled, its submit has not run its withdrawal yet
                del waiters[item.token]
                continue
            if item.deadline is not None:
                try:
                    self._check_deadline(key, item, item.deadline, now)
                except DeadlineExceededError as exc:
                    del waiters[item.token]
                    future.set_exception(exc)
                    continue
            observer.on_queue_wait(model, now - item.arrival)
            batch.append(item)
        if not queue:
            del self._groups[key]
        depth = self._depth[model] = self._depth[model] - taken
        observer.on_queue_depth(model, depth)
        if batch:
            self._busy += 1
            self._occupancy[key].running += len(batch)
            running = asyncio.get_running_loop().run_in_executor(self._executor, self._compute, model, batch)
            running.add_done_callback(functools.partial(self._finished, key, model, batch))

    def _finished(
        self,
        key: GroupKey,
        model: str,
        batch: list[InferItem],
        running: asyncio.Future[tuple[np.ndarray, float]],
    ) -> None:
        self._busy -= 1
        self._occupancy[key].running -= len(batch)
        # Refill the worker before waking the callers: their wake-ups and next submits cost loop
        # time, and a batch already waiting in the queue should not sit behind them.
        self._pump()
        self._kick()
        waiters = self._waiters
        error = running.exception()
        if error is not None:
            for item in batch:
                future = waiters.pop(item.token)
                if not future.done():
                    future.set_exception(error)
            return
        outputs, seconds = running.result()
        for row, item in enumerate(batch):
            future = waiters.pop(item.token)
            if not future.done():
                future.set_result(outputs[row])
        previous = self._estimates.get(key)
        self._estimates[key] = seconds if previous is None else previous + _ESTIMATE_WEIGHT * (seconds - previous)
        self._estimated_at[key] = time.monotonic()
        self._observer.on_batch(model, len(batch), seconds)

    def _compute(self, model: str, batch: list[InferItem]) -> tuple[np.ndarray, float]:
        """Runs on a worker thread: stacking large observations is copy work the event loop
        should not do."""
        stacked = {name: np.stack([item.inputs[name] for item in batch]) for name in batch[0].inputs}
        instructions = [item.instruction for item in batch]
        start = time.perf_counter()
        outputs = self._run_batch(model, stacked, instructions)
        seconds = time.perf_counter() - start
        if not isinstance(outputs, np.ndarray) or outputs.ndim == 0 or outputs.shape[0] != len(batch):
            shape = getattr(outputs, "shape", type(outputs).__name__)
            raise ValueError(
                f"run_batch for model {model!r} returned {shape} for a batch of {len(batch)}; "
                "expected a numpy array with the batch as first dimension"
            )
        return outputs, seconds
