"""A policy worker and an openpi endpoint as child processes on loopback (tests, bench_openpi).

The same processes an operator starts (``python -m services.policy_worker.main`` and
``python -m services.policy_worker.openpi.endpoint_main``), with free ports and logs in a folder.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from services.ops.local_stack import HOST, free_port, wait_healthy

_ROOT = Path(__file__).resolve().parents[3]


@dataclass
class Child:
    """A started service: its address, metrics port, process and log."""

    address: str
    metrics_port: int
    proc: subprocess.Popen[bytes]
    log: Path

    def metrics(self) -> str:
        """The Prometheus text of the service."""
        with urllib.request.urlopen(f"http://{HOST}:{self.metrics_port}/metrics", timeout=5) as r:
            return r.read().decode()

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after 10 s."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def child_env() -> dict[str, str]:
    """This environment with the checkout on PYTHONPATH and services bound to loopback."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(_ROOT), str(_ROOT / "clients" / "python"), env.get("PYTHONPATH", "")])
    env["ZETTA_BIND_HOST"] = HOST
    return env


def _spawn(module: str, settings: Mapping[str, str], log: Path) -> tuple[subprocess.Popen[bytes], int]:
    env = child_env()
    metrics_port = free_port()
    env["ZETTA_METRICS_PORT"] = str(metrics_port)
    env.update(settings)
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "ab") as fh:
        proc = subprocess.Popen([sys.executable, "-m", module], env=env, stdout=fh, stderr=subprocess.STDOUT,
                                start_new_session=True)
    return proc, metrics_port


def start_policy_worker(models: str, workdir: Path, settings: Mapping[str, str] | None = None) -> Child:
    """A policy worker serving ``models`` (ZETTA_MODELS), healthy when this returns."""
    port = free_port()
    log = workdir / f"policy-worker-{port}.log"
    proc, metrics_port = _spawn("services.policy_worker.main",
                                {"ZETTA_POLICY_WORKER_PORT": str(port), "ZETTA_MODELS": models, **(settings or {})}, log)
    child = Child(f"{HOST}:{port}", metrics_port, proc, log)
    try:
        wait_healthy(child.address, timeout=180, proc=proc, log=log)
    except BaseException:
        child.stop()
        raise
    return child


def start_endpoint(policy_addresses: str, workdir: Path, settings: Mapping[str, str] | None = None) -> Child:
    """The openpi endpoint in front of ``policy_addresses``, answering /healthz when this returns."""
    port = free_port()
    log = workdir / f"openpi-endpoint-{port}.log"
    proc, metrics_port = _spawn("services.policy_worker.openpi.endpoint_main",
                                {"ZETTA_OPENPI_PORT": str(port), "ZETTA_POLICY_ADDRESSES": policy_addresses,
                                 **(settings or {})}, log)
    child = Child(f"{HOST}:{port}", metrics_port, proc, log)
    deadline = time.monotonic() + 60
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"openpi endpoint exited with code {proc.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"http://{child.address}/healthz", timeout=1) as r:
                if r.status == 200:
                    return child
        except OSError:
            pass
        if time.monotonic() > deadline:
            child.stop()
            raise TimeoutError(f"openpi endpoint {child.address} not healthy after 60 s")
        time.sleep(0.1)
