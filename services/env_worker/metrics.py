"""Prometheus metrics an env worker exports (besides the shared hop latency)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge, Histogram

from services.common.metrics import LATENCY_BUCKETS

STEPS = Counter("zetta_env_steps_total", "Environment steps executed.", ["family"])
EPISODES = Counter("zetta_env_episodes_completed_total", "Episodes that ended, by outcome.", ["family", "outcome"])
RESETS = Counter("zetta_env_resets_total", "Episodes started.", ["family"])
STEP_SECONDS = Histogram(
    "zetta_env_step_duration_seconds", "Wall time of one environment step (physics and controller).", ["family"],
    buckets=LATENCY_BUCKETS,
)
RESET_SECONDS = Histogram(
    "zetta_env_reset_duration_seconds", "Wall time of a reset, env build included when it happens.", ["family"],
    buckets=LATENCY_BUCKETS,
)
SLOTS = Gauge("zetta_env_slots", "Slots of this worker by state.", ["state"])
POLICY_ERRORS = Counter("zetta_env_policy_errors_total", "Failed inference requests, by status code.", ["code"])
FRAMES = Counter(
    "zetta_env_frames_rendered_total",
    "Camera frames rendered (one per camera per rendered state: observations and video frames).", ["camera"],
)
