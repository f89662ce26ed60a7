"""A runaway harness critic on a real env worker costs its own session one hard limit.

One env worker, two Lift sessions on it, each with a harness. One package's critic runs
``sum(range(400_000_000))`` at step 4 (code critics run every 4th step): one C call that held the GIL for about 25 s when package
code ran inside the worker (the worker stopped heartbeating and every session on it was LOST,
issue #21). In its sandbox child the call is killed at the platform's hard limit; the critic is
switched off for that episode (its report says so), the other session keeps its step latency and
nothing is LOST.
"""

from __future__ import annotations

import asyncio
import os
import statistics
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import LIFT
from zetta import Gateway
from zetta_wire.v1 import types_pb2

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(os.geteuid() != 0, reason="the sandbox's full isolation needs root (degraded otherwise)"),
]

HARD_LIMIT_MS = 300.0

SKILL = f"""+++
name = "runaway-test"
description = "one critic that watches, one that may run away"

[runtime]
critic_budget_ms = 50.0
critic_hard_limit_ms = {HARD_LIMIT_MS}
+++
test harness
"""

QUIET = '''
def critic_watch(window, params):
    return None
'''

RUNAWAY = '''
def critic_watch(window, params):
    return None


def critic_spin(window, params):
    if window.now.step == 4:
        sum(range(400_000_000))
    return None
'''

STILL = np.zeros(7, np.float32)


def write_package(root: Path, critics: str) -> Path:
    (root / "tools").mkdir(parents=True)
    (root / "SKILL.md").write_text(SKILL)
    (root / "tools" / "critics.py").write_text(critics)
    return root


async def test_a_runaway_critic_costs_its_own_session_one_hard_limit(stack_factory, tmp_path: Path) -> None:
    stack = stack_factory(env_workers=1, slots=2, policy_workers=0, critic=False, families=("robosuite",))
    gw = Gateway(stack.gateway_address)
    try:
        quiet = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 400})
        bad = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 12})
        await quiet.reset(task="", seed=1, harness_dir=str(write_package(tmp_path / "quiet", QUIET)))
        await bad.reset(task="", seed=2, harness_dir=str(write_package(tmp_path / "bad", RUNAWAY)))

        async def steps(group, n: int, out: list[float]) -> list:
            results = []
            for _ in range(n):
                t = time.perf_counter()
                results.append((await group.action_step([STILL]))[0])
                out.append(time.perf_counter() - t)
            return results

        alone: list[float] = []
        await steps(quiet, 40, alone)
        during: list[float] = []
        bad_times: list[float] = []
        _, bad_results = await asyncio.gather(steps(quiet, 40, during), steps(bad, 12, bad_times))

        report = bad_results[-1].harness_report
        assert report is not None, "the bad session's episode ended with a report"
        assert [d["name"] for d in report.disabled_critics] == ["critics.spin"]
        assert "hard limit" in report.disabled_critics[0]["reason"] and report.disabled_critics[0]["step"] == 4
        slowest = max(bad_times)
        print(f"quiet session step: median {statistics.median(alone) * 1e3:.1f} ms alone, "
              f"{statistics.median(during) * 1e3:.1f} ms during (max {max(during) * 1e3:.1f}); "
              f"runaway session's slowest step {slowest * 1e3:.0f} ms (hard limit {HARD_LIMIT_MS:.0f} ms)")
        assert slowest < HARD_LIMIT_MS / 1000 + 1.0  # killed at the hard limit, plus a respawn on a busy machine
        assert max(during) < HARD_LIMIT_MS / 1000 + 1.0  # never the 25 s the GIL-holding call took in-process
        assert statistics.median(during) < 2 * statistics.median(alone) + 0.05
        # Nothing was LOST: the worker kept heartbeating and both sessions are still served.
        states = {s.session_id: s.state for s in await gw.list_sessions()}
        assert types_pb2.SESSION_STATE_LOST not in states.values()
        assert all(w.alive for w in await gw.list_workers())
        await steps(quiet, 3, [])
        await quiet.close()
        await bad.close()
    finally:
        await gw.close()
