"""Critic service settings, read from ZETTA_* environment variables at start-up."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from services.common.config import EnvReader
from services.harness.package.format import MAX_PACKAGE_BYTES


@dataclass(frozen=True)
class CriticConfig:
    """Every knob of the critic service; docs/harness.md lists the variables."""

    host: str
    port: int
    metrics_port: int
    redis_url: str
    redis_prefix: str
    store: str
    max_package_bytes: int
    package_cache: int
    import_timeout_s: float
    grace_seconds: float

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "CriticConfig":
        """Read and validate; raises ConfigError naming every bad variable."""
        env = EnvReader(environ)
        cfg = cls(
            host=env.str("ZETTA_BIND_HOST", "127.0.0.1"),
            port=env.int("ZETTA_CRITIC_PORT", 50081, minimum=0, maximum=65535),
            metrics_port=env.int("ZETTA_METRICS_PORT", 9104, minimum=-1, maximum=65535),
            redis_url=env.str("ZETTA_REDIS_URL", required=True),
            redis_prefix=env.str("ZETTA_REDIS_PREFIX", "zetta"),
            store=env.str("ZETTA_CRITIC_STORE", required=True),
            max_package_bytes=env.int("ZETTA_CRITIC_MAX_PACKAGE_BYTES", MAX_PACKAGE_BYTES, minimum=1024,
                                      maximum=200 * 1024 * 1024),
            package_cache=env.int("ZETTA_CRITIC_PACKAGE_CACHE", 32, minimum=1),
            import_timeout_s=env.float("ZETTA_CRITIC_IMPORT_TIMEOUT_S", 20.0, minimum=0.5),
            grace_seconds=env.float("ZETTA_GRACE_SECONDS", 5.0, minimum=0.0),
        )
        env.finish("critic")
        return cfg
