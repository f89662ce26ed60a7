"""The family contract: the paper's four primitives init/reset/step/obs_schema, the episode key and
what a step returns, and the errors a family raises.

An env worker hosts slots without knowing what simulator sits behind them. A family declares a
canonical observation schema that is fixed for its configuration (so policies and clients can be
matched to it before any episode runs), builds slots, and turns raw simulator observations into
canonical tensors. Families register by name and are imported lazily, so a worker that serves only
robosuite never pays for importing LIBERO and its 600 MB of assets.

One :class:`EnvFamily` instance per (family, canonical config) in a worker process is a
resource-sharing group: its slots share compiled models and warm environments (see
:class:`~services.env_worker.families.pool.EnvPool`), which turns a multi-second environment build into milliseconds.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from services.common.specs import TensorSpec


#: ``ResetSpec.init_state_index`` for "no benchmark initial state: the layout sampled from the seed".
SAMPLED_LAYOUT = -1


@dataclass(frozen=True)
class ResetSpec:
    """The key of an episode: the same key and the same actions replay the same episode.

    ``task`` is a task name of the configured suite or its index as a decimal string; empty selects
    the family's default. ``instruction`` overrides the task's own instruction for the policy.
    ``init_state_index`` names one of the benchmark's fixed initial states; ``SAMPLED_LAYOUT``
    keeps the layout the suite's placement sampler draws from the seed instead, so training data
    can cover layouts the benchmark's fixed states (kept for evaluation) do not contain.
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


class SlotClosedError(EpisodeError):
    """The slot was closed (its session closed, or its worker declared dead) while a call used it."""


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


class SingleEnvFamily(EnvFamily):
    """A family whose configuration holds one environment (``config["env_name"]``) as its only
    task, with one step budget (``config["max_steps"]``)."""

    def max_episode_steps(self, task: str) -> int:
        self.check_task(task)
        return int(self.config["max_steps"])

    def check_task(self, task: str) -> None:
        """Accept the environment's name, "0" or empty; refuse anything else, naming the one task."""
        if task not in ("", "0", self.config["env_name"]):
            raise ResetError(
                f"{self.name}: unknown task {task!r}; this config has one task: "
                f"{self.config['env_name']!r} (index 0, or empty)"
            )
