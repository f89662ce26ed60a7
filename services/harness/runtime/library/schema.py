"""Typed parameter schemas of the library's templates.

The evolver searches over the library's predicates and recoveries as templates: it needs to know,
for each, which parameters exist, their type and the range worth searching. A package that sets a
parameter outside its range, or one that does not exist, is rejected when the harness is built,
not in the middle of an episode.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any


class ParamError(ValueError):
    """A template was given a parameter it does not have, or a value outside its range."""


@dataclass(frozen=True)
class Param:
    """One tunable parameter: its default, the closed range [low, high] and its kind."""

    default: float
    low: float
    high: float
    kind: str = "float"  # "float" or "int"
    doc: str = ""

    def check(self, name: str, value: Any) -> float:
        """The value as the parameter's kind, or :class:`ParamError`."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ParamError(f"parameter {name!r} must be a number, got {value!r}")
        if self.kind == "int" and int(value) != value:
            raise ParamError(f"parameter {name!r} must be an integer, got {value!r}")
        if not self.low <= value <= self.high:
            raise ParamError(f"parameter {name!r} = {value} is outside [{self.low}, {self.high}]")
        return int(value) if self.kind == "int" else float(value)


@dataclass(frozen=True)
class PredicateSpec:
    """A predicate template: ``fn(window, params)`` returns the evidence details when it holds."""

    name: str
    fn: Callable[..., Mapping[str, float] | None]
    params: Mapping[str, Param]
    doc: str
    #: Whether the evidence implies the task object is held (True), not held (False) or says
    #: nothing about it (None): a recovery that needs the object in hand is no answer to a drop.
    holding: bool | None = None


@dataclass(frozen=True)
class RecoverySpec:
    """A recovery template: ``factory(params)`` builds a fresh recovery for one intervention."""

    name: str
    factory: Callable[[Mapping[str, float]], Any]
    params: Mapping[str, Param]
    doc: str


def resolve(schema: Mapping[str, Param], overrides: Mapping[str, Any], what: str) -> dict[str, float]:
    """Defaults of ``schema`` with ``overrides`` applied and checked."""
    unknown = sorted(set(overrides) - set(schema))
    if unknown:
        raise ParamError(f"{what}: unknown parameter(s) {', '.join(unknown)}; known: {', '.join(sorted(schema))}")
    out = {k: (int(p.default) if p.kind == "int" else float(p.default)) for k, p in schema.items()}
    for k, v in overrides.items():
        try:
            out[k] = schema[k].check(k, v)
        except ParamError as exc:
            raise ParamError(f"{what}: {exc}") from None
    return out
