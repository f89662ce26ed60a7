"""The Zetta VLA as a served :class:`PolicyModel`, and its checkpoint format.

A checkpoint is a directory: ``model.pt`` (float16 weights + normalization buffers, float32 at
load), ``config.json`` (architecture, training config, data recipe, instruction-embedding cache).
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from pathlib import Path

import numpy as np
import torch

from services.common.policies import CHECKPOINT_ROOT, DEFAULT_POLICY, PRIVILEGED_BASELINE
from services.common.specs import TensorSpec
from services.policy_worker.vla.features import PROPRIO_INPUTS, STATE_INPUTS, state_specs, state_vector
from services.policy_worker.vla.model import VLAConfig, ZettaVLA
from services.policy_worker.vla.text import TextEncoder

#: The state-based variant reads the simulator's object poses: a privileged baseline, never a default.
STATE_CHECKPOINT = CHECKPOINT_ROOT / PRIVILEGED_BASELINE
IMAGE_CHECKPOINT = CHECKPOINT_ROOT / DEFAULT_POLICY


def save_checkpoint(path: str | os.PathLike, model: ZettaVLA, meta: dict, text_cache: dict[str, np.ndarray]) -> None:
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    state = {k: (v.half() if v.is_floating_point() and not k.endswith(("_mean", "_std")) else v)
             for k, v in model.state_dict().items()}
    torch.save(state, path / "model.pt")
    inputs = [{"name": s.name, "dtype": s.dtype, "shape": list(s.shape), "privileged": s.privileged}
              for s in state_specs(model.cfg.image_size, model.cfg.cameras)]
    doc = {"model": model.cfg.to_dict(), "inputs": inputs, **meta,
           "instruction_embeddings": {k: [round(float(x), 6) for x in v] for k, v in sorted(text_cache.items())}}
    (path / "config.json").write_text(json.dumps(doc, indent=1))


def load_checkpoint(path: str | os.PathLike) -> tuple[ZettaVLA, dict, dict[str, np.ndarray]]:
    path = Path(path)
    doc = json.loads((path / "config.json").read_text())
    model = ZettaVLA(VLAConfig.from_dict(doc["model"]))
    state = torch.load(path / "model.pt", map_location="cpu", weights_only=True)
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    model.eval()
    cache = {k: np.asarray(v, np.float32) for k, v in doc.get("instruction_embeddings", {}).items()}
    return model, doc, cache


class ZettaVLAPolicy:
    """Monolithic serving of both stages in one process (the split mode lives in ``split.py``).

    ``encode`` and ``act_batch`` are the two stages, so the split server and the quantization
    plug-in can work on either one alone.
    """

    def __init__(self, checkpoint: str | os.PathLike = IMAGE_CHECKPOINT, name: str = "zetta-vla-image",
                 quantize: str = "", device: str = "cpu", threads: int = 0, noise: str | None = None,
                 seed: int = 0, trace: bool = True) -> None:
        if threads:
            torch.set_num_threads(threads)
        #: Flow-matching start x0: "gaussian" samples it, seeded per request from the request's own
        #: inputs (state and instruction), so the same observation gets the same draw whichever
        #: requests share its batch (and split or monolithic serving); "zero" starts every
        #: chunk at the noise mean. The mean start averages the modes where the teacher switches
        #: (descend vs. re-align above an object) and hovers between them; sampling commits to one.
        self.noise = noise or os.environ.get("ZETTA_VLA_NOISE", "gaussian")
        if self.noise not in ("gaussian", "zero"):
            raise ValueError(f"ZETTA_VLA_NOISE must be 'gaussian' or 'zero', got {self.noise!r}")
        self.seed = seed
        #: Row-by-row computation: a request's actions then do not depend on what shares its batch
        #: (batched CPU matmuls differ in the last bits with the batch size, and closed-loop
        #: episodes amplify that), so episode keys replay through a batching server, at the cost
        #: of batching's speed-up.
        self.batch_invariant = os.environ.get("ZETTA_VLA_BATCH_INVARIANT", "0") not in ("", "0", "false")
        self.checkpoint = str(checkpoint)
        self.model, self.meta, cache = load_checkpoint(checkpoint)
        self.device = torch.device(device)
        self.model.to(self.device)
        self.cfg = self.model.cfg
        self.name = name
        self.chunk_size = self.cfg.chunk
        self.text = TextEncoder(cache)
        #: The instructions it was trained on: the checkpoint carries their embeddings (ListModels).
        self.instructions: tuple[str, ...] = tuple(sorted(cache))
        self.quantize = quantize
        self.quantized: list[str] = []
        if quantize:
            from services.policy_worker.vla.quant import quantize_modules

            self.quantized = quantize_modules(self.model, quantize.split(","))
        #: Stage 2 as served: the action expert traced once (TorchScript), so the flow's few hundred
        #: small tensor ops run without Python's per-module dispatch, most of a CPU call's cost at
        #: the batches rollouts make (bench/bench_policy.py prints traced vs eager). The trace runs
        #: the same kernels in the same order: the same numbers, for every batch size.
        self.traced = trace
        self._expert = self._trace_expert() if trace else self.model.expert

    @torch.no_grad()
    def _trace_expert(self) -> torch.nn.Module:
        cfg = self.cfg
        prefix = torch.zeros(1, cfg.prefix_tokens, cfg.width, device=self.device)
        noise = torch.zeros(1, cfg.chunk, cfg.action_dim, device=self.device)
        # torch 2.13 marks TorchScript deprecated in favour of torch.compile, whose CPU backend
        # compiles C++ for tens of seconds at start-up; the pinned torch still runs traces.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            return torch.jit.trace(self.model.expert, (prefix, noise), check_trace=False)

    def keep_stage(self, stage: int) -> None:
        """Free the other stage's weights: a split-serving process runs one stage and should hold
        one copy of it, not the whole model (after this, only that stage's methods work)."""
        if stage not in (1, 2):
            raise ValueError(f"stage must be 1 (VLM) or 2 (action expert), got {stage}")
        del self.model._modules["expert" if stage == 1 else "encoder"]
        if stage == 1:
            self._expert = None

    def input_specs(self) -> list[TensorSpec]:
        return state_specs(self.cfg.image_size, self.cfg.cameras)

    def state_inputs(self, batch: dict[str, np.ndarray]) -> np.ndarray:
        """The [B, D] float32 state vector stage 1 reads (proprioception alone for the image
        variant); :meth:`encode` builds it once per batch for both the prefix and the noise seeds."""
        names = PROPRIO_INPUTS if self.cfg.image_size else STATE_INPUTS
        return np.ascontiguousarray(state_vector(batch, names), dtype=np.float32)

    def image_inputs(self, batch: dict[str, np.ndarray]) -> np.ndarray | None:
        """uint8 [B, cameras, H, W, 3] of the cameras the checkpoint reads, None for the state variant."""
        if not self.cfg.image_size:
            return None
        return np.stack([batch[name] for name in self.cfg.cameras], axis=1)

    @torch.inference_mode()
    def encode_batch(self, state: np.ndarray, instructions: list[str], image: np.ndarray | None = None) -> torch.Tensor:
        """Stage 1 in one call: prefix [B, prefix_tokens, width] on the model's device."""
        text = torch.from_numpy(self.text.encode(instructions)).to(self.device)
        pixels = torch.from_numpy(np.ascontiguousarray(image)).to(self.device) if image is not None else None
        return self.model.encode(torch.from_numpy(state).to(self.device), text, pixels)

    def request_seeds(self, state: np.ndarray, instructions: list[str]) -> np.ndarray:
        """One noise seed per request, a hash of its state vector and instruction (int64 [B])."""
        out = np.empty(len(instructions), np.int64)
        for i, text in enumerate(instructions):
            digest = hashlib.blake2b(state[i].tobytes(), digest_size=8, key=self.seed.to_bytes(8, "little"))
            digest.update(text.encode())
            out[i] = int.from_bytes(digest.digest(), "little") >> 1
        return out

    def start_noise(self, seeds: np.ndarray) -> torch.Tensor | None:
        """x0 of the flow for each request: per-seed Gaussian draws, or None for the mean start."""
        if self.noise != "gaussian":
            return None
        shape = (self.cfg.chunk, self.cfg.action_dim)
        draws = [torch.randn(shape, generator=torch.Generator().manual_seed(int(s))) for s in seeds]
        return torch.stack(draws).to(self.device)

    def encode(self, batch: dict[str, np.ndarray], instructions: list[str]) -> tuple[torch.Tensor, np.ndarray]:
        """Stage 1 as served, with each request's noise seed (:meth:`request_seeds`), both from one
        state vector: one batched call, or row by row when :attr:`batch_invariant`."""
        state = self.state_inputs(batch)
        image = self.image_inputs(batch)
        if not self.batch_invariant or len(instructions) == 1:
            prefix = self.encode_batch(state, instructions, image)
        else:
            prefix = torch.cat([self.encode_batch(state[i:i + 1], instructions[i:i + 1],
                                                  None if image is None else image[i:i + 1])
                                for i in range(len(instructions))])
        return prefix, self.request_seeds(state, instructions)

    @torch.inference_mode()
    def act_tensor(self, prefix: torch.Tensor, seeds: np.ndarray) -> torch.Tensor:
        """Stage 2 on the model's device: actions [B, chunk, 7], x0 drawn from ``seeds``
        (:meth:`request_seeds`); row by row when :attr:`batch_invariant`."""
        if self.batch_invariant and len(prefix) > 1:
            return torch.cat([self._act(prefix[i:i + 1], seeds[i:i + 1]) for i in range(len(prefix))])
        return self._act(prefix, seeds)

    def _act(self, prefix: torch.Tensor, seeds: np.ndarray) -> torch.Tensor:
        prefix = prefix.to(self.device)
        noise = self.start_noise(seeds)
        if noise is None:  # the mean start, given explicitly: the trace takes x0 as an input
            noise = torch.zeros(len(prefix), self.cfg.chunk, self.cfg.action_dim, device=self.device)
        return self.model.to_env_units(self._expert(prefix, noise))

    def act_batch(self, prefix: torch.Tensor, seeds: np.ndarray) -> np.ndarray:
        """Stage 2 as float32 numpy."""
        return self.act_tensor(prefix, seeds).float().cpu().numpy()

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        return self.act_batch(*self.encode(batch, instructions))


def _threads() -> int:
    # One intra-op thread by default: a policy worker shares its cores with env workers, and
    # spinning OpenMP threads on oversubscribed cores cost far more than they give.
    return int(os.environ.get("ZETTA_TORCH_THREADS", "1"))


def vla_device() -> str:
    """``ZETTA_VLA_DEVICE``: where the VLA runs (``cpu``, ``cuda`` or ``cuda:N``); checked at start-up
    so a GPU profile on a node without a usable GPU fails at once instead of at the first request."""
    device = os.environ.get("ZETTA_VLA_DEVICE", "cpu").strip() or "cpu"
    if device != "cpu":
        if not device.startswith("cuda"):
            raise ValueError(f"ZETTA_VLA_DEVICE must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
        if not torch.cuda.is_available():
            raise ValueError(f"ZETTA_VLA_DEVICE={device} but torch sees no CUDA device on this node")
    return device


def make_state_policy() -> ZettaVLAPolicy:
    return ZettaVLAPolicy(os.environ.get("ZETTA_STATE_BASELINE_CHECKPOINT", str(STATE_CHECKPOINT)),
                          name="privileged-state-baseline", quantize=os.environ.get("ZETTA_VLA_QUANTIZE", ""),
                          device=vla_device(), threads=_threads())


def make_image_policy() -> ZettaVLAPolicy:
    return ZettaVLAPolicy(os.environ.get("ZETTA_VLA_CHECKPOINT", str(IMAGE_CHECKPOINT)), name="zetta-vla-image",
                          quantize=os.environ.get("ZETTA_VLA_QUANTIZE", ""), device=vla_device(), threads=_threads())
