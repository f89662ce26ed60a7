"""Per-hop latency read back from the services' /metrics, as Prometheus would see it.

The demo and the benchmarks report latency from the same histograms Grafana plots, so the
numbers a user sees at the end of a run match the dashboard.
"""

from __future__ import annotations

import urllib.request
from collections.abc import Iterable
from dataclasses import dataclass

from prometheus_client.parser import text_string_to_metric_families


@dataclass
class HopLatency:
    """Summary of one histogram series."""

    name: str
    count: int
    mean_ms: float
    p50_ms: float
    p99_ms: float


def scrape(url: str) -> str:
    """The text exposition of one /metrics endpoint."""
    with urllib.request.urlopen(url, timeout=5) as resp:  # loopback URLs of our own services
        return resp.read().decode()


def _quantile(buckets: list[tuple[float, float]], q: float) -> float:
    """Linear interpolation inside the bucket that holds quantile q (as histogram_quantile does)."""
    total = buckets[-1][1]
    if total == 0:
        return float("nan")
    rank = q * total
    prev_le, prev_count = 0.0, 0.0
    for le, count in buckets:
        if count >= rank:
            if le == float("inf"):
                return prev_le
            return prev_le + (le - prev_le) * ((rank - prev_count) / max(count - prev_count, 1e-12))
        prev_le, prev_count = le, count
    return prev_le


def histograms(texts: Iterable[str], metric: str, label_keys: tuple[str, ...]) -> list[HopLatency]:
    """Every series of histogram ``metric`` across the given expositions, named by its labels."""
    series: dict[str, dict[str, object]] = {}
    for text in texts:
        for family in text_string_to_metric_families(text):
            if family.name != metric:
                continue
            for sample in family.samples:
                key = "/".join(sample.labels.get(k, "") for k in label_keys)
                entry = series.setdefault(key, {"buckets": {}, "sum": 0.0, "count": 0.0})
                if sample.name.endswith("_bucket"):
                    le = float(sample.labels["le"])
                    buckets = entry["buckets"]
                    assert isinstance(buckets, dict)
                    buckets[le] = buckets.get(le, 0.0) + sample.value
                elif sample.name.endswith("_sum"):
                    entry["sum"] = float(entry["sum"]) + sample.value  # type: ignore[arg-type]
                elif sample.name.endswith("_count"):
                    entry["count"] = float(entry["count"]) + sample.value  # type: ignore[arg-type]
    out = []
    for key, entry in sorted(series.items()):
        count = int(entry["count"])  # type: ignore[call-overload]
        if count == 0:
            continue
        buckets = sorted(entry["buckets"].items())
        out.append(
            HopLatency(
                name=key,
                count=count,
                mean_ms=1000.0 * float(entry["sum"]) / count,  # type: ignore[arg-type]
                p50_ms=1000.0 * _quantile(buckets, 0.5),
                p99_ms=1000.0 * _quantile(buckets, 0.99),
            )
        )
    return out
