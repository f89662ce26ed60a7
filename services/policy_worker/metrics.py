"""Prometheus metrics of a policy worker, fed by the scheduler's observer hooks."""

from __future__ import annotations

from prometheus_client import Counter, Gauge, Histogram

from services.common.metrics import BATCH_BUCKETS, LATENCY_BUCKETS

BATCH_SIZE = Histogram("zetta_policy_batch_size", "Items per inference batch.", ["model"], buckets=BATCH_BUCKETS)
COMPUTE_SECONDS = Histogram(
    "zetta_policy_batch_compute_seconds", "Model time of one batch.", ["model"], buckets=LATENCY_BUCKETS
)
QUEUE_WAIT = Histogram(
    "zetta_policy_queue_wait_seconds", "Time an item waited before its batch ran.", ["model"], buckets=LATENCY_BUCKETS
)
QUEUE_DEPTH = Gauge("zetta_policy_queue_depth", "Items waiting, by model.", ["model"])
REJECTED = Counter("zetta_policy_rejected_total", "Items refused or failed before running, by reason.", ["model", "reason"])
ITEMS = Counter("zetta_policy_items_total", "Items answered, by model.", ["model"])


class PrometheusObserver:
    """The scheduler's observer hooks, exported as metrics."""

    def on_batch(self, model: str, size: int, compute_seconds: float) -> None:
        """A batch ran."""
        BATCH_SIZE.labels(model).observe(size)
        COMPUTE_SECONDS.labels(model).observe(compute_seconds)
        ITEMS.labels(model).inc(size)

    def on_queue_wait(self, model: str, seconds: float) -> None:
        """An item left the queue."""
        QUEUE_WAIT.labels(model).observe(seconds)

    def on_queue_depth(self, model: str, depth: int) -> None:
        """The queue changed length."""
        QUEUE_DEPTH.labels(model).set(depth)

    def on_reject(self, model: str, reason: str) -> None:
        """An item was refused."""
        REJECTED.labels(model, reason).inc()
