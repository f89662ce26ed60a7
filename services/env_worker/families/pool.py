"""Warm environments of a sharing group, parked by a closed slot for the next one with the same key."""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar


E = TypeVar("E")


class EnvPool(Generic[E]):
    """Warm environments of a sharing group, kept per key (e.g. per task) for the next slot.

    A closed slot parks its environment here instead of destroying it, so the next slot with the
    same key skips the build entirely.
    """

    def __init__(self) -> None:
        self._idle: dict[Hashable, list[E]] = {}
        self._lock = threading.Lock()
        self.built = 0
        self.reused = 0

    def acquire(self, key: Hashable, build: Callable[[], E]) -> E:
        """A warm environment for ``key``, or a new one from ``build`` when none is idle."""
        with self._lock:
            idle = self._idle.get(key)
            if idle:
                self.reused += 1
                return idle.pop()
        env = build()
        with self._lock:
            self.built += 1
        return env

    def release(self, key: Hashable, env: E) -> None:
        """Park ``env`` for reuse under ``key``."""
        with self._lock:
            self._idle.setdefault(key, []).append(env)

    def idle_count(self) -> int:
        """Environments parked and ready for reuse."""
        with self._lock:
            return sum(len(v) for v in self._idle.values())

    def drain(self) -> list[E]:
        """Remove and return every parked environment, for the group to close."""
        with self._lock:
            envs = [env for idle in self._idle.values() for env in idle]
            self._idle.clear()
        return envs
