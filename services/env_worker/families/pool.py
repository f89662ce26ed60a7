"""Warm environments of a sharing group, parked by a closed slot for the next one with the same key."""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Any, Generic, TypeVar


E = TypeVar("E")


class IdleBudget:
    """One bound on the environments parked across several pools: a worker's LIBERO groups (one per
    suite and camera setting) each have a pool, and a bound per pool let a worker that served three
    suites in one evolution keep three sets of parked environments (one grew to 15 GB and was
    killed for memory on a 23 GB machine). Pools that share a budget share its lock; beyond the
    bound the environment parked longest ago in any of them is handed back to be closed."""

    def __init__(self, max_idle: int) -> None:
        self.max_idle = max_idle
        self.lock = threading.Lock()
        #: (pool, key, env) of every parked environment, oldest first.
        self.order: list[tuple[Any, Hashable, Any]] = []


class EnvPool(Generic[E]):
    """Warm environments of a sharing group, kept per key (e.g. per task) for the next slot.

    A closed slot parks its environment here instead of destroying it, so the next slot with the
    same key skips the build entirely. ``max_idle`` bounds how many wait at once (None: no bound):
    a LIBERO environment holds a private model copy and a render context with the scene's
    textures (about 0.4 GB), so a worker that visits many tasks would otherwise keep one set per
    task it ever ran (an evolution over ten LIBERO-PRO tasks grew an env worker past 13 GB).
    Beyond the bound the environment parked longest ago is handed back to be closed. ``budget``
    bounds this pool together with the others that share it (:class:`IdleBudget`).
    """

    def __init__(self, max_idle: int | None = None, budget: IdleBudget | None = None) -> None:
        self._idle: dict[Hashable, list[E]] = {}
        self._order: list[tuple[Hashable, E]] = []  # parked environments, oldest first
        self._budget = budget
        self._lock = budget.lock if budget is not None else threading.Lock()
        self.max_idle = max_idle
        self.built = 0
        self.reused = 0
        self.evicted = 0

    def acquire(self, key: Hashable, build: Callable[[], E]) -> E:
        """A warm environment for ``key``, or a new one from ``build`` when none is idle."""
        with self._lock:
            idle = self._idle.get(key)
            if idle:
                self.reused += 1
                env = idle.pop()
                self._order.remove((key, env))
                if self._budget is not None:
                    self._budget.order.remove((self, key, env))
                return env
        env = build()
        with self._lock:
            self.built += 1
        return env

    def release(self, key: Hashable, env: E) -> list[E]:
        """Park ``env`` for reuse under ``key``; returns the environments evicted to stay within
        ``max_idle`` and the shared budget (oldest first, from any pool of the budget), which the
        caller closes."""
        with self._lock:
            self._idle.setdefault(key, []).append(env)
            self._order.append((key, env))
            evicted: list[E] = []
            while self.max_idle is not None and len(self._order) > self.max_idle:
                old_key, old = self._order.pop(0)
                self._idle[old_key].remove(old)
                if self._budget is not None:
                    self._budget.order.remove((self, old_key, old))
                evicted.append(old)
            if self._budget is not None:
                self._budget.order.append((self, key, env))
                while len(self._budget.order) > self._budget.max_idle:
                    pool, old_key, old = self._budget.order.pop(0)
                    pool._idle[old_key].remove(old)
                    pool._order.remove((old_key, old))
                    evicted.append(old)
            self.evicted += len(evicted)
            return evicted

    def idle_count(self) -> int:
        """Environments parked in this pool and ready for reuse."""
        with self._lock:
            return len(self._order)

    def drain(self) -> list[E]:
        """Remove and return every environment parked in this pool, for the group to close."""
        with self._lock:
            envs = [env for _, env in self._order]
            self._idle.clear()
            self._order.clear()
            if self._budget is not None:
                self._budget.order = [entry for entry in self._budget.order if entry[0] is not self]
        return envs
