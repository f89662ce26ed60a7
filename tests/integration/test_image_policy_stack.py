"""An image VLA served through the whole stack: the session renders its camera and the policy
worker batches frames; a session rendering another size gets INVALID_ARGUMENT naming it. A
harness that redirects the policy asks it under an instruction the checkpoint was trained on,
which the env worker learned from the policy worker's ListModels.

The checkpoint is a tiny one trained here for a few steps (the mechanics, not the success: the
shipped checkpoint's success is measured by `zetta eval-policy`, docs/results/vla.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest

from services.common.specs import render_config
from tests.conftest import LIBERO_CREAM
from zetta import Gateway
from zetta.client import ZettaError

torch = pytest.importorskip("torch")

INSTRUCTION = "put the cream cheese in the bowl"
SIZE = 32


def tiny_image_checkpoint(tmp: Path) -> Path:
    from services.policy_worker.vla.model import VLAConfig
    from services.policy_worker.vla.train import TrainConfig, train

    rng = np.random.default_rng(0)
    demos = tmp / "demos.npz"
    np.savez(demos, states=rng.standard_normal((8, 156)).astype(np.float32),
             actions=rng.uniform(-1, 1, (8, 7)).astype(np.float32), episode_lengths=np.array([8]),
             instructions=np.array([INSTRUCTION]), images=rng.integers(0, 255, (4, SIZE, SIZE, 3), dtype=np.uint8),
             image_steps=np.array([0, 2, 4, 6]))
    out = tmp / "ck"
    train([str(demos)], str(out), VLAConfig(image_size=SIZE, prefix_hidden=32, width=16, expert_hidden=16),
          TrainConfig(steps=2, batch_size=4, warmup=1), log=lambda *_: None)
    return out


def image_stack(stack_factory, tmp: Path, slots: int) -> tuple[Any, dict[str, Any]]:
    """A one-worker LIBERO stack serving the tiny image checkpoint, and the env config whose camera
    it reads. A loose heartbeat budget: these tests are about frames and instructions, not
    liveness, and run beside busy cores."""
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    ck = tiny_image_checkpoint(tmp)
    specs = ZettaVLAPolicy(ck, name="zetta-vla-image").input_specs()
    stack = stack_factory(env_workers=1, slots=slots, families=("libero",), models=("zetta-vla-image",), critic=False,
                          heartbeat_timeout_ms=15000,
                          extra_env={"ZETTA_VLA_CHECKPOINT": str(ck), "ZETTA_LOG_LEVEL": "INFO"})
    return stack, {**LIBERO_CREAM, **render_config(specs)}


async def test_frames_flow_through_the_stack_and_a_wrong_size_is_refused(stack_factory, tmp_path) -> None:
    stack, config = image_stack(stack_factory, tmp_path, slots=2)
    async with Gateway(stack.gateway_address) as gw:
        good = await gw.create_sessions(env_family="libero", n=1, env_config=config)
        wrong = await gw.create_sessions(env_family="libero", n=1, env_config={**config, "camera_size": SIZE + 16})
        await good.reset(seed=0)
        await wrong.reset(seed=0)
        results = await good.policy_step(execute_steps=4)
        assert results[0].episode_step == 4 and results[0].executed_actions.shape == (4, 7)
        assert results[0].observation["agentview_image"].shape == (SIZE, SIZE, 3)
        with pytest.raises(ZettaError) as err:
            await wrong.policy_step(execute_steps=4)
        assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT
        assert wrong.ids[0] in str(err.value) and "agentview_image" in str(err.value)
        again = await good.policy_step(execute_steps=4)  # the good session is not hurt by the bad one
        assert again[0].episode_step == 8
        await good.close()
        await wrong.close()


REDIRECT_SKILL = """+++
name = "redirect-test"
description = "redirect the policy to its sub-goal at step 4"

[runtime]
critic_budget_ms = 50.0
critic_hard_limit_ms = 500.0

[[adjudication]]
evidence = "late"
mode = "ask"
priority = 1
+++
test harness
"""

REDIRECT_CRITICS = '''
from services.harness.runtime.api import Proposal


def critic_late(window, params):
    """Proposes a redirection at step 4, after the policy was first asked."""
    if window.now.step == int(params["at"]):
        return Proposal("critics.late", "late", "ask", {"step": float(window.now.step)})
    return None
'''


def redirect_package(root: Path) -> Path:
    for sub in ("tools", "plans", "params"):
        (root / sub).mkdir(parents=True)
    (root / "SKILL.md").write_text(REDIRECT_SKILL)
    (root / "tools" / "critics.py").write_text(REDIRECT_CRITICS)
    (root / "plans" / "playbooks.toml").write_text(
        '[ask]\nrecovery = "redirect_instruction"\nparams = { steps = 8 }\nmax_steps = 8\n')
    (root / "params" / "critics.toml").write_text("at = 4\n")
    return root


async def test_a_redirection_asks_the_policy_under_an_instruction_its_checkpoint_was_trained_on(
        stack_factory, tmp_path) -> None:
    """The episode's instruction is one the checkpoint never saw; the redirection of its pick
    sub-goal (reached(cream_cheese_1)) asks the policy under the checkpoint's own sentence on the
    cream cheese, not under the sub-goal's words ("pick up the cream cheese")."""
    stack, config = image_stack(stack_factory, tmp_path, slots=1)
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions(env_family="libero", n=1, env_config=config)
        await group.reset(seed=0, instruction="put the cream cheese on the plate",
                          harness_dir=str(redirect_package(tmp_path / "pkg")))
        (summary,) = await group.run_episode(max_steps=16, execute_steps=4)
        report = summary.harness_report
        assert report is not None
        (iv,) = report.interventions
        # Step 4 made the critic propose; its proposal came with step 5 (pipelined code critics).
        assert iv["kind"] == "ask" and iv["start_step"] == 5
        assert iv["instruction"] == INSTRUCTION, iv
        await group.close()


async def test_a_redirection_under_the_episodes_own_instruction_is_not_started_and_the_evolver_learns_why(
        stack_factory, tmp_path) -> None:
    """Under the checkpoint's own sentence the same redirection would ask the policy what it is
    already asked: the runtime starts nothing. The evolver asks the policy worker (ListModels) for
    the sentences, so its repair search skips the same firings; an unreachable worker is an error."""
    from services.evolver.stack import policy_instructions

    stack, config = image_stack(stack_factory, tmp_path, slots=1)
    assert policy_instructions(stack.services["policy-0"].address, "zetta-vla-image") == (INSTRUCTION,)
    assert policy_instructions(stack.services["policy-0"].address, "not-served") == ()
    assert policy_instructions("", "zetta-vla-image") == ()
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions(env_family="libero", n=1, env_config=config)
        await group.reset(seed=0, instruction=INSTRUCTION, harness_dir=str(redirect_package(tmp_path / "pkg")))
        (summary,) = await group.run_episode(max_steps=16, execute_steps=4)
        report = summary.harness_report
        assert report is not None and report.interventions == [] and report.recovery_actions == 0, report
        assert report.rejected >= 1, "the critic did propose; the runtime did not act on it"
        await group.close()
    stack.kill("policy-0")
    with pytest.raises(RuntimeError, match="did not list its models"):
        policy_instructions(stack.services["policy-0"].address, "zetta-vla-image", timeout=2)
