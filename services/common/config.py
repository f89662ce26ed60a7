"""Environment-variable configuration that fails fast, naming every bad variable at once.

Services read all their settings at start-up through :class:`EnvReader`; a typo in a deployment
must stop the process with a message that names the variable, not surface later as a timeout.
"""

from __future__ import annotations

import builtins
import os
from collections.abc import Mapping
from typing import TypeVar

from services.common.cpus import allowed_cpus, format_cpu_list, parse_cpu_list

#: A bounded number setting (the methods named ``int`` and ``float`` shadow the builtins in the class).
_N = TypeVar("_N", int, float)


class ConfigError(ValueError):
    """One or more environment variables are missing or malformed."""


class EnvReader:
    """Reads typed settings and collects every problem before reporting them together."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        self._env = os.environ if environ is None else environ
        self._errors: list[str] = []

    def _raw(self, name: str, default: str | None, required: bool) -> str | None:
        value = self._env.get(name)
        if value is None or value == "":
            if required:
                self._errors.append(f"{name} is required but not set")
            return default
        return value

    def str(self, name: str, default: str = "", required: bool = False) -> str:
        """A string setting."""
        value = self._raw(name, default, required)
        return default if value is None else value

    def int(self, name: builtins.str, default: builtins.int, minimum: builtins.int | None = None,
            maximum: builtins.int | None = None) -> builtins.int:
        """An integer setting within optional bounds."""
        raw = self._raw(name, None, False)
        if raw is None:
            return default
        try:
            value = int(raw)
        except ValueError:
            self._errors.append(f"{name}={raw!r} is not an integer")
            return default
        return self._bounded(name, value, minimum, maximum)

    def float(self, name: builtins.str, default: builtins.float, minimum: builtins.float | None = None,
              maximum: builtins.float | None = None) -> builtins.float:
        """A float setting within optional bounds."""
        raw = self._raw(name, None, False)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            self._errors.append(f"{name}={raw!r} is not a number")
            return default
        return self._bounded(name, value, minimum, maximum)

    def bool(self, name: builtins.str, default: builtins.bool) -> builtins.bool:
        """A boolean setting: 1/0, true/false, yes/no, on/off."""
        raw = self._raw(name, None, False)
        if raw is None:
            return default
        lowered = raw.strip().lower()
        if lowered in ("1", "true", "yes", "on"):
            return True
        if lowered in ("0", "false", "no", "off"):
            return False
        self._errors.append(f"{name}={raw!r} is not a boolean (use true or false)")
        return default

    def address(self, name: builtins.str, default: builtins.str = "", required: builtins.bool = False) -> builtins.str:
        """A host:port address."""
        value = self.str(name, default, required)
        if value and (":" not in value or not value.rsplit(":", 1)[1].isdigit()):
            self._errors.append(f"{name}={value!r} is not a host:port address")
        return value

    def cpus(self, name: builtins.str) -> frozenset[builtins.int] | None:
        """A CPU list (``0-3,8``) the process may run on; None when unset."""
        raw = self._raw(name, None, False)
        if raw is None:
            return None
        try:
            cpus = parse_cpu_list(raw)
        except ValueError as exc:
            self._errors.append(f"{name}={raw!r} is not a CPU list like 0-3,8: {exc}")
            return None
        allowed = allowed_cpus()
        if allowed is not None and not cpus <= allowed:
            self._errors.append(f"{name}={raw!r} names CPUs this process may not run on "
                                f"({format_cpu_list(cpus - allowed)}); allowed: {format_cpu_list(allowed)}")
            return None
        return cpus

    def fail(self, message: builtins.str) -> None:
        """Record a problem that involves several variables."""
        self._errors.append(message)

    def _bounded(self, name: builtins.str, value: _N, minimum: _N | None, maximum: _N | None) -> _N:
        if minimum is not None and value < minimum:
            self._errors.append(f"{name}={value} is below the minimum {minimum}")
        if maximum is not None and value > maximum:
            self._errors.append(f"{name}={value} is above the maximum {maximum}")
        return value

    def finish(self, service: builtins.str) -> None:
        """Raise ConfigError listing every problem found so far."""
        if self._errors:
            lines = "\n  ".join(self._errors)
            raise ConfigError(f"{service}: invalid configuration:\n  {lines}")
