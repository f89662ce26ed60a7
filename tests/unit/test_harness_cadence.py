"""When critics run: library critics at every step; a package's code critics on the reset frame,
every ``ZETTA_CODE_CRITIC_EVERY`` steps and at every step of an intervention, over a window that
holds every step, in-process and in the sandbox child alike (one round trip per evaluation)."""

from __future__ import annotations

import numpy as np
import pytest

from services.common.config import ConfigError
from services.harness.package.model import LoadedPackage
from services.harness.runtime.budget import CODE_CRITIC_EVERY, PlatformLimits
from services.harness.runtime.engine import HarnessRuntime
from services.harness.sandbox.client import SandboxClient
from tests.unit.test_harness_runtime import ACT, TOOLS, module, obs

pytestmark = pytest.mark.timeout(120)

#: A code critic that proposes at every evaluation what it saw: the step, the window's length and
#: the steps of its frames (a bit per step), so a test reads when it ran and what reached it.
SEEN = '''
from services.harness.runtime.api import Proposal


def critic_seen(window, params):
    steps = [f.step for f in window.frames]
    return Proposal("seen.seen", "seen", "", {"step": float(window.now.step), "frames": float(len(steps)),
                                              "mask": float(sum(1 << s for s in steps))})
'''

#: A library critic: it proposes whenever the held object slipped (``drifting`` states).
LIBRARY_DRIFT = {"name": "lib_drift", "predicate": "drift", "evidence": "lib"}


def drifting(on: bool) -> dict[str, np.ndarray]:
    """A state in which the library critic ``drift`` proposes (held, slipped 10 cm) or does not."""
    return {**obs(), "phi_grasp": np.array([1.0]), "phi_object_gripper_drift": np.array([0.1 if on else 0.0])}


def _package(sandboxed: bool, skill: dict | None = None) -> LoadedPackage:
    base = {"name": "t", "description": "cadence", "runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0,
                                                                "window": 64}}
    plans = {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"steps": 3}}}}
    sources = {"tools": TOOLS, "seen": SEEN}
    if sandboxed:
        return LoadedPackage("t", "1", "abc", {**base, **(skill or {})}, "", {}, plans, {}, sources=sources)
    tools = {stem: module(f"cadence_{stem}", src) for stem, src in sources.items()}
    return LoadedPackage("t", "1", "abc", {**base, **(skill or {})}, "", {}, plans, tools)


def _builder(sandboxed: bool, monkeypatch: pytest.MonkeyPatch, made: list[HarnessRuntime]):
    def build(every: int | None = None, skill: dict | None = None) -> HarnessRuntime:
        if every is None:
            monkeypatch.delenv("ZETTA_CODE_CRITIC_EVERY", raising=False)
        else:
            monkeypatch.setenv("ZETTA_CODE_CRITIC_EVERY", str(every))
        rt = HarnessRuntime(_package(sandboxed, skill))
        assert (rt.sandbox is not None) == sandboxed
        made.append(rt)
        rt.action_shape = (7,)
        rt.start("task", [])
        return rt

    return build


@pytest.fixture(params=["in-process", "sandboxed"])
def make(request, monkeypatch):
    made: list[HarnessRuntime] = []
    yield _builder(request.param == "sandboxed", monkeypatch, made)
    for rt in made:
        rt.close()


@pytest.fixture
def make_sandboxed(monkeypatch):
    made: list[HarnessRuntime] = []
    yield _builder(True, monkeypatch, made)
    for rt in made:
        rt.close()


def _seen(decision) -> dict[str, float] | None:
    hit = [p for p in decision.proposals if p.critic == "seen.seen"]
    return dict(hit[0].details) if hit else None


def test_the_default_cadence_is_four_steps_pipelined_and_bad_settings_fail_fast() -> None:
    default = PlatformLimits.from_env({})
    assert CODE_CRITIC_EVERY == 4 and default.code_critic_every == 4 and default.code_critic_pipelined
    set_ = PlatformLimits.from_env({"ZETTA_CODE_CRITIC_EVERY": "1", "ZETTA_CODE_CRITIC_PIPELINE": "off"})
    assert set_.code_critic_every == 1 and not set_.code_critic_pipelined
    for name, bad in (("ZETTA_CODE_CRITIC_EVERY", "0"), ("ZETTA_CODE_CRITIC_EVERY", "65"),
                      ("ZETTA_CODE_CRITIC_EVERY", "two"), ("ZETTA_CODE_CRITIC_PIPELINE", "maybe")):
        with pytest.raises(ConfigError, match=name):
            PlatformLimits.from_env({name: bad})


def _episode(rt: HarnessRuntime, steps: int) -> list:
    return [rt.step(obs(), None, frozenset())] + [rt.step(obs(), ACT, frozenset()) for _ in range(steps)]


def _delivered(decisions: list) -> list[tuple[int, int]]:
    """(decision index, step the code critic saw) for each decision that carries its proposal."""
    return [(k, int(s["step"])) for k, d in enumerate(decisions) if (s := _seen(d)) is not None]


def test_code_critics_run_at_the_cadence_over_a_window_of_every_step(make) -> None:
    decisions = _episode(make(), 13)  # the default: every 4 steps, pipelined
    # The reset frame is awaited; later evaluations arrive with the step after theirs.
    assert _delivered(decisions) == [(0, 0), (5, 4), (9, 8), (13, 12)]
    for d in decisions:
        if (s := _seen(d)) is not None:  # every step up to the one evaluated is in the window, none missing
            step = int(s["step"])
            assert s["frames"] == step + 1 and int(s["mask"]) == (1 << (step + 1)) - 1


def test_pipeline_off_proposals_come_with_their_own_step_and_every_one_evaluates_each_step(make, monkeypatch) -> None:
    monkeypatch.setenv("ZETTA_CODE_CRITIC_PIPELINE", "0")
    rt = HarnessRuntime(_package(False))
    try:
        rt.start("task", [])
        assert _delivered(_episode(rt, 9)) == [(0, 0), (4, 4), (8, 8)]
    finally:
        rt.close()
    monkeypatch.delenv("ZETTA_CODE_CRITIC_PIPELINE")
    assert _delivered(_episode(make(every=1), 6)) == [(0, 0)] + [(k, k - 1) for k in range(2, 7)]


def test_library_critics_run_at_every_step(make) -> None:
    rt = make(skill={"critics": [LIBRARY_DRIFT]})
    states = [drifting(k % 2 == 1) for k in range(9)]
    decisions = [rt.step(states[0], None, frozenset())] + [rt.step(s, ACT, frozenset()) for s in states[1:]]
    assert [any(p.critic == "lib_drift" for p in d.proposals) for d in decisions] == [k % 2 == 1 for k in range(9)]
    assert [k for k, _ in _delivered(decisions)] == [0, 5]


def test_code_critics_run_at_every_step_of_an_intervention(make) -> None:
    rt = make(skill={"adjudication": [{"evidence": "flag", "mode": "push", "priority": 1}]})
    flags = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    decisions = [rt.step(obs(flags[0]), None, frozenset())]
    for flag in flags[1:]:
        prev = decisions[-1]
        decisions.append(rt.step(obs(flag), prev.action if prev.action is not None else ACT, frozenset()))
    iv = rt.report.interventions[0]
    # The evaluation of step 4 saw the flag; its proposal came with step 5, which began the push.
    assert iv.kind == "push" and iv.start_step == 5 and iv.outcome == "reentered"
    during = [(k, step) for k, step in _delivered(decisions) if iv.start_step <= k <= iv.end_step]
    # From the step after it began, every step of the intervention is evaluated and awaited.
    assert during == [(5, 4)] + [(k, k) for k in range(iv.start_step + 1, iv.end_step + 1)]
    after = [step for k, step in _delivered(decisions) if k > iv.end_step]
    assert after and all(step % CODE_CRITIC_EVERY == 0 for step in after)  # back to the cadence


def test_the_sandbox_child_is_called_once_per_evaluation(make_sandboxed, monkeypatch) -> None:
    rt = make_sandboxed()
    calls: list[int] = []
    send = SandboxClient.send_step

    def counted(self, s, *args, **kwargs):
        calls.append(s)
        return send(self, s, *args, **kwargs)

    monkeypatch.setattr(SandboxClient, "send_step", counted)
    _episode(rt, 16)
    assert calls == [0, 4, 8, 12, 16]


def test_an_evaluation_in_flight_at_the_end_of_an_episode_is_dropped(make_sandboxed) -> None:
    rt = make_sandboxed()
    _episode(rt, 4)  # step 4 was sent and never collected
    assert rt.sandbox is not None and rt.sandbox.inflight
    rt.start("next", [])
    assert not rt.sandbox.inflight
    assert _delivered(_episode(rt, 5)) == [(0, 0), (5, 4)]


@pytest.mark.parametrize("slip", [6, 4])
def test_a_package_recovery_sees_every_frame_since_the_last_call(slip: int) -> None:
    """A recovery (package code in the child) started between evaluations (step 6), or while
    one is in flight (step 4), acts on a window that ends at the current step: the frames since
    the last critic call go ahead of its call."""
    watcher = '''
import numpy as np


class Watch:
    name = "watch"

    def __init__(self, params):
        self.status, self.reason = "running", ""

    def start(self, window, memory):
        self.first = window.now.step

    def act(self, window):
        steps = [f.step for f in window.frames]
        assert steps == list(range(steps[0], steps[-1] + 1)), steps
        self.status = "done"
        return np.full(7, float(window.now.step))


def make_watch(params):
    return Watch(params)
'''
    skill = {"critics": [LIBRARY_DRIFT], "adjudication": [{"evidence": "lib", "mode": "watch", "priority": 1}]}
    sources = {"tools": TOOLS, "seen": SEEN, "watcher": watcher}
    base = {"name": "t", "description": "cadence", "runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0}}
    rt = HarnessRuntime(LoadedPackage("t", "1", "abc", {**base, **skill}, "", {},
                                      {"playbooks": {"watch": {"recovery": "watcher:make_watch"}}}, {}, sources=sources))
    try:
        rt.action_shape = (7,)
        rt.start("task", [])
        d = rt.step(drifting(False), None, frozenset())
        for k in range(1, slip + 1):
            d = rt.step(drifting(k == slip), ACT, frozenset())
        assert d.mode == "watch" and d.action is not None
        assert d.action[0] == float(slip)  # the child's window ended at this very step, with no step missing
        d = rt.step(drifting(False), d.action, frozenset())
        assert _seen(d) is not None and _seen(d)["step"] == float(slip + 1)  # awaited: the intervention's own step
        assert not rt.sandbox.inflight
    finally:
        rt.close()
