"""Whether this gateway is in a position to judge workers' liveness.

A worker's heartbeat reaches Redis only through a gateway, so a silent heartbeat key is evidence
about the worker only while the gateway itself could reach Redis and kept time. Every Redis
failure, every slow Redis round trip and every stall of the event loop makes the gateway "blind"
for a moment; a worker may be declared dead only after a whole heartbeat timeout has passed
since the gateway last was blind (a stalled or restarted Redis, or a gateway that could not run,
never costs a healthy worker its sessions).
"""

from __future__ import annotations

import logging
import time

from services.gateway import metrics

log = logging.getLogger(__name__)


class Vantage:
    """When this gateway last could not see heartbeats arrive, on the monotonic clock."""

    def __init__(self) -> None:
        self._blind_at = time.monotonic()

    def restart(self) -> None:
        """A gateway that just started has seen no heartbeats yet: it waits one timeout, silently."""
        self._blind_at = time.monotonic()

    def blind(self, why: str) -> None:
        """Note that heartbeats may not have reached Redis just now (``why`` goes to the log)."""
        self._blind_at = time.monotonic()
        metrics.BLIND.labels(why.split(":", 1)[0]).inc()
        log.warning("cannot judge worker liveness for one heartbeat timeout", extra={"fields": {"why": why}})

    def clear_for_ms(self) -> float:
        """Milliseconds since the gateway was last blind."""
        return (time.monotonic() - self._blind_at) * 1000.0

    def may_judge(self, heartbeat_timeout_ms: int) -> bool:
        """True when a full heartbeat timeout passed with Redis answering and the loop on time."""
        return self.clear_for_ms() >= heartbeat_timeout_ms
