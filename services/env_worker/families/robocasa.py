"""The "robocasa" family: RoboCasa kitchen tasks (robosuite >= 1.5 environments).

RoboCasa cannot share this project's venv: it needs robosuite >= 1.5, while LIBERO (and so the
``libero`` and ``robosuite`` families) pins robosuite 1.4.0. A RoboCasa env worker therefore runs
from its own environment (docs/simulation.md, "RoboCasa") and registers with the same gateway as
the others. Where RoboCasa, a robosuite it supports or its kitchen assets (about 10 GB, downloaded
separately) are missing, :func:`unavailable_reason` says what is missing and how to install it,
and creating the family raises :class:`ConfigError` with that text, which the env worker answers
as INVALID_ARGUMENT like any other bad ``env_config``.

This module imports neither robosuite nor RoboCasa at import time, so it loads (and registers the
family) in any environment; the simulator is imported only once the checks pass.

Episodes
    A config names one RoboCasa environment (``env_name``) and the kitchens it may draw from
    (``layout_ids`` x ``style_ids``). RoboCasa rebuilds the kitchen on every reset (layout, style,
    fixtures and objects are drawn from the environment's ``rng``), so environments are built with
    ``hard_reset=True``. The episode key (``seed``, ``init_state_index``) seeds that ``rng`` (and
    numpy's global stream, which robosuite's robot noise reads) before the reset, so the same key
    draws the same kitchen and objects. Pin one kitchen with one layout id and one style id.
    Success is the environment's own ``_check_success()``; the instruction is
    ``get_ep_meta()["lang"]``.

Observation and action
    The robot tensors of the other families (``robot0_eef_pos``, ``robot0_eef_quat``,
    ``robot0_gripper_qpos``, ``robot0_joint_pos``, ``robot0_proprio``) plus, for a mobile base,
    ``robot0_base_pos``, ``robot0_base_quat``, ``robot0_base_to_eef_pos``,
    ``robot0_base_to_eef_quat``. Their widths and the action width are read from the first
    environment the group builds (PandaOmron's composite controller takes arm, gripper, base,
    torso and mode commands in one vector), not hard-coded. The privileged ``task_object_*``
    tensors follow the task's object named ``obj`` (RoboCasa's atomic tasks name their main object
    so); RoboCasa tasks have no goal plan here, so the target, obstacle, milestone and signal tensors
    are zeros and milestone lists are empty.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import random
import re
import sys
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.env_worker.families.contract import ConfigError, ResetError, ResetSpec, SingleEnvFamily, Slot
from services.env_worker.families.episode import EpisodeSlot
from services.env_worker.families.options import (
    MAX_CAMERA_SIZE,
    MAX_CONTROL_FREQ,
    MAX_EPISODE_STEPS,
    MAX_OBJECT_STATE_DIM,
    bool_option,
    camera_option,
    check_keys,
    int_option,
)
from services.env_worker.families.pool import EnvPool
from services.env_worker.families.registry import register_family
from services.env_worker.families.schema import camera_obs_name, manipulation_schema, upright_image, zero_padded
from services.env_worker.rendering import select_gl_backend
from services.env_worker.families.task_state import geoms_box
from services.env_worker.rendering import SlotRenderer

#: Oldest robosuite RoboCasa runs on (its v0.2 moved to robosuite 1.5; v1.0 follows robosuite master).
MIN_ROBOSUITE = (1, 5)
#: Asset folders under ``robocasa/models/assets`` that only the download script fills (the git
#: checkout ignores them): default textures and the objaverse objects every task samples from.
REQUIRED_ASSET_DIRS = ("textures", os.path.join("objects", "objaverse"))

DEFAULT_ENV = "PnPCounterToCab"
DEFAULT_ROBOT = "PandaOmron"
#: Cameras RoboCasa mounts on its robots (robocasa/utils/camera_utils.py).
ROBOCASA_CAMERAS = (
    "robot0_agentview_left", "robot0_agentview_right", "robot0_agentview_center", "robot0_eye_in_hand",
    "robot0_frontview",
)
VIDEO_CAMERA = "robot0_agentview_center"
DEFAULT_OBJECT_STATE_DIM = 140  # 10 objects x (pos, quat, pos and quat relative to the eef)
OBJ_REGISTRIES = ("objaverse", "aigen", "lightwheel")
#: Robot tensors of a mobile base, added to the schema when the robot reports them.
BASE_KEYS = {
    "robot0_base_pos": "mobile base position, world frame (m)",
    "robot0_base_quat": "mobile base orientation, quaternion xyzw",
    "robot0_base_to_eef_pos": "end-effector position in the base frame (m)",
    "robot0_base_to_eef_quat": "end-effector orientation in the base frame, quaternion xyzw",
}

INSTALL_STEPS = (
    "RoboCasa needs robosuite >= 1.5 and this project's venv pins robosuite 1.4.0 (LIBERO needs it), so "
    "serve it from an environment of its own (Python 3.11): "
    "python3.11 -m venv .venv-robocasa && . .venv-robocasa/bin/activate && "
    "git clone https://github.com/ARISE-Initiative/robosuite && pip install -e robosuite && "
    "git clone https://github.com/robocasa/robocasa && pip install -e robocasa && "
    "python -m robocasa.scripts.setup_macros && "
    "python -m robocasa.scripts.download_kitchen_assets (about 10 GB) && "
    "pip install --no-deps -e . plus the worker's runtime packages; then start an env worker there with "
    "ZETTA_ENV_FAMILIES=robocasa (docs/simulation.md, section RoboCasa)"
)


# ---------------------------------------------------------------------------------------------
# Availability


def _robocasa_dir() -> str | None:
    """Directory of the installed ``robocasa`` package, found without importing it; None if absent."""
    try:
        spec = importlib.util.find_spec("robocasa")
    except (ImportError, ValueError):
        return None
    if spec is None:
        return None
    locations = list(spec.submodule_search_locations or [])
    if locations:
        return locations[0]
    return os.path.dirname(spec.origin) if spec.origin else None


def _robosuite_version() -> str | None:
    """Version of the installed robosuite distribution, read from its metadata; None if absent."""
    try:
        return importlib.metadata.version("robosuite")
    except importlib.metadata.PackageNotFoundError:
        return None


def _version_tuple(version: str) -> tuple[int, ...]:
    """Leading numeric release of a version string ("1.5.1.dev0" -> (1, 5, 1))."""
    match = re.match(r"\d+(?:\.\d+)*", version.strip())
    return tuple(int(part) for part in match.group(0).split(".")) if match else ()


def _non_empty_dir(path: str) -> bool:
    try:
        with os.scandir(path) as entries:
            return any(True for _ in entries)
    except (FileNotFoundError, NotADirectoryError, PermissionError):
        return False


def unavailable_reason() -> str:
    """Why the robocasa family cannot run in this Python environment; "" when it can.

    Checks, in order: the ``robocasa`` package can be found, robosuite is installed at a version
    RoboCasa supports (>= 1.5), and the kitchen assets the download script fetches are present and
    non-empty. Nothing is imported, so the check is cheap and safe in this project's venv.
    """
    where = f"the Python environment of {sys.executable}"
    package = _robocasa_dir()
    if package is None:
        return f"robocasa: the Python package 'robocasa' is not installed in {where}. {INSTALL_STEPS}."
    version = _robosuite_version()
    if version is None:
        return (
            f"robocasa: robocasa is installed ({package}) but robosuite is not; install robosuite >= "
            f"{'.'.join(map(str, MIN_ROBOSUITE))} from https://github.com/ARISE-Initiative/robosuite. {INSTALL_STEPS}."
        )
    if _version_tuple(version) < MIN_ROBOSUITE:
        return (
            f"robocasa: robosuite {version} is installed but RoboCasa needs robosuite >= "
            f"{'.'.join(map(str, MIN_ROBOSUITE))}. {INSTALL_STEPS}."
        )
    assets = os.path.join(package, "models", "assets")
    missing = [d for d in REQUIRED_ASSET_DIRS if not _non_empty_dir(os.path.join(assets, d))]
    if missing:
        paths = ", ".join(os.path.join(assets, d) for d in missing)
        return (
            f"robocasa: the RoboCasa kitchen assets are missing or empty ({paths}); download them with "
            f"'python -m robocasa.scripts.download_kitchen_assets' (about 10 GB) in {where}."
        )
    return ""


def require_available() -> None:
    """Raise :class:`ConfigError` with :func:`unavailable_reason` unless RoboCasa can run here."""
    reason = unavailable_reason()
    if reason:
        raise ConfigError(reason)


_SIM: dict[str, Any] = {}
_SIM_LOCK = threading.Lock()


def _simulator() -> dict[str, Any]:
    """robosuite and RoboCasa, imported once (after the availability checks passed)."""
    with _SIM_LOCK:
        if not _SIM:
            select_gl_backend()  # robosuite picks its GL context class at import time
            try:
                robosuite = importlib.import_module("robosuite")
                importlib.import_module("robocasa")  # registers the kitchen environments
                controllers = importlib.import_module("robosuite.controllers")
                base = importlib.import_module("robosuite.environments.base")
                robots = importlib.import_module("robosuite.models.robots.robot_model")
            except ImportError as exc:
                raise ConfigError(f"robocasa: importing robosuite/robocasa failed: {exc}. {INSTALL_STEPS}.") from exc
            if not hasattr(controllers, "load_composite_controller_config"):
                raise ConfigError(
                    f"robocasa: the robosuite at {robosuite.__file__} has no load_composite_controller_config "
                    f"(robosuite < 1.5). {INSTALL_STEPS}."
                )
            _SIM.update(
                robosuite=robosuite,
                controller_config=controllers.load_composite_controller_config,
                envs=base.REGISTERED_ENVS,
                robots=getattr(robots, "REGISTERED_ROBOTS", {}),
            )
        return _SIM


# ---------------------------------------------------------------------------------------------
# Config


def _id_list(config: Mapping[str, Any], key: str) -> list[int] | None:
    """``layout_ids`` / ``style_ids``: an integer or a list of integers; absent or null: all of them.

    Negative ids are RoboCasa's groups (e.g. layout -2: no islands or wall stacks), passed through.
    """
    value = config.get(key)
    if value is None:
        return None
    values = [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    if isinstance(values, str) or not isinstance(values, Sequence) or not values:
        raise ConfigError(f"robocasa: {key} must be an integer or a non-empty list of integers, got {value!r}")
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer():
            raise ConfigError(f"robocasa: {key} must hold integers, got {v!r}")
        out.append(int(v))
    return out


def _registries(config: Mapping[str, Any]) -> list[str]:
    value = config.get("obj_registries", ["objaverse"])
    if isinstance(value, str) or not isinstance(value, Sequence) or not value:
        raise ConfigError(f"robocasa: obj_registries must be a non-empty list, got {value!r}")
    unknown = [v for v in value if v not in OBJ_REGISTRIES]
    if unknown:
        raise ConfigError(f"robocasa: unknown obj_registries {unknown}; valid: {list(OBJ_REGISTRIES)}")
    return list(value)


# ---------------------------------------------------------------------------------------------
# Raw observations

#: numpy's global stream is shared by the slot threads of a worker; a reset seeds and draws under it.
GLOBAL_RNG_LOCK = threading.RLock()


def joint_positions(obs: Mapping[str, Any]) -> np.ndarray:
    """Arm joint angles: robosuite's joint_pos observable when active, else atan2(sin, cos) of the
    always-active ones (an observable activated by hand is lost at each hard reset)."""
    if "robot0_joint_pos" in obs:
        return np.asarray(obs["robot0_joint_pos"], dtype=np.float64)
    return np.arctan2(np.asarray(obs["robot0_joint_pos_sin"]), np.asarray(obs["robot0_joint_pos_cos"]))


def robot_obs(obs: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The robot part of the canonical observation (before images) from a robosuite 1.5 observation."""
    raw = {
        "robot0_eef_pos": np.asarray(obs["robot0_eef_pos"]),
        "robot0_eef_quat": np.asarray(obs["robot0_eef_quat"]),
        "robot0_gripper_qpos": np.asarray(obs["robot0_gripper_qpos"]),
        "robot0_joint_pos": joint_positions(obs),
    }
    if "robot0_proprio-state" in obs:
        raw["robot0_proprio"] = np.asarray(obs["robot0_proprio-state"])
    else:  # robosuite without modality concatenation: the robot's own tensors, in name order
        raw["robot0_proprio"] = np.concatenate(
            [np.asarray(v, dtype=np.float64).reshape(-1) for k, v in sorted(obs.items())
             if k.startswith("robot0_") and not k.endswith("_image")]
        )
    for key in BASE_KEYS:
        if key in obs:
            raw[key] = np.asarray(obs[key])
    return raw


def _first_gripper(robot: Any) -> Any:
    """robosuite 1.5 keeps grippers per arm (a dict); older versions one model."""
    gripper = robot.gripper
    return next(iter(gripper.values())) if isinstance(gripper, Mapping) else gripper


# ---------------------------------------------------------------------------------------------
# The family


@register_family
class RobocasaFamily(SingleEnvFamily):
    """One RoboCasa kitchen environment over a set of layouts and styles.

    Environments are pooled: a closed slot parks its environment for the next one (building a
    RoboCasa env costs seconds; each reset rebuilds the kitchen model anyway, so models are not
    shared between environments the way the robosuite and LIBERO families share theirs).
    """

    name = "robocasa"
    _KEYS = (
        "env_name", "task", "robots", "layout_ids", "style_ids", "obj_registries", "cameras", "camera_size",
        "reflections", "antialias", "max_steps", "object_state_dim", "control_freq",
    )

    @classmethod
    def unavailable_reason(cls) -> str:
        return unavailable_reason()

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__(config)
        self._pool: EnvPool[Any] = EnvPool()
        self._spec_lock = threading.Lock()
        self._schema: dict[str, TensorSpec] | None = None
        self._action: TensorSpec | None = None

    @classmethod
    def canonical_config(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        require_available()
        check_keys(cls.name, config, cls._KEYS)
        if "env_name" in config and "task" in config and config["env_name"] != config["task"]:
            raise ConfigError("robocasa: give env_name or task (the same thing), not two different names")
        env_name = config.get("env_name", config.get("task", DEFAULT_ENV))
        sim = _simulator()
        if not isinstance(env_name, str) or env_name not in sim["envs"]:
            kitchen = sorted(n for n, c in sim["envs"].items() if getattr(c, "__module__", "").startswith("robocasa."))
            raise ConfigError(
                f"robocasa: unknown env_name {env_name!r}; {len(kitchen)} RoboCasa environments are registered, "
                f"e.g. {kitchen[:12]}"
            )
        robots = config.get("robots", DEFAULT_ROBOT)
        if robots == "PandaMobile":  # RoboCasa's old name of the same robot
            robots = "PandaOmron"
        if not isinstance(robots, str) or (sim["robots"] and robots not in sim["robots"]):
            raise ConfigError(
                f"robocasa: robots must be one registered robosuite robot (e.g. {DEFAULT_ROBOT!r}), got {robots!r}"
            )
        return {
            "env_name": env_name,
            "robots": robots,
            "layout_ids": _id_list(config, "layout_ids"),
            "style_ids": _id_list(config, "style_ids"),
            "obj_registries": _registries(config),
            "cameras": camera_option(cls.name, config, ROBOCASA_CAMERAS),
            "camera_size": int_option(cls.name, config, "camera_size", 128, minimum=8, maximum=MAX_CAMERA_SIZE),
            "reflections": bool_option(cls.name, config, "reflections", True),
            "antialias": bool_option(cls.name, config, "antialias", True),
            "max_steps": int_option(cls.name, config, "max_steps", 500, minimum=1, maximum=MAX_EPISODE_STEPS),
            "object_state_dim": int_option(cls.name, config, "object_state_dim", DEFAULT_OBJECT_STATE_DIM,
                                             maximum=MAX_OBJECT_STATE_DIM),
            "control_freq": int_option(cls.name, config, "control_freq", 20, minimum=1, maximum=MAX_CONTROL_FREQ),
        }

    # ---- schema and action, read from a built environment ----

    def obs_schema(self) -> dict[str, TensorSpec]:
        self._ensure_specs()
        assert self._schema is not None
        return dict(self._schema)

    def action_spec(self) -> TensorSpec:
        self._ensure_specs()
        assert self._action is not None
        return self._action

    def _ensure_specs(self, env: Any = None) -> None:
        """Fix the schema and action spec from an environment of this config (built once if none is)."""
        with self._spec_lock:
            if self._schema is not None:
                return
            probe = env
            if probe is None:
                probe = self._pool.acquire(self.config["env_name"], self._build)
            try:
                # A built env holds a valid state; its observation fixes the robot tensors' widths.
                obs = probe._get_observations(force_update=True)
                self._schema, self._action = self._specs_from(probe, obs)
            finally:
                if env is None:
                    self._pool.release(self.config["env_name"], probe)

    def _specs_from(self, env: Any, obs: Mapping[str, Any]) -> tuple[dict[str, TensorSpec], TensorSpec]:
        cfg = self.config
        raw = robot_obs(obs)
        schema = manipulation_schema(
            cfg["cameras"], cfg["camera_size"], int(raw["robot0_proprio"].size), cfg["object_state_dim"]
        )
        for name in ("robot0_gripper_qpos", "robot0_joint_pos"):
            old = schema[name]
            schema[name] = TensorSpec(name, "float32", (int(raw[name].size),), description=old.description)
        for name, description in BASE_KEYS.items():
            if name in raw:
                schema[name] = TensorSpec(name, "float32", (int(raw[name].size),), description=description)
        low, high = (np.asarray(b, dtype=np.float64).reshape(-1) for b in env.action_spec)
        uniform = bool(low.size) and np.all(low == low[0]) and np.all(high == high[0])
        action = TensorSpec(
            name="action",
            dtype="float32",
            shape=(int(low.size),),
            description=(
                f"{cfg['robots']} composite-controller command of {low.size} values, in the order of the env's "
                "action_spec (PandaOmron: arm OSC delta, gripper, base, torso, mode)"
            ),
            low=float(low[0]) if uniform else None,
            high=float(high[0]) if uniform else None,
        )
        return schema, action

    def init(self) -> Slot:
        env = self._pool.acquire(self.config["env_name"], self._build)
        return _RobocasaSlot(self, env)

    def park(self, env: Any) -> None:
        self._pool.release(self.config["env_name"], env)

    def sharing_stats(self) -> dict[str, int]:
        return {"envs_built": self._pool.built, "envs_reused": self._pool.reused, "envs_idle": self._pool.idle_count()}

    def close(self) -> None:
        from services.env_worker.rendering import close_env_renderer

        for env in self._pool.drain():
            close_env_renderer(env)
            env.close()

    def _build(self) -> Any:
        """``robosuite.make`` of the configured kitchen environment, never rendering by itself.

        Slots render through services/env_worker/rendering.py when an observation needs images;
        robosuite's camera observables would render every camera on every step.
        """
        cfg = self.config
        sim = _simulator()
        kwargs: dict[str, Any] = {
            "robots": cfg["robots"],
            "controller_configs": sim["controller_config"](controller=None, robot=cfg["robots"]),
            "has_renderer": False,
            "has_offscreen_renderer": False,
            "use_camera_obs": False,
            "use_object_obs": True,
            "reward_shaping": False,
            "camera_names": [c for c in cfg["cameras"]] or [VIDEO_CAMERA],
            "camera_heights": cfg["camera_size"],
            "camera_widths": cfg["camera_size"],
            "control_freq": cfg["control_freq"],
            "horizon": cfg["max_steps"],
            "ignore_done": True,  # the slot owns truncation
            "hard_reset": True,  # RoboCasa draws a new kitchen model at each reset
            "layout_ids": cfg["layout_ids"],
            "style_ids": cfg["style_ids"],
            "obj_registries": tuple(cfg["obj_registries"]),
            "translucent_robot": False,
            "seed": 0,
        }
        with GLOBAL_RNG_LOCK:
            state = np.random.get_state()
            np.random.seed(0)
            try:
                return sim["robosuite"].make(cfg["env_name"], **kwargs)
            finally:
                np.random.set_state(state)


class _RobocasaSlot(EpisodeSlot):
    def __init__(self, family: RobocasaFamily, env: Any) -> None:
        self._family = family
        self._env = env
        family._ensure_specs(env)
        cfg = family.config
        renderer = SlotRenderer(lambda: self._env, cfg["cameras"], cfg["camera_size"], cfg["reflections"], VIDEO_CAMERA,
                                 antialias=cfg["antialias"])
        super().__init__(family.obs_schema(), renderer)
        self._zeros = {name: spec.zeros() for name, spec in family.obs_schema().items()}
        self._object: Any = None
        self._object_geoms = np.zeros(0, dtype=np.int64)
        self._object_body = -1
        self._layout_style = (-1.0, -1.0)

    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        self._family.check_task(spec.task)
        if spec.init_state_index < 0:
            raise ResetError(f"robocasa: init_state_index must be >= 0, got {spec.init_state_index}")
        env = self._env
        key = np.random.SeedSequence([spec.seed % 2**63, spec.init_state_index])
        seed = int(key.generate_state(1)[0])
        with GLOBAL_RNG_LOCK:
            np.random.seed(seed)
            random.seed(seed)
            env.rng = np.random.default_rng(seed)  # what RoboCasa draws the kitchen and objects from
            if hasattr(env, "unset_ep_meta"):
                env.unset_ep_meta()  # no scene carried over from the previous episode
            obs = env.reset()
        self._bind_task_object()
        meta = env.get_ep_meta()
        self._layout_style = (float(meta.get("layout_id", -1)), float(meta.get("style_id", -1)))
        return self._observation(obs), str(meta.get("lang", "")), self._family.config["max_steps"]

    def _advance(self, action: np.ndarray, observe: bool) -> tuple[Mapping[str, Any], float, bool, dict[str, float]]:
        obs, reward, _, _ = self._env.step(np.asarray(action, dtype=np.float64))
        raw = self._observation(obs)
        success = bool(self._env._check_success())
        info = {
            "grasped": float(raw["task_grasped"][0]),
            "layout_id": self._layout_style[0],
            "style_id": self._layout_style[1],
        }
        return raw, float(reward), success, info

    def _release(self) -> None:
        self._family.park(self._env)

    def _bind_task_object(self) -> None:
        """The task's main object (named ``obj`` by RoboCasa's atomic tasks), looked up after each
        reset since every reset builds a new model."""
        env = self._env
        self._object = getattr(env, "objects", {}).get("obj")
        if self._object is None:
            self._object_geoms, self._object_body = np.zeros(0, dtype=np.int64), -1
            return
        model = env.sim.model
        self._object_body = model.body_name2id(self._object.root_body)
        self._object_geoms = np.array([model.geom_name2id(g) for g in self._object.contact_geoms], dtype=np.int64)

    def _observation(self, obs: Mapping[str, Any]) -> dict[str, Any]:
        cfg = self._family.config
        raw: dict[str, Any] = dict(self._zeros)  # target, obstacles, milestones, signals: none here
        for camera in cfg["cameras"]:
            raw.pop(camera_obs_name(camera), None)
        raw.update(robot_obs(obs))
        for camera in cfg["cameras"]:
            if f"{camera}_image" in obs:
                raw[camera_obs_name(camera)] = upright_image(obs[f"{camera}_image"])
        if "object-state" in obs:
            raw["object_state"] = zero_padded(obs["object-state"], cfg["object_state_dim"], "object-state")
        if self._object is not None:
            env = self._env
            data = env.sim.data
            quat = np.asarray(data.body_xquat[self._object_body])
            raw["task_object_pos"] = np.array(data.body_xpos[self._object_body])
            raw["task_object_quat"] = np.array([quat[1], quat[2], quat[3], quat[0]])  # wxyz -> xyzw
            if self._object_geoms.size:
                raw["task_object_bbox"] = geoms_box(env.sim.model._model, data._data, self._object_geoms)
            grasped = env._check_grasp(gripper=_first_gripper(env.robots[0]), object_geoms=self._object)
            raw["task_grasped"] = np.array([float(bool(grasped))])
        return raw
