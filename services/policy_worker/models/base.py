"""What a served model must provide, and the table of models a worker can load by name.

The scheduler and the server only see this interface, so a user's own policy (an openpi or
LeRobot checkpoint behind an adapter) plugs in by adding a factory, without touching batching.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from services.common.specs import TensorSpec


class PolicyModel(Protocol):
    """A batched policy: stacked named inputs and instructions in, action chunks out."""

    name: str
    chunk_size: int

    def input_specs(self) -> Sequence[TensorSpec]:
        """Tensors the model reads, one sample each (no batch dimension)."""
        ...

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """Return float32 actions of shape [batch, chunk_size, action_dim]."""
        ...


#: One action of every model served here: LIBERO/robosuite OSC_POSE deltas plus the gripper.
ACTION_SPEC = TensorSpec("action", "float32", (7,), description="delta eef xyz, delta rotation, gripper (-1 open, 1 close)")


class UnknownModelError(KeyError):
    """A model name no factory is registered for."""


def _scripted() -> PolicyModel:
    from services.policy_worker.models.scripted import ScriptedPickPlacePolicy

    return ScriptedPickPlacePolicy()


def _scripted_weak() -> PolicyModel:
    from services.policy_worker.models.scripted import PickPlaceParams, ScriptedPickPlacePolicy

    return ScriptedPickPlacePolicy(PickPlaceParams(close_height=0.04), name="scripted-pick-place-weak")


def _oracle() -> PolicyModel:
    from services.policy_worker.models.oracle import OraclePolicy

    return OraclePolicy()


def _do_nothing() -> PolicyModel:
    from services.policy_worker.models.do_nothing import DoNothingPolicy

    return DoNothingPolicy()


def _privileged_state_baseline() -> PolicyModel:
    from services.policy_worker.vla.policy import make_state_policy

    return make_state_policy()


def _zetta_vla_image() -> PolicyModel:
    from services.policy_worker.vla.policy import make_image_policy

    return make_image_policy()


def _openpi() -> PolicyModel:
    from services.policy_worker.openpi.pool import make_openpi_pool

    return make_openpi_pool()


def _lerobot() -> PolicyModel:
    from services.policy_worker.vla.adapter import make_lerobot_adapter

    return make_lerobot_adapter()


FACTORIES: dict[str, Callable[[], PolicyModel]] = {
    "scripted-pick-place": _scripted,
    # The same, weakened: it closes its gripper 4 cm above the grasp point (a known failure a bounded
    # regrasp fixes; the evolver's end-to-end test evolves a harness for it).
    "scripted-pick-place-weak": _scripted_weak,
    # One generic skill per BDDL goal predicate on privileged state (models/oracle.py; docs/oracle.md).
    "oracle": _oracle,
    # Zero actions: the control every evolution result is measured against (models/do_nothing.py).
    "do-nothing": _do_nothing,
    # The Zetta VLA (services/policy_worker/vla): camera image + proprioception + instruction.
    "zetta-vla-image": _zetta_vla_image,
    # Its state-based sibling, which reads the simulator's object poses: a baseline, never a default.
    "privileged-state-baseline": _privileged_state_baseline,
    # Forwards to running openpi policy servers (services/policy_worker/openpi; ZETTA_OPENPI_*).
    "openpi": _openpi,
    # A LeRobot policy (any type: tdmpc, pi05, ...) from a local checkpoint directory
    # (services/policy_worker/vla/adapter.py LeRobotAdapter; ZETTA_LEROBOT_*).
    "lerobot": _lerobot,
}


def register_adapter(name: str, factory: Callable[[], PolicyModel]) -> None:
    """Make ``name`` loadable by ``ZETTA_MODELS=name`` (call it from a module imported at start-up,
    e.g. through ``ZETTA_POLICY_PLUGINS``); the built model is served under that name."""

    def build() -> PolicyModel:
        model = factory()
        model.name = name
        return model

    FACTORIES[name] = build


def load_model(name: str) -> PolicyModel:
    """Build a served model by name."""
    try:
        factory = FACTORIES[name]
    except KeyError:
        raise UnknownModelError(f"unknown model {name!r}; known models: {', '.join(sorted(FACTORIES))}") from None
    return factory()
