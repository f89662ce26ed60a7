"""openpi both ways, over real websockets and gRPC on loopback, driven by PyPI ``openpi-client``.

The model behind every server is the scripted pick-and-place policy: deterministic and cheap, so
each answer is checked against the model called directly (the protocol and the batching do not
depend on which model answers).
"""

from __future__ import annotations

import re
import threading
from pathlib import Path

import grpc
import numpy as np
import pytest

from services.policy_worker.models.scripted import ScriptedPickPlacePolicy
from services.ops.openpi_local import start_endpoint, start_policy_worker
from services.policy_worker.openpi.observation import (
    axis_angle_to_quat,
    from_openpi,
    quat_to_axis_angle,
    to_openpi,
)
from services.policy_worker.openpi.serial_server import SerialOpenPIServer
from zetta_wire.codec import decode, encode_observation
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc

websocket_client_policy = pytest.importorskip(
    "openpi_client.websocket_client_policy", reason="PyPI openpi-client is not installed (scripts/install-interop.sh)")

MODEL = ScriptedPickPlacePolicy()


def sample(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One observation the scripted policy reads, drawn so its actions vary."""
    obj = np.concatenate([rng.uniform(-0.2, 0.2, 3), [0.0, 0.0, 0.0]]).astype(np.float32)
    obj[3:] = obj[:3] + 0.04
    tgt = obj.copy()
    tgt[:2] += 0.2
    tgt[3:5] += 0.2
    return {"robot0_eef_pos": rng.uniform(-0.3, 0.3, 3).astype(np.float32),
            "robot0_gripper_qpos": np.array([0.04, -0.04], np.float32), "task_object_bbox": obj,
            "task_target_bbox": tgt, "task_grasped": np.array([float(rng.random() < 0.5)], np.float32)}


def expected(s: dict[str, np.ndarray]) -> np.ndarray:
    return MODEL.infer({k: v[None] for k, v in s.items()}, [""])[0]


def test_observation_mapping_round_trips() -> None:
    """openpi's LIBERO state (pos, axis-angle, gripper) and Zetta's canonical tensors map both ways."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q *= np.sign(q[3])
        np.testing.assert_allclose(axis_angle_to_quat(quat_to_axis_angle(q)), q, atol=1e-5)
    image = rng.integers(0, 255, (8, 8, 3), dtype=np.uint8)
    zetta = {"agentview_image": image, "robot0_eef_pos": np.ones(3, np.float32),
             "robot0_eef_quat": np.array([0, 0, 0, 1], np.float32), "robot0_gripper_qpos": np.zeros(2, np.float32)}
    obs = to_openpi(zetta, "open the drawer")
    assert obs["observation/state"].shape == (8,) and obs["observation/image"] is not None
    back, prompt = from_openpi({k: v for k, v in obs.items() if "/" in k or k == "prompt"})
    assert prompt == "open the drawer" and np.array_equal(back["agentview_image"], image)
    np.testing.assert_allclose(back["robot0_eef_quat"], [0, 0, 0, 1])
    with pytest.raises(ValueError, match="8 floats"):
        from_openpi({"observation/state": np.zeros(5)})


def test_pool_spreads_a_batch_over_openpi_servers(tmp_path: Path) -> None:
    """ZETTA_MODELS=openpi: the policy worker answers a batch through two openpi-protocol servers,
    each taking part, every answer equal to the model's own, per-server metrics exported."""
    servers = [SerialOpenPIServer(MODEL).start() for _ in range(2)]
    worker = None
    try:
        worker = start_policy_worker("openpi", tmp_path, {
            "ZETTA_OPENPI_SERVERS": ",".join(s.address for s in servers), "ZETTA_OPENPI_CONNECTIONS": "2",
            "ZETTA_OPENPI_TIMEOUT_MS": "20000"})
        rng = np.random.default_rng(1)
        samples = [sample(rng) for _ in range(16)]
        with grpc.insecure_channel(worker.address) as ch:
            stub = policy_worker_pb2_grpc.PolicyWorkerServiceStub(ch)
            (info,) = stub.ListModels(policy_worker_pb2.ListModelsRequest()).models
            assert info.name == "openpi" and sorted(s.name for s in info.inputs) == sorted(samples[0])
            items = [policy_worker_pb2.InferItem(token=str(i), observation=encode_observation(s), instruction="go")
                     for i, s in enumerate(samples)]
            resp = stub.Infer(policy_worker_pb2.InferRequest(items=items), timeout=60)
            for s, out in zip(samples, resp.outputs):
                np.testing.assert_allclose(decode(out.actions), expected(s), atol=1e-6)
            bad = policy_worker_pb2.InferItem(token="x", observation=encode_observation({"robot0_eef_pos": np.zeros(3,
                                                                                         np.float32)}))
            with pytest.raises(grpc.RpcError) as err:
                stub.Infer(policy_worker_pb2.InferRequest(items=[bad]), timeout=10)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "task_object_bbox" in err.value.details()
        # 16 answers plus the worker's warm-up inference before it reports SERVING.
        assert all(s.requests > 0 for s in servers) and sum(s.requests for s in servers) == 16 + 1
        text = worker.metrics()
        for s in servers:
            assert re.search(rf'zetta_openpi_server_seconds_count{{server="{s.address}"}} [1-9]', text), text[-2000:]
    finally:
        if worker is not None:
            worker.stop()
        for s in servers:
            s.stop()


def test_pool_refuses_unreachable_servers(tmp_path: Path) -> None:
    """A worker whose openpi servers are not there exits at start with a message naming them."""
    with pytest.raises(RuntimeError, match="127.0.0.1:9 is not reachable"):
        start_policy_worker("openpi", tmp_path, {"ZETTA_OPENPI_SERVERS": "127.0.0.1:9"})


def test_endpoint_refuses_an_unreachable_policy_worker(tmp_path: Path) -> None:
    """An endpoint whose policy worker is not there exits at start with a message naming it."""
    with pytest.raises(RuntimeError, match="policy worker 127.0.0.1:9 did not list its models"):
        start_endpoint("127.0.0.1:9", tmp_path)


def test_endpoint_batches_concurrent_openpi_clients(tmp_path: Path) -> None:
    """Eight openpi-client connections at once through the endpoint: every answer is the model's,
    the policy worker formed batches larger than one, and a bad observation gets a readable error."""
    worker = start_policy_worker("scripted-pick-place", tmp_path,
                                 {"ZETTA_EARLY_DISPATCH": "0", "ZETTA_MAX_QUEUE_DELAY_MS": "30"})
    endpoint = None
    try:
        endpoint = start_endpoint(worker.address, tmp_path)
        host, port = endpoint.address.split(":")
        failures: list[str] = []

        def client(seed: int) -> None:
            policy = websocket_client_policy.WebsocketClientPolicy(host=host, port=int(port))
            assert policy.get_server_metadata()["model"] == "scripted-pick-place"
            rng = np.random.default_rng(seed)
            for _ in range(10):
                s = sample(rng)
                got = policy.infer({**s, "prompt": "put the cream cheese in the bowl"})["actions"]
                if not np.allclose(got, expected(s), atol=1e-6):
                    failures.append(f"client {seed}: {got} != {expected(s)}")

        threads = [threading.Thread(target=client, args=(i,)) for i in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert not failures, failures[:3]
        text = worker.metrics()
        count = float(re.search(r'zetta_policy_batch_size_count{model="scripted-pick-place"} (\S+)', text).group(1))
        total = float(re.search(r'zetta_policy_batch_size_sum{model="scripted-pick-place"} (\S+)', text).group(1))
        print(f"policy worker: {total:.0f} requests in {count:.0f} batches, mean batch {total / count:.2f}")
        assert total == 80 and total / count > 1.5
        policy = websocket_client_policy.WebsocketClientPolicy(host=host, port=int(port))
        with pytest.raises(RuntimeError, match="needs .*task_object_bbox"):
            policy.infer({"robot0_eef_pos": np.zeros(3, np.float32), "prompt": "x"})
        assert policy.infer({**sample(np.random.default_rng(9)), "prompt": "x"})["actions"].shape == (1, 7)
        assert 'zetta_openpi_endpoint_requests_total{outcome="invalid"} 1.0' in endpoint.metrics()
    finally:
        if endpoint is not None:
            endpoint.stop()
        worker.stop()
