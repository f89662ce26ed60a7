"""The whole stack on one machine: a private redis-server and every service on loopback.

Used by `zetta up`, the benchmarks and the integration tests, so all three run the real
processes the same way: each service is its own OS process started with its ZETTA_* variables,
ready when its gRPC health check says SERVING, and stopped with SIGTERM (drain) before SIGKILL.
Nothing is left behind: every child is stopped on exit, even when the caller crashes.
"""

from __future__ import annotations

import atexit
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc

from services.common.policies import DEFAULT_POLICY
from services.common.cpus import allowed_cpus, format_cpu_list, split_cpus, usable_cpus
from services.common.tls import channel_credentials, read_tls

HOST = "127.0.0.1"


def free_port() -> int:
    """A loopback port nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((HOST, 0))
        return int(s.getsockname()[1])


def find_redis_server() -> str:
    """Path of redis-server, installing Debian's package when it is missing and we may."""
    found = shutil.which("redis-server")
    if found:
        return found
    if os.geteuid() == 0 and shutil.which("apt-get"):
        print("redis-server not found; installing Debian's redis-server package", file=sys.stderr)
        subprocess.run(["apt-get", "update", "-qq"], check=False, stdout=subprocess.DEVNULL)
        subprocess.run(["apt-get", "install", "-y", "-qq", "redis-server"], check=True, stdout=subprocess.DEVNULL)
        found = shutil.which("redis-server")
        if found:
            return found
    raise RuntimeError("redis-server is not installed: install it (apt-get install redis-server, brew install redis)")


def _channel(address: str, credentials: grpc.ChannelCredentials | None) -> grpc.Channel:
    if credentials is None:
        return grpc.insecure_channel(address)
    return grpc.secure_channel(address, credentials)


def wait_healthy(address: str, timeout: float, proc: subprocess.Popen[bytes] | None = None, log: Path | None = None,
                 credentials: grpc.ChannelCredentials | None = None) -> None:
    """Block until the gRPC health check of ``address`` answers SERVING."""
    deadline = time.monotonic() + timeout
    with _channel(address, credentials) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while time.monotonic() < deadline:
            if proc is not None and proc.poll() is not None:
                tail = log.read_text()[-3000:] if log and log.exists() else ""
                raise RuntimeError(f"process for {address} exited with code {proc.returncode}:\n{tail}")
            try:
                if stub.Check(health_pb2.HealthCheckRequest(), timeout=1).status == health_pb2.HealthCheckResponse.SERVING:
                    return
            except grpc.RpcError:
                pass
            time.sleep(0.1)
    raise TimeoutError(f"{address} not healthy after {timeout:.0f} s")


@dataclass
class Service:
    """A running service process."""

    name: str
    address: str
    metrics_port: int
    proc: subprocess.Popen[bytes]
    log: Path
    env: dict[str, str]

    @property
    def metrics_url(self) -> str:
        """Where Prometheus would scrape it."""
        return f"http://{HOST}:{self.metrics_port}/metrics"


@dataclass
class LocalStack:
    """Redis, one gateway, N env workers and M policy workers as child processes."""

    env_workers: int = 2
    slots: int = 8
    policy_workers: int = 1
    families: Sequence[str] = ("libero", "robosuite")
    models: Sequence[str] = (DEFAULT_POLICY,)
    workdir: Path | None = None
    extra_env: Mapping[str, str] = field(default_factory=dict)
    heartbeat_interval_ms: int = 1000
    heartbeat_timeout_ms: int = 3000
    redis_url: str | None = None
    #: Run the private redis-server with append-only persistence (as deploy/compose and
    #: deploy/k8s do), so a Redis restart keeps the sessions.
    redis_appendonly: bool = False
    #: Also run the critic service (harness registry + Evaluate) with a store in the workdir.
    critic: bool = True
    #: Token the stack presents for its own gateway calls (ListWorkers) when the gateway has auth
    #: on (ZETTA_AUTH_TOKENS_FILE in ``extra_env``).
    client_token: str | None = None
    #: Pin each env worker to its own share of the CPUs (ZETTA_CPUS), unless the caller sets
    #: ZETTA_CPUS or a CPU quota is tighter than the CPUs (measure it: bench/bench_stack_ab.py, docs/throughput.md).
    pin_env_workers: bool = True
    services: dict[str, Service] = field(default_factory=dict, init=False)
    redis_proc: subprocess.Popen[bytes] | None = field(default=None, init=False)
    redis_port: int = field(default=0, init=False)

    def __enter__(self) -> "LocalStack":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def gateway_address(self) -> str:
        """Address clients dial."""
        return self.services["gateway"].address

    def start(self) -> None:
        """Start everything and wait until each env worker is registered."""
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix="zetta-stack-"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        atexit.register(self.stop)
        try:
            if self.redis_url is None:
                self._start_redis()
            self.start_gateway()
            if self.critic:
                self.start_critic()
            for i in range(self.policy_workers):
                self._start(
                    f"policy-{i}",
                    "services.policy_worker.main",
                    {"ZETTA_POLICY_WORKER_PORT": "{port}", "ZETTA_MODELS": ",".join(self.models)},
                )
            for i in range(self.env_workers):
                self.start_env_worker(i)
            self.wait_workers(self.env_workers)
        except BaseException:
            self.stop()
            raise

    def restart_redis(self, sig: int = signal.SIGTERM) -> None:
        """Stop the private redis-server with ``sig`` and start it again on the same port and data
        directory (what it kept depends on ``redis_appendonly``)."""
        assert self.redis_proc is not None, "the stack runs no redis-server of its own"
        self.redis_proc.send_signal(sig)
        self.redis_proc.wait(timeout=30)
        self._start_redis(self.redis_port)

    def _start_redis(self, port: int | None = None) -> None:
        assert self.workdir is not None
        self.redis_port = port or free_port()
        log = self.workdir / "redis.log"
        self.redis_proc = subprocess.Popen(
            [find_redis_server(), "--bind", HOST, "--port", str(self.redis_port), "--save", "",
             "--appendonly", "yes" if self.redis_appendonly else "no",
             "--dir", str(self.workdir), "--logfile", str(log)],
            stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True,
        )
        self.redis_url = f"redis://{HOST}:{self.redis_port}/0"
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with socket.create_connection((HOST, self.redis_port), timeout=0.2) as s:
                    s.sendall(b"PING\r\n")
                    if s.recv(16).startswith(b"+PONG"):
                        return
            except OSError:
                time.sleep(0.05)
        raise RuntimeError(f"redis-server did not start on port {self.redis_port}; see {log}")

    def _credentials(self) -> grpc.ChannelCredentials | None:
        """Mutual-TLS credentials from the services' ZETTA_TLS_* settings; None without TLS."""
        tls = read_tls(self._base_env())
        return None if tls is None else channel_credentials(tls)

    def _base_env(self) -> dict[str, str]:
        env = dict(os.environ)
        root = Path(__file__).resolve().parents[2]
        env["PYTHONPATH"] = os.pathsep.join([str(root), str(root / "clients" / "python"), env.get("PYTHONPATH", "")])
        env.setdefault("ZETTA_LOG_LEVEL", "INFO")
        env["ZETTA_BIND_HOST"] = HOST
        env.update(self.extra_env)
        return env

    def _start(self, name: str, module: str, settings: Mapping[str, str], port: int | None = None) -> Service:
        assert self.workdir is not None
        port = port or free_port()
        metrics_port = free_port()
        env = self._base_env()
        env.update({k: v.format(port=port) for k, v in settings.items()})
        env["ZETTA_METRICS_PORT"] = str(metrics_port)
        log = self.workdir / f"{name}.log"
        with open(log, "ab") as fh:
            proc = subprocess.Popen([sys.executable, "-m", module], env=env, stdout=fh, stderr=subprocess.STDOUT,
                                    start_new_session=True)
        svc = Service(name, f"{HOST}:{port}", metrics_port, proc, log, env)
        self.services[name] = svc
        wait_healthy(svc.address, timeout=120, proc=proc, log=log, credentials=self._credentials())
        return svc

    def start_gateway(self, port: int | None = None) -> Service:
        """(Re)start the gateway, on the same port when restarting."""
        old = self.services.get("gateway")
        return self._start(
            "gateway",
            "services.gateway.main",
            {
                "ZETTA_GATEWAY_PORT": "{port}",
                "ZETTA_REDIS_URL": self.redis_url or "",
                "ZETTA_HEARTBEAT_INTERVAL_MS": str(self.heartbeat_interval_ms),
                "ZETTA_HEARTBEAT_TIMEOUT_MS": str(self.heartbeat_timeout_ms),
            },
            port=port or (int(old.address.rsplit(":", 1)[1]) if old else None),
        )

    @property
    def critic_address(self) -> str:
        """Address of the critic service (harness registry and Evaluate)."""
        return self.services["critic"].address

    def start_critic(self, port: int | None = None) -> Service:
        """(Re)start the critic service, on the same port and package store when restarting."""
        assert self.workdir is not None
        old = self.services.get("critic")
        return self._start(
            "critic",
            "services.critic.main",
            {
                "ZETTA_CRITIC_PORT": "{port}",
                "ZETTA_REDIS_URL": self.redis_url or "",
                "ZETTA_CRITIC_STORE": str(self.workdir / "critic-store"),
            },
            port=port or (int(old.address.rsplit(":", 1)[1]) if old else None),
        )

    def step_concurrency(self) -> str:
        """Each env worker's ZETTA_STEP_CONCURRENCY: the caller's, else this machine's usable CPUs
        shared among the workers (at least one each). Every worker of this stack runs on the same
        cores, so more slots stepping at once than a worker's share only contend for them (more
        threads than cores switch mid-step and cost CPU; docs/throughput.md, "Settings")."""
        chosen = self._base_env().get("ZETTA_STEP_CONCURRENCY")
        return chosen if chosen else str(max(1, usable_cpus() // max(1, self.env_workers)))

    def env_worker_cpus(self, i: int) -> str:
        """Env worker ``i``'s ZETTA_CPUS: its block of this machine's CPUs (one CPU each, in turn,
        with more workers than CPUs); empty where it stays unpinned: pinning is off, the caller
        chose ZETTA_CPUS (then every worker gets the caller's), the CPU quota is below the CPUs (a
        block would promise cores the quota does not give), or the block is every CPU anyway."""
        chosen = self._base_env().get("ZETTA_CPUS")
        if chosen:
            return chosen
        allowed = allowed_cpus()
        if not self.pin_env_workers or allowed is None or usable_cpus() < len(allowed):
            return ""
        workers = max(1, self.env_workers)
        block = split_cpus(sorted(allowed), workers)[i % workers]
        return "" if len(block) == len(allowed) else format_cpu_list(set(block))

    def start_env_worker(self, i: int) -> Service:
        """Start env worker ``i``."""
        policy = ",".join(s.address for n, s in self.services.items() if n.startswith("policy-"))
        critic = {"ZETTA_CRITIC_ADDR": self.critic_address} if "critic" in self.services else {}
        return self._start(
            f"env-{i}",
            "services.env_worker.main",
            {
                **critic,
                "ZETTA_STEP_CONCURRENCY": self.step_concurrency(),
                "ZETTA_CPUS": self.env_worker_cpus(i),
                "ZETTA_ENV_WORKER_PORT": "{port}",
                "ZETTA_GATEWAY_ADDRESS": self.gateway_address,
                "ZETTA_POLICY_ADDRESSES": policy,
                "ZETTA_SLOTS": str(self.slots),
                "ZETTA_ENV_FAMILIES": ",".join(self.families),
                "ZETTA_WORKER_ID": f"env-{i}",
            },
        )

    def wait_workers(self, n: int, timeout: float = 60) -> None:
        """Block until ``n`` env workers are alive in the registry."""
        from zetta_wire.v1 import gateway_pb2, gateway_pb2_grpc

        deadline = time.monotonic() + timeout
        metadata = (("authorization", f"Bearer {self.client_token}"),) if self.client_token else ()
        with _channel(self.gateway_address, self._credentials()) as channel:
            stub = gateway_pb2_grpc.GatewayServiceStub(channel)
            while time.monotonic() < deadline:
                workers = stub.ListWorkers(gateway_pb2.ListWorkersRequest(), timeout=5, metadata=metadata).workers
                if sum(w.alive for w in workers) >= n:
                    return
                time.sleep(0.1)
        raise TimeoutError(f"{n} env workers did not register within {timeout:.0f} s")

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send a signal to a service (SIGKILL simulates a crash) and wait for it to exit."""
        svc = self.services[name]
        if svc.proc.poll() is None:
            os.killpg(svc.proc.pid, sig)
            svc.proc.wait(timeout=30)

    def stop(self) -> None:
        """Stop in phases so each drains against live peers: env workers, then policy workers, then
        the gateway (SIGTERM, SIGKILL after 15 s), then Redis."""
        phases = [
            [s for n, s in self.services.items() if n.startswith("env-")],
            [s for n, s in self.services.items() if n.startswith("policy-")],
            [s for n, s in self.services.items() if n in ("gateway", "critic")],
        ]
        for phase in phases:
            for svc in phase:
                if svc.proc.poll() is None:
                    try:
                        os.killpg(svc.proc.pid, signal.SIGTERM)
                    except ProcessLookupError:
                        pass
            for svc in phase:
                try:
                    svc.proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    os.killpg(svc.proc.pid, signal.SIGKILL)
                    svc.proc.wait(timeout=5)
        if self.redis_proc is not None and self.redis_proc.poll() is None:
            self.redis_proc.terminate()
            try:
                self.redis_proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.redis_proc.kill()
        atexit.unregister(self.stop)
