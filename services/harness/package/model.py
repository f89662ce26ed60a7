"""A harness package once loaded and checked: what the runtime builds a harness from.

The on-disk format is documented in docs/harness.md. Loading (services/harness/package/loader.py)
checks every Python file before importing it; this dataclass only ever holds checked content.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import ModuleType
from typing import Any


@dataclass(frozen=True)
class LoadedPackage:
    """One immutable harness version: ``skill`` is SKILL.md's TOML front matter (``skill_text``
    the markdown after it), ``params`` the merged params/*.toml (file stem -> table), ``plans``
    the merged plans/*.toml (file stem -> table), ``tools`` the imported tools/*.py modules by
    stem, ``manifest`` manifest.json (empty, and ``version`` "", for a directory never published),
    ``sources`` the tools' text by stem (what the runtime checks the signals a package reads on)."""

    name: str
    version: str
    content_hash: str
    skill: Mapping[str, Any]
    skill_text: str
    params: Mapping[str, Mapping[str, Any]]
    plans: Mapping[str, Mapping[str, Any]]
    tools: Mapping[str, ModuleType]
    manifest: Mapping[str, Any] = field(default_factory=dict)
    sources: Mapping[str, str] = field(default_factory=dict)
