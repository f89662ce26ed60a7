"""The harness package format, its content hash, the loader's checks and the package store.

Every rejection test asserts the file, the line and the reason the loader reports, because that
message is what the repair loop (or a person) acts on.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from services.harness.package import diff as pkg_diff
from services.harness.package import format as fmt
from services.harness.package.errors import PackageRejected
from services.harness.package.loader import load_files, load_package, unload
from services.harness.package.probe import probe_import
from services.harness.package.safety import ALLOWED_IMPORTS, check_source
from services.harness.package.store import PackageStore, StoreCorrupted

SKILL = """+++
name = "hold-when-far"
description = "Holds the arm still while the end effector is outside a radius (a test harness)."
tasks = ["test/reach"]

[runtime]
critic_budget_ms = 50.0
critic_hard_limit_ms = 1000.0

[milestones]
source = "bddl"

[[adjudication]]
evidence = "too_far"
mode = "hold"
priority = 1
unless_milestone = ["released"]

[reentry]
gamma = 0.5
k = 1
clears = ["too_far"]
+++
# hold-when-far

When the end effector leaves the radius in params/reach.toml, freeze until it is back.
"""

REACH = '''"""A critic that proposes holding still when the end effector is beyond a radius."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.harness.runtime.api import Proposal, Window

CALLS = [0]


@dataclass(frozen=True)
class Reading:
    radius: float


def critic_too_far(window: Window, params) -> Proposal | None:
    CALLS[0] += 1
    eef = np.asarray(window.now.obs["robot0_eef_pos"], dtype=np.float64)
    reading = Reading(float(math.sqrt(float(np.sum(eef * eef)))))
    if reading.radius <= params["radius"]:
        return None
    return Proposal("reach.too_far", "too_far", "hold", {"radius": reading.radius})
'''

PLANS = """[hold]
recovery = "freeze"
params = { steps = 2 }
max_steps = 20
max_uses = 3
"""


def example_files(radius: float = 0.5, name: str = "hold-when-far", extra_tool: str = "") -> dict[str, bytes]:
    """A small valid package that the runtime runs: one code critic, one playbook, one param."""
    files = {
        "SKILL.md": SKILL.replace('name = "hold-when-far"', f'name = "{name}"').encode(),
        "tools/reach.py": (REACH + extra_tool).encode(),
        "params/reach.toml": f"radius = {radius}\n[limits]\nmax_speed = 1.0\n".encode(),
        "plans/recoveries.toml": PLANS.encode(),
    }
    return files


def write_tree(root: Path, files: dict[str, bytes]) -> Path:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    return root


def rejection(files: dict[str, bytes]) -> PackageRejected:
    with pytest.raises(PackageRejected) as info:
        load_files(files)
    return info.value


def with_tool(source: str, name: str = "bad") -> dict[str, bytes]:
    files = example_files()
    files[f"tools/{name}.py"] = source.encode()
    return files


# ---- a valid package ------------------------------------------------------------------------------


def test_valid_package_directory_loads_with_every_part(tmp_path: Path) -> None:
    root = write_tree(tmp_path / "pkg", example_files())
    (root / "tools" / "__pycache__").mkdir()
    (root / "tools" / "__pycache__" / "reach.cpython-311.pyc").write_bytes(b"\0junk")
    (root / ".hidden.swp").write_bytes(b"editor state")
    pkg = load_package(root)
    assert pkg.name == "hold-when-far"
    assert pkg.version == ""
    assert pkg.skill["tasks"] == ["test/reach"]
    assert pkg.skill["adjudication"][0] == {"evidence": "too_far", "mode": "hold", "priority": 1,
                                            "unless_milestone": ["released"]}
    assert pkg.skill["reentry"]["clears"] == ["too_far"]
    assert pkg.skill_text.startswith("# hold-when-far")
    assert pkg.params["reach"] == {"radius": 0.5, "limits": {"max_speed": 1.0}}
    assert pkg.plans["recoveries"]["hold"]["recovery"] == "freeze"
    assert set(pkg.tools) == {"reach"}
    assert pkg.content_hash == fmt.content_hash(example_files())
    module = pkg.tools["reach"]
    assert module.__name__.startswith(f"_zetta_harness_{pkg.content_hash[:12]}_")
    assert sys.modules[module.__name__] is module
    assert module.Reading(2.0).radius == 2.0  # a dataclass in package code works


def test_two_loads_never_share_module_state() -> None:
    a, b = load_files(example_files()), load_files(example_files())
    assert a.tools["reach"] is not b.tools["reach"]
    assert a.tools["reach"].__name__ != b.tools["reach"].__name__
    a.tools["reach"].CALLS[0] = 7
    assert b.tools["reach"].CALLS[0] == 0
    unload(a)
    assert a.tools["reach"].__name__ not in sys.modules
    assert b.tools["reach"].__name__ in sys.modules


def test_published_manifest_gives_the_version_and_must_match_the_hash() -> None:
    files = example_files()
    manifest = {"name": "hold-when-far", "version": 3, "content_hash": fmt.content_hash(files)}
    files[fmt.MANIFEST] = fmt.manifest_bytes(manifest)
    pkg = load_files(files)
    assert pkg.version == "3"
    assert pkg.manifest["version"] == 3
    files["params/reach.toml"] = b"radius = 9.0\n"
    err = rejection(files)
    assert err.problems[0].path == "manifest.json"
    assert "does not match the files" in err.problems[0].reason


# ---- content hash ---------------------------------------------------------------------------------


def test_content_hash_is_stable_and_ignores_order_and_manifest() -> None:
    files = example_files()
    reordered = dict(reversed(list(files.items())))
    assert fmt.content_hash(files) == fmt.content_hash(reordered)
    assert fmt.content_hash({**files, fmt.MANIFEST: b'{"anything": 1}'}) == fmt.content_hash(files)
    assert fmt.content_hash(example_files(radius=0.51)) != fmt.content_hash(files)
    # path and content boundaries are part of the hash: moving a byte across them changes it
    assert fmt.content_hash({"ab": b"c"}) != fmt.content_hash({"a": b"bc"})
    # the documented construction, written out independently
    import hashlib

    digest = hashlib.sha256()
    for path in sorted(files):
        digest.update(path.encode() + b"\0" + len(files[path]).to_bytes(8, "big") + files[path])
    assert fmt.content_hash(files) == digest.hexdigest()


# ---- code rejections ------------------------------------------------------------------------------


def test_forbidden_import_is_rejected_with_file_and_line() -> None:
    err = rejection(with_tool('"""doc"""\nimport math\nimport os\n'))
    assert [(p.path, p.line) for p in err.problems] == [("tools/bad.py", 3)]
    assert "import of 'os' is not allowed" in err.problems[0].reason
    assert "numpy" in err.problems[0].reason  # the message lists what is allowed
    assert "tools/bad.py:3" in str(err)


@pytest.mark.parametrize(
    "source, line, reason",
    [
        ("from subprocess import run\n", 1, "import of 'subprocess'"),
        ("import numpy.random\nimport numpy.f2py\n", 1, "import of 'numpy.random'"),
        ("from numpy import *\n", 1, "star import"),
        ("from . import reach\n", 1, "relative imports"),
        ("from numpy import load\n", 1, "importing 'load'"),
        ("x = 1\ny = eval('1+1')\n", 2, "use of 'eval'"),
        ("def f():\n    exec('x=1')\n", 2, "use of 'exec'"),
        ("f = open\n", 1, "use of 'open'"),
        ("x = compile('1', 'f', 'eval')\n", 1, "use of 'compile'"),
        ("m = __import__('os')\n", 1, "use of '__import__'"),
        ("x = getattr(1, 'real')\n", 1, "use of 'getattr'"),
        ("g = globals()\n", 1, "use of 'globals'"),
        ("v = vars()\n", 1, "use of 'vars'"),
        ("x = ().__class__.__bases__\n", 1, "dunder attribute '.__class__'"),
        ("b = __builtins__\n", 1, "dunder name '__builtins__'"),
        ("import numpy as np\na = np.load('x.npy')\n", 2, "access to '.load'"),
        ("import numpy as np\np = np.zeros(3).ctypes\n", 2, "access to '.ctypes'"),
        ("s = '{0.__class__}'.format(1)\n", 1, "format field"),
    ],
)
def test_code_rules_reject_each_escape_hatch(source: str, line: int, reason: str) -> None:
    err = rejection(with_tool(source))
    first = err.problems[0]
    assert (first.path, first.line) == ("tools/bad.py", line)
    assert reason in first.reason


def test_syntax_error_is_rejected_with_its_line() -> None:
    err = rejection(with_tool("def ok():\n    return 1\n\ndef broken(:\n    pass\n"))
    assert [(p.path, p.line) for p in err.problems] == [("tools/bad.py", 4)]
    assert err.problems[0].reason.startswith("syntax error")


def test_every_problem_of_every_file_is_reported_and_nothing_is_imported() -> None:
    files = with_tool("import os\nx = eval('1')\n", name="one")
    files["tools/two.py"] = b"import socket\n"
    files["params/broken.toml"] = b"a = 1\nb = \n"
    before = set(sys.modules)
    err = rejection(files)
    found = {(p.path, p.line) for p in err.problems}
    assert {("tools/one.py", 1), ("tools/one.py", 2), ("tools/two.py", 1), ("params/broken.toml", 2)} <= found
    assert not any(m.startswith("_zetta_harness_") for m in set(sys.modules) - before)


def test_allowed_imports_pass_the_checks() -> None:
    source = "\n".join(f"import {m}" for m in sorted(ALLOWED_IMPORTS) if m != "__future__")
    source = "from __future__ import annotations\n" + source + "\nfrom services.harness.runtime.library import tools\n"
    check_source("tools/ok.py", source)


def test_error_at_import_time_rejects_with_the_line() -> None:
    err = rejection(with_tool("X = 1\nY = {}['missing']\n"))
    assert (err.problems[0].path, err.problems[0].line) == ("tools/bad.py", 2)
    assert "import failed: KeyError" in err.problems[0].reason


def test_loaded_code_cannot_import_past_the_allowlist_at_run_time() -> None:
    """The static checks see through plain code; the builtins are a second guard."""
    module = load_files(example_files()).tools["reach"]
    guarded = module.__builtins__["__import__"]
    assert guarded("math").sqrt(4.0) == 2.0
    with pytest.raises(ImportError, match="may not import 'os'"):
        guarded("os")
    assert "open" not in module.__builtins__ and "eval" not in module.__builtins__


# ---- SKILL.md and layout --------------------------------------------------------------------------


def test_skill_front_matter_errors_are_precise() -> None:
    files = example_files()
    files["SKILL.md"] = b"# no front matter\n"
    assert "must start with a '+++' line" in rejection(files).problems[0].reason
    files["SKILL.md"] = b"+++\nname = \"x\"\n"
    assert "not closed" in rejection(files).problems[0].reason
    files["SKILL.md"] = b'+++\nname = "x"\ndescription = "d"\ntasks = [1\n+++\n'
    problem = rejection(files).problems[0]
    assert (problem.path, problem.line) == ("SKILL.md", 4)
    assert problem.reason.startswith("invalid TOML")
    files["SKILL.md"] = b'+++\ndescription = 3\ntasks = "t"\n[[adjudication]]\nmode = "hold"\npriority = "high"\n+++\n'
    reasons = " | ".join(p.reason for p in rejection(files).problems)
    for expected in ("'name' must be", "'description' must be", "'tasks' must be", "'evidence' must be", "'priority' must be"):
        assert expected in reasons


@pytest.mark.parametrize(
    "path, reason",
    [
        ("../escape.py", "not part of the package layout"),
        ("/etc/passwd", "not part of the package layout"),
        ("tools/sub/deep.py", "not part of the package layout"),
        ("tools/1bad-name.py", "must be named <identifier>.py"),
        ("tools/notes.txt", "must be named <identifier>.py"),
        ("plans/hold.py", "must be named <identifier>.toml"),
        ("data.bin", "not part of the package layout"),
    ],
)
def test_layout_rejects_paths_outside_it(path: str, reason: str) -> None:
    files = example_files()
    files[path] = b"x = 1\n"
    problem = rejection(files).problems[0]
    assert (problem.path, reason in problem.reason) == (path, True)


def test_missing_skill_and_size_limit() -> None:
    files = example_files()
    del files["SKILL.md"]
    assert rejection(files).problems[0].path == "SKILL.md"
    with pytest.raises(PackageRejected, match="at most 1000 are allowed"):
        load_files(example_files(), max_bytes=1000)


def test_symbolic_links_are_refused(tmp_path: Path) -> None:
    root = write_tree(tmp_path / "pkg", example_files())
    (root / "params" / "link.toml").symlink_to(root / "params" / "reach.toml")
    with pytest.raises(PackageRejected, match="symbolic links"):
        load_package(root)


# ---- the import probe (child process with a deadline) ---------------------------------------------


async def test_probe_accepts_a_runnable_package() -> None:
    await probe_import(example_files(), timeout_s=60, max_bytes=fmt.MAX_PACKAGE_BYTES)


async def test_probe_rejects_a_tool_whose_import_never_ends() -> None:
    files = with_tool("import itertools\nfor _ in itertools.count():\n    pass\n", name="spin")
    with pytest.raises(PackageRejected, match="took longer than 3 s"):
        await probe_import(files, timeout_s=3, max_bytes=fmt.MAX_PACKAGE_BYTES)


async def test_probe_rejects_a_package_that_makes_no_runnable_harness() -> None:
    files = example_files()
    files["SKILL.md"] = files["SKILL.md"].replace(b'mode = "hold"', b'mode = "nowhere"')
    with pytest.raises(PackageRejected) as info:
        await probe_import(files, timeout_s=60, max_bytes=fmt.MAX_PACKAGE_BYTES)
    assert info.value.problems[0].path == "SKILL.md"
    assert "no plan defines" in info.value.problems[0].reason


async def test_probe_refuses_a_package_that_reads_the_simulators_boxes() -> None:
    """What a harness may read is checked at publish: a critic naming the goal's target box is refused."""
    peek = "def critic_peek(window, params):\n    return window.now.obs.get('task_target_bbox')\n"
    with pytest.raises(PackageRejected) as info:
        await probe_import(with_tool(peek, name="peek"), timeout_s=60, max_bytes=fmt.MAX_PACKAGE_BYTES)
    assert "tools/peek.py: reads task_target_bbox, which a harness may not read at run time" in str(info.value)


async def test_probe_reports_the_loader_problems_and_ignores_prints() -> None:
    files = with_tool("print('noise on stdout')\nx = [][1]\n", name="noisy")
    with pytest.raises(PackageRejected) as info:
        await probe_import(files, timeout_s=60, max_bytes=fmt.MAX_PACKAGE_BYTES)
    assert (info.value.problems[0].path, info.value.problems[0].line) == ("tools/noisy.py", 2)


# ---- diff and store -------------------------------------------------------------------------------


def test_diff_reports_files_and_param_changes() -> None:
    base = example_files(radius=0.5)
    head = example_files(radius=0.7)
    head["tools/extra.py"] = b"X = 1\n"
    del head["plans/recoveries.toml"]
    head["params/reach.toml"] += b"new_key = true\n"
    changes = {c.path: c for c in pkg_diff.file_changes(base, head, "a@1", "a@2")}
    assert {p: c.change for p, c in changes.items()} == {
        "params/reach.toml": "modified", "plans/recoveries.toml": "removed", "tools/extra.py": "added",
    }
    assert "-radius = 0.5\n+radius = 0.7\n" in changes["params/reach.toml"].unified_diff
    assert changes["params/reach.toml"].unified_diff.startswith("--- a@1/params/reach.toml\n+++ a@2/params/reach.toml\n")
    params = [(p.file, p.key, p.base_json, p.head_json) for p in pkg_diff.param_changes(base, head)]
    assert params == [("reach", "limits.new_key", None, "true"), ("reach", "radius", "0.5", "0.7")]


def test_store_is_content_addressed_and_write_once(tmp_path: Path) -> None:
    store = PackageStore(tmp_path / "store")
    files = example_files()
    digest = fmt.content_hash(files)
    store.put_files(digest, files)
    store.put_files(digest, files)
    assert store.manifest(digest) is None
    first = store.put_manifest(digest, {"name": "hold-when-far", "version": 1, "content_hash": digest})
    second = store.put_manifest(digest, {"name": "hold-when-far", "version": 2, "content_hash": digest})
    assert first == second and second["version"] == 1
    stored = store.files(digest)
    assert json.loads(stored.pop(fmt.MANIFEST))["version"] == 1
    assert stored == files
    assert [m["version"] for m in store.manifests()] == [1]
    (tmp_path / "store" / "packages" / digest / "params" / "reach.toml").write_bytes(b"radius = 100.0\n")
    with pytest.raises(StoreCorrupted):
        store.files(digest)
    with pytest.raises(ValueError):
        store.files("../../etc")


# ---- critic service configuration ----------------------------------------------------------------


def test_critic_config_names_every_bad_variable() -> None:
    from services.common.config import ConfigError
    from services.critic.config import CriticConfig

    with pytest.raises(ConfigError) as info:
        CriticConfig.from_env({"ZETTA_CRITIC_PORT": "http", "ZETTA_CRITIC_IMPORT_TIMEOUT_S": "0"})
    message = str(info.value)
    for name in ("ZETTA_REDIS_URL is required", "ZETTA_CRITIC_STORE is required", "ZETTA_CRITIC_PORT='http'",
                 "ZETTA_CRITIC_IMPORT_TIMEOUT_S=0.0 is below"):
        assert name in message
    cfg = CriticConfig.from_env({"ZETTA_REDIS_URL": "redis://r:6379/0", "ZETTA_CRITIC_STORE": "/s"})
    assert (cfg.port, cfg.metrics_port, cfg.max_package_bytes) == (50081, 9104, fmt.MAX_PACKAGE_BYTES)
