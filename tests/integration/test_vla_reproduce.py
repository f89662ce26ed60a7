"""`zetta train` reproduces the shipped checkpoint: same recipe, success inside its interval.

Slow (about 15 min of demo collection, 11 min of training and 10 min of evaluation on 2 cores):
``make test-slow``.
"""

from __future__ import annotations

import json

import pytest

pytestmark = pytest.mark.slow


def test_zetta_train_reproduces_shipped_success(tmp_path, monkeypatch) -> None:
    from services.policy_worker.vla.evaluate import evaluate
    from zetta.stats import wilson
    from services.policy_worker.vla.policy import STATE_CHECKPOINT
    from zetta.cli import main

    doc = json.loads((STATE_CHECKPOINT / "config.json").read_text())
    recipe = doc["data"]["recipes"][0]["recipe"]
    training = doc["training"]
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "ck"
    assert main(["train", "--out", str(out), "--teacher", recipe["teacher"],
                 "--seeds-per-task", str(recipe["seeds_per_task"]), "--collect-budget", str(recipe["time_budget_s"]),
                 "--steps", str(training["steps"]), "--time-budget", str(training["time_budget_s"])]) == 0
    tasks = recipe["tasks"]
    seeds = list(range(5))
    shipped = evaluate("zetta-vla-state", "libero_goal", tasks, seeds, str(tmp_path / "a.jsonl"), execute_steps=2)
    ours = evaluate("zetta-vla-state", "libero_goal", tasks, seeds, str(tmp_path / "b.jsonl"), execute_steps=2,
                    env={"ZETTA_VLA_CHECKPOINT": str(out)})
    ks, kn = sum(r.get("success", False) for r in shipped), len(shipped)
    os_, on = sum(r.get("success", False) for r in ours), len(ours)
    lo, hi = wilson(ks, kn)
    lo2, hi2 = wilson(os_, on)
    assert lo2 <= hi and lo <= hi2, (ks, kn, os_, on)  # the two intervals overlap
