"""Generate the Grafana dashboards in deploy/grafana/dashboards from this one description.

    python deploy/grafana/generate.py          # rewrite the JSON files
    python deploy/grafana/generate.py --check  # exit 1 when a JSON file differs from what would be written

Plain Python, no dependencies: each dashboard is rows of panels, each panel one or more PromQL
queries. Queries use the recording rules of deploy/prometheus/rules where one exists, so that a
dashboard over hours stays cheap. tests/deploy checks every metric a query names against a live
scrape of the services (and the recorded names against the rule files); the one metric no service
exports yet is listed there, with the issue that brings it (EXPECTED_LATER in
tests/deploy/test_dashboards.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
OUT = HERE / "dashboards"
#: uid of the datasource provisioned by provisioning/datasources/prometheus.yml.
DATASOURCE = {"type": "prometheus", "uid": "zetta-prometheus"}
SCHEMA_VERSION = 39


@dataclass
class Query:
    """One PromQL target of a panel."""

    expr: str
    legend: str = ""
    instant: bool = False


@dataclass
class Panel:
    """A panel: kind is timeseries, stat, bargauge or barchart."""

    title: str
    description: str
    queries: list[Query]
    unit: str = "short"
    kind: str = "timeseries"
    width: int = 12
    height: int = 8
    stacked: bool = False
    decimals: int | None = None
    thresholds: list[tuple[float | None, str]] = field(default_factory=list)
    min: float | None = None
    max: float | None = None
    #: Value mappings (value, text, color): a stat shows the text in that color instead of the number.
    mappings: list[tuple[float, str, str]] = field(default_factory=list)


@dataclass
class Row:
    """A titled row of panels, laid out left to right on a 24-column grid."""

    title: str
    panels: list[Panel]


def _target(q: Query, ref: str) -> dict[str, Any]:
    return {
        "datasource": DATASOURCE,
        "refId": ref,
        "expr": q.expr,
        "legendFormat": q.legend or "__auto",
        "range": not q.instant,
        "instant": q.instant,
    }


def _panel(p: Panel, pid: int, x: int, y: int) -> dict[str, Any]:
    steps = [{"color": color, "value": value} for value, color in (p.thresholds or [(None, "green")])]
    defaults: dict[str, Any] = {
        "unit": p.unit,
        "color": {"mode": "thresholds" if p.kind in ("stat", "bargauge") else "palette-classic"},
        "thresholds": {"mode": "absolute", "steps": steps},
    }
    if p.decimals is not None:
        defaults["decimals"] = p.decimals
    if p.min is not None:
        defaults["min"] = p.min
    if p.max is not None:
        defaults["max"] = p.max
    if p.mappings:
        defaults["mappings"] = [{
            "type": "value",
            "options": {f"{value:g}": {"text": text, "color": color, "index": i}
                        for i, (value, text, color) in enumerate(p.mappings)},
        }]
    options: dict[str, Any]
    if p.kind == "timeseries":
        defaults["custom"] = {
            "drawStyle": "line",
            "lineWidth": 1,
            "fillOpacity": 20 if p.stacked else 0,
            "showPoints": "never",
            "spanNulls": False,
            "stacking": {"mode": "normal" if p.stacked else "none", "group": "A"},
        }
        options = {
            "legend": {"displayMode": "table", "placement": "bottom", "showLegend": True,
                       "calcs": ["lastNotNull", "max"]},
            "tooltip": {"mode": "multi", "sort": "desc"},
        }
    elif p.kind == "stat":
        options = {
            "reduceOptions": {"calcs": ["lastNotNull"], "fields": "", "values": False},
            "colorMode": "value",
            "graphMode": "area",
            "justifyMode": "auto",
            "orientation": "auto",
            "textMode": "auto",
        }
    elif p.kind == "bargauge":
        options = {
            "reduceOptions": {"calcs": ["lastNotNull"], "fields": "", "values": False},
            "displayMode": "gradient",
            "orientation": "horizontal",
            "showUnfilled": True,
        }
    elif p.kind == "barchart":
        options = {
            "orientation": "vertical",
            "xTickLabelRotation": 0,
            "showValue": "auto",
            "stacking": "none",
            "groupWidth": 0.7,
            "barWidth": 0.9,
            "legend": {"displayMode": "list", "placement": "bottom", "showLegend": True},
            "tooltip": {"mode": "multi", "sort": "none"},
        }
    else:
        raise ValueError(f"unknown panel kind {p.kind!r}")
    return {
        "id": pid,
        "type": p.kind,
        "title": p.title,
        "description": p.description,
        "datasource": DATASOURCE,
        "gridPos": {"h": p.height, "w": p.width, "x": x, "y": y},
        "targets": [_target(q, chr(ord("A") + i)) for i, q in enumerate(p.queries)],
        "fieldConfig": {"defaults": defaults, "overrides": []},
        "options": options,
    }


def dashboard(uid: str, title: str, description: str, rows: list[Row], tags: list[str]) -> dict[str, Any]:
    """A Grafana dashboard model with rows laid out top to bottom."""
    panels: list[dict[str, Any]] = []
    pid = 1
    y = 0
    for row in rows:
        panels.append({
            "id": pid, "type": "row", "title": row.title, "collapsed": False,
            "gridPos": {"h": 1, "w": 24, "x": 0, "y": y}, "panels": [],
        })
        pid += 1
        y += 1
        x = 0
        line_height = 0
        for p in row.panels:
            if x + p.width > 24:
                y += line_height
                x, line_height = 0, 0
            panels.append(_panel(p, pid, x, y))
            pid += 1
            x += p.width
            line_height = max(line_height, p.height)
        y += line_height
    return {
        "uid": uid,
        "title": title,
        "description": description,
        "tags": tags,
        "editable": False,
        "graphTooltip": 1,
        "timezone": "browser",
        "refresh": "10s",
        "schemaVersion": SCHEMA_VERSION,
        "version": 1,
        "time": {"from": "now-30m", "to": "now"},
        "timepicker": {},
        "annotations": {"list": []},
        "templating": {"list": []},
        "links": [],
        "panels": panels,
    }


# ---- the rollout dashboard -----------------------------------------------------------------------

LATENCY_LEGEND = "{{service}} / {{method}}"

ROLLOUT_ROWS = [
    Row("Throughput", [
        Panel("Episodes per minute", "Episodes that ended, per minute, by env family and outcome (all env workers).",
              [Query("sum by (family, outcome) (family_outcome:zetta_env_episodes_completed:rate1m) * 60",
                     "{{family}} {{outcome}}")], unit="short", stacked=True, width=9),
        Panel("Environment steps per second", "Environment steps executed per second, by env family.",
              [Query("family:zetta_env_steps:rate1m", "{{family}}")], unit="short", stacked=True, width=9),
        Panel("Episodes/min now", "All families and outcomes.",
              [Query("sum(family_outcome:zetta_env_episodes_completed:rate1m) * 60")], kind="stat",
              width=3, decimals=1),
        Panel("Steps/s now", "All families.",
              [Query("sum(family:zetta_env_steps:rate1m)")], kind="stat", width=3, decimals=0),
        Panel("Episodes started per second", "Resets, by family.",
              [Query("family:zetta_env_resets:rate1m", "{{family}}")], unit="short", width=12),
        Panel("Gateway calls per second", "By method and gRPC status code.",
              [Query("method_code:zetta_gateway_requests:rate1m", "{{method}} {{code}}")], unit="reqps", width=12),
    ]),
    Row("Latency per hop", [
        Panel("p50 latency per hop", "Median time of each hop of a request: gateway -> env worker -> "
              "policy (env_worker/policy_infer) -> policy worker. Downstream hops are included.",
              [Query("service_method:zetta_hop_latency_seconds:p50_rate1m", LATENCY_LEGEND)], unit="s"),
        Panel("p99 latency per hop", "99th percentile time of each hop.",
              [Query("service_method:zetta_hop_latency_seconds:p99_rate1m", LATENCY_LEGEND)], unit="s"),
        Panel("Environment step time", "One env.step (physics and controller), p50 and p99, by family.",
              [Query("family:zetta_env_step_duration_seconds:p50_rate1m", "p50 {{family}}"),
               Query("family:zetta_env_step_duration_seconds:p99_rate1m", "p99 {{family}}")], unit="s", width=8),
        Panel("Policy queue wait p99", "Time an inference item waited before its batch ran.",
              [Query("model:zetta_policy_queue_wait_seconds:p99_rate1m", "{{model}}")], unit="s", width=8),
        Panel("Policy batch compute p99", "Model time of one batch.",
              [Query("model:zetta_policy_batch_compute_seconds:p99_rate1m", "{{model}}")], unit="s", width=8),
        Panel("Step calls slower than 1 s (SLO)", "Fraction of gateway step calls (Observe, ActionStep, "
              "PolicyStep, PolicyInfer) over 1 s; the SLO allows 1%.",
              [Query("zetta:gateway_step_slow_calls:ratio_rate5m", "5m"),
               Query("zetta:gateway_step_slow_calls:ratio_rate1h", "1h")], unit="percentunit", width=24,
              height=6, min=0),
    ]),
    Row("Batching and queues", [
        Panel("Inference batch size", "Items per batch formed by the policy workers: mean and p99.",
              [Query("model:zetta_policy_batch_size:mean_rate1m", "mean {{model}}"),
               Query("model:zetta_policy_batch_size:p99_rate1m", "p99 {{model}}")], unit="short", width=8),
        Panel("Policy queue depth", "Items waiting in the policy workers' queues (all workers).",
              [Query("model:zetta_policy_queue_depth:sum", "{{model}}")], unit="short", width=8),
        Panel("Inference items per second", "Items answered by the policy workers.",
              [Query("model:zetta_policy_items:rate1m", "{{model}}")], unit="short", width=8),
    ]),
    Row("Sessions and admission", [
        Panel("Sessions by state", "Sessions in the registry: CREATE (envs being built), RUNNING, "
              "TERMINATED (kept as tombstones) and LOST (their worker died).",
              [Query("sum by (state) (family_state:zetta_sessions:max)", "{{state}}")], unit="short",
              stacked=True, width=8),
        Panel("Rejected admissions", "CreateSessions calls refused per second: pool_full (no free slots, "
              "the client is told to retry), no_live_worker (the family's workers are registered but missed "
              "their heartbeats; the client is told to retry) and unknown_family.",
              [Query("family_reason:zetta_gateway_admissions_rejected:rate5m", "{{family}} {{reason}}")],
              unit="reqps", width=8),
        Panel("Rejected inference items", "Items the policy workers refused (queue_full) or that expired "
              "(deadline_expired).",
              [Query("model_reason:zetta_policy_rejected:rate5m", "{{model}} {{reason}}")], unit="reqps", width=8),
    ]),
    Row("Worker health", [
        Panel("Targets up", "Scrape targets up / known, per job.",
              [Query("job:up:sum", "{{job}} up"), Query("job:up:count", "{{job}} known")], kind="stat",
              width=8, decimals=0),
        Panel("Env workers", "Env workers alive and dead as the gateway's registry sees them.",
              [Query("state:zetta_env_workers:max", "{{state}}")], kind="stat", width=4, decimals=0,
              thresholds=[(None, "green")]),
        Panel("Slots", "Env worker slots bound to a session and free, over all workers.",
              [Query("state:zetta_env_slots:sum", "{{state}}")], kind="stat", width=4, decimals=0),
        Panel("Free slots per env worker", "From the registry (0 for a dead worker).",
              [Query("max by (worker) (zetta_env_worker_free_slots)", "{{worker}}", instant=True)],
              kind="bargauge", width=8),
        Panel("Workers declared dead and sessions lost", "Per second; a worker that misses heartbeats is "
              "declared dead and its sessions become LOST.",
              [Query("zetta:gateway_workers_declared_dead:rate5m", "workers declared dead"),
               Query("zetta:gateway_sessions_lost:rate5m", "sessions lost")], unit="short", width=12),
        Panel("Missed heartbeats", "Monitor ticks that found an env worker's heartbeat late, per worker.",
              [Query("sum by (worker) (rate(zetta_gateway_missed_heartbeats_total[$__rate_interval]))", "{{worker}}")],
              unit="short", width=12),
    ]),
    Row("Busy leases", [
        Panel("Busy leases taken per second", "Busy leases the env workers take before work that holds the GIL "
              "(services/env_worker/busy.py), by what and outcome: granted; unacknowledged (the gateway did not "
              "grant it within 2 s, or ZETTA_HEARTBEAT_MAX_BUSY_MS is 0: the worker goes ahead unprotected); "
              "unannounced; standalone (no membership).",
              [Query("sum by (what, outcome) (rate(zetta_env_busy_leases_total[$__rate_interval]))",
                     "{{what}} {{outcome}}")], unit="reqps", stacked=True, width=8),
        Panel("Busy lease heartbeats at the gateway", "Heartbeats per second that carried a busy lease, by outcome: "
              "granted, or capped (asked for more than ZETTA_HEARTBEAT_MAX_BUSY_MS).",
              [Query("sum by (outcome) (rate(zetta_gateway_busy_leases_total[$__rate_interval]))", "{{outcome}}")],
              unit="reqps", stacked=True, width=8),
        Panel("Busy lease duration", "How long the env workers held each busy lease, p50 and p99, by what it "
              "covered (a render context's lease asks for 15 s, a model copy's for 5 s).",
              [Query("histogram_quantile(0.5, sum by (what, le) (rate(zetta_env_busy_lease_seconds_bucket"
                     "[$__rate_interval])))", "p50 {{what}}"),
               Query("histogram_quantile(0.99, sum by (what, le) (rate(zetta_env_busy_lease_seconds_bucket"
                     "[$__rate_interval])))", "p99 {{what}}")], unit="s", width=8),
    ]),
]

# ---- the evolution dashboard ----------------------------------------------------------------------

EVOLUTION_ROWS = [
    Row("Evolution progress", [
        Panel("Success per round", "Success rate per task, round and arm (dev, test_bare, test_final, test_control) of "
              "the running evolution jobs (services/evolver); empty until a job runs.",
              [Query("max by (task, round, arm) (zetta_evolver_success_ratio)", "{{task}} round {{round}} {{arm}}",
                     instant=True)], kind="barchart", unit="percentunit", width=24, min=0, max=1),
        Panel("Phase progress", "Finished share of the current phase's episodes, per evolution job.",
              [Query("max by (job_id) (zetta_evolver_phase_progress_ratio)", "{{job_id}}")], unit="percentunit",
              width=12, min=0, max=1),
        Panel("Rollout episodes per minute", "Episodes the evolution loop's rollouts finish (all env workers).",
              [Query("sum(family_outcome:zetta_env_episodes_completed:rate1m) * 60", "episodes/min")],
              unit="short", width=12),
        Panel("Admitted harness versions", "Versions each evolution job's gates admitted so far.",
              [Query("sum(zetta_evolver_admitted_versions)", "admitted")], unit="short", width=24),
        Panel("Recovery share of actions", "Share of the actions of finished harnessed episodes that recoveries "
              "chose instead of the policy: a harness whose recoveries do all the work shows here.",
              [Query("sum(rate(zetta_env_harness_actions_total{by=\"recovery\"}[$__rate_interval])) / "
                     "sum(rate(zetta_env_harness_actions_total[$__rate_interval]))", "recovery share")],
              unit="percentunit", width=12, min=0, max=1),
        Panel("Interventions by kind", "Interventions of finished harnessed episodes per minute, by kind and outcome.",
              [Query("sum by (kind, outcome) (rate(zetta_env_harness_interventions_total[$__rate_interval])) * 60",
                     "{{kind}} {{outcome}}")], unit="short", width=12),
    ]),
    Row("Harness sandbox", [
        Panel("Harness sandbox mode", "How each process that runs harness package code (env workers, critic, "
              "evolver) isolates its sandbox children: root, userns, or DEGRADED (no user namespace: no private "
              "root, no change of user; docs/security.md). A process appears once its first child started.",
              [Query("max by (job, instance) (zetta_harness_sandbox_mode{mode=\"userns\"}) + 2 * "
                     "max by (job, instance) (zetta_harness_sandbox_mode{mode=\"degraded\"})",
                     "{{job}} {{instance}}", instant=True)], kind="stat", width=12, decimals=0,
              thresholds=[(None, "green"), (2, "red")],
              mappings=[(0, "root", "green"), (1, "userns", "green"), (2, "DEGRADED", "red")]),
        Panel("Sandbox isolation by feature", "Each isolation feature of the sandbox children: enforced in every "
              "process that hosts them, or OFF in at least one (zetta_harness_sandbox_isolation).",
              [Query("min by (feature) (zetta_harness_sandbox_isolation)", "{{feature}}", instant=True)],
              kind="stat", width=12, decimals=0, thresholds=[(None, "red"), (1, "green")],
              mappings=[(0, "OFF", "red"), (1, "enforced", "green")]),
    ]),
]


def dashboards() -> dict[str, dict[str, Any]]:
    """File name -> dashboard model."""
    return {
        "zetta-rollout.json": dashboard(
            "zetta-rollout", "Zetta rollout",
            "Throughput, per-hop latency, batching, sessions and worker health of the rollout infrastructure.",
            ROLLOUT_ROWS, ["zetta"],
        ),
        "zetta-evolution.json": dashboard(
            "zetta-evolution", "Zetta evolution",
            "Progress of the evolution loop: success per round on dev and held-out seeds.",
            EVOLUTION_ROWS, ["zetta"],
        ),
    }


def render(model: dict[str, Any]) -> str:
    """Stable JSON text of a dashboard."""
    return json.dumps(model, indent=2) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare, write nothing")
    args = parser.parse_args()
    OUT.mkdir(exist_ok=True)
    stale = []
    for name, model in dashboards().items():
        path = OUT / name
        text = render(model)
        if path.exists() and path.read_text() == text:
            continue
        if args.check:
            stale.append(name)
        else:
            path.write_text(text)
            print(f"wrote {path}")
    if stale:
        print(f"out of date: {', '.join(stale)}; run deploy/grafana/generate.py", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
