"""Slots of an env worker: which session holds which environment, on which pinned thread.

Each of the N slots owns one thread for its whole life. Simulator and render contexts are
thread-bound (a GL context belongs to the thread that made it), and one thread per slot lets
MuJoCo's GIL-free physics of several slots overlap. Resource-sharing groups (one per family and
canonical config) are kept here too, so every slot of the same config reuses one compiled model.
"""

from __future__ import annotations

import asyncio
import threading
import uuid
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, TypeVar

import grpc
import numpy as np

from services.common import grpc_errors as ge
from services.common.specs import TensorSpec
from services.env_worker import metrics
from services.env_worker.families import (
    ConfigError,
    EnvFamily,
    EpisodeError,
    SlotClosedError,
    UnknownFamilyError,
    canonical_config_key,
    get_family,
)

T = TypeVar("T")


@dataclass
class Episode:
    """The episode a slot is in: what the policy is told and when it must stop."""

    episode_id: str
    instruction: str
    max_steps: int
    ended: bool = False
    success: bool = False
    #: The episode's perception tool for Perceive (services/env_worker/primitives.py), seeded at reset.
    perception: Any = None
    #: ResetSpec.record_steps: every step's observation rides back with its chunk (offline traces).
    record_steps: bool = False


class SlotActivity:
    """A worker's slots' work on their threads (a step, a reset): how much, and how much at once.

    ``busy`` counts the slots with work submitted and not finished. The policy client holds its
    inference requests while enough slots are still busy, so that they leave together as one batch
    (services/env_worker/policy_client.py); it is told when a slot finishes.

    ``concurrency`` bounds how many slots run their work at the same time (0: no bound; by
    default the CPUs the worker may use, ZETTA_STEP_CONCURRENCY). The fast step's physics kernel
    releases the GIL, so slot threads of one process overlap on as many cores as there are; more
    threads than cores only contend for the GIL and the cores and are switched in and out mid-step
    (16 slot threads in each of 2 processes on 2 cores: 12 % more CPU per step than one at a time
    per process, docs/throughput.md).

    The turns are taken on the slot threads (:meth:`in_turn`), not on the event loop: work is
    handed to its thread at once and waits there, so a finishing slot wakes the next one directly.
    Taken on the event loop, each handoff waited for the loop to see the finished work, release the
    turn, resume the next slot's coroutine and submit its work, while the core idled.
    ``busy`` and the listeners are touched only by the event loop.
    """

    def __init__(self, concurrency: int = 0) -> None:
        self.busy = 0
        self._turns = threading.Semaphore(concurrency) if concurrency else None
        self._listeners: list[Callable[[], None]] = []

    def in_turn(self, abandoned: threading.Event, fn: Callable[..., T], *args: Any) -> T:
        """On a slot thread: ``fn(*args)`` once a turn is free, unless the caller gave up waiting
        for it (``abandoned``), in which case nothing runs."""
        if self._turns is None:
            return fn(*args)
        with self._turns:
            if abandoned.is_set():
                raise asyncio.CancelledError("the caller stopped waiting before the slot's turn came")
            return fn(*args)

    def listen(self, callback: Callable[[], None]) -> None:
        """Call ``callback`` (on the event loop) whenever a slot finishes its work."""
        self._listeners.append(callback)

    def enter(self) -> None:
        self.busy += 1

    def leave(self) -> None:
        self.busy -= 1
        for callback in self._listeners:
            callback()


@dataclass
class BoundSlot:
    """A slot bound to a session."""

    session_id: str
    index: int
    family: EnvFamily
    family_name: str
    executor: ThreadPoolExecutor
    env: Any = None
    episode: Episode | None = None
    last_obs: Mapping[str, np.ndarray] | None = None
    busy: asyncio.Lock = field(default_factory=asyncio.Lock)
    #: The harness over this slot's episodes (services/env_worker/harness_loop.SlotHarness); None: none.
    harness: Any = None
    #: The worker's count of busy slots, which ``run`` keeps.
    activity: SlotActivity = field(default_factory=SlotActivity)

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn`` on this slot's pinned thread, in a turn of the worker's step bound; a call
        cancelled before its turn came runs nothing (once begun, ``fn`` runs to its end)."""
        abandoned = threading.Event()
        self.activity.enter()
        try:
            return await asyncio.get_running_loop().run_in_executor(
                self.executor, self.activity.in_turn, abandoned, fn, *args)
        except asyncio.CancelledError:
            abandoned.set()
            raise
        except SlotClosedError as exc:  # the slot closed under a call that had begun
            raise ge.ServiceError(
                grpc.StatusCode.ABORTED,
                f"session {self.session_id}: {exc} while the call ran (the session was closed, or the gateway "
                "declared this worker dead and its sessions LOST); create or reset a session to go on",
                [self.session_id]) from None
        except EpisodeError as exc:  # the env has no episode the slot's record did not know of
            self.episode = None
            raise ge.failed_precondition(f"session {self.session_id}: {exc}", [self.session_id]) from None
        finally:
            self.activity.leave()

    def require_episode(self) -> Episode:
        """The running episode, or the error that tells the client to reset."""
        if self.episode is None:
            raise ge.failed_precondition(
                f"session {self.session_id} has no episode yet; call Reset first", [self.session_id]
            )
        if self.episode.ended:
            how = "success" if self.episode.success else "termination or step budget"
            raise ge.failed_precondition(
                f"episode {self.episode.episode_id} of session {self.session_id} ended ({how}); call Reset to start "
                "another",
                [self.session_id],
            )
        return self.episode


class SlotTable:
    """Binds sessions to slot indices and keeps the resource-sharing groups."""

    def __init__(self, capacity: int, families: Sequence[str], step_concurrency: int = 0) -> None:
        self.capacity = capacity
        self.families = tuple(families)
        self._executors = [
            ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"slot-{i}") for i in range(capacity)
        ]
        self._free = list(range(capacity - 1, -1, -1))
        self._bound: dict[str, BoundSlot] = {}
        self._groups: dict[str, EnvFamily] = {}
        self._group_lock = threading.Lock()
        #: Slots with work on their threads now, and how many may run at once (see SlotActivity).
        self.activity = SlotActivity(step_concurrency)
        metrics.SLOTS.labels("free").set(capacity)
        metrics.SLOTS.labels("bound").set(0)

    def group(self, family_name: str, config: Mapping[str, Any]) -> EnvFamily:
        """The resource-sharing group of a (family, config), created on first use."""
        if family_name not in self.families:
            raise ge.invalid(
                f"env family {family_name!r} is not hosted by this worker; it hosts {', '.join(self.families)}"
            )
        try:
            cls = get_family(family_name)
            key = canonical_config_key(family_name, config)
        except UnknownFamilyError as exc:
            raise ge.invalid(str(exc.args[0] if exc.args else exc)) from None
        except ConfigError as exc:  # canonical_config validates before the group exists
            raise ge.invalid(f"env_config for {family_name!r}: {exc}") from None
        with self._group_lock:
            fam = self._groups.get(key)
            if fam is None:
                try:
                    fam = cls(config)
                except ConfigError as exc:
                    raise ge.invalid(f"env_config for {family_name!r}: {exc}") from None
                self._groups[key] = fam
            return fam

    def bind(self, session_ids: Sequence[str], family_name: str, family: EnvFamily) -> list[BoundSlot]:
        """Reserve a slot per session, all or none."""
        new = [s for s in session_ids if s not in self._bound]
        if len(new) > len(self._free):
            raise ge.exhausted(
                f"worker has {len(self._free)} free slots, {len(new)} asked", retry_after_ms=1000
            )
        out = []
        for sid in session_ids:
            if sid in self._bound:
                out.append(self._bound[sid])
                continue
            index = self._free.pop()
            slot = BoundSlot(sid, index, family, family_name, self._executors[index], activity=self.activity)
            self._bound[sid] = slot
            out.append(slot)
        self._update_gauges()
        return out

    def get(self, session_ids: Sequence[str]) -> list[BoundSlot]:
        """Slots of a batch of sessions, or NOT_FOUND naming the missing ones."""
        missing = [s for s in session_ids if s not in self._bound]
        if missing:
            raise ge.not_found(f"no slot on this worker for session(s) {', '.join(missing)}", missing)
        return [self._bound[s] for s in session_ids]

    def release(self, session_id: str) -> BoundSlot | None:
        """Unbind a session; its env goes back to the group for reuse."""
        slot = self._bound.pop(session_id, None)
        if slot is not None:
            self._free.append(slot.index)
            self._update_gauges()
        return slot

    def holds(self, slot: BoundSlot) -> bool:
        """Whether ``slot`` is still bound (it may have been closed while busy)."""
        return self._bound.get(slot.session_id) is slot

    def session_ids(self) -> list[str]:
        """Sessions bound now."""
        return list(self._bound)

    def shutdown(self) -> None:
        """Stop the slot threads."""
        for ex in self._executors:
            ex.shutdown(wait=False, cancel_futures=True)

    def _update_gauges(self) -> None:
        metrics.SLOTS.labels("free").set(len(self._free))
        metrics.SLOTS.labels("bound").set(len(self._bound))


def new_episode_id() -> str:
    """Episode ids are unique across workers and restarts."""
    return uuid.uuid4().hex


def action_spec_check(spec: TensorSpec, action: np.ndarray, session_id: str) -> np.ndarray:
    """Return the action as a [n, dim] chunk, or INVALID_ARGUMENT if it does not fit the spec."""
    want = tuple(spec.shape)
    if action.dtype != np.dtype(spec.dtype):
        raise ge.invalid(f"action of session {session_id}: expected dtype {spec.dtype}, got {action.dtype}", [session_id])
    if action.shape == want:
        return action.reshape((1, *want))
    if action.ndim == len(want) + 1 and action.shape[1:] == want and action.shape[0] >= 1:
        return action
    raise ge.invalid(
        f"action of session {session_id}: expected shape {list(want)} or [n, {', '.join(map(str, want))}], "
        f"got {list(action.shape)}",
        [session_id],
    )
