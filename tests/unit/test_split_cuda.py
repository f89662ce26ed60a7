"""Split serving over CUDA IPC gives the monolithic server's actions (needs an NVIDIA GPU).

The VLM process writes each batch's prefix into a CUDA ring that the action-expert process maps
through CUDA IPC handles; only a token and a slot index cross the pipe. What must hold:

- one request at a time (batch 1 in both stages, in both modes), bit for bit: the same kernels
  run on the same shapes, and the ring stores the float32 prefix unchanged;
- under concurrent load in batch-invariant mode (ZETTA_VLA_BATCH_INVARIANT=1, rows computed one by
  one), bit for bit, whatever batches the two schedulers formed;
- under concurrent load with ordinary batching, the arm actions within 1e-4: the split's two
  schedulers batch differently from the monolithic one, and cuBLAS chooses its GEMM kernel (and
  so its summation order) by shape, which moves the last bits of float32 (about 1e-6 on the CPU
  between batch 1 and 32). The gripper is left out there: it snaps to -1/0/1 at a threshold, so a
  last-bit difference right at it flips a whole unit (the CPU test in test_vla.py does the same).

Each checkpoint shipped runs: the state VLA, and the image VLA when its checkpoint is present.
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.policy_worker.scheduler import InferItem, SchedulerConfig  # noqa: E402
from services.policy_worker.vla.policy import IMAGE_CHECKPOINT, STATE_CHECKPOINT  # noqa: E402

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")]

CHECKPOINTS = [pytest.param(STATE_CHECKPOINT, id="state"),
               pytest.param(IMAGE_CHECKPOINT, id="image", marks=pytest.mark.skipif(
                   not (IMAGE_CHECKPOINT / "model.pt").exists(), reason="no zetta-vla-image checkpoint"))]
ARM_TOLERANCE = 1e-4


def _requests(specs: list, n: int, seed: int = 0) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    return [{s.name: (rng.integers(0, 256, tuple(s.shape), dtype=np.uint8) if s.dtype == "uint8"
                      else (rng.standard_normal(tuple(s.shape)) * 0.1).astype(np.float32)) for s in specs}
            for _ in range(n)]


def _serve_both(checkpoint, n: int, together: bool) -> tuple[list[np.ndarray], list[np.ndarray], object]:
    """Answers of a CUDA monolithic and a CUDA split server to the same ``n`` requests."""
    from services.policy_worker.vla.split import MonolithicVLA, SplitVLA

    cfg = SchedulerConfig(max_batch=8, max_queue_delay=0.002)

    async def go():
        mono = MonolithicVLA(str(checkpoint), device="cuda", config=cfg)
        split = SplitVLA(str(checkpoint), device="cuda", vlm=cfg, ae=cfg, slots=64)
        assert split.prefixes.is_cuda and split.actions.is_cuda
        requests = _requests(mono.policy.input_specs(), n)
        instruction = sorted(mono.policy.text.cache)[0]
        answers = {}
        try:
            for name, server in (("mono", mono), ("split", split)):
                items = [InferItem(f"{name}{i}", "m", r, instruction, deadline=time.monotonic() + 60)
                         for i, r in enumerate(requests)]
                if together:
                    answers[name] = await asyncio.gather(*(server.submit(it) for it in items))
                else:
                    answers[name] = [await server.submit(it) for it in items]
        finally:
            await mono.drain()
            await split.drain()
        return answers["mono"], answers["split"], mono.policy

    return asyncio.run(go())


@pytest.mark.parametrize("checkpoint", CHECKPOINTS)
def test_one_request_at_a_time_is_bit_for_bit(checkpoint, monkeypatch) -> None:
    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)  # the spawned action-expert process reads it too
    mono, split, _ = _serve_both(checkpoint, 6, together=False)
    for a, b in zip(mono, split, strict=True):
        assert a.shape == b.shape == (8, 7)
        assert np.array_equal(a, b)


@pytest.mark.parametrize("checkpoint", CHECKPOINTS)
def test_concurrent_load_in_batch_invariant_mode_is_bit_for_bit(checkpoint, monkeypatch) -> None:
    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)
    monkeypatch.setenv("ZETTA_VLA_BATCH_INVARIANT", "1")
    mono, split, _ = _serve_both(checkpoint, 24, together=True)
    assert all(np.array_equal(a, b) for a, b in zip(mono, split, strict=True))


@pytest.mark.parametrize("checkpoint", CHECKPOINTS)
def test_concurrent_load_with_batching_is_within_tolerance(checkpoint, monkeypatch) -> None:
    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)
    monkeypatch.delenv("ZETTA_VLA_BATCH_INVARIANT", raising=False)
    mono, split, _ = _serve_both(checkpoint, 24, together=True)
    worst = max(float(np.abs(a[:, :6] - b[:, :6]).max()) for a, b in zip(mono, split, strict=True))
    assert worst <= ARM_TOLERANCE, f"split and monolithic arm actions differ by {worst:.2e}"


@pytest.mark.parametrize("checkpoint", CHECKPOINTS)
def test_cuda_serving_matches_the_cpu_model(checkpoint, monkeypatch) -> None:
    """The GPU computes the CPU model's actions: arm within 1e-3 (float32 on two devices, ten flow
    steps; a device that ran another model or half precision would be off by far more)."""
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)
    _, split, _ = _serve_both(checkpoint, 4, together=False)
    cpu = ZettaVLAPolicy(str(checkpoint))
    requests = _requests(cpu.input_specs(), 4)
    instruction = sorted(cpu.text.cache)[0]
    for r, got in zip(requests, split, strict=True):
        want = cpu.infer({k: v[None] for k, v in r.items()}, [instruction])[0]
        assert np.abs(want[:, :6] - got[:, :6]).max() <= 1e-3
