"""bench/bench_stack_ab.py's arguments and report (the stacks themselves are the sweep's, tested in
tests/integration/test_bench_sweep.py)."""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _module() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_stack_ab", ROOT / "bench" / "bench_stack_ab.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_settings_are_name_value_pairs() -> None:
    ab = _module()
    assert ab.settings(["ZETTA_STEP_CONCURRENCY=1", "EMPTY="]) == {"ZETTA_STEP_CONCURRENCY": "1", "EMPTY": ""}
    with pytest.raises(SystemExit, match="'ZETTA_SLOTS' is not NAME=VALUE"):
        ab.settings(["ZETTA_SLOTS"])
    with pytest.raises(SystemExit, match="'=3' is not NAME=VALUE"):
        ab.settings(["=3"])


def test_report_gives_medians_of_the_rounds_ratios() -> None:
    """Ratios are taken round by round (B over A in the same round), then the median."""
    ab = _module()
    args = argparse.Namespace(concurrency=4, env_workers=2, a=[], b=["X=1"], a_rev="", b_rev="")
    a = [ab.Window(100.0, 4.0, 90.0), ab.Window(200.0, 2.0, 90.0), ab.Window(100.0, 4.0, 90.0)]
    b = [ab.Window(110.0, 3.0, 90.0), ab.Window(180.0, 2.5, 90.0), ab.Window(130.0, 3.6, 90.0)]
    text = ab.report(args, {"A": a, "B": b})
    assert "A (defaults): median 100 steps/s, 4.00 CPU ms per step" in text
    assert "B (X=1): median 130 steps/s, 3.00 CPU ms per step" in text
    assert "steps/s x1.100, CPU per step x0.900 (B cheaper in 2 of 3 rounds)" in text


def test_a_revision_runs_from_its_own_tree(tmp_path: Path) -> None:
    """``--a-rev``: stack A's services import an exported tree of that revision (stubs built), even
    when started from the repository, whose own packages would otherwise come first."""
    ab = _module()
    args = argparse.Namespace(a=["X=1"], b=[], a_rev="HEAD", b_rev="")
    envs = ab.stack_envs(args, tmp_path)
    assert envs["B"] == {} and envs["A"]["X"] == "1"
    tree = tmp_path / "A" / "tree"
    assert (tree / "services" / "env_worker" / "slots.py").exists()
    assert list((tree / "clients" / "python" / "zetta_wire" / "v1").glob("*_pb2.py"))
    probe = "import services, zetta_wire.v1.env_worker_pb2 as pb; print(services.__file__); print(pb.__file__)"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, env={**envs["A"], "PATH": "/usr/bin:/bin"},
                         capture_output=True, text=True, check=True).stdout.split()
    assert all(Path(line).is_relative_to(tree) for line in out), out
