"""The canonical observation of single-arm manipulation families: its schema, the OSC_POSE action,
and the normalization of raw simulator observations against the schema."""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping, Sequence
from typing import Any

import numpy as np

from services.common.milestone_kinds import OBSTACLE_SLOTS
from services.common.specs import SpecError, TensorSpec
from services.env_worker.families.contract import ResetError
from services.env_worker.milestones import milestone_specs
from services.env_worker.signals import signal_specs


#: OSC_POSE deltas: xyz translation, axis-angle rotation, gripper (-1 open, +1 close).
OSC_POSE_ACTION = TensorSpec(
    name="action",
    dtype="float32",
    shape=(7,),
    description="OSC_POSE delta: dx, dy, dz, droll, dpitch, dyaw (scaled to [-1, 1]); gripper -1 open, +1 close",
    low=-1.0,
    high=1.0,
)


def camera_obs_name(camera: str) -> str:
    """Canonical image name of a camera; the robot prefix is dropped so names do not depend on the arm."""
    return f"{camera.removeprefix('robot0_')}_image"


def _privileged(name: str, shape: tuple[int, ...], description: str) -> TensorSpec:
    """A privileged float32 observation (for the oracle, milestones and offline diagnosis only)."""
    return TensorSpec(name, "float32", shape, privileged=True, description=description)


def manipulation_schema(
    cameras: Sequence[str], camera_size: int, proprio_dim: int, object_state_dim: int
) -> dict[str, TensorSpec]:
    """The canonical schema shared by the robosuite-based families.

    Sharing it lets one policy (and the scripted policy) serve LIBERO and robosuite sessions in one
    batch, since compatibility groups are decided by schema.
    """
    specs = [
        TensorSpec("robot0_eef_pos", "float32", (3,), description="end-effector position, world frame (m)"),
        TensorSpec("robot0_eef_quat", "float32", (4,), description="end-effector orientation, quaternion xyzw"),
        TensorSpec("robot0_gripper_qpos", "float32", (2,), description="finger joint positions (m)"),
        TensorSpec("robot0_joint_pos", "float32", (7,), description="arm joint positions (rad)"),
        TensorSpec(
            "robot0_proprio",
            "float32",
            (proprio_dim,),
            description="joint pos, cos, sin, vel; eef pos, quat; gripper qpos, qvel",
        ),
        _privileged("task_object_pos", (3,),
                    "position of what the current goal stage moves: the object, or the handle of the drawer, door or "
                    "knob to actuate; zeros if none"),
        _privileged("task_object_quat", (4,), "orientation (xyzw) of the task object; zeros if none"),
        _privileged("task_target_pos", (3,),
                    "position of the stage's target object, region or site (for a handle: where it must move to); "
                    "zeros if the stage has none"),
        _privileged("task_object_bbox", (6,),
                    "world axis-aligned box around the task object's collision geoms: min xyz, max xyz"),
        _privileged("task_target_bbox", (6,),
                    "world axis-aligned box of the target (geoms of a body, or a region's box); zeros if none"),
        _privileged("task_grasped", (1,), "1.0 while both fingers touch the task object, else 0.0"),
        _privileged("task_obstacle_bbox", (OBSTACLE_SLOTS, 6),
                    "world boxes (min xyz, max xyz) of what stands around the task object and its target: other "
                    "objects whole, fixtures geom by geom, the robot and the moved object left out; nearest to the "
                    "way from object to target first, zero rows pad"),
        _privileged("object_state", (object_state_dim,),
                    "per object: pos, quat, pos and quat relative to the eef; zero-padded"),
    ]
    specs += milestone_specs() + signal_specs()  # mu_t and phi_t, privileged
    specs += [
        TensorSpec(camera_obs_name(c), "uint8", (camera_size, camera_size, 3), description=f"RGB of {c}, upright")
        for c in cameras
    ]
    return {s.name: s for s in specs}


def upright_image(image: np.ndarray) -> np.ndarray:
    """MuJoCo renders with OpenGL's bottom-left origin; flip so row 0 is the top of the picture."""
    return np.ascontiguousarray(image[::-1])


def zero_padded(values: np.ndarray, length: int, what: str) -> np.ndarray:
    """Pad a variable-length vector to the schema's fixed length, refusing to drop values silently."""
    flat = np.asarray(values, dtype=np.float32).reshape(-1)
    if flat.size > length:
        raise ResetError(f"{what} has {flat.size} values but the schema holds {length}; raise object_state_dim")
    out = np.zeros(length, dtype=np.float32)
    out[: flat.size] = flat
    return out


def normalize_observation(
    raw: Mapping[str, Any], schema: Mapping[str, TensorSpec], optional: Collection[str] = ()
) -> dict[str, np.ndarray]:
    """Turn a family's raw observation into fresh canonical arrays checked against the schema.

    Values are copied so a caller never holds a view into simulator buffers that the next step
    overwrites. Names in ``optional`` (camera images not rendered for this step) may be absent.
    """
    out: dict[str, np.ndarray] = {}
    for name, spec in schema.items():
        if name not in raw:
            if name in optional:
                continue
            raise SpecError(f"{name}: missing from the family's observation (it has {sorted(raw)})")
        array = np.array(raw[name], dtype=spec.dtype)
        if array.size != math.prod(spec.shape):
            raise SpecError(f"{name}: expected shape {list(spec.shape)}, got {list(array.shape)}")
        out[name] = array.reshape(spec.shape)  # the spec's dtype and shape by construction
    return out
