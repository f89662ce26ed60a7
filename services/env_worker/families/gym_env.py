"""Any env family as an in-process ``gymnasium.Env``: no gateway, no workers, one slot.

For users who want a family's episodes (the same keys, milestones, physical signals, fast step
and success predicate an env worker serves) inside their own training loop or a Gymnasium vector
env. ``zetta.gym.ZettaEnv`` is the same API over a session of a running stack; both build their
spaces with ``zetta.gym.space_for`` from the family's schema.

    import zetta.gym  # registers the ids
    env = gymnasium.make("zetta/Local-v0", env_family="libero",
                         env_config={"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"})
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from services.common.specs import TensorSpec
from services.env_worker.families.base import ResetSpec, get_family
from zetta.gym import space_for

#: ``reset(options=...)`` keys the in-process env takes (videos go to ``video_path``).
LOCAL_RESET_OPTIONS = ("task", "init_state_index", "instruction", "video_path")


def _space(spec: TensorSpec) -> spaces.Space:
    return space_for(spec.dtype, spec.shape, spec.low, spec.high)


class LocalFamilyEnv(gymnasium.Env):
    """One slot of ``env_family`` built in this process. Episode keys replay as on an env worker."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, env_family: str, env_config: Mapping[str, Any] | None = None, task: str | int = "",
                 include_privileged: bool = True, render_mode: str | None = None, render_camera: str = "") -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        cls = get_family(env_family)
        self._family = cls(cls.canonical_config(dict(env_config or {})))
        schema = self._family.obs_schema()
        self._keys = [n for n, s in schema.items() if include_privileged or not s.privileged]
        self.observation_space = spaces.Dict({n: _space(schema[n]) for n in self._keys})
        self.action_space = _space(self._family.action_spec())
        self.task = str(task)
        self.render_mode = render_mode
        images = [n for n in self._keys if n.endswith("_image")]
        self._camera = render_camera or (images[0] if images else "")
        if render_mode == "rgb_array" and self._camera not in images:
            self._family.close()
            raise ValueError(f"render_mode='rgb_array' needs a camera in the observations "
                             f"({images or 'none: set env_config cameras'}), got {self._camera or 'none'!r}")
        self._slot = self._family.init()
        self._last: dict[str, np.ndarray] = {}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - set(LOCAL_RESET_OPTIONS)
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: {list(LOCAL_RESET_OPTIONS)}")
        episode_seed = seed if seed is not None else int(self.np_random.integers(2**31))
        spec = ResetSpec(task=str(options.get("task", self.task)), seed=episode_seed,
                         init_state_index=int(options.get("init_state_index", 0)),
                         instruction=str(options.get("instruction", "")), video_path=str(options.get("video_path", "")))
        obs, instruction = self._slot.reset(spec)
        info = {"instruction": instruction, "seed": episode_seed, "milestone_names": self._slot.milestone_names(),
                "max_steps": self._family.max_episode_steps(spec.task)}
        return self._observation(obs), info

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        out = self._slot.step(np.asarray(action, dtype=self.action_space.dtype), render=True)
        info: dict[str, Any] = {**out.info, "success": out.success, "episode_step": self._slot.episode_step,
                                "milestones_reached": self._slot.milestones_reached(),
                                "first_missing_milestone": self._slot.first_missing_milestone()}
        if out.video_path:
            info["video_path"] = out.video_path
        return self._observation(out.observation), out.reward, out.terminated, out.truncated, info

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array":
            return None
        return self._last.get(self._camera)

    def close(self) -> None:
        slot, self._slot = getattr(self, "_slot", None), None
        if slot is not None:
            slot.close()
            self._family.close()

    def _observation(self, raw: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        self._last = {k: raw[k] for k in self._keys}
        return dict(self._last)
