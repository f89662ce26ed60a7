"""The allowed import directions between Zetta's packages, and a checker that reads them from the
source (an AST walk, nothing is imported). docs/architecture.md draws the same table.

Every import counts, wherever it sits (module level, inside a function, under ``if TYPE_CHECKING``):
an import deferred into a function is still a dependency, and two modules that need each other
are one module however their imports are placed, so cycles are looked for over all of them.
A module's package ``__init__`` runs before it, so importing ``a.b.c`` also counts as importing
``a.b`` (and ``a``) for cycles.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

#: Source roots: each holds top-level packages.
ROOTS = (".", "clients/python")
#: The packages checked, and what each may import of the others (a prefix allows its submodules;
#: a name ending in "=" allows exactly that module). A package always may import itself.
ALLOWED: dict[str, tuple[str, ...]] = {
    "zetta_wire": (),
    "zetta": ("zetta_wire",),
    "services.common": ("zetta_wire",),
    "services.harness": ("services.common", "zetta_wire"),
    "services.gateway": ("services.common", "zetta_wire"),
    "services.env_worker": ("services.common", "services.harness", "zetta_wire"),
    # The policy worker runs families in-process for its oracle's and training data's episodes:
    # through the families' public API only.
    "services.policy_worker": ("services.common", "zetta_wire", "services.env_worker.families="),
    "services.critic": ("services.common", "services.harness", "zetta_wire"),
    # The evolver drives episodes through the gateway like any client (the SDK's public API) and
    # starts the local stack when no gateway is given; offline (exports, diagnosis) it may read
    # task definitions through the families' public API.
    "services.evolver": ("services.common", "services.harness", "zetta_wire", "zetta=",
                         "services.ops.local_stack=", "services.env_worker.families="),
    # Operations wire the SDK and the services together: the top of the graph.
    "services.ops": ("services", "zetta", "zetta_wire"),
}


@dataclass(frozen=True)
class Import:
    """One import statement's target, resolved to a module of the tree."""

    source: str
    target: str
    line: int


def module_name(root: Path, path: Path) -> str:
    """Dotted name of a source file under a root (a package ``__init__`` is its package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def discover(base: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Every module of the given top-level packages under the roots of ``base``."""
    out: dict[str, Path] = {}
    for rel in ROOTS:
        root = base / rel
        for top in packages:
            pkg = root / top
            if pkg.is_dir():
                for path in sorted(pkg.rglob("*.py")):
                    out[module_name(root, path)] = path
    return out


def _resolve(name: str, modules: Mapping[str, Path]) -> str | None:
    """The longest prefix of ``name`` that is a module of the tree."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def _targets(node: ast.Import | ast.ImportFrom, source: str, is_package: bool, modules: Mapping[str, Path]) -> list[str]:
    if isinstance(node, ast.Import):
        names = [alias.name for alias in node.names]
    else:
        base = node.module or ""
        if node.level:
            pkg = source.split(".") if is_package else source.split(".")[:-1]
            pkg = pkg[: len(pkg) - (node.level - 1)]
            base = ".".join([*pkg, base] if base else pkg)
        names = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
    return [t for t in (_resolve(n, modules) for n in names) if t is not None]


def parse(source: str, filename: str) -> ast.Module:
    """ast.parse of one module (run :func:`check` through :func:`check_in_fresh_process` from tests)."""
    return ast.parse(source, filename=filename)


def imports_of(modules: Mapping[str, Path]) -> list[Import]:
    """Every import between modules of the tree."""
    out: list[Import] = []
    for name, path in modules.items():
        tree = parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _targets(node, name, path.name == "__init__.py", modules):
                    if target != name:
                        out.append(Import(name, target, node.lineno))
    return out


def owner(module: str) -> str | None:
    """The checked package a module belongs to (the longest rule prefix), None when unchecked."""
    best = None
    for pkg in ALLOWED:
        if (module == pkg or module.startswith(pkg + ".")) and (best is None or len(pkg) > len(best)):
            best = pkg
    return best


def _allowed(target: str, rules: Iterable[str]) -> bool:
    for rule in rules:
        if rule.endswith("="):
            if target == rule[:-1]:
                return True
        elif target == rule or target.startswith(rule + "."):
            return True
    return False


def direction_violations(imports: Iterable[Import], path_of: Mapping[str, Path]) -> list[str]:
    """Imports that cross from one checked package into another the table does not allow."""
    out: list[str] = []
    for imp in dict.fromkeys(imports):
        src, dst = owner(imp.source), owner(imp.target)
        if src is None or dst is None or src == dst or _allowed(imp.target, ALLOWED[src]):
            continue
        out.append(f"{path_of[imp.source]}:{imp.line}: {imp.source} imports {imp.target} "
                   f"({src} may import only {', '.join(ALLOWED[src]) or 'nothing of the others'})")
    return out


def cycles(imports: Iterable[Import]) -> list[list[str]]:
    """Import cycles (each strongly connected component of two or more modules, as a sorted list),
    counting a module's import of ``a.b.c`` as one of ``a.b`` too."""
    graph: dict[str, set[str]] = {}
    for imp in imports:
        targets = {imp.target}
        parts = imp.target.split(".")
        targets |= {".".join(parts[:k]) for k in range(1, len(parts))}
        for t in targets:
            if t != imp.source and not imp.source.startswith(t + "."):
                graph.setdefault(imp.source, set()).add(t)
    return [sorted(c) for c in _strongly_connected(graph) if len(c) > 1]


def _strongly_connected(graph: Mapping[str, set[str]]) -> list[list[str]]:
    """Tarjan's algorithm, iterative (the graph has hundreds of modules)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.get(start, ()))))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == node:
                            break
                    out.append(comp)
            elif nxt not in index:
                index[nxt] = low[nxt] = counter
                counter += 1
                stack.append(nxt)
                on_stack.add(nxt)
                work.append((nxt, iter(sorted(graph.get(nxt, ())))))
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
    return out


def check(base: Path, packages: Iterable[str] = ("services", "zetta", "zetta_wire", "bench")) -> list[str]:
    """Every direction violation and every cycle in the tree at ``base``, as readable lines."""
    modules = discover(base, packages)
    imports = imports_of(modules)
    problems = direction_violations(imports, modules)
    problems += [f"import cycle: {' <-> '.join(c)}" for c in cycles(imports)]
    return problems



def check_in_fresh_process(base: Path) -> list[str]:
    """:func:`check` in a new interpreter. Late in a long test process CPython 3.11.7's AST validator
    raises a spurious SystemError ("AST constructor recursion depth mismatch") from ast.parse, on
    any thread; a fresh process parses from a clean state."""
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-m", "tests.import_graph", str(base)], capture_output=True, text=True,
                          cwd=root, timeout=120, env={**os.environ, "PYTHONPATH": str(root)})
    if proc.returncode != 0:
        raise RuntimeError(f"the import check failed to run: {proc.stderr.strip()[-2000:]}")
    return list(json.loads(proc.stdout))


if __name__ == "__main__":
    print(json.dumps(check(Path(sys.argv[1]))))
