"""Which policy a stack serves when nobody says, and what its sessions must render for it.

The shipped default is the image VLA: it reads the agentview camera, the robot's own
proprioception and the instruction, nothing the simulator alone knows. Clients that create
sessions for it (the demo, the evolver, the benchmarks) take the env config from here, so the
env renders exactly the camera the checkpoint was trained on, at its size.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from services.common.specs import TensorSpec, render_config

#: The robot's own proprioception as the shipped policy reads it, (name, width) in order: what a
#: real robot reports about itself. Exports (LeRobot's ``observation.state``) use the same columns.
PROPRIO_INPUTS: tuple[tuple[str, int], ...] = (
    ("robot0_eef_pos", 3),
    ("robot0_eef_quat", 4),
    ("robot0_gripper_qpos", 2),
    ("robot0_joint_pos", 7),
)
#: One action: end-effector delta (xyz, rotation) and the gripper.
ACTION_DIM = 7

#: The frozen policy every command uses unless told otherwise.
DEFAULT_POLICY = "zetta-vla-image"
#: The state-based VLA that reads object poses; loadable for comparison, never a default.
PRIVILEGED_BASELINE = "privileged-state-baseline"

#: Where the shipped checkpoints live (one directory each, named as the model).
CHECKPOINT_ROOT = Path(__file__).resolve().parents[1] / "policy_worker" / "checkpoints"


def default_checkpoint() -> Path:
    """The image VLA's checkpoint directory (``ZETTA_VLA_CHECKPOINT`` or the shipped one)."""
    return Path(os.environ.get("ZETTA_VLA_CHECKPOINT") or CHECKPOINT_ROOT / DEFAULT_POLICY)


def checkpoint_dir(model: str) -> Path | None:
    """The checkpoint a served model loads (after its variable), None for a scripted model."""
    if model == DEFAULT_POLICY:
        return default_checkpoint()
    if model == PRIVILEGED_BASELINE:
        return Path(os.environ.get("ZETTA_STATE_BASELINE_CHECKPOINT") or CHECKPOINT_ROOT / PRIVILEGED_BASELINE)
    return None


def policy_env_config(model: str) -> dict[str, Any]:
    """Env-config keys a model's sessions need (its cameras and their size, reflections off), {} for
    a model that reads no image. Read from the checkpoint's config.json: no model is loaded."""
    if model != DEFAULT_POLICY:
        return {}
    doc = json.loads((default_checkpoint() / "config.json").read_text())
    return render_config([TensorSpec(i["name"], i["dtype"], tuple(i["shape"])) for i in doc["inputs"]])
