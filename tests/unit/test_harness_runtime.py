"""The harness runtime: adjudication, the re-entry contract, budgets and the episode report.

Packages are built in memory (SKILL.md front matter as a dict, tools as modules made from
source) so each test states exactly the harness it needs; the last test builds the shipped
example package through the real loader.
"""

from __future__ import annotations

import types
from pathlib import Path

import numpy as np
import pytest

from services.harness.package.model import LoadedPackage
from services.harness.runtime.engine import HarnessError, HarnessRuntime
from services.harness.runtime.orchestrator import Orchestrator, Rule

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def code_critics_every_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """These tests follow code critics step by step: evaluate them at every step and wait for
    them (the cadence and the pipeline are tested in test_harness_cadence.py)."""
    monkeypatch.setenv("ZETTA_CODE_CRITIC_EVERY", "1")
    monkeypatch.setenv("ZETTA_CODE_CRITIC_PIPELINE", "0")

TOOLS = '''
import numpy as np
from services.harness.runtime.api import Proposal


def critic_flag(window, params):
    """Proposes ``flag`` evidence while the observation's ``flag`` tensor is set."""
    if window.now.obs["phi_collision_intensity"][0] > 0.5:
        return Proposal("tools.flag", "flag", "push", {"value": float(window.now.obs["phi_collision_intensity"][0])})
    return None


class Push:
    """Pushes +x for ``steps`` steps (or fails at once when ``fail`` is set)."""

    name = "push"

    def __init__(self, params):
        self.left = int(params.get("steps", 3))
        self.fail = bool(params.get("fail", False))
        self.status, self.reason = "running", ""

    def start(self, window, memory):
        pass

    def act(self, window):
        if self.fail:
            self.status, self.reason = "failed", "told to fail"
            return None
        if self.left <= 0:
            self.status = "done"
            return None
        self.left -= 1
        return np.array([1.0, 0, 0, 0, 0, 0, 0])


def make_push(params):
    return Push(params)
'''


def module(name: str, source: str) -> types.ModuleType:
    mod = types.ModuleType(name)
    exec(compile(source, f"<{name}>", "exec"), mod.__dict__)  # test-built package code
    return mod


def package(skill: dict, plans: dict | None = None, extra_tools: dict[str, str] | None = None) -> LoadedPackage:
    tools = {"tools": module("h3b_test_tools", TOOLS)}
    for stem, src in (extra_tools or {}).items():
        tools[stem] = module(f"h3b_test_{stem}", src)
    base = {"name": "test", "description": "test harness", "runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0}}
    return LoadedPackage(
        name="test", version="1", content_hash="abc", skill={**base, **skill}, skill_text="",
        params={}, plans=plans if plans is not None else {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"steps": 3}}}},
        tools=tools,
    )


RULE = {"adjudication": [{"evidence": "flag", "mode": "push", "priority": 1}]}


def obs(flag: float = 0.0, x: float = 0.0) -> dict[str, np.ndarray]:
    """A state whose ``flag`` (carried in phi_collision_intensity, a signal a harness may read) makes
    the test critic propose, with the task object's box at ``x`` (seen through the perception tool)."""
    return {"phi_collision_intensity": np.array([flag]), "phi_contact_force": np.zeros(3),
            "task_object_bbox": np.array([x, 0.0, 0.9, x + 0.04, 0.04, 0.95])}


ACT = np.zeros(7)


def run(rt: HarnessRuntime, states: list[dict]) -> list:
    """Feed states as if each followed the action the previous decision asked for."""
    decisions = [rt.step(states[0], None, frozenset())]
    for s in states[1:]:
        prev = decisions[-1]
        decisions.append(rt.step(s, prev.action if prev.action is not None else ACT, frozenset()))
    return decisions


# ---- adjudication -----------------------------------------------------------------------------------


def test_a_proposal_without_an_accepting_rule_never_takes_control() -> None:
    rt = HarnessRuntime(package({}))
    rt.start("task", [])
    decisions = run(rt, [obs(1.0)] * 5)
    assert all(d.mode == "policy" and d.action is None for d in decisions)
    assert rt.report.proposals == 5 and rt.report.rejected == 5 and not rt.report.interventions


def test_milestone_conditions_and_priorities() -> None:
    from services.harness.runtime.api import Proposal

    names = ["reached(a)", "grasped(a)", "lifted(a)"]
    rules = [Rule("x", "low", 1), Rule("x", "high", 5, requires_milestone=("grasped",)),
             Rule("y", "gated", 9, unless_milestone=("reached(a)",)), Rule("z", "m", 3, missing=("lifted",))]
    orch = Orchestrator(rules)
    px, py, pz = Proposal("c", "x", ""), Proposal("c", "y", ""), Proposal("c", "z", "")
    none: dict[str, bool] = {}
    assert orch.adjudicate([px], frozenset({"reached(a)"}), names, none).rule.mode == "low"
    assert orch.adjudicate([px], frozenset({"reached(a)", "grasped(a)"}), names, none).rule.mode == "high"
    v = orch.adjudicate([py], frozenset({"reached(a)"}), names, none)
    assert v.accepted is None and "already reached" in v.rejected[0][1]
    assert orch.adjudicate([pz], frozenset({"reached(a)", "grasped(a)"}), names, none).rule.mode == "m"
    v = orch.adjudicate([pz], frozenset(), names, none)
    assert v.accepted is None and "first missing milestone is reached(a)" in v.rejected[0][1]
    v = orch.adjudicate([px], frozenset({"grasped(a)"}), names, {"low": True, "high": True})
    assert v.accepted is None and "used its budget" in v.rejected[0][1]


# ---- the re-entry contract --------------------------------------------------------------------


def test_control_returns_only_when_evidence_cleared_and_stable_for_k_steps() -> None:
    # Stability over one frame, scaled so that perception jitter (about 0.2 m/s) stays stable and
    # an object moving 10 cm a step (2 m/s) does not.
    contract = {"gamma": 0.5, "k": 3, "stability": {"horizon": 1, "speed_scale": 1.0}}
    rt = HarnessRuntime(package({**RULE, "reentry": contract}))
    rt.start("task", [])
    states = [obs(1.0)] * 6 + [obs(0.0, x=0.1 * (i + 1)) for i in range(4)] + [obs(0.0, x=0.4)] * 5
    decisions = run(rt, states)
    modes = [d.mode for d in decisions]
    # takes control at step 0, pushes 3 steps, then holds: evidence still proposed (steps 4-5),
    # cleared but unstable (6-9), then stable: back to the policy on the 3rd stable step (12).
    assert modes[:12] == ["push"] * 12 and modes[12] == "policy", modes
    pushes = [d.action for d in decisions[:3]]
    assert all(a[0] == 1.0 for a in pushes) and decisions[5].action[:6] == pytest.approx(np.zeros(6))
    iv = rt.report.interventions[0]
    assert (iv.proposer, iv.evidence, iv.outcome, iv.start_step, iv.end_step) == ("tools.flag", "flag", "reentered", 0, 12)
    assert "rule flag->push" in iv.decision and iv.details == {"value": 1.0}


def test_clear_when_predicate_must_hold_before_reentry() -> None:
    plans = {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"steps": 1},
                                    "clear_when": "grasp_retained", "clear_params": {"steps": 2}}}}
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.5, "k": 1}}, plans))
    rt.start("task", [])
    held = {**obs(0.0), "phi_grasp": np.array([1.0]), "phi_object_gripper_drift": np.array([0.0])}
    decisions = run(rt, [obs(1.0)] + [obs(0.0)] * 4 + [held] * 3)
    assert [d.mode for d in decisions].index("policy") == 6  # after two frames of retained grasp


def test_recovery_failure_and_budget_end_an_intervention() -> None:
    plans = {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"fail": True}, "max_uses": 5}}}
    rt = HarnessRuntime(package(RULE, plans))
    rt.start("task", [])
    run(rt, [obs(1.0)] * 3)
    assert rt.report.interventions[0].outcome == "recovery_failed: told to fail"
    plans = {"playbooks": {"push": {"recovery": "tools:make_push", "params": {"steps": 100}, "max_steps": 4, "max_uses": 1}}}
    rt = HarnessRuntime(package(RULE, plans))
    rt.start("task", [])
    decisions = run(rt, [obs(1.0)] * 10)
    assert rt.report.interventions[0].outcome == "budget_exhausted"
    assert len(rt.report.interventions) == 1  # max_uses: the playbook is not granted again
    assert [d.mode for d in decisions].count("push") == 4


def test_action_shares_and_interventions_by_kind() -> None:
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.5, "k": 1}}))
    rt.start("task", [])
    run(rt, [obs(0.0)] * 3 + [obs(1.0)] + [obs(0.0)] * 6)
    report = rt.finish(success=True)
    assert report.policy_actions + report.recovery_actions == 9
    assert report.recovery_actions == report.actions_by_mode["push"] == 3  # stable at once: no hold step
    assert report.interventions_by_kind == {"push": 1}
    assert report.policy_share == pytest.approx(6 / 9)


def test_an_episode_ending_under_a_recovery_is_recorded() -> None:
    rt = HarnessRuntime(package(RULE))
    rt.start("task", [])
    run(rt, [obs(1.0)] * 2)
    assert rt.finish(success=False).interventions[0].outcome == "episode_end"


def test_start_resets_the_episode_state() -> None:
    rt = HarnessRuntime(package(RULE))
    rt.start("a", [])
    run(rt, [obs(1.0)] * 2)
    rt.start("b", [])
    assert rt.mode == "policy" and not rt.report.interventions and rt.report.policy_actions == 0


def test_cooldown_gives_the_policy_steps_before_a_new_intervention() -> None:
    rt = HarnessRuntime(package({**RULE, "runtime": {"critic_budget_ms": 20.0, "cooldown": 3},
                                 "reentry": {"gamma": 0.5, "k": 1}}))
    rt.start("task", [])
    states = [obs(1.0)] + [obs(0.0)] * 3 + [obs(1.0)] * 5
    modes = [d.mode for d in run(rt, states)]
    back = modes.index("policy")
    assert modes[back:back + 4] == ["policy"] * 4 and modes[back + 4] == "push"


# ---- misbehaving critics ------------------------------------------------------------------------


BAD = '''
from services.harness.runtime.api import Proposal


def critic_raises(window, params):
    if window.now.step >= 2:
        raise RuntimeError("boom")
    return None


def critic_slow(window, params):
    if window.now.step < 1:
        return None
    total = 0
    for i in range(400_000):
        total += i
    return None


def critic_endless(window, params):
    if window.now.step < 3:
        return None
    while True:
        pass


def critic_wrong_type(window, params):
    return "not a proposal"
'''


def test_critics_that_raise_overrun_hang_or_misreport_are_switched_off_and_the_episode_goes_on() -> None:
    rt = HarnessRuntime(package({**RULE, "runtime": {"critic_budget_ms": 5.0, "critic_hard_limit_ms": 300.0}},
                                extra_tools={"bad": BAD}))
    rt.start("task", [])
    decisions = run(rt, [obs(0.0)] * 5 + [obs(1.0)])
    disabled = {d.name: d for d in rt.report.disabled_critics}
    assert set(disabled) == {"bad.raises", "bad.slow", "bad.endless", "bad.wrong_type"}
    assert "RuntimeError: boom" in disabled["bad.raises"].reason and disabled["bad.raises"].step == 2
    # slow from step 1 on: its first slow call (wall clock) makes it suspect, the second (CPU) ends it
    assert "CPU" in disabled["bad.slow"].reason and disabled["bad.slow"].step == 2
    assert "hard limit" in disabled["bad.endless"].reason and disabled["bad.endless"].step == 3
    assert "not a Proposal" in disabled["bad.wrong_type"].reason and disabled["bad.wrong_type"].step == 0
    assert decisions[-1].mode == "push"  # the good critic still runs and its evidence is acted on
    rt.start("next", [])
    assert all(c.enabled for c in rt.critics)  # switched off for one episode only


def test_the_watchdog_leaves_no_pending_interrupt_behind() -> None:
    from services.harness.runtime.budget import CallBudget, guarded_call

    def endless() -> None:
        while True:
            pass

    result, why = guarded_call(endless, (), CallBudget(0.001, 0.05))
    assert result is None and "hard limit" in why
    total = 0
    for i in range(200_000):  # an interruption delivered late would land here
        total += i
    assert guarded_call(lambda: 7, (), CallBudget(0.05, 0.1)) == (7, "")


def test_a_call_preempted_once_is_not_switched_off() -> None:
    import time

    from services.harness.runtime.budget import CallBudget, guarded_call

    budget = CallBudget(0.005, 1.0)
    assert guarded_call(time.sleep, (0.02,), budget) == (None, "")  # over in wall time, not in CPU
    assert budget.suspect
    assert guarded_call(time.sleep, (0.02,), budget) == (None, "")  # CPU time now decides: still fine


# ---- building a harness ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("skill", "plans", "match"),
    [
        ({"critics": [{"predicate": "nope"}]}, None, "not in the library"),
        ({"critics": [{"predicate": "drift", "params": {"max_drift": 9.0}}]}, None, "outside"),
        ({"adjudication": [{"evidence": "x", "mode": "ghost"}]}, None, "no plan defines"),
        ({}, {"p": {"push": {"recovery": "teleport"}}}, "not in the library"),
        ({}, {"p": {"push": {"recovery": "tools:missing"}}}, "no recovery factory"),
        ({}, {"p": {"push": {"recovery": "freeze", "bogus": 1}}}, "unknown key"),
        ({"reentry": {"gamma": 2.0}}, None, "gamma"),
    ],
)
def test_a_package_that_does_not_make_a_harness_is_refused_with_the_reason(skill, plans, match) -> None:
    with pytest.raises(HarnessError, match=match):
        HarnessRuntime(package(skill, plans))


def test_the_example_package_builds() -> None:
    from services.harness.package.loader import load_package

    rt = HarnessRuntime(load_package(ROOT / "examples" / "harnesses" / "libero-goal-pick-place"))
    assert {"approach", "retention", "placement", "critics.empty_carry"} <= {c.name for c in rt.critics}
    assert set(rt.plans) == {"acquire", "place", "redirect"}


def test_reentry_clears_lists_evidence_that_blocks_every_handback() -> None:
    other = '''
from services.harness.runtime.api import Proposal


def critic_other(window, params):
    if window.now.obs.get("phi_finger_contact", [0.0])[0] > 0.5:
        return Proposal("other.other", "unsafe", "", {})
    return None
'''
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.0, "k": 1, "clears": ["unsafe"]}},
                                extra_tools={"other": other}))
    rt.start("task", [])
    unsafe = {**obs(0.0), "phi_finger_contact": np.array([1.0])}
    modes = [d.mode for d in run(rt, [obs(1.0)] + [unsafe] * 6 + [obs(0.0)])]
    assert modes[:7] == ["push"] * 7 and modes[7] == "policy"


def test_a_recovery_that_raises_or_acts_wrongly_fails_its_intervention_not_the_episode() -> None:
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
        return np.zeros(3)


def make_bad(params):
    return Bad(params)
'''
    for kind, why in (("raise", "raised KeyError"), ("shape", "the env takes (7,)")):
        plans = {"p": {"push": {"recovery": "broken:make_bad", "params": {"kind": kind}}}}
        rt = HarnessRuntime(package(RULE, plans, extra_tools={"broken": broken}))
        rt.action_shape = (7,)
        rt.start("task", [])
        decisions = run(rt, [obs(1.0)] * 2)
        assert decisions[0].mode == "policy" and decisions[0].action is None
        assert why in rt.report.interventions[0].outcome


# ---- what a harness may know, bounded recoveries, instruction redirection ------------------------------


def test_frames_carry_only_readable_signals_and_objects_come_through_noisy_perception() -> None:
    """The simulator's boxes never reach a critic; perception answers near them, but not exactly."""
    seen: list = []
    spy = '''
def critic_spy(window, params):
    seen = params["out"]
    seen.append((sorted(window.now.obs), window.now.perceive("object")))
    return None
'''
    pkg = package({}, extra_tools={"spy": spy})
    pkg = LoadedPackage(**{**pkg.__dict__, "params": {"spy": {"out": seen}}})
    rt = HarnessRuntime(pkg)
    rt.start("put the bowl on the plate", [])
    box = np.array([0.1, 0.2, 0.9, 0.14, 0.24, 0.95])
    for _ in range(40):
        rt.step({**obs(0.0), "task_object_bbox": box, "task_object_pos": box[:3], "object_state": np.zeros(14)}, ACT,
                frozenset())
    names, _ = seen[0]
    assert "task_object_bbox" not in names and "task_object_pos" not in names and "object_state" not in names
    hits = [d for _, d in seen if d is not None]
    assert len(hits) >= 30  # dropouts are rare
    errors = [float(np.linalg.norm(d.pos - (box[:3] + box[3:]) / 2)) for d in hits]
    assert max(errors) < 0.05 and min(errors) > 0.0


@pytest.mark.parametrize("declared", [[], ["agentview_image"]])
def test_frames_carry_camera_images_only_for_a_package_that_names_them(declared: list[str]) -> None:
    seen: list = []
    spy = '''
def critic_spy(window, params):
    params["out"].append(sorted(window.now.obs))
    return None
'''
    pkg = package({"runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0, "signals": declared}},
                  extra_tools={"spy": spy})
    pkg = LoadedPackage(**{**pkg.__dict__, "params": {"spy": {"out": seen}}})
    rt = HarnessRuntime(pkg)
    rt.start("task", [])
    image = np.zeros((8, 8, 3), dtype=np.uint8)
    rt.step({**obs(0.0), "agentview_image": image, "robot0_eye_in_hand_image": image}, None, frozenset())
    assert "robot0_eye_in_hand_image" not in seen[0] and "phi_contact_force" in seen[0]
    assert ("agentview_image" in seen[0]) == bool(declared)


@pytest.mark.parametrize(
    "source, match",
    [
        ('def critic_peek(window, params):\n    return window.now.obs.get("task_target_bbox")\n', "task_target_bbox"),
        ('KEY = "object_state"\n\ndef critic_peek(window, params):\n    return None\n', "object_state"),
    ],
)
def test_a_package_that_reads_privileged_state_is_refused(source: str, match: str) -> None:
    with pytest.raises(HarnessError, match=match):
        HarnessRuntime(LoadedPackage(**{**package({}).__dict__, "sources": {"peek": source}}))
    with pytest.raises(HarnessError, match="phi_eef_object_dist"):
        HarnessRuntime(package({"runtime": {"critic_budget_ms": 20.0, "critic_hard_limit_ms": 150.0,
                                            "signals": ["phi_eef_object_dist"]}}))


def test_a_playbook_over_the_intervention_cap_or_an_exact_sensor_is_refused() -> None:
    """80 actions for a recovery that moves the arm (a chain that includes a redirection too); 160
    for an instruction redirection alone, during which the policy acts."""
    from services.harness.runtime.limits import INTERVENTION_CAP, REDIRECTION_CAP

    plans = {"p": {"push": {"recovery": "tools:make_push", "max_steps": INTERVENTION_CAP + 1}}}
    with pytest.raises(HarnessError, match="intervention cap of 80"):
        HarnessRuntime(package(RULE, plans))
    chain = {"p": {"push": {"recovery": ["redirect_instruction", "freeze"], "max_steps": INTERVENTION_CAP + 1}}}
    with pytest.raises(HarnessError, match="intervention cap of 80"):
        HarnessRuntime(package(RULE, chain))
    redirect = {"p": {"push": {"recovery": "redirect_instruction", "max_steps": REDIRECTION_CAP}}}
    assert HarnessRuntime(package(RULE, redirect)).plans["push"].max_steps == REDIRECTION_CAP
    redirect["p"]["push"]["max_steps"] = REDIRECTION_CAP + 1
    with pytest.raises(HarnessError, match="redirection cap of 160"):
        HarnessRuntime(package(RULE, redirect))
    with pytest.raises(HarnessError, match="least noise"):
        HarnessRuntime(package({"perception": {"dropout": 0.0}}))


def test_in_control_at_success_is_recorded_as_no_hand_back() -> None:
    rt = HarnessRuntime(package(RULE))
    rt.start("task", [])
    run(rt, [obs(1.0)] * 2)
    assert rt.finish(success=True).interventions[0].outcome == "in_control_at_success"


def test_instruction_redirection_lets_the_policy_act_under_the_subgoal_until_it_is_reached() -> None:
    from services.harness.runtime.library.recoveries import subgoal_instruction

    assert subgoal_instruction("grasped(cream_cheese_1)") == "pick up the cream cheese"
    assert subgoal_instruction("in(bowl_1,wooden_cabinet_1_top_region)#2") == "put the bowl in the wooden cabinet top"
    assert subgoal_instruction("open(wooden_cabinet_1_top_region)") == "open the wooden cabinet top"
    assert subgoal_instruction("turnon(flat_stove_1)") == "turn on the flat stove"
    assert subgoal_instruction("reached(cabinet_1.handle)") == ""
    plans = {"p": {"push": {"recovery": "redirect_instruction", "params": {"steps": 5}}}}
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.0, "k": 1}}, plans))
    names = ["reached(bowl_1)", "grasped(bowl_1)", "on(bowl_1,plate_1)"]
    rt.start("put the bowl on the plate", names)
    first = rt.step(obs(1.0), None, frozenset())
    assert first.mode == "push" and first.action is None and first.instruction == "pick up the bowl"
    later = rt.step(obs(0.0), ACT, frozenset({"reached(bowl_1)"}))
    assert later.instruction == "pick up the bowl"
    done = rt.step(obs(0.0), ACT, frozenset({"reached(bowl_1)", "grasped(bowl_1)"}))
    assert done.mode == "policy" and done.instruction == "" and rt.report.interventions[0].outcome == "reentered"
    assert rt.report.recovery_actions == 2


TRAINED = ("open the middle drawer of the cabinet", "open the top drawer and put the bowl inside",
           "push the plate to the front of the stove", "put the bowl on the plate", "put the bowl on the stove",
           "put the bowl on top of the cabinet", "put the cream cheese in the bowl", "put the wine bottle on the rack",
           "put the wine bottle on top of the cabinet", "turn on the stove")


@pytest.mark.parametrize(("milestone", "episode", "expected"), [
    # A pick sub-goal: a trained pick-and-place of the same object; ties go to the episode's words.
    ("lifted(wine_bottle_1)", "put the wine bottle on the plate", "put the wine bottle on the rack"),
    ("grasped(wine_bottle_1)", "put the wine bottle in the bowl", "put the wine bottle on the rack"),
    ("grasped(akita_black_bowl_1)", "put the bowl on top of the cabinet", "put the bowl on top of the cabinet"),
    ("reached(akita_black_bowl_1)", "put the bowl in the basket", "put the bowl on the plate"),
    ("grasped(cream_cheese_1)", "put the cream cheese on the plate", "put the cream cheese in the bowl"),
    # A placement needs the same object and target.
    ("on(akita_black_bowl_1,flat_stove_1_cook_region)", "", "put the bowl on the stove"),
    ("on(wine_bottle_1,plate_1)", "", ""),
    # An articulation: the same verb, the fixture's words (its object phrase counts double).
    ("open(wooden_cabinet_1_middle_region)", "", "open the middle drawer of the cabinet"),
    ("open(wooden_cabinet_1_top_region)", "", "open the top drawer and put the bowl inside"),
    ("turnon(flat_stove_1)", "", "turn on the stove"),
    ("close(wooden_cabinet_1_top_region)", "", ""),
    # A sentence on another part of the fixture or target serves nothing.
    ("open(wooden_cabinet_1_bottom_region)", "open the bottom drawer of the cabinet", ""),
    ("on(akita_black_bowl_1,wooden_cabinet_1_bottom_side)", "", ""),
    ("on(akita_black_bowl_1,wooden_cabinet_1_top_side)", "", "put the bowl on top of the cabinet"),
    # Nothing the policy was trained on moves a plate by picking it.
    ("grasped(plate_1)", "", ""),
])
def test_a_subgoal_maps_to_an_instruction_the_policy_was_trained_on(milestone: str, episode: str,
                                                                      expected: str) -> None:
    from services.harness.runtime.library.recoveries import policy_instruction

    assert policy_instruction(milestone, TRAINED, episode) == expected
    assert policy_instruction(milestone, (), episode) == ""


def test_redirection_asks_the_policy_under_a_trained_instruction_and_reports_it() -> None:
    """With the serving model's instructions known, the pick sub-goal of an unseen task is asked
    under a trained sentence on the same object, until the object is lifted; the intervention
    records the sentence. Without them, the sub-goal's own words."""
    plans = {"p": {"push": {"recovery": "redirect_instruction", "params": {"steps": 10}}}}
    names = ["reached(wine_bottle_1)", "grasped(wine_bottle_1)", "lifted(wine_bottle_1)", "on(wine_bottle_1,plate_1)"]
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.0, "k": 1}}, plans))
    rt.policy_instructions = TRAINED
    rt.start("put the wine bottle on the plate", names)
    first = rt.step(obs(1.0), None, frozenset())
    assert first.instruction == "put the wine bottle on the rack"
    grasped = rt.step(obs(0.0), ACT, frozenset(names[:2]))
    assert grasped.instruction == "put the wine bottle on the rack", "the sub-goal runs until the bottle is lifted"
    lifted = rt.step(obs(0.0), ACT, frozenset(names[:3]))
    assert lifted.mode == "policy" and lifted.instruction == ""
    (iv,) = rt.report.interventions
    assert iv.outcome == "reentered" and iv.instruction == "put the wine bottle on the rack"
    rt.policy_instructions = ()
    rt.start("put the wine bottle on the plate", names)
    assert rt.step(obs(1.0), None, frozenset()).instruction == "pick up the wine bottle"


def test_a_redirection_under_the_episodes_own_instruction_is_not_started() -> None:
    """On a task the policy was trained on, a pick sub-goal maps back to the episode's own
    sentence: the redirection would ask the policy what it is already asked, so the runtime leaves
    the policy in control and records no intervention; the same critic on an unseen task starts one."""
    plans = {"p": {"push": {"recovery": "redirect_instruction", "params": {"steps": 10}}}}
    names = ["reached(akita_black_bowl_1)", "grasped(akita_black_bowl_1)", "on(akita_black_bowl_1,plate_1)"]
    rt = HarnessRuntime(package({**RULE, "reentry": {"gamma": 0.0, "k": 1}}, plans))
    rt.policy_instructions = TRAINED
    rt.start("Put the bowl on  the plate", names)
    for step in range(3):
        d = rt.step(obs(1.0), None if step == 0 else ACT, frozenset())
        assert d.mode == "policy" and d.instruction == "" and d.action is None
    report = rt.finish(success=True)
    assert report.interventions == [] and report.recovery_actions == 0 and report.policy_actions == 2
    assert report.rejected == 3, "each firing is counted as a proposal the runtime did not act on"
    rt.start("put the bowl in the basket", names)
    d = rt.step(obs(1.0), None, frozenset())
    assert d.mode == "push" and d.instruction == "put the bowl on the plate"
