"""bench/bench_stack_ab.py's arguments and report (the stacks themselves are the sweep's, tested in
tests/integration/test_bench_sweep.py)."""

from __future__ import annotations

import argparse
import importlib.util
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
    args = argparse.Namespace(concurrency=4, env_workers=2, a=[], b=["X=1"])
    a = [ab.Window(100.0, 4.0, 90.0), ab.Window(200.0, 2.0, 90.0), ab.Window(100.0, 4.0, 90.0)]
    b = [ab.Window(110.0, 3.0, 90.0), ab.Window(180.0, 2.5, 90.0), ab.Window(130.0, 3.6, 90.0)]
    text = ab.report(args, {"A": a, "B": b})
    assert "A (defaults): median 100 steps/s, 4.00 CPU ms per step" in text
    assert "B (X=1): median 130 steps/s, 3.00 CPU ms per step" in text
    assert "steps/s x1.100, CPU per step x0.900 (B cheaper in 2 of 3 rounds)" in text
