"""The critic-governed action loop over the real stack (gateway -> env worker -> harness runtime).

A small harness package written to a directory is named in the ResetSpec; the env worker loads
it, runs its critics at every env step inside the executed chunks, lets the recovery's actions
replace the client's or the policy's, and reports the mode per step and the interventions and
action shares per episode.
"""

from __future__ import annotations

import asyncio
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.conftest import LIFT
from zetta import Gateway
from zetta.client import ZettaError
from services.ops.harness import HarnessRegistry
from services.ops.local_stack import LocalStack

SKILL = """+++
name = "loop-test"
description = "freeze the arm from step 4 on; re-enter once still"

[runtime]
critic_budget_ms = 50.0
critic_hard_limit_ms = 500.0

[reentry]
gamma = 0.0
k = 1

[[adjudication]]
evidence = "late"
mode = "hold"
priority = 1
+++
test harness
"""

CRITICS = '''
from services.harness.runtime.api import Proposal


def critic_late(window, params):
    """Proposes a hold at step 4 of the episode (code critics run every 4th step)."""
    if window.now.step == int(params["at"]):
        return Proposal("critics.late", "late", "hold", {"step": float(window.now.step)})
    return None


def critic_broken(window, params):
    """Raises from step 2 on: switched off, the episode goes on."""
    if window.now.step >= 2:
        raise ValueError("broken critic")
    return None
'''

PLANS = """
[hold]
recovery = "freeze"
params = { steps = 4 }
max_steps = 50
"""


def write_package(root: Path, critics: str = CRITICS) -> Path:
    (root / "tools").mkdir(parents=True)
    (root / "plans").mkdir()
    (root / "params").mkdir()
    (root / "SKILL.md").write_text(SKILL)
    (root / "tools" / "critics.py").write_text(critics)
    (root / "plans" / "playbooks.toml").write_text(PLANS)
    (root / "params" / "critics.toml").write_text("at = 4\n")
    return root


def harness_counters(stack: LocalStack) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """The env workers' zetta_env_harness_* samples summed over workers, by (name, labels)."""
    out: dict[tuple[str, tuple[tuple[str, str], ...]], float] = {}
    for name, svc in stack.services.items():
        if not name.startswith("env-"):
            continue
        with urllib.request.urlopen(svc.metrics_url, timeout=5) as resp:
            text = resp.read().decode()
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                if sample.name.startswith("zetta_env_harness_") and sample.name.endswith("_total"):
                    key = (sample.name, tuple(sorted(sample.labels.items())))
                    out[key] = out.get(key, 0.0) + sample.value
    return out


MOVE = np.array([0.0, 0.0, 0.5, 0.0, 0.0, 0.0, -1.0], np.float32)


async def test_recovery_actions_replace_the_clients_until_reentry(gw: Gateway, tmp_path: Path) -> None:
    pkg = write_package(tmp_path / "pkg")
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 40})
    reset = (await group.reset(task="", seed=3, harness_dir=str(pkg)))[0]
    assert len(reset.harness_content_hash) == 64
    step = (await group.action_step([np.stack([MOVE] * 3)]))[0]
    assert step.executed_actions == pytest.approx(np.stack([MOVE] * 3)) and step.recovery_actions == 0
    assert step.harness_mode == "policy"
    step = (await group.action_step([np.stack([MOVE] * 3)]))[0]
    # Step 4 made the critic propose; its proposal came with step 5 (critics evaluated every 4th
    # step run while the env steps) and the orchestrator granted a hold, which took the third action.
    assert step.executed_actions[:2] == pytest.approx(np.stack([MOVE] * 2)) and step.recovery_actions == 1
    assert step.executed_actions[2, :6] == pytest.approx(np.zeros(6))  # frozen, not the client's move
    assert step.harness_mode == "hold" and step.harness_intervention == "iv1"
    step = (await group.action_step([np.stack([MOVE] * 4)]))[0]
    # Three more frozen actions, then re-entry hands back: the rest of the client's chunk is dropped.
    assert len(step.executed_actions) == 3 and step.recovery_actions == 3
    assert step.executed_actions[:, :6] == pytest.approx(np.zeros((3, 6)))
    assert step.harness_mode == "policy" and step.harness_intervention == ""
    step = (await group.action_step([MOVE]))[0]
    assert step.executed_actions[0] == pytest.approx(MOVE) and step.recovery_actions == 0
    await group.close()


async def test_episode_report_with_action_shares_interventions_and_disabled_critics(
    gw: Gateway, shared_stack: LocalStack, tmp_path: Path
) -> None:
    pkg = write_package(tmp_path / "pkg")
    before = harness_counters(shared_stack)
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 24})
    summary = (await group.run_episode(task="", seed=4, model="scripted-pick-place", execute_steps=2,
                                       harness_dir=str(pkg)))[0]
    report = summary.harness_report
    assert report is not None and report.harness == "loop-test" and report.version == ""
    assert report.policy_actions + report.recovery_actions == summary.steps == 24
    assert report.recovery_actions == 4 and report.actions_by_mode == {"policy": 20, "hold": 4}
    assert report.interventions_by_kind == {"hold": 1}
    iv = report.interventions[0]
    assert (iv["proposer"], iv["evidence"], iv["start_step"], iv["outcome"]) == ("critics.late", "late", 5, "reentered")
    assert iv["end_step"] == 9 and iv["actions"] == 4 and "rule late->hold" in iv["decision"]
    assert [d["name"] for d in report.disabled_critics] == ["critics.broken"]
    assert "ValueError: broken critic" in report.disabled_critics[0]["reason"]
    # The scripted policy answers one action per call: it was asked once per policy action, never
    # while the recovery had control.
    assert summary.policy_calls == report.policy_actions == 20
    after = harness_counters(shared_stack)
    delta = {k: v - before.get(k, 0.0) for k, v in after.items() if v != before.get(k, 0.0)}
    assert delta == {
        ("zetta_env_harness_actions_total", (("by", "policy"),)): 20.0,
        ("zetta_env_harness_actions_total", (("by", "recovery"),)): 4.0,
        ("zetta_env_harness_interventions_total", (("kind", "hold"), ("outcome", "reentered"))): 1.0,
        ("zetta_env_harness_critics_disabled_total", ()): 1.0,
    }, "the episode is counted once, at its end, on the worker's /metrics"
    # The same slot without a harness: no report, nothing replaced.
    plain = (await group.run_episode(task="", seed=4, model="scripted-pick-place", execute_steps=2))[0]
    assert plain.harness_report is None and plain.policy_calls == 24
    await group.close()


async def test_bad_harness_references_are_refused_at_reset(gw: Gateway, tmp_path: Path) -> None:
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 10})
    bad = write_package(tmp_path / "bad", critics="import os\n\n\ndef critic_x(window, params):\n    return None\n")
    with pytest.raises(ZettaError) as err:
        await group.reset(task="", seed=0, harness_dir=str(bad))
    assert err.value.code.name == "INVALID_ARGUMENT" and "os" in err.value.details
    with pytest.raises(ZettaError) as err:
        await group.reset(task="", seed=0, harness_dir=str(tmp_path / "missing"))
    assert err.value.code.name == "INVALID_ARGUMENT" and "not a directory" in err.value.details
    ghost = write_package(tmp_path / "ghost")
    (ghost / "SKILL.md").write_text(SKILL.replace('mode = "hold"', 'mode = "ghost"'))
    with pytest.raises(ZettaError) as err:
        await group.reset(task="", seed=0, harness_dir=str(ghost))
    assert err.value.code.name == "INVALID_ARGUMENT" and "no plan defines" in err.value.details
    # Nothing was half done: the slot still resets and runs without a harness.
    assert (await group.reset(task="", seed=0))[0].harness_content_hash == ""
    await group.close()


async def test_harness_from_the_critic_registry_by_name_and_version(
    gw: Gateway, shared_stack: LocalStack, tmp_path: Path
) -> None:
    pkg = write_package(tmp_path / "pkg")
    with HarnessRegistry(shared_stack.critic_address) as registry:
        manifest, _ = await asyncio.to_thread(registry.publish, pkg)
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 12})
    summary = (await group.run_episode(task="", seed=5, model="scripted-pick-place", harness=manifest.ref))[0]
    report = summary.harness_report
    assert report is not None and (report.harness, report.version) == ("loop-test", str(manifest.version))
    assert report.content_hash == manifest.content_hash and report.interventions_by_kind == {"hold": 1}
    with pytest.raises(ZettaError) as err:
        await group.reset(task="", seed=0, harness="loop-test@999")
    assert err.value.code.name == "NOT_FOUND"
    await group.close()


STALL_SKILL = """+++
name = "stall-test"
description = "hold when the hand stops"

[runtime]
critic_budget_ms = 50.0
critic_hard_limit_ms = 500.0

[reentry]
gamma = 0.0
k = 1

[[critics]]
name = "stall"
predicate = "stalled_progress"
evidence = "stalled"
mode = "hold"
params = { horizon = 12, min_motion = 0.01 }

[[adjudication]]
evidence = "stalled"
mode = "hold"
priority = 1
+++
test harness
"""


async def test_a_trace_of_every_step_replays_its_critic_where_the_runtime_fired(gw: Gateway, tmp_path: Path) -> None:
    """With record_steps each result carries the observation after every executed action (no
    camera images), and a replay of the package's critic over them fires at the step where the
    runtime's critic did: a horizon of 12 frames is 12 env steps in both."""
    from services.evolver.replay import first_fire
    from services.evolver.trace import TraceRecorder
    from services.harness.runtime.library import PREDICATES

    pkg = tmp_path / "stall"
    (pkg / "plans").mkdir(parents=True)
    (pkg / "SKILL.md").write_text(STALL_SKILL)
    (pkg / "plans" / "playbooks.toml").write_text(PLANS)
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 60})
    reset = (await group.reset(task="", seed=5, harness_dir=str(pkg), record_steps=True))[0]
    rec = TraceRecorder([])
    rec.frame(0, reset.observation)
    rec.step(reset.observation)
    still = np.zeros(7, np.float32)
    chunks = [np.stack([MOVE] * 4)] * 3 + [np.stack([still] * 4)] * 8
    started = None
    for chunk in chunks:
        step = (await group.action_step([chunk]))[0]
        assert len(step.step_observations) == len(step.executed_actions)
        assert not any(k.endswith("_image") for k in step.step_observations[-1])
        np.testing.assert_array_equal(step.step_observations[-1]["robot0_eef_pos"], step.observation["robot0_eef_pos"])
        for obs in step.step_observations:
            rec.step(obs)
        rec.frame(step.episode_step, step.observation, step.executed_actions)
        if step.harness_intervention and started is None:
            started = step.episode_step - step.recovery_actions
        if step.done:
            break
    await group.close()
    trace = rec.finish()
    eef = trace.step_obs["robot0_eef_pos"]
    assert trace.steps == len(trace.actions) + 1 and np.all(np.linalg.norm(np.diff(eef[:12], axis=0), axis=1) > 1e-4)
    assert started is not None, "the runtime's stalled_progress critic never fired"
    fired = first_fire(trace, PREDICATES["stalled_progress"].fn, {"horizon": 12.0, "min_motion": 0.01})
    assert fired == started, (fired, started)
