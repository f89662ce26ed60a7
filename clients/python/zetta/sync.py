"""Blocking wrapper for scripts and notebooks: the async SDK on a private event-loop thread.

    gw = SyncGateway("127.0.0.1:50051")
    sessions = gw.create_sessions(env_family="libero", n=4, env_config={"suite": "libero_goal"})
    sessions.reset(task=6)
    results = sessions.policy_step()
    sessions.close(); gw.close()
"""

from __future__ import annotations

import asyncio
import inspect
import threading
from typing import Any

from zetta.client import Gateway, Session, SessionGroup, StepStream

_WRAP = (Gateway, SessionGroup, Session, StepStream)


class _Loop:
    """An event loop running forever on a daemon thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="zetta-sync", daemon=True)
        self.thread.start()

    def run(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result()

    def stop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=5)


class _Proxy:
    """Forwards attribute access; coroutine methods run on the loop and block for their result."""

    def __init__(self, target: Any, runner: _Loop) -> None:
        object.__setattr__(self, "_target", target)
        object.__setattr__(self, "_runner", runner)

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._target, name)
        if inspect.iscoroutinefunction(attr):
            return lambda *a, **kw: self._wrap(self._runner.run(attr(*a, **kw)))
        if callable(attr):
            return lambda *a, **kw: self._wrap(attr(*a, **kw))
        return self._wrap(attr)

    def __len__(self) -> int:
        return len(self._target)

    def __iter__(self):  # type: ignore[no-untyped-def]
        return (self._wrap(x) for x in self._target)

    def __getitem__(self, i: int) -> Any:
        return self._wrap(self._target[i])

    def _wrap(self, value: Any) -> Any:
        return _Proxy(value, self._runner) if isinstance(value, _WRAP) else value


class SyncGateway(_Proxy):
    """A blocking :class:`zetta.Gateway`; every method returns its result directly."""

    def __init__(self, address: str, **credentials: Any) -> None:
        """``credentials``: ``token``, ``tls_ca``, ``client_cert``, ``client_key`` as for Gateway."""
        runner = _Loop()

        async def make() -> Gateway:
            return Gateway(address, **credentials)

        super().__init__(runner.run(make()), runner)

    def close(self) -> None:
        """Close the channel and stop the loop thread."""
        self._runner.run(self._target.close())
        self._runner.stop()

    def __enter__(self) -> "SyncGateway":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
