"""External policies behind the :class:`PolicyModel` contract, without touching the scheduler.

A user brings a pi0.5 (an openpi or a LeRobot checkpoint on local disk) by writing, or using, an
:class:`ExternalPolicyAdapter`: it declares the canonical tensors it reads (``input_specs``), maps
a stacked batch of canonical observations + instructions to the policy's own input format
(``to_policy_inputs``), runs the policy (``forward``) and maps its outputs back to
``[B, chunk, 7]`` float32 OSC_POSE actions (``to_actions``). :func:`register_adapter` adds it to
the worker's ``FACTORIES``; the scheduler, batching, deadlines and the gRPC surface are unchanged.

:class:`ZettaVLAAdapter` is our own model through this interface (the adapter contract's tests
run on it); :class:`OpenPIAdapter` and :class:`LeRobotAdapter` are the pi0.5 adapters, importing
their framework only when built (neither framework is a dependency of this repository).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from services.common.specs import TensorSpec

ACTION_DIM = 7


class AdapterContractError(ValueError):
    """An adapter produced something the policy worker cannot serve."""


class ExternalPolicyAdapter(ABC):
    """Base class of an external policy served by the policy worker."""

    name: str = "external"
    chunk_size: int = 1

    @abstractmethod
    def input_specs(self) -> Sequence[TensorSpec]:
        """Canonical observation tensors (names of the env family's schema) the policy needs."""

    @abstractmethod
    def to_policy_inputs(self, batch: dict[str, np.ndarray], instructions: list[str]) -> Any:
        """Canonical batch -> whatever ``forward`` takes (e.g. an openpi observation dict)."""

    @abstractmethod
    def forward(self, inputs: Any) -> Any:
        """Run the policy on one batch."""

    @abstractmethod
    def to_actions(self, outputs: Any, batch_size: int) -> np.ndarray:
        """Policy outputs -> [B, chunk, 7] float32 (delta eef xyz, rotation, gripper +-1)."""

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """The PolicyModel entry point; checks the contract on every batch (cheap)."""
        b = len(instructions)
        actions = self.to_actions(self.forward(self.to_policy_inputs(batch, instructions)), b)
        check_actions(actions, b, self.chunk_size)
        return actions


def check_actions(actions: Any, batch_size: int, chunk_size: int) -> None:
    if not isinstance(actions, np.ndarray) or actions.dtype != np.float32:
        raise AdapterContractError(f"actions must be a float32 numpy array, got {type(actions).__name__} "
                                   f"{getattr(actions, 'dtype', '')}")
    if actions.shape != (batch_size, chunk_size, ACTION_DIM):
        raise AdapterContractError(f"actions shape {actions.shape}, expected {(batch_size, chunk_size, ACTION_DIM)}")
    if not np.isfinite(actions).all():
        raise AdapterContractError("actions contain NaN or inf")


def register_adapter(name: str, factory: Callable[[], ExternalPolicyAdapter]) -> None:
    """Make ``name`` loadable by ``ZETTA_MODELS=name`` (call it from a module imported at start-up,
    e.g. through ``ZETTA_POLICY_PLUGINS``)."""
    from services.policy_worker.models.base import FACTORIES

    def build() -> ExternalPolicyAdapter:
        adapter = factory()
        adapter.name = name
        return adapter

    FACTORIES[name] = build


class ZettaVLAAdapter(ExternalPolicyAdapter):
    """Our VLA wrapped as if it were external: the reference implementation of the contract."""

    def __init__(self, checkpoint: str | None = None) -> None:
        from services.policy_worker.vla.policy import STATE_CHECKPOINT, ZettaVLAPolicy

        self.policy = ZettaVLAPolicy(str(checkpoint or STATE_CHECKPOINT), name="zetta-vla-adapter")
        self.name = "zetta-vla-adapter"
        self.chunk_size = self.policy.chunk_size

    def input_specs(self) -> Sequence[TensorSpec]:
        return self.policy.input_specs()

    def to_policy_inputs(self, batch, instructions):
        return batch, instructions

    def forward(self, inputs):
        return self.policy.infer(*inputs)

    def to_actions(self, outputs, batch_size):
        return np.asarray(outputs, np.float32)


def _quat_xyzw_to_axis_angle(q: np.ndarray) -> np.ndarray:
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-8)
    w = np.clip(q[..., 3:4], -1.0, 1.0)
    angle = 2 * np.arccos(w)
    s = np.sqrt(np.maximum(1 - w * w, 1e-12))
    return q[..., :3] / s * angle


class OpenPIAdapter(ExternalPolicyAdapter):
    """pi0 / pi0.5 from an openpi checkpoint directory (``openpi`` installed by the user).

    Inputs follow openpi's LIBERO example: ``observation/image`` (agentview), ``observation/
    wrist_image`` (eye-in-hand), ``observation/state`` (eef pos, axis-angle, gripper qpos: 8-d),
    ``prompt``. The env must be created with ``cameras: [agentview, robot0_eye_in_hand]`` at the
    checkpoint's resolution (224 for the openpi LIBERO checkpoints). openpi's ``infer`` takes one
    example at a time; the adapter loops over the batch (openpi has no batched entry point).
    """

    name = "pi05-openpi"

    def __init__(self, checkpoint_dir: str, config_name: str = "pi05_libero", chunk_size: int = 10,
                 image_size: int = 224) -> None:
        from openpi.policies import policy_config  # optional dependency
        from openpi.training import config as openpi_config

        self.policy = policy_config.create_trained_policy(openpi_config.get_config(config_name), checkpoint_dir)
        self.chunk_size = chunk_size
        self.image_size = image_size

    def input_specs(self) -> Sequence[TensorSpec]:
        s = self.image_size
        return [
            TensorSpec("agentview_image", "uint8", (s, s, 3)),
            TensorSpec("eye_in_hand_image", "uint8", (s, s, 3)),
            TensorSpec("robot0_eef_pos", "float32", (3,)),
            TensorSpec("robot0_eef_quat", "float32", (4,)),
            TensorSpec("robot0_gripper_qpos", "float32", (2,)),
        ]

    def to_policy_inputs(self, batch, instructions):
        state = np.concatenate([batch["robot0_eef_pos"], _quat_xyzw_to_axis_angle(batch["robot0_eef_quat"]),
                                batch["robot0_gripper_qpos"]], axis=1)
        return [{"observation/image": batch["agentview_image"][i], "observation/wrist_image":
                 batch["eye_in_hand_image"][i], "observation/state": state[i], "prompt": instructions[i]}
                for i in range(len(instructions))]

    def forward(self, inputs):
        return [self.policy.infer(x)["actions"] for x in inputs]

    def to_actions(self, outputs, batch_size):
        return np.stack([np.asarray(o, np.float32)[: self.chunk_size, :ACTION_DIM] for o in outputs])


class LeRobotAdapter(ExternalPolicyAdapter):
    """pi0 / pi0.5 from a LeRobot checkpoint directory (``lerobot`` installed by the user)."""

    name = "pi05-lerobot"

    def __init__(self, checkpoint_dir: str, chunk_size: int = 10, image_size: int = 224, device: str = "cuda") -> None:
        import torch
        from lerobot.policies.factory import get_policy_class  # optional dependency

        self.torch = torch
        self.policy = get_policy_class("pi05").from_pretrained(checkpoint_dir).to(device).eval()
        self.device = device
        self.chunk_size = chunk_size
        self.image_size = image_size

    input_specs = OpenPIAdapter.input_specs

    def to_policy_inputs(self, batch, instructions):
        t = self.torch
        state = np.concatenate([batch["robot0_eef_pos"], _quat_xyzw_to_axis_angle(batch["robot0_eef_quat"]),
                                batch["robot0_gripper_qpos"]], axis=1).astype(np.float32)

        def img(x):
            return t.from_numpy(x).to(self.device).permute(0, 3, 1, 2).float() / 255.0

        return {"observation.images.image": img(batch["agentview_image"]),
                "observation.images.wrist_image": img(batch["eye_in_hand_image"]),
                "observation.state": t.from_numpy(state).to(self.device), "task": list(instructions)}

    def forward(self, inputs):
        with self.torch.inference_mode():
            return self.policy.predict_action_chunk(inputs)

    def to_actions(self, outputs, batch_size):
        return outputs[:, : self.chunk_size, :ACTION_DIM].float().cpu().numpy().astype(np.float32)
