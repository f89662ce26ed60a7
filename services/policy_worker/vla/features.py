"""Which observation tensors the state-based VLA reads, and how they become one vector.

Only what a real robot (plus an object tracker) would report: proprioception and the
per-object state. The goal-derived privileged ``task_*`` tensors are deliberately left out:
they name the object to move and its target, which would leak the goal and erase exactly the
gap (LIBERO-PRO task redirection and position swap) the harness is meant to close.
"""

from __future__ import annotations

import argparse

import numpy as np

from services.common.policies import PROPRIO_INPUTS
from services.common.specs import TensorSpec, render_config

#: (name, width) in the order they are concatenated.
STATE_INPUTS: tuple[tuple[str, int], ...] = (*PROPRIO_INPUTS, ("object_state", 140))
STATE_DIM = sum(w for _, w in STATE_INPUTS)
#: Image inputs of the image-based variant (LIBERO camera names as canonical obs names): the
#: default camera, and the ones a checkpoint may add (``VLAConfig.cameras``).
IMAGE_INPUTS: tuple[str, ...] = ("agentview_image",)
CAMERA_INPUTS: tuple[str, ...] = ("agentview_image", "eye_in_hand_image")
PROPRIO_DIM = sum(w for _, w in PROPRIO_INPUTS)


def check_cameras(cameras: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The image tensors of an image variant, checked: known names, each once, at least one."""
    cameras = tuple(cameras)
    unknown = [c for c in cameras if c not in CAMERA_INPUTS]
    if not cameras or unknown or len(set(cameras)) != len(cameras):
        raise ValueError(f"cameras {list(cameras)!r}: give one or more of {list(CAMERA_INPUTS)}, each once")
    return cameras


def parse_cameras(text: str) -> tuple[str, ...]:
    """The argparse type of a ``--cameras`` option (``agentview_image,eye_in_hand_image``): a bad
    name is a usage error with :func:`check_cameras`' message, not a traceback."""
    try:
        return check_cameras([c.strip() for c in text.split(",") if c.strip()])
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def state_specs(image_size: int = 0, cameras: tuple[str, ...] = IMAGE_INPUTS) -> list[TensorSpec]:
    """Input specs of the state variant (``image_size`` 0) or the image variant (proprioception
    and one square RGB image per camera, in ``cameras`` order)."""
    if image_size:
        specs = [TensorSpec(n, "float32", (w,)) for n, w in PROPRIO_INPUTS]
        specs += [TensorSpec(n, "uint8", (image_size, image_size, 3)) for n in check_cameras(cameras)]
        return specs
    return [TensorSpec(n, "float32", (w,), privileged=(n == "object_state")) for n, w in STATE_INPUTS]


def image_env_config(image_size: int, antialias: bool = False, cameras: tuple[str, ...] = IMAGE_INPUTS) -> dict:
    """The env config that renders exactly what the image variant reads (reflections off, and by
    default multisampling off: each makes a frame several times cheaper on the CPU rasterizer;
    the recipe records the choice and the checkpoint's sessions render the same way)."""
    return render_config(state_specs(image_size, cameras), antialias=antialias)


def state_vector(batch: dict[str, np.ndarray], inputs=STATE_INPUTS) -> np.ndarray:
    """[B, D] float32 concatenation of the state inputs of a stacked batch."""
    return np.concatenate([np.asarray(batch[n], dtype=np.float32).reshape(len(batch[n]), w) for n, w in inputs], axis=1)
