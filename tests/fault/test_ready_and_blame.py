"""Ready means warm, and errors name the component that failed (issue #21, item 6).

A policy worker said SERVING and then loaded its instruction embedder on the first request; a dead
policy worker was reported to clients as "env worker ... is unreachable".
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.conftest import LIFT
from tests.fault.test_faults import ZEROS, expect_error, states
from zetta import Gateway
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import types_pb2


def log_messages(path: Path) -> list[str]:
    """The ``msg`` of every JSON log line, in order."""
    out = []
    for line in path.read_text(errors="replace").splitlines():
        try:
            out.append(json.loads(line).get("msg", ""))
        except ValueError:
            continue
    return out


async def test_dead_policy_worker_is_named(stack_factory: Callable[..., LocalStack]) -> None:
    """SIGKILL the policy worker: PolicyStep fails UNAVAILABLE naming the policy worker, not the env
    worker; the env workers stay alive and their sessions RUNNING; ActionStep still works."""
    stack: LocalStack = stack_factory()
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
        await group.reset(seed=[1, 2])
        await group.policy_step()
        stack.kill("policy-0")
        err = await expect_error(group.policy_step(), "UNAVAILABLE")
        assert "policy worker" in err.details, err.details
        assert "is unreachable" not in err.details, err.details
        now = await states(gw)
        assert [now[s].state for s in group.ids] == [types_pb2.SESSION_STATE_RUNNING] * 2
        assert all(w.alive for w in await gw.list_workers())
        assert [r.episode_step for r in await group.action_step([ZEROS, ZEROS])] == [2, 2]


async def test_services_warm_before_serving(stack_factory: Callable[..., LocalStack]) -> None:
    """The policy worker's warm-up inference and the env workers' kernels come before 'serving'."""
    stack: LocalStack = stack_factory(env_workers=1)
    policy = log_messages(stack.services["policy-0"].log)
    assert "model warm" in policy and policy.index("model warm") < policy.index("serving")
    env = log_messages(stack.services["env-0"].log)
    kernels = next(i for i, m in enumerate(env) if m.startswith("geom box kernel ready"))
    assert kernels < env.index("serving")


@pytest.mark.slow
async def test_vla_policy_worker_loads_its_embedder_before_serving(stack_factory: Callable[..., LocalStack]) -> None:
    """zetta-vla-state: the sentence model loads during warm-up, so the first PolicyStep with an
    instruction the checkpoint never saw needs no load (it used to exceed the 10 s budget)."""
    stack: LocalStack = stack_factory(env_workers=1, models=("zetta-vla-state",))
    policy = log_messages(stack.services["policy-0"].log)
    assert policy.index("model warm") < policy.index("serving")
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("libero", n=1, env_config={"suite": "libero_goal", "task": "open_the_middle_drawer_of_the_cabinet"})
        await group.reset(seed=[1])
        await group.policy_step(instruction="a sentence no checkpoint has seen before", timeout_ms=10_000)
