"""Metric conventions shared by every service: bucket layouts and the hop-latency histogram.

One layout for every latency histogram lets a Grafana panel put the hops of one request side by
side (client -> gateway -> env worker -> policy worker) and subtract them.
"""

from __future__ import annotations

from prometheus_client import Histogram

#: From 100 us (a loopback hop) to 30 s (an env build).
LATENCY_BUCKETS: tuple[float, ...] = (
    0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
)

#: Powers of two up to the largest batch a policy worker forms.
BATCH_BUCKETS: tuple[float, ...] = (1, 2, 4, 8, 16, 32, 64, 128, 256)

#: Latency of one hop of a request, labelled by the service that measured it and the method.
HOP_LATENCY = Histogram(
    "zetta_hop_latency_seconds",
    "Time a request spent in one hop (service and method), downstream calls included.",
    ["service", "method"],
    buckets=LATENCY_BUCKETS,
)
