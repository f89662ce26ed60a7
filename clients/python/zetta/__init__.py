"""Zetta Python SDK: sessions, episodes and steps over the gateway, batched across sessions."""

from zetta.client import (
    EpisodeSummary,
    Gateway,
    ResetResult,
    Session,
    SessionGroup,
    StepResult,
    StepStream,
    ZettaError,
)
from zetta.sync import SyncGateway

__all__ = [
    "EpisodeSummary",
    "Gateway",
    "ResetResult",
    "Session",
    "SessionGroup",
    "StepResult",
    "StepStream",
    "SyncGateway",
    "ZettaError",
]
