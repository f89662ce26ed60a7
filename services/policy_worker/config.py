"""Policy worker settings, read from ZETTA_* environment variables at start-up."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from services.common.policies import DEFAULT_POLICY
from services.common.config import EnvReader
from services.policy_worker.models.base import FACTORIES
from services.policy_worker.scheduler import SchedulerConfig


@dataclass(frozen=True)
class PolicyWorkerConfig:
    """Every knob of a policy worker; see docs/configuration.md."""

    host: str
    port: int
    metrics_port: int
    models: tuple[str, ...]
    scheduler: SchedulerConfig
    default_timeout_ms: int
    grace_seconds: float
    #: ZETTA_VLA_SPLIT: serve the Zetta VLA's two stages in two processes (docs/policies.md).
    vla_split: bool = False
    #: ZETTA_INPUT_CHECK_FAMILY: the env family whose observations every served model's inputs
    #: are checked against at start-up ("" skips the check).
    input_check_family: str = "libero"
    #: CPUs the worker pins itself to at start-up (ZETTA_CPUS, a list like 0-3,8); None: not pinned.
    cpus: frozenset[int] | None = None

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "PolicyWorkerConfig":
        """Read and validate; raises ConfigError naming every bad variable."""
        env = EnvReader(environ)
        models = tuple(m.strip() for m in env.str("ZETTA_MODELS", DEFAULT_POLICY).split(",") if m.strip())
        for m in models:
            if m not in FACTORIES:
                env.fail(f"ZETTA_MODELS: unknown model {m!r}; known: {', '.join(sorted(FACTORIES))}")
        if not models:
            env.fail("ZETTA_MODELS is empty: name at least one model")
        max_batch = env.int("ZETTA_MAX_BATCH", SchedulerConfig.max_batch, minimum=1)
        max_queue = env.int("ZETTA_MAX_QUEUE", 1024, minimum=1)
        delay_ms = env.float("ZETTA_MAX_QUEUE_DELAY_MS", SchedulerConfig.max_queue_delay * 1000, minimum=0.0)
        workers = env.int("ZETTA_INFERENCE_THREADS", 1, minimum=1)
        early = env.bool("ZETTA_EARLY_DISPATCH", SchedulerConfig.early_dispatch)
        host = env.str("ZETTA_BIND_HOST", "127.0.0.1")
        port = env.int("ZETTA_POLICY_WORKER_PORT", 50071, minimum=0, maximum=65535)
        metrics_port = env.int("ZETTA_METRICS_PORT", 9103, minimum=-1, maximum=65535)
        timeout = env.int("ZETTA_POLICY_TIMEOUT_MS", 10_000, minimum=1)
        grace = env.float("ZETTA_GRACE_SECONDS", 5.0, minimum=0.0)
        vla_split = env.bool("ZETTA_VLA_SPLIT", False)
        input_check_family = env.str("ZETTA_INPUT_CHECK_FAMILY", "libero").strip()
        cpus = env.cpus("ZETTA_CPUS")
        if max_queue < max_batch:
            env.fail(f"ZETTA_MAX_QUEUE={max_queue} must be >= ZETTA_MAX_BATCH={max_batch}")
        env.finish("policy worker")
        return cls(
            host=host,
            port=port,
            metrics_port=metrics_port,
            models=models,
            scheduler=SchedulerConfig(
                max_batch=max_batch, max_queue_delay=delay_ms / 1000.0, max_queue=max_queue, workers=workers,
                early_dispatch=early,
            ),
            default_timeout_ms=timeout,
            grace_seconds=grace,
            vla_split=vla_split,
            input_check_family=input_check_family,
            cpus=cpus,
        )
