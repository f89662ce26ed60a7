"""Declarative environment families: the paper's four primitives init/reset/step/obs_schema.

An env worker hosts slots without knowing what simulator sits behind them. A family declares a
canonical observation schema that is fixed for its configuration (so policies and clients can be
matched to it before any episode runs), builds slots, and turns raw simulator observations into
canonical tensors. Families register by name and are imported lazily, so a worker that serves only
robosuite never pays for importing LIBERO and its 600 MB of assets.

One :class:`EnvFamily` instance per (family, canonical config) in a worker process is a
resource-sharing group: its slots share compiled models and warm environments (see
:class:`EnvPool`), which turns a multi-second environment build into milliseconds.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Collection, Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np

from services.common.specs import SpecError, TensorSpec
from services.env_worker import rendering
from services.env_worker.families.task_state import OBSTACLE_SLOTS
from services.env_worker.milestones import milestone_specs
from services.env_worker.signals import signal_specs


@dataclass(frozen=True)
class ResetSpec:
    """The key of an episode: the same key and the same actions replay the same episode.

    ``task`` is a task name of the configured suite or its index as a decimal string; empty selects
    the family's default. ``instruction`` overrides the task's own instruction for the policy.
    """

    task: str
    seed: int = 0
    init_state_index: int = 0
    instruction: str = ""
    #: Where to write this episode's MP4 (services/env_worker/video.py); empty records nothing.
    video_path: str = ""


@dataclass
class StepOutcome:
    """What one executed action produced, in canonical form.

    A step taken with ``render=False`` leaves the camera images out of ``observation`` (they
    are rendered only when an observation that carries them is needed: see rendering.py).
    """

    #: None for a step taken with ``observe=False``; :meth:`Slot.observe` builds it if needed.
    observation: dict[str, np.ndarray] | None
    reward: float
    terminated: bool
    truncated: bool
    success: bool
    info: dict[str, float]
    #: Path of the episode's video when this step completed it (the episode ended), else empty.
    video_path: str = ""


class ConfigError(ValueError):
    """A family configuration is invalid; raised when the family is created, before any build."""


class UnknownFamilyError(KeyError):
    """No family is registered under the requested name."""

    def __str__(self) -> str:
        # KeyError quotes its argument; the message is meant to be read as is.
        return str(self.args[0]) if self.args else ""


class ResetError(ValueError):
    """A reset asked for something the family cannot provide (unknown task, init index out of range)."""


class EpisodeError(RuntimeError):
    """A slot was stepped or observed outside an episode (before the first reset or after its end)."""


# ---------------------------------------------------------------------------------------------
# Registry

_REGISTERED: dict[str, type[EnvFamily]] = {}
_LOCK = threading.Lock()
#: Built-in families by module, imported on first use so heavy simulators load only when needed.
_BUILTIN_MODULES: dict[str, str] = {
    "libero": "services.env_worker.families.libero",
    "robocasa": "services.env_worker.families.robocasa",
    "robosuite": "services.env_worker.families.robosuite_lift",
}


def register_family(cls: type[EnvFamily]) -> type[EnvFamily]:
    """Class decorator that makes a family reachable through :func:`get_family`."""
    name = getattr(cls, "name", "")
    if not isinstance(name, str) or not name:
        raise TypeError(f"{cls.__qualname__} needs a non-empty class attribute 'name'")
    with _LOCK:
        existing = _REGISTERED.get(name)
        if existing is not None and existing is not cls:
            raise ValueError(f"family {name!r} is already registered by {existing.__qualname__}")
        _REGISTERED[name] = cls
    return cls


def family_names() -> list[str]:
    """Every family name a worker can serve, built-in ones included even before their import."""
    return sorted(set(_REGISTERED) | set(_BUILTIN_MODULES))


def get_family(name: str) -> type[EnvFamily]:
    """The family class registered under ``name``, importing a built-in family on first use."""
    if name not in _REGISTERED and name in _BUILTIN_MODULES:
        importlib.import_module(_BUILTIN_MODULES[name])
    try:
        return _REGISTERED[name]
    except KeyError:
        raise UnknownFamilyError(
            f"unknown env family {name!r}; known families: {', '.join(family_names())}"
        ) from None


def canonical_config_key(family: str, config: Mapping[str, Any]) -> str:
    """Sorted JSON of the family name and its validated config with defaults filled in.

    Two configs that build identical slots map to one key, so a worker keeps one sharing group
    for them instead of compiling the same models twice.
    """
    canonical = get_family(family).canonical_config(config)
    return json.dumps({"family": family, "config": canonical}, sort_keys=True, separators=(",", ":"))


# ---------------------------------------------------------------------------------------------
# Family and slot interfaces


class Slot(ABC):
    """One environment instance bound to a session; it runs one episode at a time."""

    @abstractmethod
    def reset(self, spec: ResetSpec) -> tuple[dict[str, np.ndarray], str]:
        """Start the episode keyed by ``spec``; returns the canonical observation and the instruction."""

    @abstractmethod
    def step(self, action: np.ndarray, render: bool = True, observe: bool = True) -> StepOutcome:
        """Execute one action that the caller already checked against the family's action spec.

        ``render=False`` skips the camera images of this step's observation; ``observe=False``
        skips the observation altogether (e.g. on all but the last action of a chunk: only the
        reward, success, milestones and the signals' state are kept up to date). :meth:`observe`
        builds what was skipped if it is asked for before the next step.
        """

    def finish_video(self) -> str:
        """Complete the current episode's video now; its path, or "" when none is recorded."""
        return ""

    def milestone_names(self) -> list[str]:
        """The current episode's ordered milestones M (services/env_worker/milestones.py); [] if none."""
        return []

    def milestones_reached(self) -> list[str]:
        """The milestones of M observed so far in the episode, in the order of M."""
        return []

    def first_missing_milestone(self) -> str:
        """m*: the first milestone of M not observed so far in the episode; "" when all were (or none exist)."""
        return ""

    @abstractmethod
    def observe(self) -> dict[str, np.ndarray]:
        """The current canonical observation, without advancing or changing anything."""

    @property
    @abstractmethod
    def episode_step(self) -> int:
        """Actions executed in the current episode."""

    @abstractmethod
    def close(self) -> None:
        """Hand the environment back to the sharing group; the slot is unusable afterwards."""


class EnvFamily(ABC):
    """A kind of environment (simulator plus benchmark) and one configuration of it.

    The instance is the resource-sharing group of its configuration: every slot it builds shares
    its caches, so a worker must create one instance per :func:`canonical_config_key`.
    """

    name: ClassVar[str]

    def __init__(self, config: Mapping[str, Any]) -> None:
        self.config: dict[str, Any] = self.canonical_config(config)

    @classmethod
    @abstractmethod
    def canonical_config(cls, config: Mapping[str, Any]) -> dict[str, Any]:
        """Validate ``config`` and fill in defaults; raise :class:`ConfigError` naming the valid choices."""

    @abstractmethod
    def obs_schema(self) -> dict[str, TensorSpec]:
        """Canonical observation tensors, identical for every task of this configuration."""

    @abstractmethod
    def action_spec(self) -> TensorSpec:
        """The spec one action must match."""

    @abstractmethod
    def max_episode_steps(self, task: str) -> int:
        """Step budget of an episode of ``task`` (same task syntax as :class:`ResetSpec`)."""

    @abstractmethod
    def init(self) -> Slot:
        """Build a slot, reusing the group's compiled models and warm environments."""

    @classmethod
    def unavailable_reason(cls) -> str:
        """Why this family cannot run on this machine ("" when it can): a worker configured to
        serve it refuses to start with this message instead of refusing every request later."""
        return ""

    @abstractmethod
    def sharing_stats(self) -> dict[str, int]:
        """Counters of the sharing mechanism (builds, reuses), for metrics and tests."""

    @abstractmethod
    def close(self) -> None:
        """Release the group's warm environments and caches."""


# ---------------------------------------------------------------------------------------------
# Config helpers (configs arrive as protobuf Structs, where every number is a float)


def check_keys(family: str, config: Mapping[str, Any], allowed: Sequence[str]) -> None:
    """Reject keys a family does not know, since a typo would otherwise silently use a default."""
    if not isinstance(config, Mapping):
        raise ConfigError(f"{family}: config must be a mapping, got {type(config).__name__}")
    unknown = sorted(set(config) - set(allowed))
    if unknown:
        raise ConfigError(f"{family}: unknown config keys {unknown}; valid keys: {sorted(allowed)}")


def int_option(family: str, config: Mapping[str, Any], key: str, default: int, minimum: int = 0) -> int:
    """An integer option that also accepts integral floats, as JSON and protobuf Structs send them."""
    value = config.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
        raise ConfigError(f"{family}: {key} must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{family}: {key} must be >= {minimum}, got {value!r}")
    return int(value)


def camera_option(family: str, config: Mapping[str, Any], valid: Sequence[str]) -> list[str]:
    """The ``cameras`` option: a list of distinct camera names out of ``valid``."""
    cameras = config.get("cameras", [])
    if isinstance(cameras, str) or not isinstance(cameras, Sequence):
        raise ConfigError(f"{family}: cameras must be a list of camera names, got {cameras!r}")
    unknown = [c for c in cameras if c not in valid]
    if unknown:
        raise ConfigError(f"{family}: unknown cameras {unknown}; valid cameras: {list(valid)}")
    if len(set(cameras)) != len(cameras):
        raise ConfigError(f"{family}: cameras must not repeat, got {list(cameras)}")
    return list(cameras)


def bool_option(family: str, config: Mapping[str, Any], key: str, default: bool) -> bool:
    """A true/false option; numbers and strings are refused rather than guessed at."""
    value = config.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"{family}: {key} must be true or false, got {value!r}")
    return value


# ---------------------------------------------------------------------------------------------
# Canonical observations of single-arm manipulation families

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
        TensorSpec(
            "task_object_pos", "float32", (3,), privileged=True,
            description=(
                "position of what the current goal stage moves: the object, or the handle of the drawer, door or "
                "knob to actuate; zeros if none"
            ),
        ),
        TensorSpec(
            "task_object_quat", "float32", (4,), privileged=True,
            description="orientation (xyzw) of the task object; zeros if none",
        ),
        TensorSpec(
            "task_target_pos", "float32", (3,), privileged=True,
            description=(
                "position of the stage's target object, region or site (for a handle: where it must move to); "
                "zeros if the stage has none"
            ),
        ),
        TensorSpec(
            "task_object_bbox", "float32", (6,), privileged=True,
            description="world axis-aligned box around the task object's collision geoms: min xyz, max xyz",
        ),
        TensorSpec(
            "task_target_bbox", "float32", (6,), privileged=True,
            description="world axis-aligned box of the target (geoms of a body, or a region's box); zeros if none",
        ),
        TensorSpec(
            "task_grasped", "float32", (1,), privileged=True,
            description="1.0 while both fingers touch the task object, else 0.0",
        ),
        TensorSpec(
            "task_obstacle_bbox", "float32", (OBSTACLE_SLOTS, 6), privileged=True,
            description=(
                "world boxes (min xyz, max xyz) of what stands around the task object and its target: other "
                "objects whole, fixtures geom by geom, the robot and the moved object left out; nearest to the "
                "way from object to target first, zero rows pad"
            ),
        ),
        TensorSpec(
            "object_state", "float32", (object_state_dim,), privileged=True,
            description="per object: pos, quat, pos and quat relative to the eef; zero-padded",
        ),
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


# ---------------------------------------------------------------------------------------------
# Rendering backend


def select_gl_backend() -> str:
    """Pick MuJoCo's OpenGL backend before a simulator is imported, unless MUJOCO_GL is set.

    EGL on an NVIDIA GPU, else OSMesa when installed, else EGL through Mesa's software
    rasterizer (rules and measurements: services/env_worker/rendering.py). Returns the backend
    in effect, or "" when no GL library is present (state-only configs still work).
    """
    return rendering.select_gl_backend()


# ---------------------------------------------------------------------------------------------
# Sharing and episode bookkeeping

E = TypeVar("E")


class EnvPool(Generic[E]):
    """Warm environments of a sharing group, kept per key (e.g. per task) for the next slot.

    A closed slot parks its environment here instead of destroying it, so the next slot with the
    same key skips the build entirely.
    """

    def __init__(self) -> None:
        self._idle: dict[Hashable, list[E]] = {}
        self._lock = threading.Lock()
        self.built = 0
        self.reused = 0

    def acquire(self, key: Hashable, build: Callable[[], E]) -> E:
        """A warm environment for ``key``, or a new one from ``build`` when none is idle."""
        with self._lock:
            idle = self._idle.get(key)
            if idle:
                self.reused += 1
                return idle.pop()
        env = build()
        with self._lock:
            self.built += 1
        return env

    def release(self, key: Hashable, env: E) -> None:
        """Park ``env`` for reuse under ``key``."""
        with self._lock:
            self._idle.setdefault(key, []).append(env)

    def idle_count(self) -> int:
        """Environments parked and ready for reuse."""
        with self._lock:
            return sum(len(v) for v in self._idle.values())

    def drain(self) -> list[E]:
        """Remove and return every parked environment, for the group to close."""
        with self._lock:
            envs = [env for idle in self._idle.values() for env in idle]
            self._idle.clear()
        return envs


class EpisodeSlot(Slot):
    """Episode bookkeeping shared by families: step counting, truncation, end-of-episode guard.

    Subclasses implement the simulator side in :meth:`_start` and :meth:`_advance` and return raw
    observations; this class normalizes them against the schema. A subclass whose observation
    costs much more than its bookkeeping may return none from ``_advance`` for a step that is not
    observed, and build it in :meth:`_raw_observation` when it is asked for.

    Camera images and videos come from ``renderer`` (rendering.SlotRenderer), here and not in the
    subclasses, so frames are rendered only when an observation or a video frame needs them:
    after a reset (not on its settle steps), after a step taken with ``render=True``, and on
    :meth:`observe` when the last step skipped them.
    """

    def __init__(self, schema: Mapping[str, TensorSpec], renderer: rendering.SlotRenderer | None = None) -> None:
        self._schema = schema
        #: The raw observation of the current state; None while none was built for it.
        self._raw: Mapping[str, Any] | None = None
        self._running = False  # an episode was started (reset) and the slot is open
        self._step = 0
        self._max_steps = 0
        self._over = False
        self._closed = False
        self._renderer = renderer
        self._image_names: tuple[str, ...] = renderer.image_names if renderer is not None else ()
        #: Images of the current simulator state once rendered; None until then.
        self._images: dict[str, np.ndarray] | None = None
        self._video: Any = None  # video.VideoRecorder while an episode is recorded
        self._video_path = ""

    @abstractmethod
    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        """Reset the simulator: raw observation, the task's instruction and the step budget."""

    @abstractmethod
    def _advance(self, action: np.ndarray, observe: bool) -> tuple[Mapping[str, Any] | None, float, bool,
                                                                    dict[str, float]]:
        """Execute one action: raw observation, reward, success, numeric diagnostics.

        With ``observe`` False the raw observation may be None; :meth:`_raw_observation` then
        builds it for the current state if it is asked for after all.
        """

    def _raw_observation(self) -> Mapping[str, Any]:
        """The raw observation of the current state, after an ``_advance`` that returned none."""
        raise NotImplementedError(f"{type(self).__name__}._advance returned no observation but cannot build one")

    @abstractmethod
    def _release(self) -> None:
        """Hand the simulator back to the sharing group."""

    def reset(self, spec: ResetSpec) -> tuple[dict[str, np.ndarray], str]:
        self._check_open()
        self.finish_video()
        self._raw, self._images, self._video_path, self._running = None, None, "", False
        raw, instruction, max_steps = self._start(spec)
        raw = self._with_images(raw, render=True)
        self._raw, self._step, self._max_steps, self._over = raw, 0, max_steps, False
        self._running = True
        if spec.video_path:
            self._start_video(spec.video_path)
        return normalize_observation(raw, self._schema), spec.instruction or instruction

    def step(self, action: np.ndarray, render: bool = True, observe: bool = True) -> StepOutcome:
        self._check_open()
        if not self._running:
            raise EpisodeError("no episode is running: reset the slot first")
        if self._over:
            raise EpisodeError(f"the episode ended after {self._step} steps: reset the slot first")
        raw, reward, success, info = self._advance(action, observe)
        self._images = None
        if self._video is not None:
            self._record_frame()
        if raw is not None:
            raw = self._with_images(raw, render and observe)
        self._raw = raw
        self._step += 1
        truncated = self._step >= self._max_steps
        self._over = success or truncated
        video_path = self.finish_video() if self._over and self._video is not None else ""
        return StepOutcome(
            observation=normalize_observation(raw, self._schema, optional=self._image_names) if observe else None,
            reward=float(reward),
            terminated=success,
            truncated=truncated,
            success=success,
            info=info,
            video_path=video_path,
        )

    def observe(self) -> dict[str, np.ndarray]:
        self._check_open()
        if not self._running:
            raise EpisodeError("no episode is running: reset the slot first")
        if self._raw is None:
            self._raw = self._with_images(self._raw_observation(), render=False)
        if any(name not in self._raw for name in self._image_names):
            self._raw = self._with_images(self._raw, render=True)
        return normalize_observation(self._raw, self._schema)

    @property
    def renderer(self) -> rendering.SlotRenderer | None:
        """What renders this slot's cameras and video frames (None for a family without cameras)."""
        return self._renderer

    def finish_video(self) -> str:
        if self._video is not None:
            self._video.close()
            self._video = None
        return self._video_path

    def _with_images(self, raw: Mapping[str, Any], render: bool) -> Mapping[str, Any]:
        """``raw`` plus the camera images of the current state: rendered now if ``render``, else
        only those a video frame already rendered."""
        if not self._image_names:
            return raw
        if render and self._images is None:
            self._images = self._renderer.images() if self._renderer is not None else {}
        return {**raw, **self._images} if self._images else raw

    def _start_video(self, path: str) -> None:
        from services.env_worker.video import VideoRecorder

        if self._renderer is None:
            raise ResetError("this family renders no frames, so it cannot record a video")
        width, height = self._renderer.video_size()
        self._video = VideoRecorder(path, self._renderer.fps(), width, height)
        self._video_path = path
        self._record_frame()

    def _record_frame(self) -> None:
        """Append the current state to the video, sharing the observation's render if there is one."""
        assert self._renderer is not None and self._video is not None
        if self._image_names:
            self._with_images({}, render=True)  # fills self._images for this state
        self._video.add(self._renderer.video_frame(self._images))

    @property
    def episode_step(self) -> int:
        return self._step

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.finish_video()
            self._raw, self._images, self._running = None, None, False
            self._release()

    def _check_open(self) -> None:
        if self._closed:
            raise EpisodeError("the slot is closed")
