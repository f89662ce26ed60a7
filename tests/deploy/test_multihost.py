"""Multi-host: the gateway and two env workers on three hosts (network namespaces), one cut off.

Topology, all on this machine (run as root; skipped with the reason otherwise):

    netns A  10.231.N.1   redis-server (A's loopback), gateway :50051, policy worker :50071,
                          and the client (tests/deploy/netns_driver.py, run inside A)
    netns B  10.231.N.2   env worker "env-b" :50061
    netns C  10.231.N.3   env worker "env-c" :50061
    netns SW              a bridge joining the three veth pairs

Before anything is created, ``ip route add unreachable 10.231.N.0/24`` goes into the root
namespace, and the root namespace gets no interface on the subnet: no packet for these addresses
can leave the machine, and only processes inside the namespaces talk to them. Everything is
removed at the end (processes, namespaces with their veths and bridge, the route), also when the
test fails.

The test: sessions on both workers step (the env workers call the policy worker across hosts);
then B fails, either cut off (its bridge port goes down: B is alive but partitioned) or killed
(SIGKILL). Its sessions become LOST within the heartbeat timeout, C's sessions keep stepping from
where they were, new sessions land on C, and the gateway reports B dead. When B is back (link up,
or restarted with the same id), it re-registers, its old sessions stay LOST and it takes new
sessions again.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.deploy.deployfiles import ROOT

pytestmark = pytest.mark.netns

HEARTBEAT_INTERVAL_MS = 200
HEARTBEAT_TIMEOUT_MS = 1000
SLOTS = 3
#: Host of each env worker -> its address index on the subnet.
ENV_HOSTS = {"b": 2, "c": 3}
#: Seconds the monitor may take past the heartbeat timeout on two busy cores.
DETECTION_MARGIN_S = 2.0


def _sh(*argv: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(list(argv), capture_output=True, text=True, timeout=30)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: {done.stderr.strip()}")
    return done


def _skip_reason() -> str | None:
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "creating network namespaces needs root (run the suite as root, as CI does)"
    if shutil.which("ip") is None:
        return "iproute2's `ip` is not installed (apt-get install iproute2)"
    if shutil.which("redis-server") is None:
        return "redis-server is not installed (make setup installs it as root)"
    probe = f"zprobe{os.getpid()}"
    done = _sh("ip", "netns", "add", probe, check=False)
    if done.returncode != 0:
        return f"network namespaces are not permitted here: {done.stderr.strip()}"
    _sh("ip", "netns", "del", probe, check=False)
    return None


@dataclass
class Net:
    """Three hosts and a switch on a private /24 that cannot leave the machine."""

    tag: str = field(default_factory=lambda: f"z{os.getpid() % 100000}")
    subnet: str = ""
    namespaces: list[str] = field(default_factory=list)
    route_added: bool = False

    def ns(self, host: str) -> str:
        """Namespace name of a host (a, b, c, sw)."""
        return f"{self.tag}-{host}"

    def ip(self, index: int) -> str:
        """Address of host number ``index`` (1, 2, 3)."""
        return self.subnet.replace(".0/24", f".{index}")

    def create(self) -> None:
        """Route first, then namespaces, bridge and veths."""
        for attempt in range(20):
            third = 20 + (os.getpid() + attempt) % 200
            subnet = f"10.231.{third}.0/24"
            if _sh("ip", "route", "add", "unreachable", subnet, check=False).returncode == 0:
                self.subnet, self.route_added = subnet, True
                break
        else:
            raise RuntimeError("no free 10.231.x.0/24 for the test network")
        sw = self.ns("sw")
        for host in ("sw", "a", "b", "c"):
            _sh("ip", "netns", "add", self.ns(host))
            self.namespaces.append(self.ns(host))
            _sh("ip", "-n", self.ns(host), "link", "set", "lo", "up")
        _sh("ip", "-n", sw, "link", "add", "br0", "type", "bridge")
        _sh("ip", "-n", sw, "link", "set", "br0", "up")
        for index, host in enumerate(("a", "b", "c"), start=1):
            inner, outer = f"{self.tag}{host}0", self.port(host)
            _sh("ip", "link", "add", inner, "netns", self.ns(host), "type", "veth", "peer", "name", outer, "netns", sw)
            _sh("ip", "-n", self.ns(host), "link", "set", inner, "name", "eth0")
            _sh("ip", "-n", self.ns(host), "addr", "add", f"{self.ip(index)}/24", "dev", "eth0")
            _sh("ip", "-n", self.ns(host), "link", "set", "eth0", "up")
            _sh("ip", "-n", sw, "link", "set", outer, "master", "br0")
            _sh("ip", "-n", sw, "link", "set", outer, "up")

    def port(self, host: str) -> str:
        """The switch-side veth of a host."""
        return f"{self.tag}{host}1"

    def set_link(self, host: str, up: bool) -> None:
        """Connect or cut a host at the switch."""
        _sh("ip", "-n", self.ns("sw"), "link", "set", self.port(host), "up" if up else "down")

    def destroy(self) -> None:
        """Namespaces (with their veths and the bridge), then the route."""
        for name in reversed(self.namespaces):
            _sh("ip", "netns", "del", name, check=False)
        self.namespaces.clear()
        if self.route_added:
            _sh("ip", "route", "del", "unreachable", self.subnet, check=False)
            self.route_added = False


@dataclass
class Hosts:
    """Processes started inside the namespaces."""

    net: Net
    workdir: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="zetta-netns-")))
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def env(self, **settings: str) -> dict[str, str]:
        env = {k: v for k, v in os.environ.items() if not k.startswith("ZETTA_")}
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")])
        env.update(settings)
        return env

    def start(self, name: str, host: str, argv: list[str], **settings: str) -> None:
        log = open(self.workdir / f"{name}.log", "ab")  # closed with the process
        self.procs[name] = subprocess.Popen(
            ["ip", "netns", "exec", self.net.ns(host), *argv], env=self.env(**settings), cwd=ROOT,
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )
        log.close()

    def start_env_worker(self, host: str, wait: bool = True) -> None:
        """Env worker "env-<host>" on host b or c, registered with the gateway on A."""
        ip, gateway = self.net.ip(ENV_HOSTS[host]), self.net.ip(1)
        name = f"env-{host}"
        self.start(name, host, [sys.executable, "-m", "services.env_worker.main"],
                   # A wildcard bind and no ZETTA_ADVERTISE_ADDRESS: the worker must advertise the
                   # address the gateway reaches it by (its host's IP), as on a real second host.
                   ZETTA_BIND_HOST="0.0.0.0", ZETTA_ENV_WORKER_PORT="50061", ZETTA_METRICS_PORT="-1",
                   ZETTA_WORKER_ID=name,
                   ZETTA_GATEWAY_ADDRESS=f"{gateway}:50051", ZETTA_POLICY_ADDRESSES=f"{gateway}:50071",
                   ZETTA_SLOTS=str(SLOTS), ZETTA_ENV_FAMILIES="robosuite", ZETTA_GRACE_SECONDS="2")
        if wait:
            self.wait_healthy(name, host, f"{ip}:50061")

    def kill(self, name: str) -> None:
        """SIGKILL a process: a crash, no deregistration."""
        proc = self.procs[name]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)

    def python(self, host: str, *args: str, timeout: float = 90) -> subprocess.CompletedProcess[str]:
        """Run a Python module inside a host and wait for it."""
        return subprocess.run(["ip", "netns", "exec", self.net.ns(host), sys.executable, *args],
                              env=self.env(), cwd=ROOT, capture_output=True, text=True, timeout=timeout)

    def wait_healthy(self, name: str, host: str, address: str, timeout: float = 60) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.procs[name].poll() is not None:
                raise RuntimeError(f"{name} exited:\n{self.log(name)}")
            if self.python(host, "deploy/docker/healthcheck.py", address, "--timeout", "1").returncode == 0:
                return
            time.sleep(0.2)
        raise TimeoutError(f"{name} not healthy at {address}:\n{self.log(name)}")

    def drive(self, phase: str, **args: object) -> dict:
        done = self.python("a", "-m", "tests.deploy.netns_driver", phase, json.dumps(args), timeout=120)
        assert done.returncode == 0, f"driver {phase} failed:\n{done.stderr}\n{self.logs()}"
        return json.loads(done.stdout.strip().splitlines()[-1])

    def log(self, name: str, lines: int = 30) -> str:
        path = self.workdir / f"{name}.log"
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.exists() else ""

    def logs(self) -> str:
        return "\n".join(f"----- {n} -----\n{self.log(n)}" for n in self.procs)

    def stop(self) -> None:
        for name in reversed(list(self.procs)):
            proc = self.procs[name]
            if proc.poll() is None:
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                    proc.wait(timeout=10)
                except ProcessLookupError:
                    pass
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=5)


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    """The three hosts with redis, gateway and policy worker on A and an env worker each on B, C."""
    reason = _skip_reason()
    if reason:
        pytest.skip(reason)
    net = Net()
    hosts = Hosts(net)
    try:
        net.create()
        a = net.ip(1)
        from services.ops.local_stack import find_redis_server

        hosts.start("redis", "a", [find_redis_server(), "--bind", "127.0.0.1", "--port", "6379", "--save", "",
                                   "--appendonly", "no", "--dir", str(hosts.workdir)])
        hosts.start("gateway", "a", [sys.executable, "-m", "services.gateway.main"],
                    ZETTA_BIND_HOST=a, ZETTA_GATEWAY_PORT="50051", ZETTA_METRICS_PORT="-1",
                    ZETTA_REDIS_URL="redis://127.0.0.1:6379/0",
                    ZETTA_HEARTBEAT_INTERVAL_MS=str(HEARTBEAT_INTERVAL_MS),
                    ZETTA_HEARTBEAT_TIMEOUT_MS=str(HEARTBEAT_TIMEOUT_MS))
        hosts.start("policy", "a", [sys.executable, "-m", "services.policy_worker.main"],
                    ZETTA_BIND_HOST=a, ZETTA_POLICY_WORKER_PORT="50071", ZETTA_METRICS_PORT="-1",
                    ZETTA_MODELS="scripted-pick-place")  # state-only Lift sessions: no camera to serve the VLA
        for _ in range(50):  # redis answers before the gateway's start-up PING
            ping = _sh("ip", "netns", "exec", net.ns("a"), "redis-cli", "-p", "6379", "ping", check=False)
            if ping.stdout.strip() == "PONG":
                break
            time.sleep(0.1)
        hosts.wait_healthy("gateway", "a", f"{a}:50051")
        hosts.wait_healthy("policy", "a", f"{a}:50071")
        for host in ("b", "c"):
            hosts.start_env_worker(host, wait=False)
        for host in ("b", "c"):
            hosts.wait_healthy(f"env-{host}", host, f"{net.ip(ENV_HOSTS[host])}:50061")
        yield hosts
    finally:
        hosts.stop()
        net.destroy()
        shutil.rmtree(hosts.workdir, ignore_errors=True)


@pytest.mark.parametrize("fault", ["cut", "kill"])
def test_env_worker_failure_loses_only_its_sessions(hosts: Hosts, fault: str) -> None:
    """Cut env worker B off the network (it keeps running) or SIGKILL it: its sessions become LOST,
    C and its sessions are undisturbed, new sessions land on C. When B is back (link up again, or
    restarted with the same worker id) it serves new sessions and the LOST ones stay LOST."""
    net = hosts.net
    gateway = f"{net.ip(1)}:50051"
    first = hosts.drive("start", gateway=gateway, n=4)
    assert {w: v["address"] for w, v in first["workers"].items()} == {
        "env-b": f"{net.ip(2)}:50061", "env-c": f"{net.ip(3)}:50061"}
    on_b = sorted(s for s, w in first["sessions"].items() if w == "env-b")
    on_c = sorted(s for s, w in first["sessions"].items() if w == "env-c")
    assert len(on_b) == 2 and len(on_c) == 2, first["sessions"]
    # One action step and one policy step (env worker -> policy worker across hosts) each.
    assert all(step == 2 for step in first["episode_step"].values()), first["episode_step"]

    if fault == "cut":
        net.set_link("b", up=False)
    else:
        hosts.kill("env-b")
    cut = hosts.drive("after_cut", gateway=gateway, lost=on_b, live=on_c, fresh=1,
                      timeout=HEARTBEAT_TIMEOUT_MS / 1000 + 10)
    assert all(cut["states"][s] == "LOST" for s in on_b), (cut["states"], hosts.logs())
    assert cut["lost_after_s"] <= HEARTBEAT_TIMEOUT_MS / 1000 + DETECTION_MARGIN_S, cut["lost_after_s"]
    assert all("env-b" in cut["reasons"][s] for s in on_b), cut["reasons"]
    assert all(cut["states"][s] == "RUNNING" for s in on_c), cut["states"]
    assert cut["workers"]["env-b"]["alive"] is False and cut["workers"]["env-c"]["alive"] is True
    # C's sessions continue exactly where they were: step 3, then 4.
    assert cut["live_steps"] == {s: 3 for s in on_c}, cut["live_steps"]
    assert cut["live_policy"] == {s: 4 for s in on_c}, cut["live_policy"]
    err = cut["lost_step_error"]
    assert err and err["code"] == "FAILED_PRECONDITION" and "LOST" in err["details"] and err["ids"] == on_b
    assert set(cut["fresh"].values()) == {"env-c"}, cut["fresh"]
    assert all(step == 1 for step in cut["fresh_steps"].values())

    if fault == "cut":
        net.set_link("b", up=True)
    else:
        hosts.start_env_worker("b")
    healed = hosts.drive("after_heal", gateway=gateway, worker="env-b", slots=SLOTS, lost=on_b, n=2, timeout=30)
    assert healed["workers"]["env-b"] == {"alive": True, "free": SLOTS}, (healed, hosts.logs())
    assert healed["old_states"] == {s: "LOST" for s in on_b}
    # C has one free slot left (2 old + 1 fresh of 3), so two new sessions need B.
    assert "env-b" in set(healed["new"].values()), healed["new"]
    assert all(step == 1 for step in healed["new_steps"].values())
