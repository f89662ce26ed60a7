"""The Grafana dashboards and the Prometheus rules only name metrics the services really export.

Every PromQL expression of every dashboard panel, recording rule and alert is parsed (promql-parser);
each metric it selects must be one of:
- a series a running service exports: the /metrics of the compose stack's gateway, env workers
  and policy worker, scraped after one episode of traffic (tests/deploy/conftest.py);
- a series a recording rule in deploy/prometheus/rules records;
- ``up``, which Prometheus itself writes for every scrape target;
- a metric listed in EXPECTED_LATER: named by a dashboard before its exporter exists, with the
  issue that brings the exporter. The test fails once such a metric is exported, so the list
  cannot go stale.
Where Prometheus runs here, every panel query is also executed against it and must return series.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import promql_parser
import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from tests.deploy.compose_stack import fetch
from tests.deploy.conftest import ComposeRun
from tests.deploy.deployfiles import GRAFANA, PROMETHEUS

DASHBOARDS = sorted((GRAFANA / "dashboards").glob("*.json"))
RULE_FILES = sorted((PROMETHEUS / "rules").glob("*.yml"))

#: Metrics a dashboard shows before any service exports them: metric -> the issue that brings the
#: exporter. Only panels of the evolution dashboard may use them.
EXPECTED_LATER: dict[str, str] = {}
#: Panels whose queries may return nothing after the test traffic, and why.
MAY_BE_EMPTY: dict[str, str] = {
    "Rejected inference items": "no policy worker refuses an item under the test's light load",
    "Missed heartbeats": "series appear per worker only once a heartbeat is late",
    "Success per round": "the evolver exports success once an evolution job has finished a round",
    "Phase progress": "series appear per evolution job; the test traffic starts none",
    "Admitted harness versions": "series appear per evolution job; the test traffic starts none",
    "Recovery share of actions": "the test traffic runs no harnessed episode",
    "Interventions by kind": "the test traffic runs no harnessed episode",
    "Busy leases taken per second": "a worker takes a busy lease only around a call that holds the GIL (a render "
                                    "context made by the bindings, a model copy without mj_copyModel)",
    "Busy lease heartbeats at the gateway": "series appear per outcome only once a heartbeat carries a busy lease",
    "Busy lease duration": "a worker takes a busy lease only around a call that holds the GIL",
    "Harness sandbox mode": "the gauge is set when a process starts its first sandbox child; the test traffic runs "
                            "no harnessed episode",
    "Sandbox isolation by feature": "the gauge is set when a process starts its first sandbox child; the test "
                                    "traffic runs no harnessed episode",
}
#: Metrics a service creates only on first use, so a scrape after the test traffic may lack them
#: (checked like any other once they are there), and why.
CREATED_ON_FIRST_USE: dict[str, str] = {
    "zetta_harness_sandbox_mode": "registered by services/harness/sandbox/client.py when the first sandbox child "
                                  "reports its isolation",
    "zetta_harness_sandbox_isolation": "registered with zetta_harness_sandbox_mode",
}
#: Series Prometheus writes itself for every target.
PROMETHEUS_SERIES = {"up", "scrape_duration_seconds", "scrape_samples_scraped"}
#: Stand-in for Grafana's variables when a query is parsed or run outside Grafana.
GRAFANA_VARIABLES = {"$__rate_interval": "1m", "$__interval": "15s", "$__range": "5m"}


def _dashboard_queries() -> Iterator[tuple[str, str, str]]:
    """(dashboard uid, panel title, expr) of every panel target."""
    for path in DASHBOARDS:
        model = json.loads(path.read_text())
        for panel in model["panels"]:
            for target in panel.get("targets", []):
                yield model["uid"], panel["title"], target["expr"]


def _rules() -> Iterator[dict[str, Any]]:
    for path in RULE_FILES:
        for group in yaml.safe_load(path.read_text())["groups"]:
            yield from group["rules"]


RECORDED = {r["record"] for r in _rules() if "record" in r}


def expand(expr: str) -> str:
    """Grafana variables replaced by values PromQL accepts."""
    for var, value in GRAFANA_VARIABLES.items():
        expr = expr.replace(var, value)
    return expr


def selectors(expr: str) -> list[tuple[str, list[str]]]:
    """(metric name, label names matched) of every vector selector in a PromQL expression."""
    found: list[tuple[str, list[str]]] = []

    def walk(node: Any) -> None:
        if isinstance(node, promql_parser.VectorSelector):
            found.append((node.name or "", [m.name for m in node.matchers.matchers]))
        elif isinstance(node, promql_parser.MatrixSelector):
            walk(node.vector_selector)
        elif isinstance(node, promql_parser.Call):
            for arg in node.args:
                walk(arg)
        elif isinstance(node, promql_parser.BinaryExpr):
            walk(node.lhs)
            walk(node.rhs)
        elif isinstance(node, (promql_parser.AggregateExpr, promql_parser.UnaryExpr, promql_parser.ParenExpr,
                               promql_parser.SubqueryExpr)):
            walk(node.expr)
            if isinstance(node, promql_parser.AggregateExpr) and node.param is not None:
                walk(node.param)

    walk(promql_parser.parse(expand(expr)))
    return found


def all_expressions() -> list[tuple[str, str]]:
    """(where, expr) of every dashboard query, recording rule and alert."""
    out = [(f"dashboard {uid} / {title}", expr) for uid, title, expr in _dashboard_queries()]
    for rule in _rules():
        out.append((f"rule {rule.get('record') or rule.get('alert')}", rule["expr"]))
    return out


def exported_series(texts: list[str]) -> dict[str, set[str]]:
    """Series name -> label names, from /metrics texts (families without samples yet included)."""
    suffixes = {"counter": ["_total", "_created"], "histogram": ["_bucket", "_count", "_sum", "_created"],
                "summary": ["_count", "_sum", "_created", ""], "gauge": [""], "info": ["_info"]}
    out: dict[str, set[str]] = {}
    for text in texts:
        for family in text_string_to_metric_families(text):
            for suffix in suffixes.get(family.type, [""]):
                out.setdefault(family.name + suffix, set())
            for sample in family.samples:
                out.setdefault(sample.name, set()).update(sample.labels)
    return out


# ---- static checks -------------------------------------------------------------------------------


def test_dashboards_are_generated_from_source() -> None:
    """The JSON files are what deploy/grafana/generate.py writes (edit the generator, not the JSON)."""
    done = subprocess.run([sys.executable, str(GRAFANA / "generate.py"), "--check"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_dashboard_models_are_well_formed() -> None:
    """Unique uids and panel ids, the provisioned datasource, panels inside the 24-column grid and
    not overlapping, every required panel present."""
    datasource = yaml.safe_load((GRAFANA / "provisioning" / "datasources" / "prometheus.yml").read_text())
    ds_uid = datasource["datasources"][0]["uid"]
    uids = set()
    titles: set[str] = set()
    for path in DASHBOARDS:
        model = json.loads(path.read_text())
        assert model["uid"] not in uids
        uids.add(model["uid"])
        ids = [p["id"] for p in model["panels"]]
        assert len(ids) == len(set(ids)), path.name
        cells: set[tuple[int, int]] = set()
        for p in model["panels"]:
            g = p["gridPos"]
            assert 0 <= g["x"] and g["x"] + g["w"] <= 24, (path.name, p["title"])
            area = {(x, y) for x in range(g["x"], g["x"] + g["w"]) for y in range(g["y"], g["y"] + g["h"])}
            assert not area & cells, f"{path.name}: panel {p['title']!r} overlaps another"
            cells |= area
            if p["type"] == "row":
                continue
            titles.add(p["title"])
            assert p["datasource"]["uid"] == ds_uid, (path.name, p["title"])
            assert p["targets"], (path.name, p["title"])
            for t in p["targets"]:
                assert t["datasource"]["uid"] == ds_uid and t["expr"].strip()
    required = {"Episodes per minute", "Environment steps per second", "p50 latency per hop", "p99 latency per hop",
                "Inference batch size", "Policy queue depth", "Sessions by state", "Rejected admissions",
                "Targets up", "Env workers", "Success per round"}
    assert required <= titles, sorted(required - titles)


def test_every_expression_parses_and_names_known_series() -> None:
    """Every metric is exported (per docs/architecture.md's table, checked live below), recorded,
    Prometheus' own, or expected later; recorded names are defined exactly once."""
    records = [r["record"] for r in _rules() if "record" in r]
    assert len(records) == len(set(records)), "a recording rule name is defined twice"
    documented = (Path(__file__).resolve().parents[2] / "docs" / "architecture.md").read_text()
    for where, expr in all_expressions():
        for name, _ in selectors(expr):
            assert name, f"{where}: selector without a metric name in {expr!r}"
            if name in RECORDED or name in PROMETHEUS_SERIES:
                continue
            if name in EXPECTED_LATER:
                assert where.startswith("dashboard zetta-evolution"), f"{where} uses {name}, expected only later"
                continue
            base = name.removesuffix("_bucket").removesuffix("_count").removesuffix("_sum")
            assert base in documented, f"{where}: {name} is not in docs/architecture.md's metric table"


def test_rule_label_matchers_use_job_names_of_the_scrape_configs() -> None:
    """Rules select ``job=~"zetta-.*"``; every Zetta job of the scrape configurations matches it."""
    config = yaml.safe_load((PROMETHEUS / "prometheus.yml").read_text())
    jobs = {j["job_name"] for j in config["scrape_configs"]} - {"prometheus"}
    assert jobs == {"zetta-gateway", "zetta-env-worker", "zetta-policy-worker", "zetta-critic", "zetta-evolver"}


# ---- against the running services ----------------------------------------------------------------


@pytest.fixture(scope="module")
def scraped(compose_run: ComposeRun) -> dict[str, set[str]]:
    """Series the compose stack's services export after the test traffic."""
    stack = compose_run.stack
    return exported_series([fetch(stack.metrics_url(n)) for n in stack.zetta_services()])


def test_every_metric_used_is_exported(scraped: dict[str, set[str]]) -> None:
    """Each metric a panel, recording rule or alert selects is in a live scrape (or recorded, or
    Prometheus' own, or expected later), and the labels it matches on exist on that metric."""
    missing = []
    for where, expr in all_expressions():
        for name, labels in selectors(expr):
            if name in RECORDED or name in PROMETHEUS_SERIES or name in EXPECTED_LATER:
                continue
            if name not in scraped:
                if name in CREATED_ON_FIRST_USE:
                    continue
                missing.append(f"{where}: {name}")
                continue
            known = scraped[name] | {"job", "instance"}
            if scraped[name]:  # label names are known once the family has samples
                unknown = set(labels) - known
                assert not unknown, f"{where}: {name} has no label(s) {sorted(unknown)}; it has {sorted(known)}"
    assert not missing, "metrics no service exports:\n  " + "\n  ".join(missing)


def test_expected_later_metrics_are_not_exported_yet(scraped: dict[str, set[str]]) -> None:
    """Once the evolver exports a metric of EXPECTED_LATER, remove it from the list."""
    now_exported = sorted(set(EXPECTED_LATER) & set(scraped))
    assert not now_exported, f"exported now, remove from EXPECTED_LATER: {now_exported}"


def test_every_panel_query_returns_series_in_prometheus(compose_run: ComposeRun) -> None:
    """Run every panel's queries against the real Prometheus scraping the compose stack: each one
    executes, and each returns series except the few that need an event the traffic does not cause
    (MAY_BE_EMPTY) and those of metrics no service exports yet (EXPECTED_LATER)."""
    if compose_run.prometheus is None:
        pytest.skip(f"Prometheus not started: {compose_run.stack.not_started.get('prometheus')}")
    queries = list(_dashboard_queries())
    pending = {}
    for uid, title, expr in queries:
        names = {n for n, _ in selectors(expr)}
        if title in MAY_BE_EMPTY or names & set(EXPECTED_LATER):
            pending[(uid, title, expr)] = False
        else:
            pending[(uid, title, expr)] = True
    deadline = time.monotonic() + 45
    empty: list[str] = []
    while True:
        empty = []
        for (uid, title, expr), must_have_data in pending.items():
            url = f"{compose_run.prometheus}/api/v1/query?query={urllib.parse.quote(expand(expr))}"
            reply = json.loads(fetch(url))
            assert reply["status"] == "success", (uid, title, expr, reply)
            if must_have_data and not reply["data"]["result"]:
                empty.append(f"{uid} / {title}: {expr}")
        if not empty or time.monotonic() > deadline:
            break
        time.sleep(1)
    assert not empty, "panels without data after the test traffic:\n  " + "\n  ".join(empty)
