"""Gateway settings, read from ZETTA_* environment variables at start-up."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from services.common.config import EnvReader


@dataclass(frozen=True)
class GatewayConfig:
    """Every knob of the gateway; see docs/configuration.md for the variables."""

    host: str
    port: int
    metrics_port: int
    redis_url: str
    redis_prefix: str
    heartbeat_interval_ms: int
    heartbeat_timeout_ms: int
    #: Longest busy lease a worker's heartbeat may ask for (0: leases are refused, capped to none).
    heartbeat_max_busy_ms: int
    default_lease_seconds: int
    max_lease_seconds: int
    max_sessions_per_call: int
    max_request_bytes: int
    auth_tokens_file: str
    tombstone_seconds: int
    retry_after_ms: int
    create_timeout_ms: int
    reset_timeout_ms: int
    step_timeout_ms: int
    episode_timeout_ms: int
    monitor_interval_ms: int
    grace_seconds: float

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "GatewayConfig":
        """Read and validate; raises ConfigError naming every bad variable."""
        env = EnvReader(environ)
        hb_interval = env.int("ZETTA_HEARTBEAT_INTERVAL_MS", 1000, minimum=50)
        cfg = cls(
            host=env.str("ZETTA_BIND_HOST", "127.0.0.1"),
            port=env.int("ZETTA_GATEWAY_PORT", 50051, minimum=0, maximum=65535),
            metrics_port=env.int("ZETTA_METRICS_PORT", 9101, minimum=-1, maximum=65535),
            redis_url=env.str("ZETTA_REDIS_URL", required=True),
            redis_prefix=env.str("ZETTA_REDIS_PREFIX", "zetta"),
            heartbeat_interval_ms=hb_interval,
            heartbeat_timeout_ms=env.int("ZETTA_HEARTBEAT_TIMEOUT_MS", 3 * hb_interval, minimum=100),
            heartbeat_max_busy_ms=env.int("ZETTA_HEARTBEAT_MAX_BUSY_MS", 30_000, minimum=0, maximum=3_600_000),
            default_lease_seconds=env.int("ZETTA_DEFAULT_LEASE_SECONDS", 600, minimum=1),
            max_lease_seconds=env.int("ZETTA_MAX_LEASE_SECONDS", 86400, minimum=1),
            max_sessions_per_call=env.int("ZETTA_MAX_SESSIONS_PER_CALL", 1024, minimum=1, maximum=100_000),
            max_request_bytes=env.int("ZETTA_MAX_REQUEST_BYTES", 16 * 1024 * 1024, minimum=64 * 1024,
                                      maximum=1024 * 1024 * 1024),
            auth_tokens_file=env.str("ZETTA_AUTH_TOKENS_FILE", ""),
            tombstone_seconds=env.int("ZETTA_TOMBSTONE_SECONDS", 3600, minimum=1),
            retry_after_ms=env.int("ZETTA_RETRY_AFTER_MS", 2000, minimum=1),
            create_timeout_ms=env.int("ZETTA_CREATE_TIMEOUT_MS", 300_000, minimum=100),
            reset_timeout_ms=env.int("ZETTA_RESET_TIMEOUT_MS", 120_000, minimum=100),
            step_timeout_ms=env.int("ZETTA_STEP_TIMEOUT_MS", 30_000, minimum=10),
            episode_timeout_ms=env.int("ZETTA_EPISODE_TIMEOUT_MS", 1_800_000, minimum=100),
            monitor_interval_ms=env.int("ZETTA_MONITOR_INTERVAL_MS", max(50, hb_interval // 2), minimum=10),
            grace_seconds=env.float("ZETTA_GRACE_SECONDS", 5.0, minimum=0.0),
        )
        if cfg.heartbeat_timeout_ms <= cfg.heartbeat_interval_ms:
            env.fail(
                f"ZETTA_HEARTBEAT_TIMEOUT_MS={cfg.heartbeat_timeout_ms} must exceed "
                f"ZETTA_HEARTBEAT_INTERVAL_MS={cfg.heartbeat_interval_ms}"
            )
        if cfg.default_lease_seconds > cfg.max_lease_seconds:
            env.fail("ZETTA_DEFAULT_LEASE_SECONDS exceeds ZETTA_MAX_LEASE_SECONDS")
        env.finish("gateway")
        return cfg
