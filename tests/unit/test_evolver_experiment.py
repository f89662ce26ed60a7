"""`zetta evolve experiment`: task ranges, and the summary built from what the stores recorded."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.evolver.cmd_experiment import summary, task_list
from services.evolver.store import EpisodeKey, RolloutStore
from tests.unit.test_evolver_store import outcome


def test_task_ranges_and_lists_mix() -> None:
    assert task_list("0-2,6") == ("0", "1", "2", "6")
    assert task_list("9, 6,9") == ("9", "6")
    assert task_list("put_the_bowl_on_the_plate") == ("put_the_bowl_on_the_plate",)
    with pytest.raises(SystemExit):
        task_list(" , ")


def test_summary_reports_every_task_the_average_and_the_transfer(tmp_path: Path) -> None:
    """Per task bare vs final with Wilson intervals and its rollouts; per suite totals and wall time;
    the mean of per-task rates; the transfer rows with the suite/task each harness came from."""
    for suite, finals in (("libero_goal_task", {"6": ([0, 10], [0, 10], "bare"), "9": ([0, 10], [10, 10], "e-9@1")}),
                          ("libero_goal_swap", {"9": ([1, 10], [6, 10], "e-9@1")})):
        store = RolloutStore(tmp_path / suite)
        for task, (bare, final, ref) in finals.items():
            store.assign_splits(suite, task, dev=2, heldout=1)
            store.add(EpisodeKey(suite, task, 2, "", "profile"), outcome("miss", 1))
            store.record("final", {"suite": suite, "task": task, "harness": ref, "bare": bare, "final": final,
                                   "seeds": [1]}, ident=f"{suite}/{task}")
        store.record("wall", {"command": "experiment", "wall_s": 100.0})
        store.record("wall", {"command": "experiment", "wall_s": 20.0})
    transfer = RolloutStore(tmp_path / "transfer-libero_goal")
    transfer.record("transfer_source", {"suite": "libero_goal", "task": "9", "harness": "e-9@1", "bare": [3, 10],
                                        "final": [5, 10], "source": "libero_goal_task/9"})
    text = summary(tmp_path, ["libero_goal_task", "libero_goal_swap"], "libero_goal")
    assert "| 9 | 0/10 = 0% [0%, 28%] | 10/10 = 100% [72%, 100%] | +100% | e-9@1 | 1 |" in text
    assert "| **all** | 0/20 = 0% [0%, 16%] | 10/20 = 50% [30%, 70%] | | | 2 |" in text
    assert "Wall time: 120 s" in text
    # Mean of per-task rates: bare (0 + 0 + 10 %) / 3, final (0 + 100 + 60 %) / 3.
    assert "bare 3.3% -> final 53.3%" in text and "pooled: bare 1/30" in text
    assert "| 9 | e-9@1 (libero_goal_task/9) | 3/10 = 30%" in text
