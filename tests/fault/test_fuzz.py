"""Malformed requests of every kind in bench/fuzz_kinds.py get their clear status (issue #21).

The default suite sends each kind once to a stack with auth on (statuses only, no timing); the
slow suite runs bench/bench_fuzz.py: good sessions run episodes while a fuzzer sends the kinds for
a fixed time, and holds it to zero wrong statuses, zero good sessions lost and a p99 PolicyStep
latency of the good sessions within 2x of the quiet windows of the same run.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from pathlib import Path

import pytest

from bench import bench_fuzz
from bench.fuzz_kinds import KINDS, LIFT_CONFIG, Ctx, send
from services.ops.local_stack import LocalStack
from tests.conftest import LIFT
from tests.fault.test_faults import ZEROS, expect_error, states
from zetta import Gateway
from zetta_wire.v1 import types_pb2

TOKENS = bench_fuzz.TOKENS


@pytest.fixture
def fuzz_stack(stack_factory: Callable[..., LocalStack], tmp_path: Path) -> LocalStack:
    """Auth on, two env workers of robosuite, the scripted policy, the critic service."""
    return stack_factory(**bench_fuzz.stack_settings(tmp_path))


@pytest.fixture
async def alice(fuzz_stack: LocalStack) -> AsyncIterator[Gateway]:
    async with Gateway(fuzz_stack.gateway_address, token=TOKENS["alice"][1]) as gw:
        yield gw


def test_at_least_25_distinct_kinds_all_in_the_docs() -> None:
    names = [k.name for k in KINDS]
    assert len(set(names)) == len(names) >= 25
    assert not {k.expected for k in KINDS} & {"OK", "UNKNOWN", "INTERNAL"}
    docs = (Path(__file__).resolve().parents[2] / "docs" / "security.md").read_text()
    missing = [k.name for k in KINDS if f"| `{k.name}` | {k.what} | {k.expected} |" not in docs]
    assert not missing, f"docs/security.md, 'Fuzzed requests', lacks: {missing}"


async def test_every_kind_gets_its_status(fuzz_stack: LocalStack, alice: Gateway) -> None:
    """Each kind once: the expected status with a message; afterwards both workers are alive and
    the sessions involved (the fuzzer's own and the one of another identity) RUNNING and stepping."""
    victim = await alice.create_sessions("robosuite", n=1, env_config=LIFT_CONFIG)
    await victim.reset(seed=[3])
    async with Gateway(fuzz_stack.gateway_address, token=TOKENS["mallory"][1]) as mallory:
        own = await mallory.create_sessions("robosuite", n=2, env_config=LIFT_CONFIG)
        await own.reset(seed=[4, 5])
        ctx = Ctx(fuzz_stack.gateway_address, TOKENS["mallory"][1], TOKENS["pool"][1], own.ids[0], victim.ids[0],
                  scratch=own.ids[1])
        try:
            outcomes = [await send(ctx, k) for k in KINDS]
        finally:
            await ctx.close()
        wrong = [f"{o.kind}: expected {o.expected}, got {o.code} {o.details!r}" for o in outcomes if not o.ok]
        assert not wrong, "\n".join(wrong)
        assert all(w.alive for w in await alice.list_workers())
        async with Gateway(fuzz_stack.gateway_address, token=TOKENS["ops"][1]) as admin:
            now = await states(admin)
        assert now[victim.ids[0]].state == types_pb2.SESSION_STATE_RUNNING
        assert [now[s].state for s in own.ids] == [types_pb2.SESSION_STATE_RUNNING] * 2
        # The failed resets (unknown task) left the scratch session without an episode: it resets.
        await own.reset(seed=[6, 7])
        assert [r.episode_step for r in await own.action_step([ZEROS, ZEROS])] == [1, 1]
        assert (await victim.action_step([ZEROS]))[0].episode_step == 1
        await own.close()
    await victim.close()


async def test_step_after_a_failed_reset_says_reset_first(gw: Gateway) -> None:
    """A reset that fails (unknown task) ends the episode; the next step is FAILED_PRECONDITION
    "Reset first" (it was UNKNOWN "Unexpected EpisodeError" from the env worker), and a good reset
    brings the session back."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    await group.reset(seed=[1])
    err = await expect_error(group.reset(task="no_such_task"), "INVALID_ARGUMENT")
    assert "no running episode" in err.details
    for step in (group.action_step([ZEROS]), group.policy_step(model="scripted-pick-place")):
        err = await expect_error(step, "FAILED_PRECONDITION")
        assert "Reset first" in err.details and err.session_ids == group.ids
    await group.reset(seed=[2])
    assert (await group.action_step([ZEROS]))[0].episode_step == 1
    await group.close()


@pytest.mark.slow
@pytest.mark.timeout(600)
async def test_fuzz_under_load(fuzz_stack: LocalStack) -> None:
    """40 s in 5 s windows, quiet and fuzzed in turn: 20 malformed requests a second in the fuzzed
    ones, four good sessions running episodes throughout."""
    result = await bench_fuzz.run(fuzz_stack.gateway_address, seconds=40, window=5, rate=20, sessions=4)
    print(bench_fuzz.summary(result))
    assert result["kinds"] == len(KINDS)
    assert result["fuzz"]["wrong_count"] == 0, result["fuzz"]["wrong"]
    good = result["good"]
    assert not good["errors"] and not good["lost"] and good["victim_alive"], good
    assert good["episodes"] > 0
    assert result["p99_ratio"] <= 2.0, result["latency_ms"]
