"""Zetta's named observation tensors <-> openpi's LIBERO observation dicts.

openpi's LIBERO client (examples/libero/main.py) sends ``observation/image`` and
``observation/wrist_image`` (uint8 HxWx3, row 0 at the top after its 180-degree turn),
``observation/state`` (8 floats: eef position 3, eef rotation as an axis-angle 3, gripper qpos 2)
and ``prompt``; the server answers ``{"actions": [chunk, 7]}``. Zetta's canonical names
(services/policy_worker/vla/features.py) carry the same signals: ``agentview_image``,
``eye_in_hand_image``, ``robot0_eef_pos``, ``robot0_eef_quat`` (x, y, z, w),
``robot0_gripper_qpos``. A key that already has a canonical name passes through unchanged, so a
client can send what openpi's LIBERO format lacks (``robot0_joint_pos``, for one).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.common.specs import TensorSpec

IMAGE = "observation/image"
WRIST_IMAGE = "observation/wrist_image"
STATE = "observation/state"
PROMPT = "prompt"
#: openpi image key -> Zetta camera tensor.
IMAGES = {IMAGE: "agentview_image", WRIST_IMAGE: "eye_in_hand_image"}


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternion -> axis-angle 3-vector (robosuite's quat2axisangle, as openpi's client uses)."""
    q = np.asarray(quat, dtype=np.float64)
    w = float(np.clip(q[3], -1.0, 1.0))
    den = np.sqrt(1.0 - w * w)
    if den < 1e-9:
        return np.zeros(3, np.float32)
    return (q[:3] * 2.0 * np.arccos(w) / den).astype(np.float32)


def axis_angle_to_quat(vec: np.ndarray) -> np.ndarray:
    """Axis-angle 3-vector -> (x, y, z, w) quaternion with w >= 0 (the inverse of :func:`quat_to_axis_angle`)."""
    v = np.asarray(vec, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    if angle < 1e-9:
        return np.array([0.0, 0.0, 0.0, 1.0], np.float32)
    return np.concatenate([v / angle * np.sin(angle / 2), [np.cos(angle / 2)]]).astype(np.float32)


def to_openpi(sample: Mapping[str, np.ndarray], instruction: str) -> dict[str, Any]:
    """One Zetta sample (canonical names) as openpi's LIBERO observation dict.

    Tensors other than the cameras also travel under their own names, so a Zetta server behind
    the protocol reads them exactly (the quaternion's sign survives, ``robot0_joint_pos`` arrives)."""
    obs: dict[str, Any] = {PROMPT: instruction}
    obs.update({k: np.asarray(v) for k, v in sample.items() if k not in IMAGES.values()})
    for key, name in IMAGES.items():
        if name in sample:
            obs[key] = np.ascontiguousarray(sample[name], dtype=np.uint8)
    if all(k in sample for k in ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")):
        obs[STATE] = np.concatenate([np.asarray(sample["robot0_eef_pos"], np.float32),
                                     quat_to_axis_angle(sample["robot0_eef_quat"]),
                                     np.asarray(sample["robot0_gripper_qpos"], np.float32)])
    return obs


def from_openpi(obs: Mapping[str, Any]) -> tuple[dict[str, np.ndarray], str]:
    """An openpi observation dict as Zetta tensors (canonical names) and the instruction.

    Canonical names in ``obs`` win over the ones derived from openpi's LIBERO keys."""
    if not isinstance(obs, Mapping):
        raise ValueError(f"an observation must be a dict, got {type(obs).__name__}")
    out: dict[str, np.ndarray] = {}
    for key, name in IMAGES.items():
        if key in obs:
            out[name] = np.asarray(obs[key])
    if STATE in obs:
        state = np.asarray(obs[STATE], dtype=np.float32).reshape(-1)
        if state.shape != (8,):
            raise ValueError(f"{STATE} must hold 8 floats (eef pos 3, axis-angle 3, gripper 2), got {state.shape[0]}")
        out.update(robot0_eef_pos=state[:3], robot0_eef_quat=axis_angle_to_quat(state[3:6]),
                   robot0_gripper_qpos=state[6:8])
    for key, value in obs.items():
        if "/" not in key and key != PROMPT:
            out[key] = np.asarray(value)
    prompt = obs.get(PROMPT, "")
    if not isinstance(prompt, str):
        raise ValueError(f"{PROMPT} must be a string, got {type(prompt).__name__}")
    return out, prompt


def server_metadata(model: str, chunk_size: int, specs: Sequence[TensorSpec]) -> dict[str, Any]:
    """What a Zetta openpi-protocol server sends on connect: the model, its chunk and its inputs
    (the openpi pool declares these inputs when its servers are Zetta's)."""
    return {"model": model, "chunk_size": chunk_size,
            "inputs": [{"name": s.name, "dtype": str(np.dtype(s.dtype)), "shape": list(s.shape)} for s in specs]}


def specs_from_metadata(metadata: Mapping[str, Any]) -> list[TensorSpec] | None:
    """The inputs a server's metadata declares, or None for a server that declares none (openpi's)."""
    inputs = metadata.get("inputs") if isinstance(metadata, Mapping) else None
    if not inputs:
        return None
    return [TensorSpec(i["name"], i["dtype"], tuple(i["shape"])) for i in inputs]
