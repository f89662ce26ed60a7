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
#: Actions of each 8-action chunk executed per policy call: the shipped VLA's DAgger rounds and
#: every published figure of it (docs/results/vla.md) use 4; 2 gained nothing on test (earlier
#: weights) nor on dev (single-sampled weights).
EXECUTE_STEPS = 4
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


#: The served model answering from a LeRobot checkpoint directory (policy_worker/vla/adapter.py).
LEROBOT_POLICY = "lerobot"
#: A LeRobot image key whose last part holds one of these reads the eye-in-hand camera.
_WRIST_HINTS = ("wrist", "hand")


def lerobot_cameras(visual: list[tuple[str, tuple[int, ...]]], explicit: dict[str, str] | None = None
                    ) -> list[tuple[str, str, int]]:
    """A LeRobot policy's VISUAL inputs ``(key, [3, S, S])`` -> ``(key, image tensor, S)``: a key
    naming a wrist or hand camera reads ``robot0_eye_in_hand`` (tensor ``eye_in_hand_image``), the
    first other one ``agentview`` (``agentview_image``); ``explicit`` maps keys to env cameras
    (ZETTA_LEROBOT_CAMERAS). Raises ValueError naming the input."""
    explicit = dict(explicit or {})
    out: list[tuple[str, str, int]] = []
    used: set[str] = set()
    for key, shape in visual:
        if len(shape) != 3 or shape[0] != 3 or shape[1] != shape[2]:
            raise ValueError(f"LeRobot input {key} has shape {list(shape)}; Zetta's env cameras render square "
                             "RGB frames ([3, S, S])")
        camera = explicit.pop(key, None)
        if camera is None:
            wrist = any(h in key.rsplit(".", 1)[-1].lower() for h in _WRIST_HINTS)
            camera = "robot0_eye_in_hand" if wrist else "agentview"
        camera = camera.removesuffix("_image").removeprefix("robot0_")  # the tensor drops the robot prefix
        if camera in used:
            raise ValueError(f"LeRobot inputs {[k for k, _ in visual]}: two of them would read the {camera} camera; "
                             "map them explicitly (ZETTA_LEROBOT_CAMERAS=key=camera,...)")
        used.add(camera)
        out.append((key, f"{camera}_image", int(shape[1])))
    if explicit:
        raise ValueError(f"ZETTA_LEROBOT_CAMERAS names {sorted(explicit)}, which the policy does not read "
                         f"(its image inputs: {[k for k, _ in visual]})")
    return out


def _lerobot_env_config() -> dict[str, Any]:
    """Cameras of the LeRobot checkpoint ZETTA_LEROBOT_CHECKPOINT names, from its config.json."""
    ck = os.environ.get("ZETTA_LEROBOT_CHECKPOINT", "").strip()
    if not ck:
        return {}
    doc = json.loads((Path(ck) / "config.json").read_text())
    visual = [(k, tuple(f["shape"])) for k, f in doc.get("input_features", {}).items() if f.get("type") == "VISUAL"]
    explicit = {}
    for item in (t.strip() for t in os.environ.get("ZETTA_LEROBOT_CAMERAS", "").split(",") if t.strip()):
        key, _, camera = item.partition("=")
        explicit[key.strip()] = camera.strip()
    cams = lerobot_cameras(visual, explicit)
    return render_config([TensorSpec(tensor, "uint8", (side, side, 3)) for _, tensor, side in cams])


def policy_env_config(model: str) -> dict[str, Any]:
    """Env-config keys a model's sessions need (its cameras and their size, reflections off), {} for
    a model that reads no image. Read from the checkpoint's config.json: no model is loaded (for
    ``lerobot``, the directory ZETTA_LEROBOT_CHECKPOINT names, when set)."""
    if model == LEROBOT_POLICY:
        return _lerobot_env_config()
    if model != DEFAULT_POLICY:
        return {}
    doc = json.loads((default_checkpoint() / "config.json").read_text())
    return render_config([TensorSpec(i["name"], i["dtype"], tuple(i["shape"])) for i in doc["inputs"]],
                         antialias=trained_antialiased(doc))


def trained_antialiased(config: dict[str, Any]) -> bool:
    """Whether a checkpoint's training frames were multisampled (a checkpoint config.json): its
    sessions render the same way. Recipes that do not say were rendered before the choice
    existed, multisampled."""
    recipes = [r.get("recipe", r) for r in config.get("data", {}).get("recipes", [])]
    return any(r.get("antialias", True) for r in recipes if r.get("image_size")) or not recipes


#: A data recipe's ``init_states``: the benchmark's fixed initial states (seed % 50), or layouts
#: sampled from each seed (init_state_index -1), which are none of the benchmark's states.
BENCHMARK_INITS = "init_state_index = seed % 50"
SAMPLED_LAYOUTS = "sampled layout per seed (init_state_index -1)"


def training_init_states(checkpoint: str | Path | None) -> dict[str, list[int]]:
    """LIBERO init states per suite that a checkpoint's demonstrations came from (its data recipes;
    {} for a checkpoint that records none; sets on sampled layouts use none). A reported number
    must start from others."""
    config = Path(checkpoint) / "config.json" if checkpoint else None
    if config is None or not config.is_file():
        return {}
    doc = json.loads(config.read_text())
    out: dict[str, set[int]] = {}
    for r in doc.get("data", {}).get("recipes", []):
        recipe = r.get("recipe", r)
        if recipe.get("init_states", BENCHMARK_INITS) == SAMPLED_LAYOUTS:
            continue
        n = recipe.get("max_episodes") or recipe["seeds_per_task"] * len(recipe["tasks"])
        per_task = -(-n // len(recipe["tasks"]))
        seeds = range(recipe["seed_offset"], recipe["seed_offset"] + per_task)
        out.setdefault(recipe["suite"], set()).update(s % 50 for s in seeds)
    return {k: sorted(v) for k, v in out.items()}


def trained_layouts(model: str, suite: str) -> list[int]:
    """Init states of ``suite``'s layouts that ``model`` was trained on: a LIBERO-PRO variant
    (libero_goal_swap, _task, _lan, _object) starts from its base suite's init states."""
    base = "_".join(suite.split("_")[:2])
    return training_init_states(checkpoint_dir(model)).get(base, [])
