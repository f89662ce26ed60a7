"""External policies behind the :class:`PolicyModel` contract, without touching the scheduler.

A user brings a pi0.5 (an openpi or a LeRobot checkpoint on local disk) by writing, or using, an
:class:`ExternalPolicyAdapter`: it declares the canonical tensors it reads (``input_specs``), maps
a stacked batch of canonical observations + instructions to the policy's own input format
(``to_policy_inputs``), runs the policy (``forward``) and maps its outputs back to
``[B, chunk, 7]`` float32 OSC_POSE actions (``to_actions``). :func:`services.policy_worker.models.base.register_adapter` adds it to
the worker's ``FACTORIES``; the scheduler, batching, deadlines and the gRPC surface are unchanged.

:class:`ZettaVLAAdapter` is our own model through this interface (the adapter contract's tests
run on it); :class:`OpenPIAdapter` serves pi0.5 from an openpi checkpoint and :class:`LeRobotAdapter`
any LeRobot policy (pi0.5, TD-MPC, ...) from a LeRobot checkpoint directory (``ZETTA_MODELS=lerobot``,
``ZETTA_LEROBOT_CHECKPOINT``), importing their framework only when built (neither framework is a
dependency of this repository).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import numpy as np

from services.common.policies import PROPRIO_INPUTS, lerobot_cameras
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


#: Proprioception Zetta can hand a LeRobot ``observation.state``, with widths. ``robot0_eef_axis_angle``
#: is derived from ``robot0_eef_quat`` (robosuite's quat2axisangle, as LeRobot's and openpi's LIBERO code use).
_STATE_PARTS: dict[str, int] = {**dict(PROPRIO_INPUTS), "robot0_eef_axis_angle": 3}
#: ``observation.state`` layouts recognised by width: LIBERO's as LeRobot and openpi write it (8),
#: and the columns of Zetta's own LeRobot export (16, services.common.policies.PROPRIO_INPUTS).
_STATE_LAYOUTS: dict[int, tuple[str, ...]] = {
    8: ("robot0_eef_pos", "robot0_eef_axis_angle", "robot0_gripper_qpos"),
    sum(w for _, w in PROPRIO_INPUTS): tuple(n for n, _ in PROPRIO_INPUTS),
}
#: Policy types that keep an observation history in ``_queues`` and read it in ``predict_action_chunk``.
_QUEUED = ("tdmpc", "diffusion", "vqbet")


def _parse_pairs(text: str, what: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in (t.strip() for t in text.split(",") if t.strip()):
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise ValueError(f"{what}: expected key=value items separated by commas, got {item!r}")
        out[key.strip()] = value.strip()
    return out


class LeRobotAdapter(ExternalPolicyAdapter):
    """Any LeRobot policy from a local checkpoint directory (``lerobot`` installed; no hub access).

    The directory is what LeRobot's ``save_pretrained`` writes: ``config.json`` (its ``type`` names
    the policy class: ``tdmpc``, ``pi05``, ``act``...), ``model.safetensors`` and, since lerobot 0.4,
    the pre/post-processor pipelines (``policy_preprocessor.json``, ``policy_postprocessor.json`` with
    their normalization statistics), which are applied when present. The policy's declared
    ``input_features`` become Zetta tensors:

    * each VISUAL feature ``[3, S, S]`` -> a camera ``<camera>_image`` uint8 ``[S, S, 3]`` (row 0 at
      the top, as the env renders it), passed as float in [0, 1]; a key naming a wrist or hand camera
      reads ``robot0_eye_in_hand`` (``eye_in_hand_image``), the first other one ``agentview``;
      ``cameras`` maps keys explicitly (``{"observation.images.top": "agentview"}``);
    * ``observation.state`` -> proprioception concatenated in a known layout: 8 wide is LIBERO's
      (eef position, eef axis-angle, gripper qpos), 16 wide the columns of Zetta's LeRobot export; else
      ``state`` lists the parts (names of ``_STATE_PARTS``);
    * ``observation.environment_state`` (privileged simulator state) is refused.

    The instruction goes in as ``task``. Each batch starts from ``policy.reset()`` (a served request
    carries no history), so policies with an observation queue (TD-MPC, Diffusion, VQ-BeT) see one
    observation, repeated as they do at an episode's start. Actions: the first ``chunk_size`` steps,
    the first 7 dimensions, unnormalized by the postprocessor.
    """

    name = "lerobot"

    def __init__(self, checkpoint_dir: str, chunk_size: int | None = None, image_size: int | None = None,
                 device: str | None = None, state: Sequence[str] | None = None,
                 cameras: dict[str, str] | None = None) -> None:
        import os

        import torch

        from services.policy_worker.vla.lerobot_import import import_lerobot

        factory = import_lerobot()
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.configs.types import FeatureType

        self.torch = torch
        if not os.path.isfile(os.path.join(checkpoint_dir, "config.json")):
            raise ValueError(f"LeRobot checkpoint {checkpoint_dir!r} has no config.json (a directory written by "
                             "a LeRobot policy's save_pretrained is expected; nothing is downloaded)")
        self.device = device or ("cuda" if torch.cuda.is_available() else "cpu")
        cfg = PreTrainedConfig.from_pretrained(checkpoint_dir, local_files_only=True)
        cfg.device = self.device
        self.config = cfg
        self.policy_type: str = cfg.type
        self.policy = factory.get_policy_class(cfg.type).from_pretrained(
            checkpoint_dir, config=cfg, local_files_only=True).to(self.device).eval()
        self.preprocessor: Any = None
        self.postprocessor: Any = None
        if os.path.isfile(os.path.join(checkpoint_dir, "policy_preprocessor.json")):
            self.preprocessor, self.postprocessor = factory.make_pre_post_processors(
                cfg, pretrained_path=checkpoint_dir,
                preprocessor_overrides={"device_processor": {"device": self.device}})

        visual = [(k, tuple(f.shape)) for k, f in cfg.input_features.items() if f.type is FeatureType.VISUAL]
        #: (LeRobot key, Zetta tensor, side)
        self.cameras: list[tuple[str, str, int]] = lerobot_cameras(visual, cameras)
        for key, _, side in self.cameras:
            if image_size is not None and side != image_size:
                raise ValueError(f"LeRobot input {key} is {side} px, image_size={image_size} was asked")
        self.state_key: str | None = None
        self.state_parts: tuple[str, ...] = ()
        for key, feature in cfg.input_features.items():
            if feature.type is FeatureType.ENV:
                raise ValueError(f"LeRobot input {key} is the simulator's environment state: privileged, not served")
            if feature.type is FeatureType.STATE:
                width = int(feature.shape[0])
                parts = tuple(state) if state else _STATE_LAYOUTS.get(width, ())
                unknown = [p for p in parts if p not in _STATE_PARTS]
                if not parts or unknown:
                    raise ValueError(f"LeRobot input {key} is {width} wide; name its parts (ZETTA_LEROBOT_STATE="
                                     f"a,b,...) from {sorted(_STATE_PARTS)}" + (f"; unknown: {unknown}" if unknown else ""))
                if sum(_STATE_PARTS[p] for p in parts) != width:
                    raise ValueError(f"LeRobot input {key} is {width} wide but {list(parts)} make "
                                     f"{sum(_STATE_PARTS[p] for p in parts)}")
                self.state_key, self.state_parts = key, parts
        action = cfg.output_features.get("action")
        if action is None or int(action.shape[0]) < ACTION_DIM:
            raise ValueError(f"LeRobot {cfg.type} outputs {dict(cfg.output_features)}; an action of at least "
                             f"{ACTION_DIM} dims (OSC_POSE deltas + gripper) is needed")
        self.chunk_size = int(chunk_size or getattr(cfg, "n_action_steps", 1) or 1)

    def input_specs(self) -> Sequence[TensorSpec]:
        specs = [TensorSpec(tensor, "uint8", (side, side, 3)) for _, tensor, side in self.cameras]
        needed = {"robot0_eef_quat" if p == "robot0_eef_axis_angle" else p for p in self.state_parts}
        specs += [TensorSpec(n, "float32", (w,)) for n, w in PROPRIO_INPUTS if n in needed]
        return specs

    def _state(self, batch: dict[str, np.ndarray]) -> np.ndarray:
        cols = [_quat_xyzw_to_axis_angle(np.asarray(batch["robot0_eef_quat"], np.float64)) if p == "robot0_eef_axis_angle"
                else batch[p] for p in self.state_parts]
        return np.concatenate([np.asarray(c, np.float32).reshape(len(c), -1) for c in cols], axis=1)

    def to_policy_inputs(self, batch, instructions):
        t = self.torch
        out: dict[str, Any] = {"task": list(instructions)}
        for key, tensor, _ in self.cameras:
            out[key] = t.from_numpy(np.ascontiguousarray(batch[tensor])).to(self.device).permute(0, 3, 1, 2).float() / 255.0
        if self.state_key:
            out[self.state_key] = t.from_numpy(self._state(batch)).to(self.device)
        if self.preprocessor is not None:
            out = self.preprocessor(out)
        return {k: v for k, v in out.items() if v is not None and k != "action"}

    def forward(self, inputs):
        t = self.torch
        policy = self.policy
        with t.inference_mode():
            policy.reset()  # a request carries no history: each batch starts an "episode"
            if self.policy_type in _QUEUED:
                from lerobot.policies.utils import populate_queues
                from lerobot.utils.constants import OBS_IMAGE, OBS_IMAGES

                images = [k for k, _, _ in self.cameras]
                if images and self.policy_type == "tdmpc":
                    inputs = {**inputs, OBS_IMAGE: inputs[images[0]]}
                elif images:
                    inputs = {**inputs, OBS_IMAGES: t.stack([inputs[k] for k in images], dim=-4)}
                policy._queues = populate_queues(policy._queues, inputs)
            try:
                actions = policy.predict_action_chunk(inputs)
            except NotImplementedError:  # single-step policies (SAC)
                actions = policy.select_action(inputs)[:, None]
            if self.policy_type == "tdmpc":  # its plan is (horizon, batch, dim)
                actions = actions.transpose(0, 1)
            if actions.ndim == 2:
                actions = actions[:, None]
            if self.postprocessor is not None:
                actions = self.postprocessor(actions)
            return actions

    def to_actions(self, outputs, batch_size):
        return outputs[:, : self.chunk_size, :ACTION_DIM].float().cpu().numpy().astype(np.float32)


def make_lerobot_adapter(environ: Any = None) -> LeRobotAdapter:
    """The ``lerobot`` model: ``ZETTA_LEROBOT_CHECKPOINT`` (required), ``ZETTA_LEROBOT_DEVICE``,
    ``ZETTA_LEROBOT_CHUNK``, ``ZETTA_LEROBOT_STATE``, ``ZETTA_LEROBOT_CAMERAS`` (docs/policies.md)."""
    import os

    env = os.environ if environ is None else environ
    checkpoint = env.get("ZETTA_LEROBOT_CHECKPOINT", "").strip()
    if not checkpoint:
        raise ValueError("model 'lerobot' needs ZETTA_LEROBOT_CHECKPOINT: a LeRobot policy directory "
                         "(config.json, model.safetensors) on local disk")
    chunk = env.get("ZETTA_LEROBOT_CHUNK", "").strip()
    state = [p.strip() for p in env.get("ZETTA_LEROBOT_STATE", "").split(",") if p.strip()]
    cameras = _parse_pairs(env.get("ZETTA_LEROBOT_CAMERAS", ""), "ZETTA_LEROBOT_CAMERAS")
    import torch

    torch.set_num_threads(int(env.get("ZETTA_TORCH_THREADS", "1")))
    return LeRobotAdapter(checkpoint, chunk_size=int(chunk) if chunk else None,
                          device=env.get("ZETTA_LEROBOT_DEVICE", "").strip() or None, state=state or None,
                          cameras=cameras or None)
