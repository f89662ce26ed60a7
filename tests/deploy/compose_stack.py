"""Run deploy/docker-compose.yml without Docker: every service as a local process.

No Docker engine exists on our machines, so the compose wiring is proven this way: each service
runs the command its compose entry (or its image's CMD, read from deploy/docker/Dockerfile) names,
with the environment the image and the compose file give it. Every service gets its own loopback
address (127.A.B.n), standing in for its container; compose hostnames in the configuration are
mapped to those addresses, "0.0.0.0" and "127.0.0.1"/"localhost" inside a service mean its own
address, and paths inside the image (/app, bind mounts) mean the files in this repository.
Services start in depends_on order and each must pass its own compose healthcheck before its
dependents start, as `docker compose up` does with `condition: service_healthy`.

What cannot run here is reported, not faked: Grafana (no binary on our machines) is never started,
and Prometheus only where the `prometheus` binary is installed (make setup extracts it from
Debian's package).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from tests.deploy.deployfiles import COMPOSE, ROOT, environment, image_config, load_compose, tool
from services.ops.local_stack import find_redis_server

#: Image variables that describe the container's filesystem, not the service: the test keeps its own.
IMAGE_ONLY_ENV = {"PATH", "VIRTUAL_ENV", "HOME", "XDG_CACHE_HOME", "MPLCONFIGDIR", "NUMBA_CACHE_DIR", "HF_HOME",
                  "TORCHINDUCTOR_CACHE_DIR"}
#: Scrape and rule evaluation interval used for the local Prometheus (compose: 15 s).
FAST_INTERVAL = "1s"


@dataclass
class Proc:
    """One started service."""

    name: str
    ip: str
    argv: list[str]
    env: dict[str, str]
    proc: subprocess.Popen[bytes]
    log: Path


@dataclass
class ComposeStack:
    """The services of a compose model, run locally."""

    model: dict[str, Any]
    compose_dir: Path = COMPOSE.parent
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="zetta-compose-")))
    ips: dict[str, str] = field(default_factory=dict)
    procs: dict[str, Proc] = field(default_factory=dict)
    not_started: dict[str, str] = field(default_factory=dict)
    #: container path -> rewritten local copy of a bind mount (Prometheus' configuration).
    staged: dict[str, Path] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # A per-process /16 block of 127/8 so that concurrent runs never collide.
        a, b = 64 + os.getpid() % 160, (os.getpid() // 160) % 250 + 1
        for i, name in enumerate(sorted(self.services), start=1):
            self.ips[name] = f"127.{a}.{b}.{i}"
        self._names: dict[str, str] = {}
        for name, svc in self.services.items():
            self._names[name] = self.ips[name]
            if svc.get("hostname"):
                self._names[svc["hostname"]] = self.ips[name]

    @property
    def services(self) -> dict[str, dict[str, Any]]:
        """The compose services."""
        return self.model["services"]

    # ---- translation ------------------------------------------------------------------------------

    def translate(self, value: str, own: str) -> str:
        """A string as the service ``own`` sees it, with compose hostnames and image paths local."""
        ip = self.ips[own]
        value = value.replace("0.0.0.0", ip)
        if value in ("127.0.0.1", "localhost"):
            return ip
        value = re.sub(r"(?<![\w.-])(127\.0\.0\.1|localhost)(?=:\d)", ip, value)
        for host in sorted(self._names, key=len, reverse=True):
            value = re.sub(rf"(?<![\w.-]){re.escape(host)}(?=:\d)", self._names[host], value)
        value = re.sub(r"(?<![\w.-])/app(?=/|$|:)", str(ROOT), value)
        for container_path, host_path in self._mounts(own).items():
            value = re.sub(rf"(?<![\w.-]){re.escape(container_path)}(?=/|$)", str(host_path), value)
        return value

    def _mounts(self, name: str) -> dict[str, Path]:
        """Container path -> local path for the volumes of a service: bind mounts map to the
        repository (Prometheus' configuration to a rewritten copy), named volumes to temp dirs."""
        out: dict[str, Path] = {}
        for vol in self.services[name].get("volumes", []):
            src, target = vol.split(":")[:2]
            if src.startswith("."):
                out[target] = self.staged.get(target, (self.compose_dir / src).resolve())
            else:
                out[target] = self.workdir / "volumes" / name / src
                out[target].mkdir(parents=True, exist_ok=True)
        return out

    def _stage_prometheus_config(self, name: str) -> None:
        """Copy the mounted Prometheus directory and point its targets at the local addresses."""
        self.staged = {}
        for vol in self.services[name].get("volumes", []):
            src, target = vol.split(":")[:2]
            if not src.startswith("."):
                continue
            local = self.workdir / "mounts" / name / target.strip("/").replace("/", "_")
            shutil.copytree((self.compose_dir / src).resolve(), local)
            config = local / "prometheus.yml"
            if config.exists():
                cfg = yaml.safe_load(config.read_text())
                cfg["global"].update(scrape_interval=FAST_INTERVAL, evaluation_interval=FAST_INTERVAL,
                                     scrape_timeout=FAST_INTERVAL)
                for job in cfg["scrape_configs"]:
                    for sc in job.get("static_configs", []):
                        sc["targets"] = [self.translate(t, name) for t in sc["targets"]]
                config.write_text(yaml.safe_dump(cfg))
            self.staged[target] = local

    # ---- commands ---------------------------------------------------------------------------------

    def command(self, name: str) -> tuple[list[str], dict[str, str]] | None:
        """argv and environment of a service, or None (with the reason in not_started)."""
        svc = self.services[name]
        image = str(svc.get("image", ""))
        env = {k: v for k, v in os.environ.items() if not k.startswith("ZETTA_")}
        target = (svc.get("build") or {}).get("target")
        if target:
            cfg = image_config(target)
            argv = list(svc.get("command") or cfg.cmd or [])
            for k, v in cfg.env.items():
                if k not in IMAGE_ONLY_ENV:
                    env[k] = self.translate(v, name)
            if argv and argv[0] == "python":
                argv[0] = sys.executable
        elif image.startswith("redis:"):
            argv = list(svc["command"])
            argv[0] = find_redis_server()
            data = self.workdir / "volumes" / name
            data.mkdir(parents=True, exist_ok=True)
            argv += ["--bind", self.ips[name], "--port", "6379", "--dir", str(data), "--daemonize", "no"]
        elif image.startswith("prom/prometheus:"):
            binary = tool("prometheus")
            if binary is None:
                self.not_started[name] = "no prometheus binary (make setup installs it from Debian's package)"
                return None
            self._stage_prometheus_config(name)
            argv = [binary] + list(svc.get("command") or [])
        else:
            self.not_started[name] = f"no local binary for image {image} (no Grafana binary on our machines)"
            return None
        env.update({k: self.translate(v, name) for k, v in environment(svc).items()})
        argv = [self.translate(a, name) for a in argv]
        return argv, env

    def healthcheck(self, name: str) -> list[str] | None:
        """The service's compose healthcheck as a local command."""
        hc = self.services[name].get("healthcheck")
        if not hc or hc.get("disable"):
            return None
        test = list(hc["test"])
        assert test[0] == "CMD", f"{name}: healthcheck must use the exec form ['CMD', ...], got {test}"
        argv = [self.translate(a, name) for a in test[1:]]
        if argv[0] == "python":
            argv[0] = sys.executable
        elif argv[0] == "wget" and shutil.which("wget") is None:
            url = argv[-1]
            argv = [sys.executable, "-c", f"import urllib.request; urllib.request.urlopen({url!r}, timeout=3)"]
        return argv

    def healthy(self, name: str) -> bool:
        """Whether the service's healthcheck passes now."""
        argv = self.healthcheck(name)
        if argv is None:
            return True
        try:
            return subprocess.run(argv, capture_output=True, timeout=10).returncode == 0
        except subprocess.TimeoutExpired:
            return False

    # ---- lifecycle --------------------------------------------------------------------------------

    def order(self) -> list[str]:
        """Services in depends_on order."""
        done: list[str] = []

        def visit(n: str, path: tuple[str, ...]) -> None:
            assert n not in path, f"depends_on cycle: {path + (n,)}"
            if n in done:
                return
            for dep in self.services[n].get("depends_on") or {}:
                visit(dep, path + (n,))
            done.append(n)

        for n in self.services:
            visit(n, ())
        return done

    def start(self, timeout: float = 120) -> None:
        """Start every service that can run here, each healthy before its dependents start."""
        try:
            for name in self.order():
                deps = self.services[name].get("depends_on") or {}
                missing = [d for d in deps if d not in self.procs]
                if missing:
                    self.not_started[name] = f"depends on {missing}, not started"
                    continue
                spec = self.command(name)
                if spec is None:
                    continue
                argv, env = spec
                log = self.workdir / f"{name}.log"
                with open(log, "ab") as fh:
                    proc = subprocess.Popen(argv, env=env, cwd=ROOT, stdout=fh, stderr=subprocess.STDOUT,
                                            start_new_session=True)
                self.procs[name] = Proc(name, self.ips[name], argv, env, proc, log)
                self.wait_healthy(name, timeout)
        except BaseException:
            self.stop()
            raise

    def wait_healthy(self, name: str, timeout: float) -> None:
        """Poll the healthcheck until it passes; fail with the log when the process exits."""
        p = self.procs[name]
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if p.proc.poll() is not None:
                raise RuntimeError(f"{name} exited with {p.proc.returncode}:\n{self.tail(name)}")
            if self.healthy(name):
                return
            time.sleep(0.2)
        raise TimeoutError(f"{name} not healthy after {timeout:.0f} s:\n{self.tail(name)}")

    def tail(self, name: str, lines: int = 40) -> str:
        """The end of a service's log."""
        log = self.procs[name].log
        return "\n".join(log.read_text(errors="replace").splitlines()[-lines:]) if log.exists() else ""

    def logs(self) -> str:
        """Every service's log tail, for failure reports."""
        return "\n".join(f"----- {n} -----\n{self.tail(n)}" for n in self.procs)

    def stop(self) -> None:
        """SIGTERM in reverse start order (each drains against live peers), SIGKILL after 15 s."""
        for name in reversed(list(self.procs)):
            p = self.procs[name].proc
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait(timeout=5)

    def remove_files(self) -> None:
        """Delete the logs and data of the run (after stop)."""
        shutil.rmtree(self.workdir, ignore_errors=True)

    # ---- addresses ----------------------------------------------------------------------------------

    def address(self, name: str, port_var: str) -> str:
        """host:port of a service's port, from its environment variable (e.g. ZETTA_GATEWAY_PORT)."""
        return f"{self.ips[name]}:{self.procs[name].env[port_var]}"

    def metrics_url(self, name: str) -> str:
        """/metrics of a Zetta service, from its ZETTA_METRICS_PORT."""
        return f"http://{self.ips[name]}:{self.procs[name].env['ZETTA_METRICS_PORT']}/metrics"

    def zetta_services(self) -> list[str]:
        """Started services that export Zetta metrics."""
        return [n for n, p in self.procs.items() if "ZETTA_METRICS_PORT" in p.env]


def fetch(url: str, timeout: float = 5) -> str:
    """GET a URL (only ever a loopback address here)."""
    with urllib.request.urlopen(url, timeout=timeout) as resp:  # loopback only
        return resp.read().decode()


def compose_stack(*files: Path) -> ComposeStack:
    """A ComposeStack of the merged compose files (not started)."""
    return ComposeStack(load_compose(*files))
