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
INFER_CALL_ITEMS = Histogram(
    "zetta_env_infer_call_items", "Inference requests sent together in one Infer call to a policy worker.",
    buckets=(1, 2, 4, 8, 16, 32, 64, 128),
)
INFER_HOLD_SECONDS = Histogram(
    "zetta_env_infer_hold_seconds",
    "How long the oldest request of an Infer call waited in the env worker for others to join it.",
    buckets=LATENCY_BUCKETS,
)
POLICY_ERRORS = Counter("zetta_env_policy_errors_total", "Failed inference requests, by status code.", ["code"])
FRAMES = Counter(
    "zetta_env_frames_rendered_total",
    "Camera frames rendered (one per camera per rendered state: observations and video frames).", ["camera"],
)
BUSY_LEASES = Counter(
    "zetta_env_busy_leases_total",
    "Busy leases taken before work that holds the GIL (services/env_worker/busy.py), by what and outcome "
    "(granted; unacknowledged: the gateway did not answer in time; unannounced; standalone: no membership).",
    ["what", "outcome"],
)
BUSY_LEASE_SECONDS = Histogram(
    "zetta_env_busy_lease_seconds", "How long each busy lease was held, by what it covered.", ["what"],
    buckets=(0.05, 0.1, 0.25, 0.5, 1, 2, 4, 8, 15, 30, 60),
)
HARNESS_ACTIONS = Counter(
    "zetta_env_harness_actions_total",
    "Actions executed in harnessed episodes, by who chose them (policy or recovery); counted at episode end.",
    ["by"],
)
HARNESS_INTERVENTIONS = Counter(
    "zetta_env_harness_interventions_total", "Interventions of finished harnessed episodes, by kind and outcome.",
    ["kind", "outcome"],
)
HARNESS_CRITICS_DISABLED = Counter(
    "zetta_env_harness_critics_disabled_total", "Critics switched off mid-episode (raised, overran, bad output).",
)


def count_harness_episode(policy_actions: int, recovery_actions: int, interventions: list[tuple[str, str]],
                          disabled_critics: int) -> None:
    """Once per finished harnessed episode, so a dashboard shows how much the recoveries do."""
    HARNESS_ACTIONS.labels("policy").inc(policy_actions)
    HARNESS_ACTIONS.labels("recovery").inc(recovery_actions)
    for kind, outcome in interventions:
        HARNESS_INTERVENTIONS.labels(kind, outcome).inc()
    HARNESS_CRITICS_DISABLED.inc(disabled_critics)
