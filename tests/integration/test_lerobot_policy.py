"""A real LeRobot policy served by the policy worker, end to end (docs/policies.md).

The policy is LeRobot's own ``TDMPCPolicy`` (random weights, built offline from its config class
and saved with ``save_pretrained`` by tests/integration/lerobot_build.py in a child process). A
stack with a robosuite Lift env worker and a policy worker serving it as ``ZETTA_MODELS=lerobot``
then answers: the worker declares the camera (mapped to the wrist camera) and proprioception the
checkpoint's ``config.json`` asks for, four sessions render that camera and step on the policy's action chunks through the
gateway (the SDK's PolicyStep), and the worker forms batches of several sessions.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import grpc
import numpy as np
import pytest

from services.common.policies import policy_env_config
from services.common.specs import TensorSpec, render_config
from services.ops.openpi_local import child_env
from tests.conftest import LIFT
from tests.integration import lerobot_build
from zetta import Gateway
from zetta_wire.codec import decode, encode_observation
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc

LOW = np.array(lerobot_build.LOW, np.float32)
HIGH = np.array(lerobot_build.HIGH, np.float32)
SESSIONS = 4
#: The stack serves the policy on the wrist camera (by default its one image reads agentview, as the
#: builder reports): the robot-prefixed camera goes through the input check, the sessions' render
#: config and the env's rendering.
WRIST = "observation.image=robot0_eye_in_hand"


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, object]]:
    """The TD-MPC checkpoint directory, built in a child process; skips when lerobot is missing."""
    out = tmp_path_factory.mktemp("lerobot") / "tdmpc"
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "tests.integration.lerobot_build", str(out)], env=child_env(),
                          capture_output=True, text=True, timeout=300)
    if proc.returncode == 3:
        pytest.skip(f"lerobot is not importable: {json.loads(proc.stdout.splitlines()[-1])['unavailable']}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    print(f"checkpoint built in {time.monotonic() - t0:.1f} s")
    return out, json.loads(proc.stdout.splitlines()[-1])


def _batch_sizes(url: str) -> tuple[float, float]:
    with urllib.request.urlopen(url, timeout=10) as r:
        metrics = r.read().decode()
    count = float(re.search(r'zetta_policy_batch_size_count{model="lerobot"} (\S+)', metrics).group(1))
    total = float(re.search(r'zetta_policy_batch_size_sum{model="lerobot"} (\S+)', metrics).group(1))
    return count, total


async def test_lerobot_policy_served_end_to_end(stack_factory, checkpoint, monkeypatch) -> None:
    ck, info = checkpoint
    assert info["class"] == "lerobot.policies.tdmpc.modeling_tdmpc.TDMPCPolicy", info
    assert info["default_inputs"] == ["agentview_image", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos"]
    # A camera-less policy on the 16 columns of Zetta's LeRobot export, served by the adapter in the builder.
    assert info["state_only"] == {"inputs": ["robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
                                             "robot0_joint_pos"],
                                  "state_parts": ["robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos",
                                                  "robot0_joint_pos"],
                                  "actions_shape": [3, 3, 7], "in_range": True}, info
    assert {"config.json", "model.safetensors", "policy_preprocessor.json"} <= set(os.listdir(ck))
    t0 = time.monotonic()
    stack = stack_factory(env_workers=1, slots=SESSIONS, families=("robosuite",), models=("lerobot",), critic=False,
                          heartbeat_timeout_ms=15000,
                          extra_env={"ZETTA_LEROBOT_CHECKPOINT": str(ck), "ZETTA_LEROBOT_CAMERAS": WRIST,
                                     "ZETTA_INPUT_CHECK_FAMILY": "robosuite",
                                     "ZETTA_EARLY_DISPATCH": "0", "ZETTA_MAX_QUEUE_DELAY_MS": "50"})
    worker = stack.services["policy-0"]
    print(f"stack up in {time.monotonic() - t0:.1f} s")

    # The worker declares what the checkpoint's config.json reads, mapped to Zetta's tensors.
    with grpc.insecure_channel(worker.address) as ch:
        stub = policy_worker_pb2_grpc.PolicyWorkerServiceStub(ch)
        (model,) = stub.ListModels(policy_worker_pb2.ListModelsRequest()).models
        inputs = {s.name: tuple(s.shape) for s in model.inputs}
        assert model.name == "lerobot" and model.chunk_size == lerobot_build.CHUNK
        assert inputs == {"eye_in_hand_image": (64, 64, 3), "robot0_eef_pos": (3,), "robot0_eef_quat": (4,),
                          "robot0_gripper_qpos": (2,)}, inputs

        # Direct Infer, from several clients at once: every chunk [5, 7], finite, unnormalized into
        # the checkpoint's action range; concurrent requests share batches.
        rng = np.random.default_rng(0)
        failures: list[str] = []

        def client(i: int) -> None:
            try:
                ask(i)
            except Exception as exc:  # noqa: BLE001 - reported by the assertion below
                failures.append(f"client {i}: {exc!r}")

        def ask(i: int) -> None:
            for _ in range(3):
                obs = {"eye_in_hand_image": rng.integers(0, 255, (64, 64, 3), dtype=np.uint8),
                       "robot0_eef_pos": rng.normal(size=3).astype(np.float32),
                       "robot0_eef_quat": np.array([0, 0, 0, 1], np.float32),
                       "robot0_gripper_qpos": np.array([0.02, -0.02], np.float32)}
                item = policy_worker_pb2.InferItem(token=str(i), observation=encode_observation(obs),
                                                   instruction="lift the cube")
                out = decode(stub.Infer(policy_worker_pb2.InferRequest(items=[item]), timeout=60).outputs[0].actions)
                if out.shape != (lerobot_build.CHUNK, 7) or not np.isfinite(out).all() \
                        or (out < LOW - 1e-5).any() or (out > HIGH + 1e-5).any():
                    failures.append(f"client {i}: {out.shape} {out}")

        threads = [threading.Thread(target=client, args=(i,)) for i in range(6)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert not failures, failures[:2]
    count, total = _batch_sizes(worker.metrics_url)
    print(f"direct Infer: {total:.0f} requests in {count:.0f} batches")
    assert total == 18 and count < total  # some batches held more than one client's request

    # Through the gateway: sessions render the camera the policy declares and step on its chunks.
    cameras = render_config([TensorSpec(n, "uint8", shape) for n, shape in inputs.items() if n.endswith("_image")])
    assert cameras == {"cameras": ["robot0_eye_in_hand"], "camera_size": 64, "reflections": False, "antialias": True}
    monkeypatch.setenv("ZETTA_LEROBOT_CHECKPOINT", str(ck))
    monkeypatch.setenv("ZETTA_LEROBOT_CAMERAS", WRIST)
    assert policy_env_config("lerobot") == cameras  # what the CLI commands create sessions with
    async with Gateway(stack.gateway_address) as gw:
        t0 = time.monotonic()
        group = await gw.create_sessions(env_family="robosuite", n=SESSIONS, env_config={**LIFT, **cameras})
        await group.reset(seed=0)
        before = _batch_sizes(worker.metrics_url)
        for step in range(1, 4):
            results = await group.policy_step(model="lerobot", instruction="lift the cube", execute_steps=5)
            assert len(results) == SESSIONS
            for r in results:
                assert r.episode_step == 5 * step and r.executed_actions.shape == (5, 7)
                assert np.isfinite(r.executed_actions).all()
                assert r.observation["eye_in_hand_image"].shape == (64, 64, 3)
        after = _batch_sizes(worker.metrics_url)
        print(f"4 Lift sessions created, reset and stepped 3 chunks in {time.monotonic() - t0:.1f} s")
        await group.close()
    batches, requests = after[0] - before[0], after[1] - before[1]
    print(f"PolicyStep: {requests:.0f} requests in {batches:.0f} batches, mean {requests / batches:.2f}")
    assert requests == 3 * SESSIONS and requests / batches > 1
