"""What changed between two harness versions: per-file unified diffs and changed parameters.

Reviewing an evolved harness means reading what the repair loop touched; thresholds deserve a
line each (old -> new) because a bare text diff of TOML hides which key of which table moved.
"""

from __future__ import annotations

import difflib
import json
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from services.harness.package import format as fmt


@dataclass(frozen=True)
class FileChange:
    """One file that differs: ``change`` is "added", "removed" or "modified"."""

    path: str
    change: str
    unified_diff: str


@dataclass(frozen=True)
class ParamChange:
    """One params key whose value differs; a side without the key has ``None`` JSON."""

    file: str
    key: str
    base_json: str | None
    head_json: str | None


def _text(data: bytes | None) -> list[str] | None:
    if data is None:
        return []
    try:
        return data.decode("utf-8").splitlines(keepends=True)
    except UnicodeDecodeError:
        return None


def file_changes(base: Mapping[str, bytes], head: Mapping[str, bytes], base_label: str, head_label: str) -> list[FileChange]:
    """Changed files in path order (manifest.json is not compared: it always differs)."""
    out: list[FileChange] = []
    for path in sorted((set(base) | set(head)) - {fmt.MANIFEST}):
        old, new = base.get(path), head.get(path)
        if old == new:
            continue
        change = "added" if old is None else "removed" if new is None else "modified"
        old_lines, new_lines = _text(old), _text(new)
        diff = ""
        if old_lines is not None and new_lines is not None:
            diff = "".join(
                difflib.unified_diff(old_lines, new_lines, f"{base_label}/{path}", f"{head_label}/{path}")
            )
        out.append(FileChange(path, change, diff))
    return out


def _flatten(table: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in table.items():
        dotted = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from _flatten(value, dotted + ".")
        else:
            yield dotted, value


def _params(files: Mapping[str, bytes]) -> dict[tuple[str, str], Any]:
    values: dict[tuple[str, str], Any] = {}
    for path, data in files.items():
        if path.startswith("params/") and path.endswith(".toml"):
            stem = path[len("params/") : -len(".toml")]
            for key, value in _flatten(tomllib.loads(data.decode("utf-8"))):
                values[(stem, key)] = value
    return values


def _json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=str)


def param_changes(base: Mapping[str, bytes], head: Mapping[str, bytes]) -> list[ParamChange]:
    """Changed params keys by file and dotted key; both sides are stored packages, so valid TOML."""
    old, new = _params(base), _params(head)
    out: list[ParamChange] = []
    missing = object()
    for file, key in sorted(set(old) | set(new)):
        a, b = old.get((file, key), missing), new.get((file, key), missing)
        if a is not missing and b is not missing and _json(a) == _json(b):
            continue
        out.append(
            ParamChange(file, key, None if a is missing else _json(a), None if b is missing else _json(b))
        )
    return out
