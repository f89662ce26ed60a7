"""The error contract in a failed call's trailing metadata: which sessions failed, when to retry.

Services write it (services/common/grpc_errors.py) and clients read it (zetta.ZettaError); both go
through these two functions so the keys and their encoding are defined once.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

#: Comma-separated ids of the sessions the error concerns.
FAILED_SESSIONS_KEY = "zetta-failed-sessions"
#: How many failed sessions the bounded list above leaves out.
FAILED_SESSIONS_MORE_KEY = "zetta-failed-sessions-more"
#: Milliseconds after which a refused call (RESOURCE_EXHAUSTED) may be retried.
RETRY_AFTER_KEY = "retry-after-ms"


@dataclass(frozen=True)
class ErrorDetails:
    """What the trailing metadata of a failed call says beyond its status."""

    session_ids: list[str] = field(default_factory=list)
    retry_after_ms: int | None = None
    #: Failed sessions left out of ``session_ids`` (the list is bounded).
    more: int = 0


def error_metadata(session_ids: Sequence[str] = (), retry_after_ms: int | None = None) -> tuple[tuple[str, str], ...]:
    """The trailing metadata that carries ``session_ids`` and ``retry_after_ms`` (omitted when empty)."""
    md: list[tuple[str, str]] = []
    if session_ids:
        md.append((FAILED_SESSIONS_KEY, ",".join(session_ids)))
    if retry_after_ms is not None:
        md.append((RETRY_AFTER_KEY, str(retry_after_ms)))
    return tuple(md)


def parse_error_metadata(metadata: Iterable[tuple[str, str | bytes]] | None) -> ErrorDetails:
    """The sessions and retry hint of a failed call's trailing metadata; unknown keys are ignored."""
    sessions: list[str] = []
    retry: int | None = None
    more = 0
    for key, value in metadata or ():
        text = value.decode() if isinstance(value, bytes) else value
        if key == FAILED_SESSIONS_KEY:
            sessions = [s for s in text.split(",") if s]
        elif key == RETRY_AFTER_KEY:
            retry = int(text)
        elif key == FAILED_SESSIONS_MORE_KEY:
            more = int(text)
    return ErrorDetails(sessions, retry, more)
