"""Every GatewayService RPC over real gRPC, against real redis-server, env workers and MuJoCo.

Each test asserts on values the system computed (ids, steps, observations, metric samples), so a
regression in routing, batching, validation or the simulator plumbing fails here.
"""

from __future__ import annotations

import asyncio
import time
import urllib.request

import grpc
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from tests.conftest import LIBERO_CREAM, LIFT, eventually, free_slots
from zetta import Gateway, SyncGateway, ZettaError
from zetta_wire.codec import decode_observation
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import gateway_pb2, types_pb2

#: Tensors the shipped scripted policy needs; both families must publish them.
POLICY_INPUTS = {"robot0_eef_pos", "robot0_gripper_qpos", "task_object_pos", "task_target_pos", "task_grasped"}


async def observe_raw(gw: Gateway, ids: list[str]) -> list[types_pb2.ObserveResult]:
    """ObserveResults with episode id and step (the SDK's observe() returns only tensors)."""
    return list((await gw.call("Observe", gateway_pb2.ObserveRequest(session_ids=ids))).results)


def assert_obs_equal(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    """Same tensor names, dtypes and bit-identical values."""
    assert set(a) == set(b)
    for name in a:
        assert a[name].dtype == b[name].dtype, name
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def scrape(url: str) -> tuple[str, dict[str, list[tuple[dict[str, str], float]]]]:
    """The raw exposition text and its samples by sample name."""
    with urllib.request.urlopen(url, timeout=5) as resp:
        text = resp.read().decode()
    samples: dict[str, list[tuple[dict[str, str], float]]] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            samples.setdefault(s.name, []).append((dict(s.labels), s.value))
    return text, samples


def sample_sum(samples: dict[str, list[tuple[dict[str, str], float]]], name: str, **labels: str) -> float:
    """Sum of the samples of ``name`` whose labels include ``labels``."""
    return sum(v for lab, v in samples.get(name, []) if all(lab.get(k) == x for k, x in labels.items()))


# ---- sessions ------------------------------------------------------------------------------------


async def test_create_sessions_returns_running_sessions_with_schema(gw: Gateway) -> None:
    """CreateSessions allocates exactly `count` slots, spread over workers, with lease and specs."""
    before = await free_slots(gw)
    t0 = time.time()
    group = await gw.create_sessions("robosuite", n=3, env_config=LIFT, lease_seconds=120, keepalive=False)
    assert len(group) == 3
    assert len(set(group.ids)) == 3
    for info in group.infos:
        assert info.state == types_pb2.SESSION_STATE_RUNNING
        assert info.env_family == "robosuite"
        assert info.worker_id in before
        # Lease: now + 120 s (allow for the build time of the call).
        assert t0 * 1000 + 115_000 <= info.lease_expires_unix_ms <= time.time() * 1000 + 121_000
        assert info.action_spec.name == "action"
        assert info.action_spec.dtype == types_pb2.DTYPE_FLOAT32
        assert list(info.action_spec.shape) == [7]
        schema = {s.name: s for s in info.observation_schema}
        assert POLICY_INPUTS <= set(schema)
        assert list(schema["robot0_eef_pos"].shape) == [3]
        assert schema["task_object_pos"].privileged and not schema["robot0_eef_pos"].privileged
    assert group.action_shape == (7,)
    # The least-loaded worker gets each slot: 3 sessions on 2 equal workers split 2 + 1.
    per_worker = sorted(sum(i.worker_id == w for i in group.infos) for w in before)
    assert per_worker == [1, 2]
    after = await free_slots(gw)
    assert sum(before.values()) - sum(after.values()) == 3
    listed = {s.session_id: s for s in await gw.list_sessions()}
    for info in group.infos:
        assert listed[info.session_id].state == types_pb2.SESSION_STATE_RUNNING
        assert listed[info.session_id].worker_id == info.worker_id
        assert list(listed[info.session_id].action_spec.shape) == [7]
    await group.close()
    assert await free_slots(gw) == before


async def test_reset_per_session_seeds_and_instruction(gw: Gateway) -> None:
    """Each session gets its own seed; the same seed replays the same scene; the instruction comes back."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    first = await group.reset(seed=[11, 12])
    assert [r.session_id for r in first] == group.ids
    assert all(r.instruction == "lift the cube" for r in first)
    assert all(r.max_steps == 500 for r in first)
    assert len({r.episode_id for r in first}) == 2
    assert POLICY_INPUTS <= set(first[0].observation)
    cube = [r.observation["task_object_pos"] for r in first]
    assert not np.array_equal(cube[0], cube[1]), "different seeds must place the cube differently"
    # Swapped seeds: each scene follows its seed, not its session.
    swapped = await group.reset(seed=[12, 11])
    np.testing.assert_array_equal(swapped[0].observation["task_object_pos"], cube[1])
    np.testing.assert_array_equal(swapped[1].observation["task_object_pos"], cube[0])
    assert {r.episode_id for r in swapped}.isdisjoint({r.episode_id for r in first})
    # An instruction override is what the episode (and the policy) uses.
    custom = await group.reset(seed=1, instruction="raise the red block")
    assert [r.instruction for r in custom] == ["raise the red block"] * 2
    await group.close()


async def test_observe_has_no_side_effects(gw: Gateway) -> None:
    """Observe twice: same step counter, same episode, bit-identical tensors equal to the last step's."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    reset = (await group.reset(seed=3))[0]
    step = (await group.action_step(np.full((1, 7), 0.3, np.float32)))[0]
    a = (await observe_raw(gw, group.ids))[0]
    b = (await observe_raw(gw, group.ids))[0]
    assert a.episode_step == b.episode_step == step.episode_step == 1
    assert a.episode_id == b.episode_id == reset.episode_id
    assert_obs_equal(decode_observation(a.observation), decode_observation(b.observation))
    assert_obs_equal(decode_observation(a.observation), step.observation)
    sdk = await group.observe()
    assert_obs_equal(sdk[0], step.observation)
    # The next step starts from where the last one left off: observing did not advance the sim.
    nxt = (await group.action_step(np.zeros((1, 7), np.float32)))[0]
    assert nxt.episode_step == 2
    await group.close()


async def test_action_step_single_and_chunk(gw: Gateway) -> None:
    """A [7] action runs one step; a [n, 7] chunk runs n steps and reports exactly what ran."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    start = await group.reset(seed=[5, 6])
    single = await group.action_step([np.array([0, 0, 0.5, 0, 0, 0, -1], np.float32)] * 2)
    assert [r.session_id for r in single] == group.ids
    assert [r.episode_step for r in single] == [1, 1]
    assert single[0].executed_actions.shape == (1, 7)
    np.testing.assert_array_equal(single[0].executed_actions[0], [0, 0, 0.5, 0, 0, 0, -1])
    # Moving up moved the end effector up.
    assert single[0].observation["robot0_eef_pos"][2] > start[0].observation["robot0_eef_pos"][2]
    rng = np.random.default_rng(0)
    chunks = [rng.uniform(-0.5, 0.5, (5, 7)).astype(np.float32), rng.uniform(-0.5, 0.5, (3, 7)).astype(np.float32)]
    res = await group.action_step(chunks)
    assert [r.episode_step for r in res] == [6, 4]
    np.testing.assert_array_equal(res[0].executed_actions, chunks[0])
    np.testing.assert_array_equal(res[1].executed_actions, chunks[1])
    assert not any(r.done for r in res)
    assert all("grasped" in r.info for r in res)
    await group.close()


async def test_episode_budget_truncates_chunk(gw: Gateway) -> None:
    """A chunk stops at the episode's step budget, reports truncation, and the ended episode refuses steps."""
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 4})
    reset = (await group.reset())[0]
    assert reset.max_steps == 4
    res = (await group.action_step([np.zeros((6, 7), np.float32)]))[0]
    assert res.truncated and not res.terminated and res.done
    assert res.episode_step == 4
    assert res.executed_actions.shape == (4, 7)
    with pytest.raises(ZettaError) as err:
        await group.action_step(np.zeros((1, 7), np.float32))
    assert err.value.code.name == "FAILED_PRECONDITION"
    assert "ended" in err.value.details and "Reset" in err.value.details
    assert err.value.session_ids == group.ids
    await group.reset()  # a new episode may start
    assert (await group.action_step(np.zeros((1, 7), np.float32)))[0].episode_step == 1
    await group.close()


# ---- policy --------------------------------------------------------------------------------------


async def test_policy_step_returns_executed_actions(gw: Gateway) -> None:
    """PolicyStep observes, infers and steps; executed_actions are what the policy chose."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    await group.reset(seed=[1, 2])
    steps = await group.policy_step()
    assert [r.session_id for r in steps] == group.ids
    for r in steps:
        assert r.executed_actions.ndim == 2 and r.executed_actions.shape[1] == 7
        assert r.episode_step == r.executed_actions.shape[0] >= 1
        assert np.all(np.abs(r.executed_actions) <= 1.0)
        assert np.any(r.executed_actions != 0), "the scripted policy moves towards the cube"
    again = await group.policy_step(execute_steps=1)
    assert [r.episode_step for r in again] == [r.episode_step + 1 for r in steps]
    assert all(r.executed_actions.shape == (1, 7) for r in again)
    await group.close()


async def test_policy_infer_does_not_step(gw: Gateway) -> None:
    """PolicyInfer returns the chunk the policy would run, and the episode does not move."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    await group.reset(seed=4)
    await group.action_step(np.zeros((1, 7), np.float32))
    before = (await observe_raw(gw, group.ids))[0]
    chunks = await group.policy_infer()
    assert len(chunks) == 1
    chunk = chunks[0]
    assert chunk.ndim == 2 and chunk.shape[1] == 7 and chunk.shape[0] >= 1
    after = (await observe_raw(gw, group.ids))[0]
    assert after.episode_step == before.episode_step == 1
    assert_obs_equal(decode_observation(after.observation), decode_observation(before.observation))
    # The policy is deterministic on the same observation, and PolicyStep executes that very chunk.
    np.testing.assert_array_equal((await group.policy_infer())[0], chunk)
    step = (await group.policy_step())[0]
    np.testing.assert_array_equal(step.executed_actions, chunk)
    raw = await gw.call("PolicyInfer", gateway_pb2.PolicyInferRequest(session_ids=group.ids))
    assert raw.results[0].session_id == group.ids[0]
    await group.close()


async def test_run_episode_summary(gw: Gateway) -> None:
    """RunEpisode resets, runs the policy inside the worker and summarises each session's episode."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    summaries = await group.run_episode(task="", seed=[7, 8], max_steps=12)
    assert [s.session_id for s in summaries] == group.ids
    for s in summaries:
        assert s.episode_id
        assert 1 <= s.steps <= 12
        assert s.policy_calls >= 1
        assert s.wall_ms > 0
        if s.success:
            assert s.stop_reason == "success"
        else:
            assert (s.steps, s.stop_reason) == (12, "max_steps")
    # Without specs the current episode continues from where it stopped.
    obs = await observe_raw(gw, group.ids)
    assert [o.episode_step for o in obs] == [s.steps for s in summaries]
    assert [o.episode_id for o in obs] == [s.episode_id for s in summaries]
    more = await group.run_episode(max_steps=3)
    assert [m.episode_id for m in more] == [s.episode_id for s in summaries]
    assert all(m.steps == 3 for m in more)
    await group.close()


@pytest.mark.slow
async def test_run_episode_to_success(gw: Gateway) -> None:
    """The scripted policy lifts the cube: a whole episode ends with stop_reason success."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    summary = (await group.run_episode(task="", seed=0))[0]
    assert summary.success and summary.stop_reason == "success"
    assert summary.steps < 500
    await group.close()


# ---- streams, closing, listings -------------------------------------------------------------------


async def test_step_stream(gw: Gateway) -> None:
    """One stream drives reset, policy steps, actions and observations of one session, in order."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    stream = group[0].stream()
    reset = await stream.reset(seed=9)
    assert reset.session_id == group.ids[0]
    assert reset.instruction == "lift the cube"
    first = await stream.policy_step()
    assert first.session_id == group.ids[0]
    assert first.episode_step == first.executed_actions.shape[0] >= 1
    obs = await stream.observe()
    assert_obs_equal(obs, first.observation)
    act = await stream.action_step(np.zeros((2, 7), np.float32))
    assert act.episode_step == first.episode_step + 2
    # Errors end the stream with the gateway's status.
    with pytest.raises(ZettaError) as err:
        await stream.action_step(np.zeros(6, np.float32))
    assert err.value.code.name == "INVALID_ARGUMENT"
    # A fresh stream on the same session sees the same episode (the failed call stepped nothing).
    other = group[0].stream()
    assert_obs_equal(await other.observe(), act.observation)
    await other.close()
    await group.close()


async def test_close_sessions_is_idempotent(gw: Gateway) -> None:
    """The first close frees the slots; a second lists the sessions as already closed."""
    before = await free_slots(gw)
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    req = gateway_pb2.CloseSessionsRequest(session_ids=group.ids)
    first = await gw.call("CloseSessions", req)
    assert sorted(first.closed_session_ids) == sorted(group.ids)
    assert list(first.already_closed_session_ids) == []
    second = await gw.call("CloseSessions", req)
    assert list(second.closed_session_ids) == []
    assert sorted(second.already_closed_session_ids) == sorted(group.ids)
    unknown = await gw.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=["no-such-session"]))
    assert list(unknown.already_closed_session_ids) == ["no-such-session"]
    listed = {s.session_id: s for s in await gw.list_sessions()}
    for sid in group.ids:
        assert listed[sid].state == types_pb2.SESSION_STATE_TERMINATED
        assert listed[sid].reason == "closed by client"
    assert await free_slots(gw) == before
    await group.close()  # the SDK close is idempotent too


async def test_list_workers_and_sessions(gw: Gateway, stack: LocalStack) -> None:
    """ListWorkers shows both env workers with their families and slots; ListSessions filters."""
    workers = {w.worker_id: w for w in await gw.list_workers()}
    assert set(workers) == {"env-0", "env-1"}
    now_ms = time.time() * 1000
    for wid, w in workers.items():
        assert w.alive
        assert w.slots == 4
        assert set(w.env_families) == {"libero", "robosuite"}
        assert w.address == stack.services[wid].address
        assert now_ms - 3000 < w.last_heartbeat_unix_ms <= now_ms + 1000
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    workers_after = {w.worker_id: w for w in await gw.list_workers()}
    holder = group.infos[0].worker_id
    assert workers_after[holder].free_slots == workers[holder].free_slots - 1
    ours = [s for s in await gw.list_sessions("robosuite") if s.session_id == group.ids[0]]
    assert len(ours) == 1 and ours[0].state == types_pb2.SESSION_STATE_RUNNING
    assert not [s for s in await gw.list_sessions("libero") if s.session_id == group.ids[0]]
    running = await gw.call("ListSessions", gateway_pb2.ListSessionsRequest(states=[types_pb2.SESSION_STATE_RUNNING]))
    assert group.ids[0] in {s.session_id for s in running.sessions}
    assert all(s.state == types_pb2.SESSION_STATE_RUNNING for s in running.sessions)
    await group.close()
    terminated = await gw.call(
        "ListSessions", gateway_pb2.ListSessionsRequest(states=[types_pb2.SESSION_STATE_TERMINATED]))
    assert group.ids[0] in {s.session_id for s in terminated.sessions}


async def test_renew_sessions_extends_lease(gw: Gateway) -> None:
    """RenewSessions pushes the lease out from now."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT, lease_seconds=60, keepalive=False)
    old = group.infos[0].lease_expires_unix_ms
    resp = await gw.call("RenewSessions", gateway_pb2.RenewSessionsRequest(session_ids=group.ids, lease_seconds=600))
    new = resp.sessions[0].lease_expires_unix_ms
    assert new - old > 500_000
    listed = {s.session_id: s for s in await gw.list_sessions()}
    assert listed[group.ids[0]].lease_expires_unix_ms == new
    await group.close()


async def test_keepalive_renews_until_the_gateway_closes(stack: LocalStack) -> None:
    """A keepalive group outlives its lease, and closing the gateway (not the group) stops the
    renewals with it: none is left calling a closed channel."""
    gateway = Gateway(stack.gateway_address)
    group = await gateway.create_sessions("robosuite", n=1, env_config=LIFT, lease_seconds=3)
    first = group.infos[0].lease_expires_unix_ms
    await asyncio.sleep(4.5)
    listed = {s.session_id: s for s in await gateway.list_sessions()}
    assert listed[group.ids[0]].state == types_pb2.SESSION_STATE_RUNNING
    assert listed[group.ids[0]].lease_expires_unix_ms > first
    renewing = group._keepalive
    assert renewing is not None and not renewing.done()
    await gateway.close()
    assert renewing.cancelled()
    async with Gateway(stack.gateway_address) as other:
        await other.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=group.ids))


async def test_calls_on_a_closing_gateway_fail_instead_of_hanging(stack: LocalStack) -> None:
    """A coalesced call in flight when the gateway closes, and one made after, both raise a
    ZettaError that says to open a new Gateway; neither leaves its caller waiting forever."""
    gateway = Gateway(stack.gateway_address)
    group = await gateway.create_sessions("robosuite", n=2, env_config=LIFT, lease_seconds=60, keepalive=False)
    first, second = list(group)
    in_flight = asyncio.gather(first.reset(seed=1), second.reset(seed=2), return_exceptions=True)
    for _ in range(3):  # the SDK coalesces the two and starts their RPC
        await asyncio.sleep(0)
    await gateway.close()
    outcomes = await asyncio.wait_for(in_flight, timeout=10)
    assert all(isinstance(o, ZettaError) and o.code == grpc.StatusCode.CANCELLED for o in outcomes), outcomes
    with pytest.raises(ZettaError, match="open a new Gateway") as err:
        await asyncio.wait_for(first.reset(seed=3), timeout=10)
    assert err.value.code == grpc.StatusCode.CANCELLED
    async with Gateway(stack.gateway_address) as other:
        await other.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=group.ids))


# ---- the SDK ---------------------------------------------------------------------------------------


async def test_sdk_coalesces_concurrent_session_calls(gw: Gateway, stack: LocalStack) -> None:
    """asyncio.gather over single Session handles leaves as one RPC, and each gets its own result."""
    group = await gw.create_sessions("robosuite", n=4, env_config=LIFT)
    handles = list(group)
    seeds = [21, 22, 23, 24]
    url = stack.services["gateway"].metrics_url
    _, m0 = scrape(url)
    resets = await asyncio.gather(*(h.reset(seed=s) for h, s in zip(handles, seeds)))
    _, m1 = scrape(url)
    assert [r.session_id for r in resets] == group.ids
    assert sample_sum(m1, "zetta_gateway_requests_total", method="Reset", code="OK") - \
        sample_sum(m0, "zetta_gateway_requests_total", method="Reset", code="OK") == 1
    # Each handle got the scene of its own seed: a batched reset with the same seeds agrees.
    batched = await group.reset(seed=seeds)
    for single, ref in zip(resets, batched):
        np.testing.assert_array_equal(single.observation["task_object_pos"], ref.observation["task_object_pos"])
    steps = await asyncio.gather(*(h.policy_step() for h in handles))
    _, m2 = scrape(url)
    assert sample_sum(m2, "zetta_gateway_requests_total", method="PolicyStep", code="OK") - \
        sample_sum(m1, "zetta_gateway_requests_total", method="PolicyStep", code="OK") == 1
    assert [s.session_id for s in steps] == group.ids
    assert all(s.episode_step >= 1 for s in steps)
    # Different actions per handle: every session executed its own.
    actions = [np.full(7, 0.1 * (i + 1), np.float32) for i in range(4)]
    acted = await asyncio.gather(*(h.action_step(a) for h, a in zip(handles, actions)))
    for a, r, h in zip(actions, acted, handles):
        assert r.session_id == h.session_id
        np.testing.assert_array_equal(r.executed_actions[0], a)
    # A failure reaches every caller of the coalesced call.
    with pytest.raises(ZettaError) as err:
        await asyncio.gather(handles[0].action_step(np.zeros(7, np.float32)),
                             handles[1].action_step(np.zeros(5, np.float32)))
    assert err.value.code.name == "INVALID_ARGUMENT"
    assert err.value.session_ids == [handles[1].session_id]
    await group.close()


def test_sync_gateway(stack: LocalStack) -> None:
    """The blocking wrapper runs the async SDK on its own loop thread and returns plain results."""
    with SyncGateway(stack.gateway_address) as gw:
        sessions = gw.create_sessions("robosuite", n=2, env_config=LIFT)
        assert len(sessions) == 2
        ids = list(sessions.ids)
        resets = sessions.reset(seed=[1, 2])
        assert [r.session_id for r in resets] == ids
        steps = sessions.policy_step()
        assert [s.episode_step >= 1 for s in steps] == [True, True]
        one = sessions[0].action_step(np.zeros(7, np.float32))
        assert one.session_id == ids[0]
        assert one.episode_step == steps[0].episode_step + 1
        assert len(gw.list_workers()) == 2
        sessions.close()
        states = {s.session_id: s.state for s in gw.list_sessions()}
        assert [states[i] for i in ids] == [types_pb2.SESSION_STATE_TERMINATED] * 2


async def test_same_seed_same_actions_is_deterministic(gw: Gateway) -> None:
    """Two sessions (on different workers) with the same seed and actions see identical observations."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    assert group.infos[0].worker_id != group.infos[1].worker_id
    resets = await group.reset(seed=[42, 42])
    assert_obs_equal(resets[0].observation, resets[1].observation)
    rng = np.random.default_rng(42)
    for _ in range(4):
        chunk = rng.uniform(-1, 1, (3, 7)).astype(np.float32)
        res = await group.action_step([chunk, chunk])
        assert res[0].episode_step == res[1].episode_step
        assert_obs_equal(res[0].observation, res[1].observation)
        assert res[0].reward == res[1].reward
    policy = await group.policy_step()
    np.testing.assert_array_equal(policy[0].executed_actions, policy[1].executed_actions)
    assert_obs_equal(policy[0].observation, policy[1].observation)
    # And a different seed gives a different episode.
    other = await group.reset(seed=[42, 43])
    assert not np.array_equal(other[0].observation["task_object_pos"], other[1].observation["task_object_pos"])
    await group.close()


async def test_libero_session(gw: Gateway) -> None:
    """A LIBERO-Goal session: the suite's instruction, the canonical schema and policy steps."""
    group = await gw.create_sessions("libero", n=1, env_config=LIBERO_CREAM)
    schema = {s.name for s in group.infos[0].observation_schema}
    assert POLICY_INPUTS <= schema
    reset = (await group.reset(seed=0, init_state_index=0))[0]
    assert reset.instruction == "put the cream cheese in the bowl"
    assert reset.max_steps == 300
    assert set(reset.observation) == schema
    eef0 = reset.observation["robot0_eef_pos"].copy()
    last = None
    for i in range(3):
        last = (await group.policy_step())[0]
        assert last.episode_step == i + 1
        assert not last.done
    assert last is not None
    assert not np.allclose(last.observation["robot0_eef_pos"], eef0), "the arm moved"
    # The object and target are where the task says (distinct, on the table).
    assert not np.allclose(last.observation["task_object_pos"], last.observation["task_target_pos"])
    await group.close()


# ---- metrics -----------------------------------------------------------------------------------


async def test_metrics_expose_required_names(gw: Gateway, stack: LocalStack) -> None:
    """Each service's /metrics has the series the dashboards and alerts are built on, with live values."""
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 2})
    await group.reset()
    await group.policy_step()
    await group.policy_step()  # ends the 2-step episode: one completed episode
    with pytest.raises(ZettaError):
        await gw.create_sessions("no-such-family", n=1)

    text, gw_samples = scrape(stack.services["gateway"].metrics_url)
    for name, kind in (("zetta_sessions", "gauge"), ("zetta_hop_latency_seconds", "histogram"),
                       ("zetta_gateway_admissions_rejected_total", "counter"),
                       ("zetta_gateway_missed_heartbeats_total", "counter")):
        assert f"# TYPE {name} {kind}" in text, name
    assert sample_sum(gw_samples, "zetta_gateway_admissions_rejected_total", family="no-such-family") >= 1
    assert sample_sum(gw_samples, "zetta_hop_latency_seconds_count", service="gateway", method="PolicyStep") >= 2
    assert gw_samples.get("zetta_sessions"), "session gauges are published"

    env_text = ""
    env_steps = env_episodes = env_hops = 0.0
    for name in ("env-0", "env-1"):
        t, s = scrape(stack.services[name].metrics_url)
        env_text += t
        env_steps += sample_sum(s, "zetta_env_steps_total", family="robosuite")
        env_episodes += sample_sum(s, "zetta_env_episodes_completed_total", family="robosuite")
        env_hops += sample_sum(s, "zetta_hop_latency_seconds_count", service="env_worker", method="PolicyStepSlots")
    for name, kind in (("zetta_env_steps_total", "counter"), ("zetta_env_episodes_completed_total", "counter"),
                       ("zetta_hop_latency_seconds", "histogram")):
        assert f"# TYPE {name} {kind}" in env_text, name
    assert env_steps >= 2
    assert env_episodes >= 1
    assert env_hops >= 2

    pol_text, pol = scrape(stack.services["policy-0"].metrics_url)
    for name, kind in (("zetta_policy_batch_size", "histogram"), ("zetta_policy_queue_depth", "gauge"),
                       ("zetta_policy_queue_wait_seconds", "histogram"), ("zetta_hop_latency_seconds", "histogram")):
        assert f"# TYPE {name} {kind}" in pol_text, name
    assert sample_sum(pol, "zetta_policy_batch_size_count", model="scripted-pick-place") >= 2
    assert sample_sum(pol, "zetta_policy_queue_wait_seconds_count", model="scripted-pick-place") >= 2
    assert sample_sum(pol, "zetta_policy_queue_depth", model="scripted-pick-place") == 0  # drained
    assert sample_sum(pol, "zetta_hop_latency_seconds_count", service="policy_worker", method="Infer") >= 2

    # The session gauge follows the registry (refreshed every few seconds by the monitor).
    holder_family = group.infos[0].env_family

    async def gauge_counts_running() -> bool:
        _, s = scrape(stack.services["gateway"].metrics_url)
        return sample_sum(s, "zetta_sessions", family=holder_family, state="RUNNING") == 1

    await eventually(gauge_counts_running, timeout=8, interval=0.25)
    await group.close()


async def test_observation_tensors_match_schema(gw: Gateway) -> None:
    """Every observed tensor has the dtype and shape its session's schema declares."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    schema = {s.name: s for s in group.infos[0].observation_schema}
    obs = (await group.reset())[0].observation
    assert set(obs) == set(schema)
    for name, arr in obs.items():
        spec = schema[name]
        assert types_pb2.Dtype.Name(spec.dtype).removeprefix("DTYPE_").lower() == str(arr.dtype)
        assert list(arr.shape) == list(spec.shape), name
    await group.close()
