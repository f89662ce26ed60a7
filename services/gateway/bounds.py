"""Limits every request is checked against before the gateway does any work for it.

A call names at most ``max_sessions_per_call`` sessions, each id is short printable ASCII, and no
id appears twice; all checks are linear in the size of the request, so one request cannot hold
the event loop (and with it the heartbeats that loop serves) for long.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from services.common import grpc_errors as ge

#: Longest session id accepted; the gateway issues 32 hex digits.
MAX_SESSION_ID_CHARS = 64
_SESSION_ID = re.compile(r"[A-Za-z0-9_.-]{1,%d}" % MAX_SESSION_ID_CHARS)
#: Ids spelled out in one error message; the rest are counted ("and N more").
NAMED_IN_MESSAGE = 8


def name_ids(ids: Sequence[str], shown: int = NAMED_IN_MESSAGE) -> str:
    """``a, b, c and N more``: a bounded list of ids for a message."""
    head = ", ".join(ids[:shown])
    rest = len(ids) - shown
    return f"{head} and {rest} more" if rest > 0 else head


def quote_bad_id(value: str) -> str:
    """An id as it can be echoed safely: ASCII escapes, at most 40 characters."""
    text = ascii(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_session_ids(sids: Sequence[str], limit: int) -> None:
    """Refuse an empty, oversized, malformed or duplicated list of session ids (INVALID_ARGUMENT)."""
    if not sids:
        raise ge.invalid("session_ids is empty; pass the ids returned by CreateSessions")
    if len(sids) > limit:
        raise ge.invalid(
            f"{len(sids)} session ids in one call; at most {limit} are allowed (ZETTA_MAX_SESSIONS_PER_CALL): "
            "split the batch"
        )
    for i, sid in enumerate(sids):
        if not _SESSION_ID.fullmatch(sid):
            raise ge.invalid(
                f"session_ids[{i}] = {quote_bad_id(sid)} is not a session id: ids are 1-{MAX_SESSION_ID_CHARS} "
                "characters of A-Z a-z 0-9 _ . - as returned by CreateSessions"
            )
    seen: set[str] = set()
    dups: dict[str, None] = {}
    for sid in sids:
        if sid in seen:
            dups[sid] = None
        seen.add(sid)
    if dups:
        listed = sorted(dups)
        raise ge.invalid(f"session ids appear more than once in one call: {name_ids(listed)}", listed)
