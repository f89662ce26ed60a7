"""Evolver service settings, read from ZETTA_* environment variables at start-up."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from services.common.config import EnvReader


@dataclass(frozen=True)
class EvolverConfig:
    """Every knob of the evolver service (docs/evolution.md lists them)."""

    host: str
    port: int
    metrics_port: int
    gateway: str
    registry: str
    store: str
    #: A policy worker of the stack, asked which instructions the frozen policy was trained on ("": none).
    policy_worker: str
    max_jobs: int
    grace_seconds: float

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "EvolverConfig":
        """Read and validate; raises ConfigError naming every bad variable."""
        env = EnvReader(environ)
        cfg = cls(
            host=env.str("ZETTA_BIND_HOST", "127.0.0.1"),
            port=env.int("ZETTA_EVOLVER_PORT", 50091, minimum=0, maximum=65535),
            metrics_port=env.int("ZETTA_METRICS_PORT", 9105, minimum=-1, maximum=65535),
            gateway=env.address("ZETTA_GATEWAY_ADDRESS", required=True),
            registry=env.address("ZETTA_CRITIC_ADDR", required=True),
            store=env.str("ZETTA_EVOLVER_STORE", required=True),
            policy_worker=env.address("ZETTA_POLICY_WORKER_ADDR"),
            max_jobs=env.int("ZETTA_EVOLVER_MAX_JOBS", 1, minimum=1, maximum=64),
            grace_seconds=env.float("ZETTA_GRACE_SECONDS", 30.0, minimum=0.0),
        )
        env.finish("evolver")
        return cfg
