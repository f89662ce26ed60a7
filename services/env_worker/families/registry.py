"""Families by name: registration, lazy import of the built-in ones, and the canonical config key
that makes two equivalent configs one resource-sharing group."""

from __future__ import annotations

import importlib
import json
import threading
from collections.abc import Mapping
from typing import Any

from services.env_worker.families.contract import EnvFamily, UnknownFamilyError


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
