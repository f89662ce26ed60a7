"""Gymnasium environments over Zetta sessions, for code that expects ``gymnasium.Env``.

``ZettaEnv`` holds one session of any env family the stack serves (LIBERO, LIBERO-PRO, robosuite,
RoboCasa where installed) and speaks the Gymnasium API: ``reset(seed=..., options=...)`` starts an
episode (the options carry the rest of the episode key: task, init state, instruction, video,
harness), ``step(action)`` executes one action (or a chunk) on the env worker. The spaces come
from the session's own schema, so an observation always lies in ``observation_space``; privileged
(simulation-only) signals can be left out with ``include_privileged=False``.

    env = gymnasium.make("zetta/Session-v0", gateway="127.0.0.1:50051", env_family="libero",
                         env_config={"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"})
    obs, info = env.reset(seed=0, options={"init_state_index": 3})
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

Vectorized training wants one session per sub-environment: ``gymnasium.vector.AsyncVectorEnv`` over
``ZettaEnv`` factories works, and ``zetta.SessionGroup`` batches many sessions in one RPC when a
vector env's per-env calls are the bottleneck.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from zetta.client import ResetResult, StepResult
from zetta_wire.codec import dtype_from_wire
from zetta.sync import SyncGateway
from zetta_wire.v1 import types_pb2

#: ``reset(options=...)`` keys and the SessionGroup.reset arguments they set.
RESET_OPTIONS = ("task", "init_state_index", "instruction", "record_video", "harness", "harness_dir")


def space_for(dtype: np.dtype | str, shape: Iterable[int], low: float | None = None,
              high: float | None = None) -> spaces.Space:
    """The Gymnasium space of one tensor spec: bool tensors are MultiBinary, numbers a Box over the
    declared bounds or, where the spec declares none, the dtype's own range."""
    dtype = np.dtype(dtype)
    shape = tuple(int(d) for d in shape)
    if any(d < 0 for d in shape):
        raise ValueError(f"shape {list(shape)} has a free dimension: a Gymnasium space needs fixed ones")
    if dtype == np.bool_:
        return spaces.MultiBinary(shape)
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        lo, hi = (info.min if low is None else low), (info.max if high is None else high)
    else:
        lo, hi = (-np.inf if low is None else low), (np.inf if high is None else high)
    return spaces.Box(low=lo, high=hi, shape=shape, dtype=dtype)


def spec_space(spec: types_pb2.TensorSpec) -> spaces.Space:
    """:func:`space_for` of a wire-format TensorSpec."""
    return space_for(dtype_from_wire(spec.dtype).newbyteorder("="), spec.shape,
                     spec.low if spec.HasField("low") else None, spec.high if spec.HasField("high") else None)


def check_render_mode(render_mode: str | None) -> None:
    """Refuse a render mode the Zetta envs do not offer, before anything is built."""
    if render_mode not in (None, "rgb_array"):
        raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")


class SchemaEnv(gymnasium.Env):
    """What every Zetta env shares, whatever steps it: spaces and the observation's keys from a
    tensor schema, episode seeds, and ``render`` of the latest camera frame."""

    metadata = {"render_modes": ["rgb_array"]}

    def _set_spaces(self, observation: Mapping[str, spaces.Space], privileged: Iterable[str], action: spaces.Space,
                    include_privileged: bool, render_mode: str | None, render_camera: str) -> None:
        """Spaces of the tensors kept (privileged ones only if asked); ValueError for rgb_array
        without a camera among them (the caller frees what it built)."""
        hidden = set() if include_privileged else set(privileged)
        self._keys = [name for name in observation if name not in hidden]
        self.observation_space = spaces.Dict({name: observation[name] for name in self._keys})
        self.action_space = action
        self.render_mode = render_mode
        images = [name for name in self._keys if name.endswith("_image")]
        self._camera = render_camera or (images[0] if images else "")
        self._last: dict[str, np.ndarray] = {}
        if render_mode == "rgb_array" and self._camera not in images:
            raise ValueError(f"render_mode='rgb_array' needs a camera in the observations "
                             f"({images or 'none: set env_config cameras'}), got {self._camera or 'none'!r}")

    def _start(self, seed: int | None, options: Mapping[str, Any] | None, known: Iterable[str]
               ) -> tuple[dict[str, Any], int]:
        """The checked reset options and the episode seed: ``seed``, or a draw from the env's own
        generator (seeded by the first ``reset(seed=...)``) when None."""
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - set(known)
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: {list(known)}")
        return options, seed if seed is not None else int(self.np_random.integers(2**31))

    def render(self) -> np.ndarray | None:
        """The latest frame of ``render_camera`` (the first camera by default) with rgb_array."""
        if self.render_mode != "rgb_array":
            return None
        return self._last.get(self._camera)

    def _observation(self, raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        self._last = {k: raw[k] for k in self._keys}
        return dict(self._last)


class ZettaEnv(SchemaEnv):
    """One session of ``env_family`` through the gateway at ``gateway``, as a ``gymnasium.Env``.

    ``gateway`` is an address (a private blocking connection is opened and closed with the env) or
    a :class:`zetta.SyncGateway` to share. The session's lease renews in the background until
    :meth:`close`. ``seed=None`` on reset draws the episode seed from the env's own generator, so
    a seeded first reset makes the whole sequence of episodes reproducible.
    """

    def __init__(self, gateway: str | SyncGateway, env_family: str, env_config: Mapping[str, Any] | None = None,
                 task: str | int = "", include_privileged: bool = True, render_mode: str | None = None,
                 render_camera: str = "") -> None:
        check_render_mode(render_mode)
        self._owns_gateway = isinstance(gateway, str)
        gw = SyncGateway(gateway) if isinstance(gateway, str) else gateway
        #: None once closed.
        self._gateway: SyncGateway | None = gw
        try:
            self._sessions = gw.create_sessions(env_family=env_family, n=1, env_config=env_config)
        except BaseException:
            if self._owns_gateway:
                gw.close()
            raise
        info = self._sessions.infos[0]
        self.session_id: str = info.session_id
        self.task = str(task)
        try:
            self._set_spaces({s.name: spec_space(s) for s in info.observation_schema},
                             [s.name for s in info.observation_schema if s.privileged], spec_space(info.action_spec),
                             include_privileged, render_mode, render_camera)
        except ValueError:
            self.close()
            raise

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        options, episode_seed = self._start(seed, options, RESET_OPTIONS)
        options.setdefault("task", self.task)
        result: ResetResult = self._sessions.reset(seed=episode_seed, **options)[0]
        info = {"episode_id": result.episode_id, "instruction": result.instruction, "max_steps": result.max_steps,
                "milestone_names": list(result.milestone_names), "seed": episode_seed}
        if result.video_path:
            info["video_path"] = result.video_path
        return self._observation(result.observation), info

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        action = np.asarray(action, dtype=self.action_space.dtype)
        result: StepResult = self._sessions.action_step([action])[0]
        info: dict[str, Any] = {**result.info, "success": result.success, "episode_step": result.episode_step,
                                "milestones_reached": list(result.milestones_reached),
                                "first_missing_milestone": result.first_missing_milestone,
                                "executed_actions": result.executed_actions}
        if result.video_path:
            info["video_path"] = result.video_path
        return self._observation(result.observation), result.reward, result.terminated, result.truncated, info

    def close(self) -> None:
        sessions, self._sessions = getattr(self, "_sessions", None), None
        if sessions is not None:
            sessions.close()
        if self._owns_gateway and self._gateway is not None:
            self._gateway.close()
            self._gateway = None


gymnasium.register(id="zetta/Session-v0", entry_point="zetta.gym:ZettaEnv")
# The in-process env needs this repository's services package (resolved only by gymnasium.make).
gymnasium.register(id="zetta/Local-v0", entry_point="services.ops.gym_env:LocalFamilyEnv")
