"""Each failure promise of the system, tested for real: processes are killed with real signals,
leases run out on the wall clock, and malformed requests go over real gRPC.

Tests that leave the stack healthy share the session-wide stack (``gw`` fixture); tests that kill
or restart a process start their own stack through ``stack_factory``.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.env_worker.families.robocasa import unavailable_reason as robocasa_unavailable_reason
from tests.conftest import HEARTBEAT_TIMEOUT_MS, LIFT, eventually, free_slots
from zetta import Gateway, SessionGroup, ZettaError
from zetta_wire.codec import encode
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import gateway_pb2, types_pb2

ROOT = Path(__file__).resolve().parents[2]
ZEROS = np.zeros(7, np.float32)
#: Time the monitor may take beyond the heartbeat timeout (one tick, scheduling on two busy cores).
DETECTION_MARGIN_S = 1.5


async def states(gw: Gateway) -> dict[str, types_pb2.SessionInfo]:
    """Every session the registry knows, by id."""
    return {s.session_id: s for s in await gw.list_sessions()}


async def expect_error(coro: Awaitable[Any], code: str) -> ZettaError:
    """Await ``coro`` and return the ZettaError it must raise with status ``code``."""
    with pytest.raises(ZettaError) as err:
        await coro
    assert err.value.code.name == code, err.value
    return err.value


async def episode_steps(gw: Gateway, ids: list[str]) -> list[int]:
    """Current episode_step of each session (Observe has no side effects)."""
    resp = await gw.call("Observe", gateway_pb2.ObserveRequest(session_ids=ids))
    return [r.episode_step for r in resp.results]


# ---- env worker crash --------------------------------------------------------------------------


async def test_killed_env_worker_sessions_become_lost(stack_factory: Callable[..., LocalStack]) -> None:
    """SIGKILL env-0: its sessions turn LOST within the heartbeat timeout, env-1 keeps serving."""
    stack: LocalStack = stack_factory()
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=4, env_config=LIFT)
        await group.reset(seed=[1, 2, 3, 4])
        await group.action_step([ZEROS] * 4)
        on0 = [i.session_id for i in group.infos if i.worker_id == "env-0"]
        on1 = [i.session_id for i in group.infos if i.worker_id == "env-1"]
        assert len(on0) == 2 and len(on1) == 2

        stack.kill("env-0")  # SIGKILL: no deregistration, only silence
        killed_at = time.monotonic()

        async def lost() -> bool:
            now = await states(gw)
            return all(now[s].state == types_pb2.SESSION_STATE_LOST for s in on0)

        took = await eventually(lost, timeout=10)
        assert took <= HEARTBEAT_TIMEOUT_MS / 1000 + DETECTION_MARGIN_S, f"LOST after {took:.2f} s"
        now = await states(gw)
        for sid in on0:
            assert "env-0" in now[sid].reason and "heartbeat" in now[sid].reason
        for sid in on1:
            assert now[sid].state == types_pb2.SESSION_STATE_RUNNING

        lost_group = group.subset(on0)
        err = await expect_error(lost_group.policy_step(), "FAILED_PRECONDITION")
        assert "LOST" in err.details
        assert sorted(err.session_ids) == sorted(on0)
        err = await expect_error(lost_group.action_step([ZEROS] * 2), "FAILED_PRECONDITION")
        assert "LOST" in err.details
        # A batch mixing live and LOST sessions fails whole and steps none of the live ones.
        before = await episode_steps(gw, on1)
        await expect_error(group.action_step([ZEROS] * 4), "FAILED_PRECONDITION")
        assert await episode_steps(gw, on1) == before

        # env-1's sessions are untouched: their episodes continue where they were.
        live = group.subset(on1)
        stepped = await live.action_step([ZEROS] * 2)
        assert [r.episode_step for r in stepped] == [b + 1 for b in before]
        await live.policy_step()

        workers = {w.worker_id: w for w in await gw.list_workers()}
        assert not workers["env-0"].alive
        assert workers["env-0"].free_slots == 0
        assert workers["env-1"].alive and workers["env-1"].free_slots == 2

        # New sessions go to the surviving worker, and only as many as it has room for.
        fresh = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
        assert [i.worker_id for i in fresh.infos] == ["env-1", "env-1"]
        assert (await fresh.reset())[0].episode_id
        err = await expect_error(gw.create_sessions("robosuite", n=1, env_config=LIFT), "RESOURCE_EXHAUSTED")
        assert err.retry_after_ms and err.retry_after_ms > 0
        # Closing a LOST session is not an error; it is reported as already gone.
        closed = await gw.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=on0))
        assert sorted(closed.already_closed_session_ids) == sorted(on0)

        # Every worker of the family silent: the family is not unknown, it is unavailable for now.
        stack.kill("env-1")

        async def all_dead() -> bool:
            return not any(w.alive for w in await gw.list_workers())

        await eventually(all_dead, timeout=10)
        err = await expect_error(gw.create_sessions("robosuite", n=1, env_config=LIFT), "UNAVAILABLE")
        assert "env-0" in err.details and "env-1" in err.details and "heartbeats" in err.details
        assert err.retry_after_ms and err.retry_after_ms > 0
        assert time.monotonic() - killed_at < 60


# ---- leases ------------------------------------------------------------------------------------


async def test_lease_expiry_closes_session_and_frees_slot(gw: Gateway) -> None:
    """A lease that is not renewed closes the session and frees its slot; a renewed one survives."""
    before = await free_slots(gw)
    t0 = time.time()
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT, lease_seconds=1, keepalive=False)
    # The lease runs from activation, not from allocation: building the envs does not eat it.
    assert all(i.lease_expires_unix_ms >= t0 * 1000 + 900 for i in group.infos)
    assert all(i.state == types_pb2.SESSION_STATE_RUNNING for i in group.infos)
    expiring, renewed = group.ids
    await group.subset([renewed]).renew(lease_seconds=60)
    await group.subset([renewed]).reset()
    assert sum((await free_slots(gw)).values()) == sum(before.values()) - 2

    async def expired() -> bool:
        return (await states(gw))[expiring].state == types_pb2.SESSION_STATE_TERMINATED

    await eventually(expired, timeout=4)
    await asyncio.sleep(0.5)
    info = (await states(gw))[expiring]
    assert info.reason == "lease expired"
    err = await expect_error(group.subset([expiring]).action_step([ZEROS]), "NOT_FOUND")
    assert "closed" in err.details and "lease expired" in err.details
    assert err.session_ids == [expiring]
    # The renewed session is still live and steps.
    assert (await states(gw))[renewed].state == types_pb2.SESSION_STATE_RUNNING
    assert (await group.subset([renewed]).action_step([ZEROS]))[0].episode_step == 1
    # The expired session's slot is free again (the renewed one still holds its own).
    assert sum((await free_slots(gw)).values()) == sum(before.values()) - 1
    await group.subset([renewed]).close()
    assert await free_slots(gw) == before


# ---- admission -------------------------------------------------------------------------------------


async def test_full_pool_is_refused_with_retry_hint(gw: Gateway) -> None:
    """Asking for more slots than are free fails whole with RESOURCE_EXHAUSTED and allocates nothing."""
    before = await free_slots(gw)
    total = sum(before.values())
    assert total == 8
    sessions_before = await states(gw)
    err = await expect_error(gw.create_sessions("robosuite", n=total + 1, env_config=LIFT), "RESOURCE_EXHAUSTED")
    assert err.retry_after_ms is not None and err.retry_after_ms > 0
    assert "pool full" in err.details and f"{total} slots free" in err.details
    assert await free_slots(gw) == before
    assert set(await states(gw)) == set(sessions_before), "no session record was written"
    # Partly occupied pool: the remainder is the limit.
    held = await gw.create_sessions("robosuite", n=3, env_config=LIFT)
    err = await expect_error(gw.create_sessions("robosuite", n=total - 2, env_config=LIFT), "RESOURCE_EXHAUSTED")
    assert f"{total - 3} slots free" in err.details
    assert sum((await free_slots(gw)).values()) == total - 3
    await held.close()
    assert await free_slots(gw) == before


# ---- malformed requests ----------------------------------------------------------------------------


@pytest.fixture
async def pair(gw: Gateway) -> SessionGroup:
    """Two reset robosuite sessions, one on each worker (closed by the gw fixture)."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    await group.reset(seed=[1, 2])
    return group


async def test_unknown_family_names_hosted_families(gw: Gateway) -> None:
    """An unknown family is INVALID_ARGUMENT and the message lists what is hosted."""
    before = await free_slots(gw)
    err = await expect_error(gw.create_sessions("mujoco-playground", n=1), "INVALID_ARGUMENT")
    assert "mujoco-playground" in err.details
    assert "libero" in err.details and "robosuite" in err.details
    assert await free_slots(gw) == before


@pytest.mark.parametrize(
    "family,config,needle",
    [
        ("robosuite", {"env_name": "Nope"}, "'Nope'"),
        ("robosuite", {"env_name": "Lift", "colour": "red"}, "colour"),
        ("libero", {"suite": "nope"}, "'nope'"),
    ],
)
async def test_bad_env_config_is_invalid_and_frees_slots(gw: Gateway, family: str, config: dict[str, Any],
                                                       needle: str) -> None:
    """A config the family rejects is INVALID_ARGUMENT (not an internal error) and frees the slots."""
    before = await free_slots(gw)
    known = set(await states(gw))
    err = await expect_error(gw.create_sessions(family, n=2, env_config=config), "INVALID_ARGUMENT")
    assert needle in err.details
    assert await free_slots(gw) == before
    for sid, info in (await states(gw)).items():
        if sid not in known:
            assert info.state == types_pb2.SESSION_STATE_TERMINATED, "abandoned sessions are closed"
    # The pool still works after the refusal.
    ok = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    await ok.close()


async def test_wrong_action_shape(gw: Gateway, pair: SessionGroup) -> None:
    """Shapes other than [7] or [n, 7] are INVALID_ARGUMENT naming the expected shape."""
    for bad in (np.zeros(6, np.float32), np.zeros((2, 2, 7), np.float32), np.zeros((0, 7), np.float32),
                np.zeros((300, 7), np.float32)):
        err = await expect_error(pair.subset(pair.ids[:1]).action_step([bad]), "INVALID_ARGUMENT")
        assert "expected shape [7]" in err.details, bad.shape
        assert err.session_ids == pair.ids[:1]
    assert await episode_steps(gw, pair.ids) == [0, 0]


async def test_wrong_dtype(gw: Gateway, pair: SessionGroup) -> None:
    """float64 actions are refused (the SDK's group helper would convert them, so send raw)."""
    req = gateway_pb2.ActionStepRequest(session_ids=pair.ids[:1], actions=[encode(np.zeros(7, np.float64))])
    err = await expect_error(gw.call("ActionStep", req), "INVALID_ARGUMENT")
    assert "float32" in err.details and "float64" in err.details
    # The single-session SDK path sends the array as is.
    err = await expect_error(pair[0].action_step(np.zeros(7, np.int32)), "INVALID_ARGUMENT")
    assert "int32" in err.details
    assert await episode_steps(gw, pair.ids) == [0, 0]


async def test_one_bad_action_steps_nothing(gw: Gateway, pair: SessionGroup) -> None:
    """A batch with one malformed action fails whole: the well-formed sessions do not move."""
    await pair.action_step([ZEROS, ZEROS])
    obs_before = await pair.observe()
    err = await expect_error(pair.action_step([ZEROS, np.zeros(8, np.float32)]), "INVALID_ARGUMENT")
    assert err.session_ids == [pair.ids[1]]
    assert pair.ids[1] in err.details
    assert await episode_steps(gw, pair.ids) == [1, 1]
    for a, b in zip(obs_before, await pair.observe()):
        np.testing.assert_array_equal(a["robot0_eef_pos"], b["robot0_eef_pos"])
    # One action for two sessions is refused too.
    req = gateway_pb2.ActionStepRequest(session_ids=pair.ids, actions=[encode(ZEROS)])
    await expect_error(gw.call("ActionStep", req), "INVALID_ARGUMENT")
    assert await episode_steps(gw, pair.ids) == [1, 1]


async def test_garbage_tensor_bytes(gw: Gateway, pair: SessionGroup) -> None:
    """Data whose length does not match dtype x shape is INVALID_ARGUMENT, never a crash."""
    for data in (b"\x00" * 5, b"\x00" * 32, b""):
        tensor = types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[7], data=data)
        req = gateway_pb2.ActionStepRequest(session_ids=pair.ids[:1], actions=[tensor])
        err = await expect_error(gw.call("ActionStep", req), "INVALID_ARGUMENT")
        assert "bytes" in err.details
    unset = types_pb2.Tensor(dtype=types_pb2.DTYPE_UNSPECIFIED, shape=[7], data=b"\x00" * 28)
    req = gateway_pb2.ActionStepRequest(session_ids=pair.ids[:1], actions=[unset])
    await expect_error(gw.call("ActionStep", req), "INVALID_ARGUMENT")
    assert await episode_steps(gw, pair.ids) == [0, 0]


async def test_unknown_closed_and_duplicate_sessions(gw: Gateway, pair: SessionGroup) -> None:
    """Unknown ids are NOT_FOUND, closed ones NOT_FOUND saying closed, duplicates INVALID_ARGUMENT."""
    err = await expect_error(gw.call("Observe", gateway_pb2.ObserveRequest(session_ids=["deadbeef"])), "NOT_FOUND")
    assert "deadbeef" in err.details and err.session_ids == ["deadbeef"]
    err = await expect_error(
        gw.call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=[pair.ids[0], "deadbeef"])), "NOT_FOUND")
    assert err.session_ids == ["deadbeef"]
    assert await episode_steps(gw, pair.ids) == [0, 0]

    dup = gateway_pb2.ActionStepRequest(session_ids=[pair.ids[0], pair.ids[0]], actions=[encode(ZEROS)] * 2)
    err = await expect_error(gw.call("ActionStep", dup), "INVALID_ARGUMENT")
    assert "more than once" in err.details and pair.ids[0] in err.details
    await expect_error(gw.call("Reset", gateway_pb2.ResetRequest(session_ids=[])), "INVALID_ARGUMENT")
    assert await episode_steps(gw, pair.ids) == [0, 0]

    closed = pair.subset(pair.ids[1:])
    await closed.close()
    for call in (closed.action_step([ZEROS]), closed.policy_step(), closed.reset()):
        err = await expect_error(call, "NOT_FOUND")
        assert "closed" in err.details and err.session_ids == pair.ids[1:]
    # A stream on a closed session ends with the same status.
    stream = closed[0].stream()
    err = await expect_error(stream.observe(), "NOT_FOUND")
    assert "closed" in err.details


async def test_step_before_reset(gw: Gateway) -> None:
    """A session without an episode refuses steps and inference with FAILED_PRECONDITION."""
    group = await gw.create_sessions("robosuite", n=1, env_config=LIFT)
    for call in (group.action_step([ZEROS]), group.policy_step(), group.policy_infer(), group.run_episode()):
        err = await expect_error(call, "FAILED_PRECONDITION")
        assert "Reset" in err.details
    await group.reset()
    assert (await group.action_step([ZEROS]))[0].episode_step == 1


async def test_unknown_model(gw: Gateway, pair: SessionGroup) -> None:
    """PolicyStep with a model no policy worker serves is NOT_FOUND naming it; nothing steps."""
    err = await expect_error(pair.policy_step(model="gr00t-giant"), "NOT_FOUND")
    assert "gr00t-giant" in err.details and "scripted-pick-place" in err.details
    await expect_error(pair.policy_infer(model="gr00t-giant"), "NOT_FOUND")
    assert await episode_steps(gw, pair.ids) == [0, 0]
    # The default model still works afterwards.
    assert [r.episode_step for r in await pair.policy_step()] == [1, 1]


async def test_bad_reset_spec(gw: Gateway, pair: SessionGroup) -> None:
    """An unknown task or a spec count that matches neither one nor all sessions is INVALID_ARGUMENT."""
    err = await expect_error(pair.reset(task="Stack"), "INVALID_ARGUMENT")
    assert "Stack" in err.details
    specs = [types_pb2.ResetSpec()] * 3
    await expect_error(gw.call("Reset", gateway_pb2.ResetRequest(session_ids=pair.ids, specs=specs)), "INVALID_ARGUMENT")


# ---- gateway restart -----------------------------------------------------------------------------


async def test_gateway_restart_keeps_sessions(stack_factory: Callable[..., LocalStack]) -> None:
    """SIGKILL the gateway and start it again on the same port: sessions live on in Redis and the workers."""
    stack: LocalStack = stack_factory()
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
        await group.reset(seed=[3, 4])
        first = await group.action_step([ZEROS, ZEROS])
        assert [r.episode_step for r in first] == [1, 1]
        address = stack.gateway_address

        stack.kill("gateway")
        with pytest.raises(ZettaError) as err:
            await group.action_step([ZEROS, ZEROS])
        assert err.value.code.name == "UNAVAILABLE"
        stack.start_gateway()
        assert stack.gateway_address == address

        async def answering() -> bool:
            try:
                await gw.list_workers()
                return True
            except ZettaError:
                return False

        await eventually(answering, timeout=10)
        # Give the monitor time to run its dead-worker check on the restarted gateway.
        await asyncio.sleep(HEARTBEAT_TIMEOUT_MS / 1000 + 1.0)
        now = await states(gw)
        assert [now[s].state for s in group.ids] == [types_pb2.SESSION_STATE_RUNNING] * 2
        assert all(w.alive for w in await gw.list_workers())
        again = await group.action_step([ZEROS, ZEROS])
        assert [r.episode_step for r in again] == [2, 2]
        assert [r.episode_step for r in await group.policy_step()] == [3, 3]
        await group.close()


# ---- graceful shutdown -------------------------------------------------------------------------


async def test_sigterm_env_worker_deregisters_and_exits_cleanly(stack_factory: Callable[..., LocalStack]) -> None:
    """SIGTERM: the worker drains, deregisters (its sessions LOST, 'shut down') and exits 0 in time."""
    stack: LocalStack = stack_factory()
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
        await group.reset()
        on0 = [i.session_id for i in group.infos if i.worker_id == "env-0"]
        on1 = [i.session_id for i in group.infos if i.worker_id == "env-1"]
        assert len(on0) == len(on1) == 1
        proc = stack.services["env-0"].proc
        grace = 10.0  # the env worker's default ZETTA_GRACE_SECONDS
        start = time.monotonic()
        os.killpg(proc.pid, signal.SIGTERM)
        code = await asyncio.to_thread(proc.wait, grace + 5)
        took = time.monotonic() - start
        assert code == 0
        assert took < grace, f"exit took {took:.1f} s"
        # Deregistration is immediate: no heartbeat timeout needed.
        now = await states(gw)
        assert now[on0[0]].state == types_pb2.SESSION_STATE_LOST
        assert "shut down" in now[on0[0]].reason
        assert now[on1[0]].state == types_pb2.SESSION_STATE_RUNNING
        assert "env-0" not in {w.worker_id for w in await gw.list_workers()}
        err = await expect_error(group.subset(on0).action_step([ZEROS]), "FAILED_PRECONDITION")
        assert "LOST" in err.details and "shut down" in err.details
        assert (await group.subset(on1).action_step([ZEROS]))[0].episode_step == 1
        log = stack.services["env-0"].log.read_text()
        assert "draining" in log and "Traceback" not in log


# ---- configuration fails fast ------------------------------------------------------------------


def _run_service(module: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("ZETTA_")}
    base["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")])
    base.update({"ZETTA_BIND_HOST": "127.0.0.1", "ZETTA_METRICS_PORT": "-1"}, **env)
    return subprocess.run([sys.executable, "-m", module], env=base, capture_output=True, text=True, timeout=60,
                          cwd=ROOT)


@pytest.mark.parametrize(
    "module,env,variable",
    [
        ("services.gateway.main", {}, "ZETTA_REDIS_URL"),
        ("services.gateway.main", {"ZETTA_REDIS_URL": "redis://127.0.0.1:1/0", "ZETTA_HEARTBEAT_INTERVAL_MS": "1000",
                                   "ZETTA_HEARTBEAT_TIMEOUT_MS": "500"}, "ZETTA_HEARTBEAT_TIMEOUT_MS"),
        ("services.gateway.main", {"ZETTA_REDIS_URL": "redis://127.0.0.1:1/0", "ZETTA_GATEWAY_PORT": "0"},
         "ZETTA_REDIS_URL"),
        ("services.env_worker.main", {"ZETTA_GATEWAY_ADDRESS": "127.0.0.1:1", "ZETTA_ENV_FAMILIES": "nope",
                                      "ZETTA_ENV_WORKER_PORT": "0"}, "ZETTA_ENV_FAMILIES"),
        pytest.param("services.env_worker.main", {"ZETTA_GATEWAY_ADDRESS": "127.0.0.1:1",
                                                  "ZETTA_ENV_FAMILIES": "libero,robocasa", "ZETTA_ENV_WORKER_PORT": "0"},
                     "ZETTA_ENV_FAMILIES", marks=pytest.mark.skipif(not robocasa_unavailable_reason(),
                                                                    reason="RoboCasa is installed here")),
        ("services.policy_worker.main", {"ZETTA_MODELS": "nope", "ZETTA_POLICY_WORKER_PORT": "0"}, "ZETTA_MODELS"),
        ("services.policy_worker.main", {"ZETTA_MODELS": "privileged-state-baseline", "ZETTA_VLA_DEVICE": "tpu",
                                         "ZETTA_POLICY_WORKER_PORT": "0"}, "ZETTA_VLA_DEVICE"),
    ],
    ids=["gateway-no-redis-url", "gateway-timeout-below-interval", "gateway-redis-unreachable",
         "env-worker-unknown-family", "env-worker-family-not-installed", "policy-worker-unknown-model", "policy-worker-bad-vla-device"],
)
def test_bad_configuration_exits_2_naming_variable(module: str, env: dict[str, str], variable: str) -> None:
    """A misconfigured service stops at once with a message naming the variable, not a traceback."""
    proc = _run_service(module, env)
    assert proc.returncode == 2, proc.stderr
    assert variable in proc.stderr
    assert "Traceback" not in proc.stderr
    if "nope" in env.values():
        assert "'nope'" in proc.stderr, "the bad value is quoted back"
    if "robocasa" in env.get("ZETTA_ENV_FAMILIES", ""):
        assert "robocasa" in proc.stderr and "install" in proc.stderr, "what is missing and how to install it"


async def test_session_closed_under_a_running_episode_is_aborted_by_name(gw: Gateway) -> None:
    """A RunEpisode whose session is closed while it runs ends with ABORTED naming the session (not
    UNKNOWN), the way a worker declared dead mid-episode ends its callers' calls."""
    group = await gw.create_sessions("robosuite", n=1, env_config={**LIFT, "max_steps": 50_000})
    await group.reset(seed=0)
    # An episode the do-nothing policy cannot end early, with a step budget far beyond the close.
    running = asyncio.ensure_future(group.run_episode(model="do-nothing", max_steps=50_000, execute_steps=1))
    await asyncio.sleep(1.0)
    await gw.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=group.ids))
    err = await expect_error(running, "ABORTED")
    assert group.ids[0] in err.details and "closed" in err.details
