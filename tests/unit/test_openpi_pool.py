"""The openpi pool's settings and its deadline, against a real openpi-protocol server on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from services.policy_worker.models.scripted import ScriptedPickPlacePolicy
from services.policy_worker.openpi.pool import OpenPIPool, PoolConfig
from services.policy_worker.openpi.serial_server import SerialOpenPIServer

pytest.importorskip("openpi_client", reason="PyPI openpi-client is not installed (scripts/install-interop.sh)")


class SlowFirstAnswer(ScriptedPickPlacePolicy):
    """The scripted policy, stalled for ``stall`` seconds on its first request (a server hiccup)."""

    def __init__(self, stall: float) -> None:
        super().__init__()
        self.stall = stall

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        if self.stall:
            time.sleep(self.stall)
            self.stall = 0.0
        return super().infer(batch, instructions)


def _sample(x: float) -> dict[str, np.ndarray]:
    box = np.array([x, 0.0, 0.0, x + 0.04, 0.04, 0.04], np.float32)
    return {"robot0_eef_pos": np.array([0.0, 0.0, 0.3], np.float32), "robot0_gripper_qpos": np.array([0.04, -0.04],
            np.float32), "task_object_bbox": box, "task_target_bbox": box + 0.2,
            "task_grasped": np.zeros(1, np.float32)}


def test_config_names_the_bad_variable() -> None:
    """Every refused setting says which variable and what it should be."""
    with pytest.raises(ValueError, match="ZETTA_OPENPI_SERVERS is empty"):
        PoolConfig.from_env({})
    with pytest.raises(ValueError, match="'gpu1' is not host:port"):
        PoolConfig.from_env({"ZETTA_OPENPI_SERVERS": "gpu1"})
    with pytest.raises(ValueError, match="ZETTA_OPENPI_CONNECTIONS must be > 0"):
        PoolConfig.from_env({"ZETTA_OPENPI_SERVERS": "a:1", "ZETTA_OPENPI_CONNECTIONS": "0"})
    with pytest.raises(ValueError, match="ZETTA_OPENPI_TIMEOUT_MS='soon' is not a number"):
        PoolConfig.from_env({"ZETTA_OPENPI_SERVERS": "a:1", "ZETTA_OPENPI_TIMEOUT_MS": "soon"})
    cfg = PoolConfig.from_env({"ZETTA_OPENPI_SERVERS": "a:1,[::1]:2", "ZETTA_OPENPI_CHUNK": "3"})
    assert cfg.servers == ("a:1", "[::1]:2") and cfg.chunk_size == 3 and cfg.chunk_size_set


def test_a_late_answer_fails_the_batch_and_is_never_read_as_the_next_one() -> None:
    """A server that stalls past the deadline fails that batch with TimeoutError; the next batch on
    the replaced connection gets its own answer, not the stale one."""
    model = SlowFirstAnswer(stall=1.5)
    server = SerialOpenPIServer(model).start()
    try:
        pool = OpenPIPool(PoolConfig(servers=(server.address,), timeout_s=0.3))
        assert pool.chunk_size == 1 and {s.name for s in pool.input_specs()} == set(_sample(0.0))
        first, second = _sample(0.1), _sample(-0.1)
        with pytest.raises(TimeoutError, match="ZETTA_OPENPI_TIMEOUT_MS"):
            pool.infer({k: v[None] for k, v in first.items()}, ["go"])
        pool.config = PoolConfig(servers=(server.address,), timeout_s=10.0)
        got = pool.infer({k: v[None] for k, v in second.items()}, ["go"])
        want = ScriptedPickPlacePolicy().infer({k: v[None] for k, v in second.items()}, ["go"])
        np.testing.assert_allclose(got, want)
        assert not np.allclose(want, ScriptedPickPlacePolicy().infer({k: v[None] for k, v in first.items()}, ["go"]))
    finally:
        server.stop()
