"""Authentication, ownership and TLS, on real stacks on loopback (issue #21, item 2).

The repros: without credentials anyone could RegisterWorker a live worker's id to 127.0.0.1:1
(rerouting its sessions), DeregisterWorker it (its sessions LOST), and list and close anyone's
sessions; nothing spoke TLS.
"""

from __future__ import annotations

import subprocess
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np
import pytest

from services.gateway.auth import digest
from tests.conftest import LIFT
from tests.fault.test_faults import expect_error, states
from zetta import Gateway, Session
from zetta_wire.codec import encode
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import gateway_pb2, registry_pb2, registry_pb2_grpc, types_pb2

ROOT = Path(__file__).resolve().parents[2]
ZEROS = np.zeros(7, np.float32)
TOKENS = {"alice": ("user", "alice-token-1"), "bob": ("user", "bob-token-2"), "ops": ("admin", "ops-token-3"),
          "pool": ("worker", "pool-token-4")}


def tokens_file(directory: Path) -> Path:
    """The gateway's tokens file for TOKENS (digests only)."""
    path = directory / "tokens"
    path.write_text("".join(f"{name} {role} {digest(tok)}\n" for name, (role, tok) in TOKENS.items()))
    return path


@pytest.fixture
def auth_stack(stack_factory: Callable[..., LocalStack], tmp_path: Path) -> LocalStack:
    """One env worker, auth on: the worker registers with the worker credential."""
    return stack_factory(env_workers=1, client_token=TOKENS["ops"][1], extra_env={
        "ZETTA_AUTH_TOKENS_FILE": str(tokens_file(tmp_path)), "ZETTA_WORKER_TOKEN": TOKENS["pool"][1]})


def bearer(name: str) -> tuple[tuple[str, str], ...]:
    """Call metadata with ``name``'s token."""
    return (("authorization", f"Bearer {TOKENS[name][1]}"),)


async def test_unauthenticated_calls_are_refused(auth_stack: LocalStack) -> None:
    """No token or an unknown one: UNAUTHENTICATED on every GatewayService call, saying what to send."""
    for gw in (Gateway(auth_stack.gateway_address), Gateway(auth_stack.gateway_address, token="forged")):
        async with gw:
            err = await expect_error(gw.list_sessions(), "UNAUTHENTICATED")
            assert "token" in err.details
            await expect_error(gw.list_workers(), "UNAUTHENTICATED")
            await expect_error(gw.create_sessions("robosuite", n=1, env_config=LIFT), "UNAUTHENTICATED")
            await expect_error(gw.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=["a"])),
                               "UNAUTHENTICATED")
    # The worker credential is not a client credential.
    async with Gateway(auth_stack.gateway_address, token=TOKENS["pool"][1]) as gw:
        await expect_error(gw.list_sessions(), "PERMISSION_DENIED")


async def test_sessions_belong_to_their_creator(auth_stack: LocalStack) -> None:
    """bob can neither step, close, stream nor list alice's session; an admin can list and close it."""
    address = auth_stack.gateway_address
    async with Gateway(address, token=TOKENS["alice"][1]) as alice, \
            Gateway(address, token=TOKENS["bob"][1]) as bob, Gateway(address, token=TOKENS["ops"][1]) as ops:
        group = await alice.create_sessions("robosuite", n=1, env_config=LIFT)
        await group.reset(seed=[1])
        sid = group.ids[0]
        for method, req in (
            ("ActionStep", gateway_pb2.ActionStepRequest(session_ids=[sid], actions=[encode(ZEROS)])),
            ("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=[sid])),
            ("Observe", gateway_pb2.ObserveRequest(session_ids=[sid])),
            ("Reset", gateway_pb2.ResetRequest(session_ids=[sid])),
            ("RenewSessions", gateway_pb2.RenewSessionsRequest(session_ids=[sid])),
            ("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=[sid])),
        ):
            err = await expect_error(bob.call(method, req), "PERMISSION_DENIED")
            assert "another identity" in err.details and err.session_ids == [sid], method
        stream_err = await expect_error(
            Session(bob, sid).stream().observe(), "PERMISSION_DENIED")
        assert sid in stream_err.details
        assert sid not in {s.session_id for s in await bob.list_sessions()}
        assert sid in {s.session_id for s in await alice.list_sessions()}
        assert sid in {s.session_id for s in await ops.list_sessions()}
        # bob's refusals moved nothing; alice still steps.
        assert (await group.action_step([ZEROS]))[0].episode_step == 1
        closed = await ops.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=[sid]))
        assert list(closed.closed_session_ids) == [sid]


async def test_worker_registration_needs_the_worker_credential(auth_stack: LocalStack) -> None:
    """Register/Deregister/Heartbeat without the worker credential are refused; nothing is rerouted or LOST."""
    async with Gateway(auth_stack.gateway_address, token=TOKENS["alice"][1]) as alice:
        group = await alice.create_sessions("robosuite", n=1, env_config=LIFT)
        await group.reset(seed=[2])
        worker = group.infos[0].worker_id
        async with grpc.aio.insecure_channel(auth_stack.gateway_address) as channel:
            stub = registry_pb2_grpc.WorkerRegistryServiceStub(channel)
            hijack = registry_pb2.RegisterWorkerRequest(worker_id=worker, address="127.0.0.1:1",
                                                        env_families=["robosuite"], slots=4)
            for metadata, code in (((), grpc.StatusCode.UNAUTHENTICATED),
                                   (bearer("alice"), grpc.StatusCode.PERMISSION_DENIED)):
                for call, req in ((stub.RegisterWorker, hijack),
                                  (stub.DeregisterWorker, registry_pb2.DeregisterWorkerRequest(worker_id=worker)),
                                  (stub.Heartbeat, registry_pb2.HeartbeatRequest(worker_id=worker))):
                    with pytest.raises(grpc.aio.AioRpcError) as err:
                        await call(req, timeout=5, metadata=metadata)
                    assert err.value.code() == code
        async with Gateway(auth_stack.gateway_address, token=TOKENS["ops"][1]) as ops:
            workers = {w.worker_id: w for w in await ops.list_workers()}
            assert workers[worker].alive and workers[worker].address != "127.0.0.1:1"
            assert (await states(ops))[group.ids[0]].state == types_pb2.SESSION_STATE_RUNNING
        assert (await group.action_step([ZEROS]))[0].episode_step == 1


def make_certs(directory: Path) -> dict[str, str]:
    """A CA and one certificate for every service, made with scripts/make_certs.sh (openssl)."""
    subprocess.run([str(ROOT / "scripts" / "make_certs.sh"), str(directory), "service"], check=True,
                   capture_output=True)
    return {"ZETTA_TLS_CERT": str(directory / "service.pem"), "ZETTA_TLS_KEY": str(directory / "service-key.pem"),
            "ZETTA_TLS_CA": str(directory / "ca.pem")}


async def test_tls_stack_runs_an_episode(stack_factory: Callable[..., LocalStack], tmp_path: Path) -> None:
    """Every service on TLS (mutual between services): an SDK client with the CA runs an episode;
    a plaintext client gets nowhere, and an env worker refuses a TLS client without a certificate."""
    tls = make_certs(tmp_path / "certs")
    # Not a liveness test: a loose heartbeat budget, so a busy machine cannot LOST its one session.
    stack = stack_factory(env_workers=1, extra_env=tls, heartbeat_timeout_ms=8000)
    async with Gateway(stack.gateway_address, tls_ca=tls["ZETTA_TLS_CA"]) as gw:
        group = await gw.create_sessions("libero", n=1, env_config={
            "suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"})
        await group.reset(seed=[1])
        assert (await group.policy_step())[0].episode_step > 0
        await group.reset(seed=[2])
        summary = (await group.run_episode(max_steps=40))[0]
        assert summary.steps > 0 and summary.policy_calls > 0
        await group.close()
    async with Gateway(stack.gateway_address) as plain:
        await expect_error(plain.list_workers(), "UNAVAILABLE")
    creds = grpc.ssl_channel_credentials(root_certificates=Path(tls["ZETTA_TLS_CA"]).read_bytes())
    async with grpc.aio.secure_channel(stack.services["env-0"].address, creds) as channel:
        with pytest.raises(grpc.aio.AioRpcError) as err:
            await channel.unary_unary("/grpc.health.v1.Health/Check")(b"", timeout=5)
        assert err.value.code() == grpc.StatusCode.UNAVAILABLE
    for name in ("gateway", "env-0", "policy-0", "critic"):
        assert '"tls": "' in stack.services[name].log.read_text()
