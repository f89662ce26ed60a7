"""The env families' public API: what code outside the env worker may use to run a family in its
own process (the oracle's and the training data's episodes, benchmarks, the local gym env).

Families themselves are written against the modules behind it: ``contract`` (the interfaces),
``registry``, ``options``, ``schema`` (the canonical manipulation observation), ``pool`` and
``episode`` (the slot base class).
"""

from services.env_worker.families.contract import (
    ConfigError,
    EnvFamily,
    EpisodeError,
    SlotClosedError,
    ResetError,
    ResetSpec,
    SAMPLED_LAYOUT,
    Slot,
    StepOutcome,
    UnknownFamilyError,
)
from services.env_worker.families.registry import canonical_config_key, family_names, get_family, register_family
from services.env_worker.rendering import select_gl_backend


def libero_instruction(suite_name: str, task: str) -> str | None:
    """The instruction a LIBERO session of (suite, task) is given, read from LIBERO's task files
    without building an env (offline tools name episodes by it); None for an unknown suite."""
    from services.env_worker.families.libero import libero_instruction as lookup

    return lookup(suite_name, task)


def is_libero_pro_variant(suite_name: str) -> bool:
    """Whether a LIBERO suite name is one of LIBERO-PRO's perturbations (``libero_goal_swap``, ...)."""
    from services.env_worker.families.libero import LIBERO_PRO_VARIANTS

    return suite_name.endswith(tuple(f"_{v}" for v in LIBERO_PRO_VARIANTS))

__all__ = [
    "ConfigError",
    "EnvFamily",
    "EpisodeError",
    "SlotClosedError",
    "ResetError",
    "ResetSpec",
    "SAMPLED_LAYOUT",
    "Slot",
    "StepOutcome",
    "UnknownFamilyError",
    "canonical_config_key",
    "family_names",
    "get_family",
    "is_libero_pro_variant",
    "libero_instruction",
    "register_family",
    "select_gl_backend",
]
