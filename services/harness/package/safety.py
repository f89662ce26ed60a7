"""Static checks on harness code before it is ever imported.

Critics and tools are written by the evolver's template search or by an LLM, and they run
inside the env worker and the critic service at every env step. Before import, each module's
syntax tree must show that it only imports an allowlist of pure computation modules and cannot
reach the usual escape hatches (dynamic code, files, reflection through dunder attributes or
getattr, modules held by allowed modules, frames, private attributes of anything but self). The checks guard against careless or confused code, not against a determined attacker;
the runtime adds a time budget per critic call (docs/harness.md, "Safety").
"""

from __future__ import annotations

import ast
import re

from services.harness.package.errors import PackageRejected, Problem

#: Modules harness code may import, exactly by these names.
ALLOWED_IMPORTS: frozenset[str] = frozenset(
    {
        "__future__",
        "math",
        "numpy",
        "dataclasses",
        "typing",
        "collections",
        "collections.abc",
        "functools",
        "itertools",
        "services.harness.runtime.api",
    }
)
#: Packages harness code may import together with every submodule.
ALLOWED_PACKAGES: frozenset[str] = frozenset({"services.harness.runtime.library"})
#: Built-in names that run code, touch files, reflect on objects or wait on a terminal; never referenced.
FORBIDDEN_NAMES: frozenset[str] = frozenset(
    {
        "eval",
        "exec",
        "compile",
        "open",
        "__import__",
        "globals",
        "locals",
        "getattr",
        "setattr",
        "delattr",
        "vars",
        "breakpoint",
        "input",
        "exit",
        "quit",
        "help",
        "license",
        "credits",
        "copyright",
    }
)
#: Attributes that reach files, pickles or raw memory through numpy (np.load, arr.tofile, ...).
FORBIDDEN_ATTRIBUTES: frozenset[str] = frozenset(
    {
        "load",
        "save",
        "savez",
        "savez_compressed",
        "fromfile",
        "tofile",
        "loadtxt",
        "savetxt",
        "genfromtxt",
        "fromregex",
        "memmap",
        "dump",
        "DataSource",
        "ctypes",
        "ctypeslib",
        "f2py",
        "lib",
        "testing",
    }
)
#: Attributes that lead out of the allowlist: modules that allowed modules hold (``typing.sys``,
#: ``dataclasses.inspect``, ``numpy.core``), frames and code objects (a running generator's
#: ``gi_frame.f_back.f_globals`` is its caller's globals), string-named attribute access
#: (``operator.attrgetter``) and ``str.format``, whose fields walk attributes of its arguments
#: even when the format string is built at run time (f-strings remain).
ESCAPE_ATTRIBUTES: frozenset[str] = frozenset(
    {
        "sys", "os", "builtins", "modules", "inspect", "types", "operator", "importlib", "subprocess",
        "core", "contextlib", "warnings", "copyreg", "gc",
        "gi_frame", "gi_code", "cr_frame", "cr_code", "ag_frame", "ag_code", "f_back", "f_globals", "f_locals",
        "f_builtins", "f_code", "tb_frame", "tb_next", "co_code",
        "attrgetter", "methodcaller", "format", "format_map",
    }
)
#: A str.format field that walks attributes of its argument, e.g. "{0.__class__}".
_FORMAT_DUNDER = re.compile(r"\{[^{}]*__")


def is_allowed_import(module: str) -> bool:
    """Whether ``module`` is on the allowlist (packages count with their submodules)."""
    return module in ALLOWED_IMPORTS or any(module == p or module.startswith(p + ".") for p in ALLOWED_PACKAGES)


def _is_dunder(name: str) -> bool:
    return len(name) > 4 and name.startswith("__") and name.endswith("__")


class _Checker(ast.NodeVisitor):
    """Collects every violation in one module."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._found: list[tuple[int, int, int, Problem]] = []

    @property
    def problems(self) -> list[Problem]:
        """In source order (an outer node is visited before the inner one written first)."""
        return [f[3] for f in sorted(self._found, key=lambda f: f[:3])]

    def _add(self, node: ast.AST, reason: str) -> None:
        line, col, end = getattr(node, "lineno", 0), getattr(node, "col_offset", 0), getattr(node, "end_col_offset", 0)
        self._found.append((line, col, end or 0, Problem(self.path, line, reason)))

    def _check_module(self, node: ast.AST, module: str) -> None:
        if not is_allowed_import(module):
            allowed = ", ".join(sorted(ALLOWED_IMPORTS | {p + ".*" for p in ALLOWED_PACKAGES}))
            self._add(node, f"import of '{module}' is not allowed (allowed: {allowed})")

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._check_module(node, alias.name)
        self.generic_visit(node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            self._add(node, "relative imports are not allowed; a tool module may only import the allowlist")
        elif node.module is not None:
            self._check_module(node, node.module)
        for alias in node.names:
            if alias.name == "*":
                self._add(node, f"star import from '{node.module}' is not allowed; import names explicitly")
            elif alias.name in FORBIDDEN_NAMES or alias.name in FORBIDDEN_ATTRIBUTES or _is_dunder(alias.name):
                self._add(node, f"importing '{alias.name}' is not allowed")
        self.generic_visit(node)

    def visit_Name(self, node: ast.Name) -> None:
        if node.id in FORBIDDEN_NAMES:
            self._add(node, f"use of '{node.id}' is not allowed")
        elif _is_dunder(node.id):
            self._add(node, f"use of the dunder name '{node.id}' is not allowed")
        self.generic_visit(node)

    def visit_Attribute(self, node: ast.Attribute) -> None:
        if _is_dunder(node.attr):
            self._add(node, f"access to the dunder attribute '.{node.attr}' is not allowed")
        elif node.attr in FORBIDDEN_ATTRIBUTES:
            self._add(node, f"access to '.{node.attr}' is not allowed (file, pickle or raw-memory access)")
        elif node.attr in ESCAPE_ATTRIBUTES:
            hint = "; use an f-string" if node.attr in ("format", "format_map") else ""
            self._add(node, f"access to '.{node.attr}' is not allowed (it leads out of the allowed modules{hint})")
        elif node.attr.startswith("_") and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
            self._add(node, f"access to the private attribute '.{node.attr}' is only allowed on self or cls")
        self.generic_visit(node)

    def visit_Constant(self, node: ast.Constant) -> None:
        if isinstance(node.value, str) and _FORMAT_DUNDER.search(node.value):
            self._add(node, "a format field that reaches a dunder attribute ('{x.__...}') is not allowed")
        self.generic_visit(node)


def check_source(path: str, source: str) -> ast.Module:
    """Parse and check one module; raises PackageRejected listing every violation in it."""
    try:
        tree = ast.parse(source, filename=path)
    except SyntaxError as exc:
        raise PackageRejected([Problem(path, exc.lineno or 0, f"syntax error: {exc.msg}")]) from None
    except (RecursionError, MemoryError, ValueError) as exc:
        raise PackageRejected([Problem(path, 0, f"cannot be parsed: {type(exc).__name__}: {exc}")]) from None
    checker = _Checker(path)
    checker.visit(tree)
    problems = checker.problems
    if problems:
        raise PackageRejected(problems)
    return tree
