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

import numpy as np
from gymnasium import spaces

from services.common.specs import TensorSpec
from services.env_worker.families import ResetSpec, get_family
from zetta.gym import SchemaEnv, check_render_mode, space_for

#: ``reset(options=...)`` keys the in-process env takes (videos go to ``video_path``).
LOCAL_RESET_OPTIONS = ("task", "init_state_index", "instruction", "video_path")


def _space(spec: TensorSpec) -> spaces.Space:
    return space_for(spec.dtype, spec.shape, spec.low, spec.high)


class LocalFamilyEnv(SchemaEnv):
    """One slot of ``env_family`` built in this process. Episode keys replay as on an env worker."""

    def __init__(self, env_family: str, env_config: Mapping[str, Any] | None = None, task: str | int = "",
                 include_privileged: bool = True, render_mode: str | None = None, render_camera: str = "") -> None:
        check_render_mode(render_mode)
        cls = get_family(env_family)
        self._family = cls(cls.canonical_config(dict(env_config or {})))
        schema = self._family.obs_schema()
        self.task = str(task)
        try:
            self._set_spaces({n: _space(s) for n, s in schema.items()}, [n for n, s in schema.items() if s.privileged],
                             _space(self._family.action_spec()), include_privileged, render_mode, render_camera)
        except ValueError:
            self._family.close()
            raise
        self._slot = self._family.init()

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        options, episode_seed = self._start(seed, options, LOCAL_RESET_OPTIONS)
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

    def close(self) -> None:
        slot, self._slot = getattr(self, "_slot", None), None
        if slot is not None:
            slot.close()
            self._family.close()
