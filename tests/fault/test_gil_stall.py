"""A slot that holds the GIL longer than the heartbeat timeout (issue #21 item 4).

MuJoCo's ``MjrContext`` holds the GIL for 2.6-3.8 s while it uploads a LIBERO scene's textures;
the worker's heartbeats stop meanwhile. Inside a busy lease (services/env_worker/busy.py) the
gateway knows and keeps the worker's sessions; without one the same stall gets the worker
declared dead and its sessions LOST. Both are shown on one real stack.

The stall is injected into the env workers only (a ``sitecustomize`` module on their
PYTHONPATH wraps the slots' reset): a reset with seed ``LEASED_SEED`` or ``BARE_SEED`` first
calls libc's ``usleep`` through ``ctypes.PyDLL``, whose calls keep the GIL (``ctypes.CDLL``
calls and ``time.sleep`` release it), inside a lease or without one.
"""

from __future__ import annotations

import asyncio
import textwrap
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

import numpy as np

from services.ops.local_stack import LocalStack
from tests.conftest import HEARTBEAT_TIMEOUT_MS, LIFT
from zetta import Gateway
from zetta_wire.v1 import types_pb2

ROOT = Path(__file__).resolve().parents[2]
#: The stall inside a lease, and the one without: longer, so that a monitor that could not judge
#: for a moment (a late tick on two loaded cores, services/gateway/vantage.py) still sees it.
STALL_S, BARE_STALL_S = 5.0, 8.0
LEASED_SEED, BARE_SEED = 424_242, 434_343
ZEROS = np.zeros(7, np.float32)

SITECUSTOMIZE = f"""
import os

if os.environ.get("ZETTA_WORKER_ID") and os.environ.get("ZETTA_ENV_FAMILIES"):
    import ctypes

    from services.env_worker.busy import busy
    from services.env_worker.families import episode

    _hold_gil = ctypes.PyDLL(None).usleep  # PyDLL: the call keeps the GIL
    _reset = episode.EpisodeSlot.reset

    def reset(self, spec):
        if spec.seed == {LEASED_SEED}:
            with busy({int(STALL_S * 1000) + 5000}, "test stall"):
                _hold_gil({int(STALL_S * 1e6)})
        elif spec.seed == {BARE_SEED}:
            _hold_gil({int(BARE_STALL_S * 1e6)})
        return _reset(self, spec)

    episode.EpisodeSlot.reset = reset
"""


def _metric(url: str, name: str, **labels: str) -> float:
    """The sum of a metric's samples with these labels on a Prometheus text page (0 when absent)."""
    text = urllib.request.urlopen(url, timeout=5).read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if line.startswith(name + "{") and all(f'{k}="{v}"' in line for k, v in labels.items()))


async def test_a_gil_stall_inside_a_busy_lease_loses_nothing_and_without_one_loses_the_worker(
        stack_factory: Callable[..., LocalStack], tmp_path: Path) -> None:
    assert STALL_S * 1000 > HEARTBEAT_TIMEOUT_MS + 2000  # the stalls outlast the timeout and a monitor tick
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(textwrap.dedent(SITECUSTOMIZE))
    stack: LocalStack = stack_factory(
        families=("robosuite",), slots=2,
        extra_env={"ZETTA_LOG_LEVEL": "DEBUG",
                   "PYTHONPATH": f"{ROOT}:{ROOT / 'clients' / 'python'}:{hook}"},
    )
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=4, env_config=LIFT)
        await group.reset(seed=[1, 2, 3, 4])
        on0 = [i.session_id for i in group.infos if i.worker_id == "env-0"]
        on1 = [i.session_id for i in group.infos if i.worker_id == "env-1"]
        assert len(on0) == 2 and len(on1) == 2

        async def states() -> dict[str, int]:
            return {s.session_id: s.state for s in await gw.list_sessions()}

        async def watch(during: asyncio.Task[object]) -> set[bool]:
            """Whether env-0 was alive at each look while ``during`` runs."""
            seen = set()
            while not during.done():
                seen |= {w.alive for w in await gw.list_workers() if w.worker_id == "env-0"}
                await asyncio.sleep(0.2)
            return seen

        # 1. The stall inside a lease: env-0 stays alive throughout, no session is LOST.
        env0 = stack.services["env-0"].metrics_url
        started = time.monotonic()
        leased = asyncio.create_task(group.subset(on0[:1]).reset(seed=LEASED_SEED))
        alive = await watch(leased)
        outcomes = {o: _metric(env0, "zetta_env_busy_leases_total", what="test stall", outcome=o)
                    for o in ("granted", "unacknowledged", "unannounced", "standalone")}
        assert alive == {True}, f"env-0 was seen dead during a stall inside a lease (lease: {outcomes})"
        await leased
        assert time.monotonic() - started >= STALL_S  # it did stall
        assert set((await states()).values()) == {types_pb2.SESSION_STATE_RUNNING}
        stepped = await group.action_step([ZEROS] * 4)
        assert len(stepped) == 4
        assert outcomes["granted"] == 1, outcomes
        assert _metric(env0, "zetta_env_busy_lease_seconds_count", what="test stall") == 1
        assert _metric(stack.services["gateway"].metrics_url, "zetta_gateway_busy_leases_total",
                       outcome="granted") >= 1

        # 2. The same stall without a lease: env-0 is declared dead, its sessions LOST.
        # (The reset itself may fail: its worker was declared dead under it.)
        await asyncio.gather(group.subset(on0[:1]).reset(seed=BARE_SEED), return_exceptions=True)
        now = await states()
        blind = _metric(stack.services["gateway"].metrics_url, "zetta_gateway_liveness_blind_total")
        assert [now[s] for s in on0] == [types_pb2.SESSION_STATE_LOST] * 2, \
            f"env-0 survived a {BARE_STALL_S} s stall without a lease (gateway blind counts: {blind})"
        assert [now[s] for s in on1] == [types_pb2.SESSION_STATE_RUNNING] * 2
        reasons = {s.session_id: s.reason for s in await gw.list_sessions()}
        assert all("env-0" in reasons[s] and "heartbeat" in reasons[s] for s in on0)
        await group.subset(on1).action_step([ZEROS] * 2)  # env-1 kept serving
