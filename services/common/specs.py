"""Tensor specifications shared by every service.

An observation or action is described once, as a :class:`TensorSpec`, and every hop checks
arrays against it. Keeping the declaration in one place is what lets the env worker, the policy
worker and clients in other languages agree on names, dtypes and shapes without negotiating.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: dtypes that may travel on the wire, by their numpy name.
WIRE_DTYPES: tuple[str, ...] = (
    "float32",
    "float64",
    "float16",
    "uint8",
    "int8",
    "int32",
    "int64",
    "bool",
)


class SpecError(ValueError):
    """An array does not match the spec it was declared against."""


@dataclass(frozen=True)
class TensorSpec:
    """Name, dtype and shape of one named tensor.

    A dimension of ``-1`` matches any length (used for action chunks whose horizon is chosen by
    the policy). ``privileged`` marks simulation-only signals that a real robot could not read.
    """

    name: str
    dtype: str
    shape: tuple[int, ...]
    privileged: bool = False
    description: str = ""
    low: float | None = field(default=None, compare=False)
    high: float | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.dtype not in WIRE_DTYPES:
            raise ValueError(f"tensor {self.name!r}: dtype {self.dtype!r} is not one of {WIRE_DTYPES}")

    def check(self, array: np.ndarray) -> None:
        """Raise :class:`SpecError` with a message a person can act on when ``array`` does not fit."""
        if array.dtype != np.dtype(self.dtype):
            raise SpecError(f"{self.name}: expected dtype {self.dtype}, got {array.dtype}")
        if len(array.shape) != len(self.shape) or any(
            want not in (-1, got) for want, got in zip(self.shape, array.shape)
        ):
            raise SpecError(f"{self.name}: expected shape {list(self.shape)}, got {list(array.shape)}")

    def zeros(self) -> np.ndarray:
        """An all-zero array of this spec (free dimensions get length 1)."""
        return np.zeros([d if d >= 0 else 1 for d in self.shape], dtype=self.dtype)


#: Cameras whose image tensor drops the robot prefix (``robot0_eye_in_hand`` -> ``eye_in_hand_image``,
#: services/env_worker/families/schema.py camera_obs_name): render_config names them with it again.
ROBOT_CAMERAS = ("eye_in_hand", "robotview", "agentview_left", "agentview_right", "agentview_center")


def camera_of_image(name: str) -> str:
    """The env's camera name of an image tensor: ``agentview_image`` -> ``agentview``,
    ``eye_in_hand_image`` -> ``robot0_eye_in_hand``."""
    camera = name.removesuffix("_image")
    return f"robot0_{camera}" if camera in ROBOT_CAMERAS else camera


def render_config(specs: list[TensorSpec], antialias: bool = True) -> dict[str, Any]:
    """The env-config keys that make a slot render exactly the camera images these input specs
    declare (``<camera>_image``, uint8 [S, S, 3]) with reflections off, or {} for a policy that
    reads no image: clients create sessions with it so a policy is shown what it was trained on.
    ``antialias`` is how its training frames were rendered (robosuite's default, and so LIBERO's
    datasets, is multisampled)."""
    cameras = [s for s in specs if s.name.endswith("_image")]
    if not cameras:
        return {}
    return {"cameras": [camera_of_image(s.name) for s in cameras], "camera_size": int(cameras[0].shape[0]),
            "reflections": False, "antialias": antialias}
