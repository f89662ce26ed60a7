"""Zetta Python SDK: sessions, episodes and steps over the gateway, batched across sessions."""

from zetta.client import (
    Detection,
    EpisodeSummary,
    Gateway,
    PerceiveResult,
    ResetResult,
    Session,
    SessionGroup,
    StepResult,
    StepStream,
    ZettaError,
)
from zetta.credentials import ClientCredentials
from zetta.sync import SyncGateway

__all__ = [
    "ClientCredentials",
    "Detection",
    "EpisodeSummary",
    "Gateway",
    "PerceiveResult",
    "ResetResult",
    "Session",
    "SessionGroup",
    "StepResult",
    "StepStream",
    "SyncGateway",
    "ZettaError",
]
