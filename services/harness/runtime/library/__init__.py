"""The built-in library of generic predicates, recoveries and tools that harness packages build on.

``PREDICATES`` and ``RECOVERIES`` map a template name to its callable and its typed parameter
schema (services/harness/runtime/library/schema.py); the evolver searches over them, and a package
names them in SKILL.md ``[[critics]]`` and plans/*.toml instead of writing code.
"""

from services.harness.runtime.library.predicates import PREDICATES, STABILITY_PARAMS, contact_stability
from services.harness.runtime.library.recoveries import RECOVERIES, EpisodeMemory, Recovery
from services.harness.runtime.library.schema import Param, ParamError, PredicateSpec, RecoverySpec, resolve

__all__ = [
    "PREDICATES",
    "RECOVERIES",
    "STABILITY_PARAMS",
    "EpisodeMemory",
    "Param",
    "ParamError",
    "PredicateSpec",
    "Recovery",
    "RecoverySpec",
    "contact_stability",
    "resolve",
]
