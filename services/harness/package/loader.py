"""Loads a harness package: layout, SKILL.md, plans, params, then the checked tool modules.

Every Python file passes the static checks (services/harness/package/safety.py) before any of
them is imported; a package with one bad file is rejected whole, with every reason. Accepted
modules are imported under a private module name made of the content hash and a load counter,
so two versions of a package (or two loads of the same one) never share module state. Their
builtins leave out the forbidden names and only let ``import`` reach the allowlist, a second
guard behind the static checks.
"""

from __future__ import annotations

import builtins
import itertools
import linecache
import sys
import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType, ModuleType
from typing import Any

from services.harness.package import format as fmt
from services.harness.package.errors import PackageRejected, Problem, reject
from services.harness.package.model import LoadedPackage
from services.harness.package.safety import FORBIDDEN_NAMES, check_source, is_allowed_import

_load_counter = itertools.count(1)


def _guarded_import(name: str, globals: Any = None, locals: Any = None, fromlist: Any = (), level: int = 0) -> ModuleType:  # the signature of __import__
    """``__import__`` for harness modules: the allowlist only, absolute imports only."""
    if level != 0 or not is_allowed_import(name):
        raise ImportError(f"harness code may not import {name!r}")
    return builtins.__import__(name, globals, locals, fromlist, level)


def _safe_builtins() -> dict[str, Any]:
    table = {k: v for k, v in vars(builtins).items() if k not in FORBIDDEN_NAMES}
    table["__import__"] = _guarded_import
    return table


_SAFE_BUILTINS = _safe_builtins()


def _import_tool(stem: str, path: str, source: str, module_prefix: str, origin: str) -> ModuleType:
    """Execute one checked module as ``<module_prefix>_<stem>``; a failure at import is a rejection."""
    module_name = f"{module_prefix}_{stem}"
    filename = f"<harness {origin}>/{path}"
    module = ModuleType(module_name)
    module.__dict__["__builtins__"] = _SAFE_BUILTINS
    module.__dict__["__file__"] = filename
    linecache.cache[filename] = (len(source), None, source.splitlines(keepends=True), filename)
    sys.modules[module_name] = module
    try:
        exec(compile(source, filename, "exec", dont_inherit=True), module.__dict__)  # checked code
    except Exception as exc:  # noqa: BLE001 - any error at import rejects the package
        sys.modules.pop(module_name, None)
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == filename]
        line = frames[-1].lineno if frames else 0
        raise PackageRejected([Problem(path, line or 0, f"import failed: {type(exc).__name__}: {exc}")]) from None
    return module


def _tables(files: Mapping[str, bytes], subdir: str) -> dict[str, dict[str, Any]]:
    """plans/*.toml or params/*.toml by file stem, with every parse error collected."""
    tables: dict[str, dict[str, Any]] = {}
    problems: list[Problem] = []
    for path in sorted(p for p in files if p.startswith(subdir + "/")):
        try:
            tables[path[len(subdir) + 1 : -len(".toml")]] = fmt.parse_toml(path, files[path])
        except PackageRejected as exc:
            problems.extend(exc.problems)
    if problems:
        raise PackageRejected(problems)
    return tables


@dataclass(frozen=True)
class CheckedFiles:
    """A package that passed every check short of importing its tools."""

    skill: dict[str, Any]
    body: str
    plans: dict[str, dict[str, Any]]
    params: dict[str, dict[str, Any]]
    sources: dict[str, str]


def check_files(files: Mapping[str, bytes], max_bytes: int = fmt.MAX_PACKAGE_BYTES) -> CheckedFiles:
    """Everything but the import: layout, SKILL.md, TOML syntax and the static code checks,
    with every problem of every file collected into one rejection."""
    fmt.check_layout(files, max_bytes)
    problems: list[Problem] = []
    skill: dict[str, Any] = {}
    body = ""
    try:
        skill, body = fmt.split_skill(files[fmt.SKILL])
    except PackageRejected as exc:
        problems.extend(exc.problems)
    tables: dict[str, dict[str, dict[str, Any]]] = {}
    for subdir in ("plans", "params"):
        try:
            tables[subdir] = _tables(files, subdir)
        except PackageRejected as exc:
            problems.extend(exc.problems)
    sources: dict[str, str] = {}
    for path in sorted(p for p in files if p.startswith("tools/")):
        try:
            text = files[path].decode("utf-8")
        except UnicodeDecodeError:
            problems.append(Problem(path, 0, "not UTF-8 text"))
            continue
        try:
            check_source(path, text)
        except PackageRejected as exc:
            problems.extend(exc.problems)
            continue
        sources[path[len("tools/") : -len(".py")]] = text
    if problems:
        raise PackageRejected(problems)
    return CheckedFiles(skill, body, tables["plans"], tables["params"], sources)


def load_files(files: Mapping[str, bytes], max_bytes: int = fmt.MAX_PACKAGE_BYTES,
               import_tools: bool = True) -> LoadedPackage:
    """Check and load a package given as bytes by relative path (what the registry stores).

    A manifest.json among the files supplies the version and must carry the files' content
    hash; without one (a package still being written) the version is empty. ``import_tools``
    False: the tools pass the static checks but are not imported in this process (``tools`` is
    empty, ``sources`` holds them): a runtime built from it runs them in its sandbox child."""
    checked = check_files(files, max_bytes)
    digest = fmt.content_hash(files)
    manifest: dict[str, Any] = {}
    if fmt.MANIFEST in files:
        manifest = fmt.parse_manifest(files[fmt.MANIFEST])
        if manifest.get("content_hash") != digest:
            raise reject(fmt.MANIFEST, f"content_hash {manifest.get('content_hash')!r} does not match the files ({digest}); "
                                       "a published package was edited")
    name = checked.skill["name"]
    version = str(manifest.get("version", ""))
    prefix = f"_zetta_harness_{digest[:12]}_{next(_load_counter)}"
    origin = f"{name}@{version}" if version else name
    tools: dict[str, ModuleType] = {}
    try:
        for stem, source in checked.sources.items() if import_tools else ():
            tools[stem] = _import_tool(stem, f"tools/{stem}.py", source, prefix, origin)
    except PackageRejected:
        for stem in tools:
            sys.modules.pop(f"{prefix}_{stem}", None)
        raise
    return LoadedPackage(
        name=name,
        version=version,
        content_hash=digest,
        skill=MappingProxyType(checked.skill),
        skill_text=checked.body,
        params=MappingProxyType(checked.params),
        plans=MappingProxyType(checked.plans),
        tools=MappingProxyType(tools),
        manifest=MappingProxyType(manifest),
        sources=MappingProxyType(dict(checked.sources)),
    )


def load_package(path: str | Path, max_bytes: int = fmt.MAX_PACKAGE_BYTES, import_tools: bool = True) -> LoadedPackage:
    """Check and load the package directory at ``path``; raises PackageRejected with every reason."""
    return load_files(fmt.read_tree(Path(path)), max_bytes, import_tools)


def unload(package: LoadedPackage) -> None:
    """Drop the package's private module names from ``sys.modules`` once no new runtime will be
    built from it (objects already built keep their modules alive)."""
    for module in package.tools.values():
        sys.modules.pop(module.__name__, None)
