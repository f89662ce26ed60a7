"""Fixtures of the deployment tests: the compose stack run as local processes, with traffic.

The stack (deploy/docker-compose.yml plus docker-compose.test.yml) starts once per test session,
in about 6 s: Redis, the gateway, the policy worker, two env workers and, where the binary is
installed, Prometheus. One episode of robosuite Lift runs on four sessions (two per env worker)
through the gateway, and one CreateSessions is refused because the pool is full, so that every
panel of the dashboards has series to show.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tests.deploy.compose_stack import ComposeStack, compose_stack
from tests.deploy.deployfiles import COMPOSE, COMPOSE_TEST
from zetta import Gateway, ZettaError

#: A short episode: Lift truncated after 30 steps (or earlier on success).
LIFT_SHORT: dict[str, Any] = {"env_name": "Lift", "max_steps": 30}


@dataclass
class Traffic:
    """What driving the compose stack showed."""

    workers: dict[str, str] = field(default_factory=dict)  # worker id -> registered address
    session_workers: dict[str, str] = field(default_factory=dict)  # session id -> worker id
    episode_steps: dict[str, int] = field(default_factory=dict)  # session id -> steps at the end
    episode_success: dict[str, bool] = field(default_factory=dict)
    policy_step_calls: int = 0
    rejected_code: str = ""
    rejected_retry_after_ms: int | None = None
    seconds: float = 0.0


async def drive(address: str, slots_total: int) -> Traffic:
    """Run one episode on every slot through the gateway, then ask for one session too many."""
    t0 = time.monotonic()
    out = Traffic()
    async with Gateway(address) as gw:
        out.workers = {w.worker_id: w.address for w in await gw.list_workers() if w.alive}
        group = await gw.create_sessions("robosuite", n=slots_total, env_config=LIFT_SHORT)
        out.session_workers = {i.session_id: i.worker_id for i in group.infos}
        await group.reset(seed=list(range(slots_total)))
        running = group
        while len(running):
            # The compose stack serves the image VLA first; these Lift sessions render no camera,
            # so they ask for the scripted policy it serves beside it (the wiring is the subject).
            results = await running.policy_step(model="scripted-pick-place")
            out.policy_step_calls += 1
            for r in results:
                if r.done:
                    out.episode_steps[r.session_id] = r.episode_step
                    out.episode_success[r.session_id] = r.success
            running = running.subset([r.session_id for r in results if not r.done])
            if out.policy_step_calls > 200:
                raise AssertionError("episodes did not end within 200 policy steps")
        try:
            await gw.create_sessions("robosuite", n=1, env_config=LIFT_SHORT)
        except ZettaError as err:
            out.rejected_code = err.code.name
            out.rejected_retry_after_ms = err.retry_after_ms
        await group.close()
    out.seconds = time.monotonic() - t0
    return out


@dataclass
class ComposeRun:
    """The running compose stack and the traffic it served."""

    stack: ComposeStack
    traffic: Traffic

    @property
    def gateway(self) -> str:
        """Address a client dials."""
        return self.stack.address("gateway", "ZETTA_GATEWAY_PORT")

    @property
    def prometheus(self) -> str | None:
        """Base URL of the local Prometheus, if it runs here."""
        if "prometheus" not in self.stack.procs:
            return None
        return f"http://{self.stack.ips['prometheus']}:9090"


#: Stacks of the session fixture, stopped as soon as the last test that uses one has run.
_RUNNING: list[ComposeStack] = []
_LAST_USER: set[str] = set()
HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(session: pytest.Session, config: pytest.Config, items: list[pytest.Item]) -> None:
    """Remember the last test that needs the compose stack."""
    users = [i for i in items if "compose_run" in getattr(i, "fixturenames", ())]
    _LAST_USER.clear()
    if users:
        _LAST_USER.add(users[-1].nodeid)


def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    """Stop the compose stack after the last test that uses it, so that its processes do not load
    the machine (and skew timings) while other tests run; stop is idempotent."""
    if item.nodeid in _LAST_USER or nextitem is None or HERE not in Path(nextitem.path).resolve().parents:
        while _RUNNING:
            _RUNNING.pop().stop()


@pytest.fixture(scope="session")
def compose_run() -> Iterator[ComposeRun]:
    """deploy/docker-compose.yml (+ the test overlay) running locally, after one episode of traffic."""
    stack = compose_stack(COMPOSE, COMPOSE_TEST)
    stack.start()
    _RUNNING.append(stack)
    try:
        slots = sum(int(stack.procs[n].env["ZETTA_SLOTS"]) for n in stack.procs if n.startswith("env-worker"))
        try:
            traffic = asyncio.run(drive(stack.address("gateway", "ZETTA_GATEWAY_PORT"), slots))
        except BaseException as exc:
            raise RuntimeError(f"driving the compose stack failed: {exc!r}\n{stack.logs()}") from exc
        yield ComposeRun(stack, traffic)
    finally:
        stack.stop()
        stack.remove_files()
