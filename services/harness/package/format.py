"""The on-disk harness package format: layout, SKILL.md front matter, content hash, manifest.

One module owns these rules so that the loader, the registry and the SDK agree on what a package
is and on its hash: the hash is the package's identity (identical content publishes to the same
version), so it must not depend on who computed it or on file-system order.

Layout (docs/harness.md):
  SKILL.md              TOML front matter between two ``+++`` lines, then free markdown
  README.md             optional, free text
  tools/<name>.py       critic and tool modules
  plans/<name>.toml     recovery playbooks
  params/<name>.toml    thresholds
  manifest.json         written by the registry at publish; not part of the hash
"""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from services.harness.package.errors import PackageRejected, Problem, reject

SKILL = "SKILL.md"
MANIFEST = "manifest.json"
README = "README.md"
#: Directory -> the suffix its files must have.
SUBDIRS: dict[str, str] = {"tools": ".py", "plans": ".toml", "params": ".toml"}
#: Names of packages and of files under the subdirectories (they become module and table names).
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
STEM_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")
FRONT_MATTER_FENCE = "+++"
#: Default ceiling on a package's total size; the critic service can lower or raise it.
MAX_PACKAGE_BYTES = 8 * 1024 * 1024
MAX_FILES = 256


def check_layout(files: Mapping[str, bytes], max_bytes: int = MAX_PACKAGE_BYTES) -> None:
    """Every path is relative, inside the layout and well named; sizes are bounded.

    Paths come from clients over the network, so nothing here may ever resolve outside the
    package (no "..", no absolute paths, no backslashes)."""
    problems: list[Problem] = []
    if SKILL not in files:
        problems.append(Problem(SKILL, 0, "missing: every package needs SKILL.md"))
    if len(files) > MAX_FILES:
        problems.append(Problem(".", 0, f"{len(files)} files; at most {MAX_FILES} are allowed"))
    total = sum(len(b) for b in files.values())
    if total > max_bytes:
        problems.append(Problem(".", 0, f"{total} bytes in all; at most {max_bytes} are allowed"))
    for path in sorted(files):
        parts = path.split("/")
        if path in (SKILL, MANIFEST, README):
            continue
        if len(parts) == 2 and parts[0] in SUBDIRS:
            suffix = SUBDIRS[parts[0]]
            stem = parts[1][: -len(suffix)] if parts[1].endswith(suffix) else ""
            if stem and STEM_RE.match(stem):
                continue
            problems.append(Problem(path, 0, f"files in {parts[0]}/ must be named <identifier>{suffix}"))
            continue
        problems.append(
            Problem(path, 0, "not part of the package layout (SKILL.md, README.md, tools/*.py, plans/*.toml, params/*.toml)")
        )
    if problems:
        raise PackageRejected(problems)


def read_tree(root: Path) -> dict[str, bytes]:
    """The files of a package directory by relative POSIX path.

    Python byte-code caches and hidden files (editor swap files, .DS_Store) are skipped: they are
    not content. Symbolic links are refused, since they could pull in files from elsewhere."""
    root = Path(root)
    if not root.is_dir():
        raise reject(str(root), "not a directory")
    files: dict[str, bytes] = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(part.startswith(".") or part == "__pycache__" for part in rel.parts):
            continue
        if path.is_symlink():
            raise reject(rel.as_posix(), "symbolic links are not allowed in a package")
        if path.is_file():
            files[rel.as_posix()] = path.read_bytes()
    return files


def content_hash(files: Mapping[str, bytes]) -> str:
    """Hex SHA-256 over every file but manifest.json, in sorted path order.

    Each file contributes its UTF-8 path, a NUL byte, its length as 8 big-endian bytes and its
    bytes, so no two different packages can produce the same byte stream."""
    digest = hashlib.sha256()
    for path in sorted(p for p in files if p != MANIFEST):
        data = files[path]
        digest.update(path.encode("utf-8"))
        digest.update(b"\0")
        digest.update(len(data).to_bytes(8, "big"))
        digest.update(data)
    return digest.hexdigest()


def _decode_text(path: str, data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise reject(path, f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def _toml_problem(path: str, exc: tomllib.TOMLDecodeError, text: str, line_offset: int) -> Problem:
    """tomllib reports '(at line L, column C)' or '(at end of document)' inside its message;
    turn that into a file-relative line."""
    message = str(exc)
    match = re.search(r"\s*\(at line (\d+), column \d+\)", message)
    if match:
        line = int(match.group(1))
    else:
        match = re.search(r"\s*\(at end of document\)", message)
        line = max(1, len(text.splitlines())) if match else 0
    reason = message.replace(match.group(0), "") if match else message
    return Problem(path, line + line_offset if line else 0, f"invalid TOML: {reason}")


def parse_toml(path: str, data: bytes) -> dict[str, Any]:
    """One plans/ or params/ file as a table."""
    text = _decode_text(path, data)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PackageRejected([_toml_problem(path, exc, text, 0)]) from None


def split_skill(data: bytes) -> tuple[dict[str, Any], str]:
    """SKILL.md's front matter (a TOML table) and the markdown after it."""
    text = _decode_text(SKILL, data)
    lines = text.splitlines(keepends=True)
    if not lines or lines[0].strip() != FRONT_MATTER_FENCE:
        raise reject(SKILL, f"must start with a '{FRONT_MATTER_FENCE}' line opening the TOML front matter", 1)
    try:
        end = next(i for i in range(1, len(lines)) if lines[i].strip() == FRONT_MATTER_FENCE)
    except StopIteration:
        raise reject(SKILL, f"front matter is not closed by a '{FRONT_MATTER_FENCE}' line", 1) from None
    front_text = "".join(lines[1:end])
    try:
        front = tomllib.loads(front_text)
    except tomllib.TOMLDecodeError as exc:
        raise PackageRejected([_toml_problem(SKILL, exc, front_text, 1)]) from None
    check_skill(front)
    return front, "".join(lines[end + 1 :])


def _is_str_list(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(v, str) for v in value)


def check_skill(front: Mapping[str, Any]) -> None:
    """Types of the front-matter keys the runtime reads; unknown keys are kept, not refused, so
    the runtime can grow new ones without a format change."""
    problems: list[str] = []
    name = front.get("name")
    if not isinstance(name, str) or not NAME_RE.match(name):
        problems.append("'name' must be a string of letters, digits, '_', '.', '-' (at most 128)")
    if not isinstance(front.get("description"), str):
        problems.append("'description' must be a string")
    if "tasks" in front and not _is_str_list(front["tasks"]):
        problems.append("'tasks' must be a list of strings")
    if "milestones" in front and not isinstance(front["milestones"], dict):
        problems.append("[milestones] must be a table")
    rules = front.get("adjudication", [])
    if not isinstance(rules, list) or not all(isinstance(r, dict) for r in rules):
        problems.append("'adjudication' must be an array of tables ([[adjudication]])")
        rules = []
    for i, rule in enumerate(rules):
        for key in ("evidence", "mode"):
            if not isinstance(rule.get(key), str):
                problems.append(f"adjudication rule {i + 1}: '{key}' must be a string")
        if "priority" in rule and (not isinstance(rule["priority"], int) or isinstance(rule["priority"], bool)):
            problems.append(f"adjudication rule {i + 1}: 'priority' must be an integer")
        for key in ("requires_milestone", "unless_milestone", "missing"):
            if key in rule and not (isinstance(rule[key], str) or _is_str_list(rule[key])):
                problems.append(f"adjudication rule {i + 1}: '{key}' must be a milestone name or a list of them")
    reentry = front.get("reentry", {})
    if not isinstance(reentry, dict):
        problems.append("[reentry] must be a table")
    else:
        gamma = reentry.get("gamma")
        if "gamma" in reentry and (not isinstance(gamma, (int, float)) or isinstance(gamma, bool)):
            problems.append("reentry.gamma must be a number")
        k = reentry.get("k")
        if "k" in reentry and (not isinstance(k, int) or isinstance(k, bool) or k < 1):
            problems.append("reentry.k must be a positive integer")
        if "clears" in reentry and not _is_str_list(reentry["clears"]):
            problems.append("reentry.clears must be a list of evidence kinds (strings)")
    if problems:
        raise PackageRejected([Problem(SKILL, 0, p) for p in problems])


def manifest_bytes(manifest: Mapping[str, Any]) -> bytes:
    """The canonical manifest.json encoding (sorted keys, two-space indent, final newline)."""
    return (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode("utf-8")


def parse_manifest(data: bytes) -> dict[str, Any]:
    """manifest.json as a dict; rejected when it is not a JSON object."""
    try:
        value = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise reject(MANIFEST, f"not valid JSON: {exc}") from None
    if not isinstance(value, dict):
        raise reject(MANIFEST, "must be a JSON object")
    return value
