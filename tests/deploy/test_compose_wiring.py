"""deploy/docker-compose.yml is wired correctly: its services, started as local processes with the
commands and environments the compose file and the images give them, form a working stack.

See tests/deploy/compose_stack.py for how a compose service becomes a local process, and
tests/deploy/conftest.py for the traffic (one episode on every slot, one refused admission).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
import urllib.parse
from pathlib import Path

import pytest
import yaml

from tests.deploy.compose_stack import fetch
from tests.deploy.conftest import LIFT_SHORT, ComposeRun
from tests.deploy.deployfiles import COMPOSE, GRAFANA, environment, image_config, load_compose


def test_every_runnable_service_started(compose_run: ComposeRun) -> None:
    """Everything but Grafana runs here; nothing else is skipped silently."""
    stack = compose_run.stack
    assert set(stack.procs) | set(stack.not_started) == set(stack.services)
    assert "grafana" in stack.not_started
    allowed_missing = {"grafana", "prometheus"}
    assert set(stack.not_started) <= allowed_missing, stack.not_started
    for name, proc in stack.procs.items():
        assert proc.proc.poll() is None, f"{name} exited:\n{stack.tail(name)}"


def test_episode_runs_through_the_compose_stack(compose_run: ComposeRun) -> None:
    """Both env workers registered under their compose identities and advertised addresses, the
    sessions spread over both, every episode ran to its end with the policy worker's actions, and
    the full pool refused one more session with a retry hint."""
    stack, traffic = compose_run.stack, compose_run.traffic
    expected = {}
    for name in ("env-worker-1", "env-worker-2"):
        env = environment(stack.services[name])
        expected[env["ZETTA_WORKER_ID"]] = stack.translate(env["ZETTA_ADVERTISE_ADDRESS"], name)
    assert traffic.workers == expected, stack.logs()
    assert set(traffic.session_workers.values()) == set(expected)
    assert set(traffic.episode_steps) == set(traffic.session_workers), "every session finished its episode"
    for sid, steps in traffic.episode_steps.items():
        assert 1 <= steps <= LIFT_SHORT["max_steps"], (sid, steps)
    assert traffic.rejected_code == "RESOURCE_EXHAUSTED"
    assert traffic.rejected_retry_after_ms and traffic.rejected_retry_after_ms > 0


def test_healthchecks_pass(compose_run: ComposeRun) -> None:
    """Each service's own compose healthcheck, run as a local command, reports healthy."""
    stack = compose_run.stack
    for name in stack.procs:
        assert stack.healthcheck(name) is not None, f"{name} has no healthcheck in {COMPOSE.name}"
        assert stack.healthy(name), f"healthcheck of {name} fails: {stack.healthcheck(name)}"


def test_healthcheck_reports_an_unreachable_server() -> None:
    """The health-check script fails (exit 1) when nothing serves, so compose would see it."""
    argv = [sys.executable, str(COMPOSE.parent / "docker" / "healthcheck.py"), "127.0.0.1:1", "--timeout", "0.5"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    assert done.returncode == 1
    assert "UNAVAILABLE" in done.stderr or "DEADLINE_EXCEEDED" in done.stderr


def test_metrics_served_where_compose_says(compose_run: ComposeRun) -> None:
    """Every Zetta service serves /metrics on the port its compose environment names."""
    stack = compose_run.stack
    services = stack.zetta_services()
    assert sorted(services) == ["critic", "env-worker-1", "env-worker-2", "evolver", "gateway", "policy-worker"]
    for name in services:
        text = fetch(stack.metrics_url(name))
        assert "zetta_hop_latency_seconds" in text, name


def test_prometheus_scrapes_every_service(compose_run: ComposeRun) -> None:
    """The real Prometheus with deploy/prometheus/prometheus.yml scrapes every Zetta service of the
    compose file and finds each one up."""
    if compose_run.prometheus is None:
        pytest.skip(f"Prometheus not started: {compose_run.stack.not_started.get('prometheus')}")
    stack = compose_run.stack
    wanted = {f"{stack.ips[n]}:{stack.procs[n].env['ZETTA_METRICS_PORT']}" for n in stack.zetta_services()}
    deadline = time.monotonic() + 30
    while True:
        targets = json.loads(fetch(f"{compose_run.prometheus}/api/v1/targets"))["data"]["activeTargets"]
        up = {t["labels"]["instance"] for t in targets
              if t["health"] == "up" and t["labels"]["job"].startswith("zetta-")}
        if wanted <= up or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert wanted <= up, f"not scraped or down: {sorted(wanted - up)}; targets: {targets}"
    jobs = {t["labels"]["instance"]: t["labels"]["job"] for t in targets}
    for name in stack.zetta_services():
        instance = f"{stack.ips[name]}:{stack.procs[name].env['ZETTA_METRICS_PORT']}"
        kind = re.sub(r"-\d+$", "", name)
        assert jobs[instance] == f"zetta-{kind}", (name, jobs[instance])
    # The rule files the compose mount provides were loaded.
    groups = json.loads(fetch(f"{compose_run.prometheus}/api/v1/rules"))["data"]["groups"]
    assert {g["name"] for g in groups} >= {"zetta-throughput", "zetta-latency", "zetta-availability"}
    for g in groups:
        for rule in g["rules"]:
            assert rule.get("health") in ("ok", "unknown"), (g["name"], rule.get("name"), rule.get("lastError"))


def test_steps_reach_prometheus(compose_run: ComposeRun) -> None:
    """The steps the episode ran show up in Prometheus, through the recording rule too."""
    if compose_run.prometheus is None:
        pytest.skip(f"Prometheus not started: {compose_run.stack.not_started.get('prometheus')}")
    steps = sum(compose_run.traffic.episode_steps.values())

    def query(q: str) -> list[dict]:
        url = f"{compose_run.prometheus}/api/v1/query?query={urllib.parse.quote(q)}"
        return json.loads(fetch(url))["data"]["result"]

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        raw = query("sum(zetta_env_steps_total)")
        recorded = query("family:zetta_env_steps:rate1m")
        if raw and float(raw[0]["value"][1]) >= steps and recorded:
            break
        time.sleep(0.5)
    assert raw and float(raw[0]["value"][1]) >= steps, raw
    assert recorded and recorded[0]["metric"]["family"] == "robosuite", recorded


def test_grafana_provisioning_is_wired_to_compose() -> None:
    """Grafana cannot run here, so its wiring is checked on the files: the provisioned datasource
    points at the compose Prometheus service and port, the dashboard provider reads the directory
    compose mounts the dashboards at, and the home dashboard exists there."""
    model = load_compose(COMPOSE)
    grafana, prometheus = model["services"]["grafana"], model["services"]["prometheus"]
    mounts = {v.split(":")[1]: v.split(":")[0] for v in grafana["volumes"]}
    provisioning = Path(COMPOSE.parent / mounts["/etc/grafana/provisioning"]).resolve()
    assert provisioning == GRAFANA / "provisioning"
    datasources = yaml.safe_load((provisioning / "datasources" / "prometheus.yml").read_text())["datasources"]
    url = urllib.parse.urlparse(datasources[0]["url"])
    listen = next(a.split("=", 1)[1] for a in prometheus["command"] if a.startswith("--web.listen-address="))
    assert url.hostname == "prometheus" and "prometheus" in model["services"]
    assert str(url.port) == listen.rsplit(":", 1)[1]
    providers = yaml.safe_load((provisioning / "dashboards" / "zetta.yml").read_text())["providers"]
    path = providers[0]["options"]["path"]
    assert path in mounts, f"dashboard provider reads {path}, compose mounts {sorted(mounts)}"
    assert Path(COMPOSE.parent / mounts[path]).resolve() == GRAFANA / "dashboards"
    home = grafana["environment"]["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
    assert home.startswith(path + "/") and (GRAFANA / "dashboards" / Path(home).name).exists()


def test_compose_uses_image_commands_and_ports() -> None:
    """Each Zetta service's compose command is its image's CMD, and the ports its environment
    names are the ones the image exposes and the healthcheck dials."""
    model = load_compose(COMPOSE)
    for name, svc in model["services"].items():
        target = (svc.get("build") or {}).get("target")
        if not target:
            continue
        image = image_config(target)
        assert svc["command"] == image.cmd, name
        env = {**image.env, **environment(svc)}
        port_vars = [k for k in env if k.endswith("_PORT") and k != "ZETTA_METRICS_PORT"]
        assert len(port_vars) == 1, (name, port_vars)
        grpc_port, metrics_port = env[port_vars[0]], env["ZETTA_METRICS_PORT"]
        assert {grpc_port, metrics_port} <= set(image.expose), (name, image.expose)
        assert svc["healthcheck"]["test"][-1] == f"127.0.0.1:{grpc_port}", name
        assert image.healthcheck and image.healthcheck[-1] == f"127.0.0.1:{grpc_port}", name
        assert env["ZETTA_BIND_HOST"] == "0.0.0.0", name
