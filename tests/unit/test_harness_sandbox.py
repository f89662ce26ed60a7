"""The harness runtime with package code in its sandbox child: the same behaviour as in-process
(proposals, package recoveries, perception, budgets), plus what only a separate process gives:
a runaway critic is killed at the hard limit, the child respawns with the window, the episode
goes on; and another runtime's steps are not held up meanwhile."""

from __future__ import annotations

import statistics
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from services.harness.package.loader import load_package
from services.harness.package.model import LoadedPackage
from services.harness.runtime.engine import HarnessError, HarnessRuntime
from services.harness.sandbox.client import UID_BASE
from tests.unit.test_harness_runtime import ACT, BAD, RULE, TOOLS, obs, run

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(autouse=True)
def code_critics_every_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests follow code critics step by step: evaluate them at every step and wait for
    them (the cadence and the pipeline are tested in test_harness_cadence.py)."""
    monkeypatch.setenv("ZETTA_CODE_CRITIC_EVERY", "1")
    monkeypatch.setenv("ZETTA_CODE_CRITIC_PIPELINE", "0")


def sandboxed(skill: dict, plans: dict | None = None, extra: dict[str, str] | None = None,
              params: dict | None = None) -> LoadedPackage:
    """A package whose tools exist only as source: the runtime runs them in its sandbox child."""
    base = {"name": "test", "description": "test harness", "runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0}}
    return LoadedPackage(
        name="test", version="1", content_hash="abc", skill={**base, **skill}, skill_text="", params=params or {},
        plans=plans if plans is not None else {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"steps": 3}}}},
        tools={}, sources={"tools": TOOLS, **(extra or {})},
    )


@pytest.fixture
def runtimes():
    made: list[HarnessRuntime] = []
    yield made
    for rt in made:
        rt.close()


def test_critics_and_a_package_recovery_run_in_the_sandbox(runtimes) -> None:
    rt = HarnessRuntime(sandboxed(RULE))
    runtimes.append(rt)
    assert rt.sandbox is not None and rt.sandbox.isolation["uid"] == UID_BASE + rt.sandbox.pid
    rt.action_shape = (7,)
    rt.start("task", [])
    decisions = run(rt, [obs(0.0), obs(1.0), obs(1.0), obs(1.0), obs(1.0), obs(0.0), obs(0.0), obs(0.0), obs(0.0)])
    assert [d.mode for d in decisions[:2]] == ["policy", "push"]
    assert decisions[1].proposals[0].critic == "tools.flag" and decisions[1].proposals[0].details == {"value": 1.0}
    np.testing.assert_array_equal(decisions[1].action, [1.0, 0, 0, 0, 0, 0, 0])
    assert rt.report.interventions[0].kind == "push"
    assert rt.report.recovery_actions >= 3


KNOWN = """
from services.harness.runtime.api import Proposal


def critic_known(window, params):
    return Proposal("known.count", "known", "", {"n": float(len(window.policy_instructions))})
"""


def test_package_code_sees_the_policys_instructions_from_when_the_host_learns_them(runtimes) -> None:
    """Learned mid-episode (the env worker asks the model at the first policy call), the trained
    instructions reach the child's windows at once, and stay through the next episode and a respawn."""
    rt = HarnessRuntime(sandboxed(RULE, extra={"known": KNOWN}))
    runtimes.append(rt)
    rt.start("task", [])

    def seen(decision) -> float:
        return next(p.details["n"] for p in decision.proposals if p.evidence == "known")

    assert seen(rt.step(obs(0.0), None, frozenset())) == 0.0
    rt.policy_instructions = ("put the bowl on the plate", "turn on the stove")
    assert seen(rt.step(obs(0.0), ACT, frozenset())) == 2.0
    rt.start("task", [])
    assert seen(rt.step(obs(0.0), None, frozenset())) == 2.0
    rt.sandbox.close()  # killed: respawned at the next step, started with what the host knows
    assert seen(rt.step(obs(0.0), ACT, frozenset())) == 2.0


def test_bad_critics_are_switched_off_and_a_runaway_is_killed_at_the_hard_limit(runtimes) -> None:
    rt = HarnessRuntime(sandboxed({**RULE, "runtime": {"critic_budget_ms": 5.0, "critic_hard_limit_ms": 300.0}},
                                  extra={"bad": BAD}))
    runtimes.append(rt)
    rt.start("task", [])
    first = rt.sandbox.pid
    t0 = time.perf_counter()
    decisions = run(rt, [obs(0.0)] * 5 + [obs(1.0)])
    took = time.perf_counter() - t0
    disabled = {d.name: d for d in rt.report.disabled_critics}
    assert set(disabled) == {"bad.raises", "bad.slow", "bad.endless", "bad.wrong_type"}
    assert "RuntimeError: boom" in disabled["bad.raises"].reason and disabled["bad.raises"].step == 2
    assert "CPU" in disabled["bad.slow"].reason
    assert "hard limit" in disabled["bad.endless"].reason and disabled["bad.endless"].step == 3
    assert "not a Proposal" in disabled["bad.wrong_type"].reason
    assert decisions[-1].mode == "push"  # the good critic runs on in the respawned child
    assert rt.sandbox.pid != first and rt.sandbox.respawns == 1
    assert took < 5.0
    rt.start("next", [])
    assert all(c.enabled for c in rt.critics)


def test_perception_answers_from_the_host_and_exact_state_never_reaches_the_child(runtimes) -> None:
    spy = '''
from services.harness.runtime.api import Proposal


def critic_spy(window, params):
    d = window.now.perceive("object")
    names = ",".join(sorted(window.now.obs))
    if d is None:
        return None
    return Proposal("spy.spy", names, "", {"x": float(d.pos[0]), "n": float(len(window.frames))})
'''
    rt = HarnessRuntime(sandboxed({}, extra={"spy": spy}))
    runtimes.append(rt)
    rt.start("put the bowl on the plate", [])
    box = np.array([0.1, 0.2, 0.9, 0.14, 0.24, 0.95])
    seen = []
    for _ in range(30):
        d = rt.step({**obs(0.0), "task_object_bbox": box, "task_object_pos": box[:3], "object_state": np.zeros(14)},
                    ACT, frozenset())
        seen += [p for p in d.proposals if p.critic == "spy.spy"]
    assert len(seen) >= 20
    assert all("task_" not in p.evidence and "object_state" not in p.evidence for p in seen)
    errors = [abs(p.details["x"] - 0.12) for p in seen]
    assert max(errors) < 0.05 and min(errors) > 0.0


def test_a_package_recovery_that_raises_or_overruns_fails_its_intervention(runtimes) -> None:
    broken = '''
import numpy as np


class Bad:
    def __init__(self, params):
        self.kind = params["kind"]
        self.status, self.reason = "running", ""

    def start(self, window, memory):
        pass

    def act(self, window):
        if self.kind == "raise":
            raise KeyError("missing")
        while True:
            pass


def make_bad(params):
    return Bad(params)
'''
    for kind, why in (("raise", "KeyError"), ("loop", "hard limit")):
        plans = {"p": {"push": {"recovery": "broken:make_bad", "params": {"kind": kind}}}}
        rt = HarnessRuntime(sandboxed(RULE, plans, extra={"broken": broken}))
        runtimes.append(rt)
        rt.action_shape = (7,)
        rt.start("task", [])
        decisions = run(rt, [obs(1.0)] * 3)
        assert decisions[0].mode == "policy" and decisions[0].action is None
        assert why in rt.report.interventions[0].outcome, rt.report.interventions[0].outcome


def test_module_level_code_that_fails_in_the_sandbox_refuses_the_package() -> None:
    with pytest.raises(HarnessError, match="do not load in the sandbox"):
        HarnessRuntime(sandboxed({}, extra={"boom": "raise RuntimeError('at import')\n"}))


def test_the_example_package_runs_sandboxed_as_loaded_by_the_services(runtimes) -> None:
    pkg = load_package(ROOT / "examples" / "harnesses" / "libero-goal-pick-place", import_tools=False)
    assert not pkg.tools and pkg.sources
    rt = HarnessRuntime(pkg)
    runtimes.append(rt)
    assert rt.sandbox is not None
    assert [c.name for c in rt.critics] == [c.name for c in HarnessRuntime(load_package(
        ROOT / "examples" / "harnesses" / "libero-goal-pick-place")).critics]


def test_a_runaway_critic_does_not_hold_up_another_runtime(runtimes) -> None:
    """Two runtimes (two slots) step on two threads; one runs a critic that never returns. The
    other keeps its step latency, and the runaway costs its own runtime one hard limit."""
    runaway = '''
def critic_spin(window, params):
    if window.now.step == 5:
        sum(range(400_000_000))  # one C call holding the GIL for seconds, in-process
    return None
'''
    skill = {"runtime": {"critic_budget_ms": 50.0, "critic_hard_limit_ms": 200.0}}
    quiet = HarnessRuntime(sandboxed(skill))
    bad = HarnessRuntime(sandboxed(skill, extra={"spin": runaway}))
    runtimes += [quiet, bad]
    quiet.start("task", [])
    bad.start("task", [])

    def steps(rt: HarnessRuntime, n: int, out: list[float]) -> None:
        rt.step(obs(0.0), None, frozenset())
        for _ in range(n):
            t = time.perf_counter()
            rt.step(obs(0.0), ACT, frozenset())
            out.append(time.perf_counter() - t)

    alone: list[float] = []
    steps(quiet, 60, alone)
    quiet.start("task", [])
    during: list[float] = []
    bad_times: list[float] = []
    worker = threading.Thread(target=steps, args=(bad, 20, bad_times))
    worker.start()
    steps(quiet, 60, during)
    worker.join(30)
    assert not worker.is_alive()
    (off,) = bad.report.disabled_critics
    assert off.name == "spin.spin" and "hard limit" in off.reason
    assert max(bad_times) < 0.2 + 0.5  # killed at the hard limit (plus scheduling on a busy machine)
    assert max(during) < 0.1, (statistics.median(alone), max(during))
    assert statistics.median(during) < statistics.median(alone) * 3 + 0.002


def test_the_sandbox_is_on_unless_turned_off_explicitly() -> None:
    from services.common.config import ConfigError
    from services.env_worker.harness_loop import HarnessSource
    from services.harness.sandbox.client import SandboxLimits, enabled

    assert enabled({}) and enabled({"ZETTA_HARNESS_SANDBOX": "on"})
    assert not enabled({"ZETTA_HARNESS_SANDBOX": "off"})
    with pytest.raises(ConfigError, match="ZETTA_HARNESS_SANDBOX"):
        enabled({"ZETTA_HARNESS_SANDBOX": "maybe"})
    assert SandboxLimits.from_env({"ZETTA_SANDBOX_MEMORY_MB": "256"}).memory_mb == 256
    with pytest.raises(ConfigError):
        SandboxLimits.from_env({"ZETTA_SANDBOX_MEMORY_MB": "1"})
    # The env worker checks a package's tools but imports them only with the sandbox off.
    assert HarnessSource().sandboxed and not HarnessSource(sandboxed=False).sandboxed


def test_a_dead_zygote_is_replaced_at_the_next_spawn() -> None:
    from services.harness.sandbox.client import SandboxClient, start_zygote, zygote

    start_zygote(wait=True)
    proc = zygote()._proc
    assert proc is not None
    proc.kill()
    proc.wait()
    child = SandboxClient()
    try:
        assert child.isolation["uid"] == UID_BASE + child.pid or child.isolation["degraded"]
        assert zygote()._proc is not proc
    finally:
        child.close()


def test_perception_answers_go_along_only_while_the_critics_ask_for_them(runtimes) -> None:
    from services.harness.runtime.perception import QUERIES
    from services.harness.sandbox.host import PREFETCH_STEPS

    asker = '''
from services.harness.runtime.api import Proposal


def critic_asker(window, params):
    n = len(window.frames)
    if n <= 3 or n == 20:
        d = window.now.perceive("target")
        return None if d is None else Proposal("asker.asker", "seen", "", {"n": float(n)})
    return None
'''
    rt = HarnessRuntime(sandboxed({}, extra={"asker": asker}))
    runtimes.append(rt)
    rt.start("put the bowl on the plate", [])
    assert rt.sandbox is not None
    target = QUERIES.index("target")
    box = np.array([0.1, 0.2, 0.9, 0.14, 0.24, 0.95])
    seen, prefetching = [], []
    for _ in range(21):
        d = rt.step({**obs(0.0), "task_target_bbox": box}, ACT, frozenset())
        seen += [int(p.details["n"]) for p in d.proposals if p.critic == "asker.asker"]
        prefetching.append(rt.sandbox._unasked[target] < PREFETCH_STEPS)
    # Asked on the first frames (a round trip, then sent along), no longer sent once unasked for
    # PREFETCH_STEPS frames, asked again at frame 20 (a round trip): every answer arrived.
    assert prefetching[:3 + PREFETCH_STEPS - 1] == [True] * (3 + PREFETCH_STEPS - 1)
    assert not any(prefetching[3 + PREFETCH_STEPS:19]) and prefetching[19]
    assert len(seen) >= 3 and seen[-1] == 20  # perception drops a detection now and then (3 %)
    assert not rt.report.disabled_critics
