"""Busy leases: a slot about to hold the GIL for long tells the gateway first.

The worker's heartbeats come from its asyncio loop (services/env_worker/membership.py). A C call
that holds Python's GIL stops that loop, and the gateway declares a worker dead after
ZETTA_HEARTBEAT_TIMEOUT_MS without a heartbeat: every session on it becomes LOST although the
worker is only busy. The one such call measured on the step path is MuJoCo's ``MjrContext``
(the first render of a new environment uploads the scene's textures: 2.6-3.8 s for a LIBERO
scene on a loaded two-core machine, services/env_worker/rendering.py).

A slot thread wraps such a call in :func:`busy`::

    with busy(15_000, "render context"):
        con = mujoco.MjrContext(model, ...)

which registers the lease, has the membership send a heartbeat with ``busy_ms`` at once and
waits until the gateway acknowledged it (at most ``ACK_WAIT_S``). The gateway then judges the
worker alive until the later of its last heartbeat plus the timeout and the lease's end (the
lease capped at ZETTA_HEARTBEAT_MAX_BUSY_MS). Every heartbeat sent while a lease is held carries
the time the longest one has left; when the block ends the membership sends a heartbeat at once,
which carries no lease (or only what other slots still hold) and so ends it at the gateway.

The wait never blocks for long and never deadlocks: outside a worker (tests, benchmarks, no
membership), on the event loop's own thread, with the loop closed, or with the gateway not
answering, the block just runs (a debug or info line says why). A worker that really dies
inside a lease is declared dead only when the lease ends: leases are therefore held around the
one call that needs them, not around whole resets.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Protocol

from services.env_worker import metrics

log = logging.getLogger(__name__)

#: How long a slot waits for the gateway to acknowledge its lease before going ahead anyway (a
#: heartbeat round trip is milliseconds; on two loaded cores the gateway's loop may take longer).
ACK_WAIT_S = 2.0


class Announcer(Protocol):
    """What the leases need from the membership (the heartbeat sender)."""

    def announce(self) -> concurrent.futures.Future[int] | None:
        """Send a heartbeat carrying the current leases now; the future gives the granted busy_ms
        (0: none, or the gateway did not answer). None when nothing can be awaited (the calling
        thread is the event loop's, or the loop is gone)."""

    def wake(self) -> None:
        """Send a heartbeat soon, without waiting for it (a lease ended)."""


class BusyLeases:
    """The leases this worker's slots hold, and the announcer that tells the gateway about them."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._ends: dict[int, float] = {}
        self._next = 0
        self._announcer: Announcer | None = None

    def install(self, announcer: Announcer | None) -> None:
        """Set (or, with None, remove) the membership that announces leases."""
        with self._lock:
            self._announcer = announcer

    def remaining_ms(self) -> int:
        """Milliseconds the longest lease held now has left (0 when none): a heartbeat's busy_ms."""
        with self._lock:
            if not self._ends:
                return 0
            left = max(self._ends.values()) - self._clock()
        return max(0, int(left * 1000) + 1)

    def held(self) -> int:
        """How many leases are held now."""
        with self._lock:
            return len(self._ends)

    @contextmanager
    def hold(self, ms: int, what: str, ack_wait_s: float = ACK_WAIT_S) -> Iterator[None]:
        """Within the block this worker may not answer for up to ``ms`` milliseconds (see the module)."""
        if ms <= 0:
            raise ValueError(f"a busy lease must be > 0 ms, got {ms}")
        start = self._clock()
        with self._lock:
            key = self._next
            self._next += 1
            self._ends[key] = start + ms / 1000
            announcer = self._announcer
        try:
            outcome = self._announce(announcer, ms, what, ack_wait_s)
            metrics.BUSY_LEASES.labels(what, outcome).inc()
            yield
        finally:
            with self._lock:
                del self._ends[key]
            took = self._clock() - start
            metrics.BUSY_LEASE_SECONDS.labels(what).observe(took)
            log.debug("busy lease ended", extra={"fields": {"what": what, "lease_ms": ms, "held_s": round(took, 3)}})
            if took * 1000 > ms:
                log.warning("a busy lease was shorter than the work it covered",
                            extra={"fields": {"what": what, "lease_ms": ms, "held_s": round(took, 3)}})
            if announcer is not None:
                try:
                    announcer.wake()
                except Exception:  # noqa: BLE001 - a closing loop: the next heartbeat clears the lease
                    pass

    @staticmethod
    def _announce(announcer: Announcer | None, ms: int, what: str, ack_wait_s: float) -> str:
        """Tell the gateway and wait for its answer; returns the outcome label."""
        if announcer is None:
            return "standalone"
        try:
            future = announcer.announce()
        except Exception as exc:  # noqa: BLE001 - the loop is closing: go ahead
            log.info("busy lease not announced", extra={"fields": {"what": what, "error": repr(exc)}})
            return "unannounced"
        if future is None:
            log.debug("busy lease not awaited (on the event loop's thread, or no loop)", extra={"fields": {"what": what}})
            return "unannounced"
        try:
            granted = future.result(timeout=ack_wait_s)
        except concurrent.futures.TimeoutError:
            log.info("busy lease not acknowledged in time; going ahead",
                     extra={"fields": {"what": what, "lease_ms": ms, "waited_s": ack_wait_s}})
            return "unacknowledged"
        except Exception as exc:  # noqa: BLE001 - cancelled (the membership stopped): go ahead
            log.info("busy lease not acknowledged", extra={"fields": {"what": what, "error": repr(exc)}})
            return "unacknowledged"
        if granted <= 0:
            log.info("busy lease not granted (gateway unreachable, or leases off); going ahead",
                     extra={"fields": {"what": what, "lease_ms": ms}})
            return "unacknowledged"
        log.debug("busy lease granted", extra={"fields": {"what": what, "lease_ms": ms, "granted_ms": granted}})
        return "granted"


#: The leases of this process's worker (one env worker per process).
LEASES = BusyLeases()


def busy(ms: int, what: str) -> AbstractContextManager[None]:
    """Context manager: this worker may not answer for up to ``ms`` ms within the block (module docs).

    ``what`` names the work (a metric label: keep it to a few fixed strings).
    """
    return LEASES.hold(ms, what)
