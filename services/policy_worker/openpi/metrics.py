"""Prometheus metrics of the openpi pool (per server) and the openpi endpoint (per client batch)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge, Histogram

from services.common.metrics import LATENCY_BUCKETS

LATENCY = Histogram("zetta_openpi_server_seconds", "Round trip of one request to an openpi server.", ["server"],
                    buckets=LATENCY_BUCKETS)
IN_FLIGHT = Gauge("zetta_openpi_server_in_flight", "Requests waiting on an openpi server.", ["server"])
ERRORS = Counter("zetta_openpi_server_errors_total", "Requests to an openpi server that failed or came late.",
                 ["server"])
ENDPOINT_REQUESTS = Counter("zetta_openpi_endpoint_requests_total", "openpi requests answered, by outcome.",
                            ["outcome"])
ENDPOINT_LATENCY = Histogram("zetta_openpi_endpoint_seconds", "openpi request to reply through the endpoint.",
                             buckets=LATENCY_BUCKETS)
ENDPOINT_CLIENTS = Gauge("zetta_openpi_endpoint_clients", "Connected openpi clients.")
