"""Prometheus metrics the critic service exports (besides the shared hop latency)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge

REQUESTS = Counter("zetta_critic_requests_total", "Critic service calls by method and status code.", ["method", "code"])
PUBLISHED = Counter(
    "zetta_critic_published_total", "Publish calls that stored a package, by whether a new version was created.",
    ["created"],
)
REJECTED = Counter("zetta_critic_packages_rejected_total", "Packages the loader rejected at publish.")
STREAMS = Gauge("zetta_critic_evaluate_streams", "Evaluate streams open now.")
DECISIONS = Counter("zetta_critic_decisions_total", "Evaluate steps answered, by the mode in control.", ["mode"])
PROPOSALS = Counter("zetta_critic_proposals_total", "Critic proposals made on Evaluate streams, by evidence kind.",
                    ["evidence"])
LOADED = Gauge("zetta_critic_loaded_packages", "Harness versions loaded in memory for Evaluate.")
