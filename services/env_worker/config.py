"""Env worker settings, read from ZETTA_* environment variables at start-up."""

from __future__ import annotations

import socket
from collections.abc import Mapping
from dataclasses import dataclass

from services.common.config import EnvReader
from services.common.cpus import usable_cpus
from services.env_worker.advertise import advertised_address
from services.env_worker.policy_client import InferHold

#: Longest wait of a held inference request (policy_client.py); docs/throughput.md measures it.
DEFAULT_INFER_HOLD_MS = 200.0


@dataclass(frozen=True)
class EnvWorkerConfig:
    """Every knob of an env worker; see docs/configuration.md."""

    host: str
    port: int
    metrics_port: int
    worker_id: str
    advertise_address: str
    gateway_address: str
    policy_addresses: tuple[str, ...]
    families: tuple[str, ...]
    slots: int
    default_policy_timeout_ms: int
    grace_seconds: float
    #: Directory for episode videos (ZETTA_VIDEO_DIR), created and proven writable at start-up;
    #: empty: sessions cannot ask for videos.
    video_dir: str = ""
    #: One resource-sharing group per (family, config) (ZETTA_RESOURCE_SHARING, default on); off,
    #: every session compiles its own scene: the baseline `zetta bench rollout` compares against.
    resource_sharing: bool = True
    #: The critic service (ZETTA_CRITIC_ADDR, host:port) that resets naming a harness by registry
    #: reference load it from; empty: only harness_dir packages can run.
    critic_address: str = ""
    #: Worker credential presented to the gateway's WorkerRegistryService (ZETTA_WORKER_TOKEN);
    #: empty where the gateway runs without auth.
    worker_token: str = ""
    #: How inference requests wait for each other to leave as one batch (ZETTA_INFER_HOLD_MS,
    #: ZETTA_INFER_HOLD_MIN_BUSY; services/env_worker/policy_client.py).
    infer_hold: InferHold = InferHold()
    #: How many slots run env work at the same time (ZETTA_STEP_CONCURRENCY; default the CPUs this
    #: process may use, ZETTA_CPUS if set, services/common/cpus.py; 0: no bound; SlotActivity).
    step_concurrency: int = 0
    #: CPUs the worker pins itself to at start-up (ZETTA_CPUS, a list like 0-3,8); None: not pinned.
    cpus: frozenset[int] | None = None

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "EnvWorkerConfig":
        """Read and validate; raises ConfigError naming every bad variable."""
        env = EnvReader(environ)
        host = env.str("ZETTA_BIND_HOST", "127.0.0.1")
        port = env.int("ZETTA_ENV_WORKER_PORT", 50061, minimum=0, maximum=65535)
        policy = tuple(a.strip() for a in env.str("ZETTA_POLICY_ADDRESSES", "").split(",") if a.strip())
        for addr in policy:
            if ":" not in addr:
                env.fail(f"ZETTA_POLICY_ADDRESSES: {addr!r} is not a host:port address")
        families = tuple(f.strip() for f in env.str("ZETTA_ENV_FAMILIES", "libero,robosuite").split(",") if f.strip())
        if not families:
            env.fail("ZETTA_ENV_FAMILIES is empty: name at least one family")
        cpus = env.cpus("ZETTA_CPUS")
        cfg = cls(
            host=host,
            port=port,
            metrics_port=env.int("ZETTA_METRICS_PORT", 9102, minimum=-1, maximum=65535),
            worker_id=env.str("ZETTA_WORKER_ID", ""),
            advertise_address=env.str("ZETTA_ADVERTISE_ADDRESS", ""),
            gateway_address=env.address("ZETTA_GATEWAY_ADDRESS", required=True),
            policy_addresses=policy,
            families=families,
            slots=env.int("ZETTA_SLOTS", 8, minimum=1, maximum=1024),
            default_policy_timeout_ms=env.int("ZETTA_POLICY_TIMEOUT_MS", 10_000, minimum=1),
            grace_seconds=env.float("ZETTA_GRACE_SECONDS", 10.0, minimum=0.0),
            video_dir=_video_dir(env),
            resource_sharing=env.bool("ZETTA_RESOURCE_SHARING", True),
            critic_address=env.address("ZETTA_CRITIC_ADDR"),
            worker_token=env.str("ZETTA_WORKER_TOKEN", ""),
            step_concurrency=env.int("ZETTA_STEP_CONCURRENCY", usable_cpus(mask=cpus), minimum=0),
            cpus=cpus,
            infer_hold=InferHold(
                max_ms=env.float("ZETTA_INFER_HOLD_MS", DEFAULT_INFER_HOLD_MS, minimum=0.0),
                min_busy=env.int("ZETTA_INFER_HOLD_MIN_BUSY", InferHold.min_busy, minimum=1),
            ),
        )
        env.finish("env worker")
        return cfg

    def resolved(self, bound_port: int) -> "EnvWorkerConfig":
        """Fill the worker id and advertised address once the port is bound."""
        from dataclasses import replace

        address = advertised_address(self.host, bound_port, self.gateway_address, self.advertise_address)
        return replace(
            self,
            port=bound_port,
            advertise_address=address,
            worker_id=self.worker_id or f"{socket.gethostname()}-{bound_port}",
        )


def _video_dir(env: EnvReader) -> str:
    """ZETTA_VIDEO_DIR as an absolute path, or "" when unset; an unusable directory is reported."""
    from services.env_worker.video import VideoError, check_video_dir

    raw = env.str("ZETTA_VIDEO_DIR", "")
    if not raw:
        return ""
    try:
        return check_video_dir(raw)
    except VideoError as exc:
        env.fail(f"ZETTA_VIDEO_DIR: {exc}")
        return ""
