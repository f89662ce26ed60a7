"""Reading a family's config options (configs arrive as protobuf Structs, where every number is a
float), with errors that name the family and the option."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from services.env_worker.families.contract import ConfigError


def check_keys(family: str, config: Mapping[str, Any], allowed: Sequence[str]) -> None:
    """Reject keys a family does not know, since a typo would otherwise silently use a default."""
    if not isinstance(config, Mapping):
        raise ConfigError(f"{family}: config must be a mapping, got {type(config).__name__}")
    unknown = sorted(set(config) - set(allowed))
    if unknown:
        raise ConfigError(f"{family}: unknown config keys {unknown}; valid keys: {sorted(allowed)}")


#: Upper bounds of the size-like options every family shares: a config is client input, and an
#: unbounded ``camera_size`` or ``object_state_dim`` would have the env worker allocate whatever a
#: client asks for (1e9 is 4 GB per observation), an unbounded ``settle_steps`` would hold a slot
#: for hours, and a ``max_steps`` beyond int32 cannot be sent back in a ResetResult.
MAX_CAMERA_SIZE = 1024
MAX_OBJECT_STATE_DIM = 4096
MAX_EPISODE_STEPS = 100_000
MAX_SETTLE_STEPS = 1000
MAX_CONTROL_FREQ = 1000


def int_option(family: str, config: Mapping[str, Any], key: str, default: int, minimum: int = 0,
               maximum: int | None = None) -> int:
    """An integer option that also accepts integral floats, as JSON and protobuf Structs send them,
    between ``minimum`` and ``maximum`` (inclusive; no upper bound when None)."""
    value = config.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not float(value).is_integer():
        raise ConfigError(f"{family}: {key} must be an integer, got {value!r}")
    if value < minimum:
        raise ConfigError(f"{family}: {key} must be >= {minimum}, got {value!r}")
    if maximum is not None and value > maximum:
        raise ConfigError(f"{family}: {key} must be <= {maximum}, got {value!r}")
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
