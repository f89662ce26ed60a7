"""Prometheus metrics the gateway exports (besides the shared hop latency)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge

REQUESTS = Counter("zetta_gateway_requests_total", "Gateway calls by method and status code.", ["method", "code"])
REJECTED = Counter(
    "zetta_gateway_admissions_rejected_total", "CreateSessions calls refused, by family and reason.", ["family", "reason"]
)
SESSIONS = Gauge("zetta_sessions", "Sessions in the registry by family and state.", ["family", "state"])
WORKERS = Gauge("zetta_env_workers", "Registered env workers by health.", ["state"])
FREE_SLOTS = Gauge("zetta_env_worker_free_slots", "Free slots of each live env worker.", ["worker"])
MISSED_HEARTBEATS = Counter(
    "zetta_gateway_missed_heartbeats_total", "Monitor ticks that found a worker's heartbeat late.", ["worker"]
)
BUSY_LEASES = Counter(
    "zetta_gateway_busy_leases_total",
    "Heartbeats that carried a busy lease (a worker about to hold its GIL), by outcome (granted, capped "
    "at ZETTA_HEARTBEAT_MAX_BUSY_MS).",
    ["outcome"],
)
WORKERS_DEAD = Counter("zetta_gateway_workers_declared_dead_total", "Workers declared dead after missing heartbeats.")
SESSIONS_LOST = Counter("zetta_gateway_sessions_lost_total", "Sessions marked LOST because their worker died.")
LEASES_EXPIRED = Counter("zetta_gateway_leases_expired_total", "Sessions closed because their lease ran out.")
BLIND = Counter(
    "zetta_gateway_liveness_blind_total",
    "Times the gateway suspended dead-worker detection for a heartbeat timeout because it could not "
    "see heartbeats arrive (Redis error, slow Redis, event loop stall), by cause.",
    ["cause"],
)
