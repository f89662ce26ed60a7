"""A Node.js client from proto/ alone (clients/node/session.js, @grpc/grpc-js + @grpc/proto-loader)
drives a session against a real stack on loopback: the Struct, int64 and tensor-bytes traps of
grpc-js are handled there and checked here. Skipped without ``node`` or without
clients/node/node_modules (``make setup`` runs ``npm ci`` there when npm exists).
"""

from __future__ import annotations

import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.ops.local_stack import LocalStack

ROOT = Path(__file__).resolve().parents[2]
NODE_DIR = ROOT / "clients" / "node"
NODE = shutil.which("node")

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(NODE is None, reason="node is not installed (Node.js >= 18 runs clients/node)"),
    pytest.mark.skipif(not (NODE_DIR / "node_modules" / "@grpc" / "grpc-js").is_dir(),
                       reason="clients/node/node_modules is missing: run `npm ci` in clients/node (make setup does)"),
]


@pytest.fixture(scope="module")
def robosuite_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    # Lift sessions render no camera: the scripted policy answers their policy steps.
    with LocalStack(env_workers=1, slots=2, policy_workers=1, families=("robosuite",), models=("scripted-pick-place",),
                    workdir=tmp_path_factory.mktemp("stack"), extra_env={"ZETTA_LOG_LEVEL": "WARNING"}) as s:
        yield s


def _run(stack: LocalStack, *args: str) -> subprocess.CompletedProcess[str]:
    assert NODE is not None
    return subprocess.run([NODE, str(NODE_DIR / "session.js"), stack.gateway_address, *args], capture_output=True,
                          text=True, timeout=150, cwd=NODE_DIR)


def _line(out: str, step: str) -> dict[str, str]:
    match = re.search(rf"^{step}: (.*)$", out, re.MULTILINE)
    assert match, f"no {step!r} line in:\n{out}"
    return dict(re.findall(r"(\w+)=(\S*)", match.group(1)))


def test_node_client_drives_a_session(robosuite_stack: LocalStack) -> None:
    """Create, reset, one action, one policy step, close: every summary line is as the API says."""
    proc = _run(robosuite_stack, "robosuite", '{"env_name": "Lift"}')
    out = proc.stdout
    assert proc.returncode == 0, f"exit {proc.returncode}\nstdout:\n{out}\nstderr:\n{proc.stderr}"
    create = _line(out, "create")
    sid = create["session_id"]
    assert create["action_shape"] == "[7]"
    reset = _line(out, "reset")
    assert reset["session_id"] == sid and int(reset["max_steps"]) > 0 and int(reset["observation_tensors"]) > 0
    eef = [float(x) for x in reset["eef_pos"].strip("[]").replace('"', "").split(",")]
    assert len(eef) == 3 and 0.5 < eef[2] < 1.5  # the Panda's hand above Lift's table: real float32 bytes
    assert _line(out, "action_step") == {"session_id": sid, "episode_step": "1", "executed_shape": "[1,7]"}
    policy = _line(out, "policy_step")
    assert policy["episode_step"] == "2" and policy["executed_shape"] == "[1,7]"
    assert len(policy["action"].strip("[]").split(",")) == 7
    assert _line(out, "close")["closed"] == sid


def test_node_client_env_config_arrives(robosuite_stack: LocalStack) -> None:
    """The Struct reaches the gateway: a bad env_name is refused by name, with the gRPC status."""
    proc = _run(robosuite_stack, "robosuite", '{"env_name": "NoSuchEnv"}')
    assert proc.returncode == 1
    assert "CreateSessions: INVALID_ARGUMENT" in proc.stderr and "NoSuchEnv" in proc.stderr, proc.stderr
