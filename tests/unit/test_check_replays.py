"""scripts/check_replays.py: where two replays of one key part."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from services.evolver.trace import Trace

ROOT = Path(__file__).resolve().parents[2]


def _script():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("_test_check_replays", ROOT / "scripts" / "check_replays.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _trace(eef: np.ndarray) -> Trace:
    empty = np.zeros(0, np.int32)
    return Trace(obs={}, frame_step=empty, actions=np.zeros((0, 7), np.float32), action_frame=empty,
                 milestone_names=[], step_obs={"robot0_eef_pos": eef.astype(np.float32)})


def test_first_divergence_is_the_first_step_that_differs_or_where_the_shorter_one_ends() -> None:
    first_divergence = _script().first_divergence
    base = np.cumsum(np.full((10, 3), 0.01), axis=0)
    assert first_divergence(_trace(base), _trace(base.copy())) is None
    moved = base.copy()
    moved[4, 1] += 1e-6
    assert first_divergence(_trace(base), _trace(moved)) == 4
    assert first_divergence(_trace(base), _trace(base[:7])) == 7
