"""`zetta evolve experiment`: task ranges, and the summary built from what the stores recorded."""

from __future__ import annotations

from pathlib import Path

import pytest

import json

from services.evolver import results
from services.evolver.cmd_experiment import task_list
from services.evolver.store import EpisodeKey, RolloutStore
from tests.unit.test_evolver_store import outcome


def test_task_ranges_and_lists_mix() -> None:
    assert task_list("0-2,6") == ("0", "1", "2", "6")
    assert task_list("9, 6,9") == ("9", "6")
    assert task_list("put_the_bowl_on_the_plate") == ("put_the_bowl_on_the_plate",)
    with pytest.raises(SystemExit):
        task_list(" , ")


def _arm(s: int, n: int, seeds: list[int], share: float = 0.0, in_control: float = 1.0) -> dict:
    from zetta_wire.stats import wilson

    return {"successes": s, "episodes": n, "rate": s / n, "wilson95": list(wilson(s, n)), "seeds": seeds,
            "recovery_share": share, "policy_in_control_at_success": in_control}


def test_results_file_holds_provenance_splits_arms_and_means_and_renders_the_tables(tmp_path: Path) -> None:
    """The results come from what the stores recorded: every task's test arms (bare, harness, harness
    around the do-nothing policy) with Wilson intervals, the means, the splits, the transfer rows, the
    wall time; the tables rendered from them carry the control and who did the work."""
    seeds = list(range(1, 11))
    for suite, finals in (("libero_goal_task", {"6": (0, 0, 0, "bare"), "9": (0, 10, 0, "e-9@1")}),
                          ("libero_goal_swap", {"9": (1, 6, 1, "e-9@1")})):
        store = RolloutStore(tmp_path / suite)
        for task, (b, f, c, ref) in finals.items():
            store.assign_splits(suite, task, dev=2, heldout=1, test=1)
            store.add(EpisodeKey(suite, task, 3, "", "profile"), outcome("miss", 1))
            store.record("final", {"suite": suite, "task": task, "harness": ref, "bare": [b, 10], "final": [f, 10],
                                   "seeds": seeds, "split": store.split_manifest(suite, task),
                                   "arms": {"bare": _arm(b, 10, seeds), "final": _arm(f, 10, seeds, 0.25, 0.9),
                                            "control": _arm(c, 10, seeds)}}, ident=f"{suite}/{task}")
        store.record("wall", {"command": "experiment", "wall_s": 100.0})
        store.record("wall", {"command": "experiment", "wall_s": 20.0})
    for transfer_suite, bare, final, wall in (("libero_goal", 3, 5, 30.0), ("libero_goal_lan", 2, 7, 40.0)):
        transfer = RolloutStore(tmp_path / f"transfer-{transfer_suite}")
        transfer.record("transfer_source", {"suite": transfer_suite, "task": "9", "harness": "e-9@1",
                                            "source": "libero_goal_task/9", "arms": {"bare": _arm(bare, 10, seeds),
                                                                                     "final": _arm(final, 10, seeds),
                                                                                     "control": _arm(0, 10, seeds)}})
        transfer.record("wall", {"command": "experiment transfer", "wall_s": wall})
    meta = {"command": "zetta evolve experiment --tasks 6,9", "source": {"commit": "abc123def4567890", "dirty": False},
            "policy": {"model": "zetta-vla-state", "checkpoint_sha256": "f" * 64}, "control_model": "do-nothing"}
    data = results.collect(tmp_path, ["libero_goal_task", "libero_goal_swap"], ["libero_goal", "libero_goal_lan"],
                           meta)
    task = data["suites"]["libero_goal_task"]
    assert [t["task"] for t in task["tasks"]] == ["6", "9"] and task["mean"]["final"] == pytest.approx(0.5)
    assert task["tasks"][1]["split"]["test"] == [1] and data["wall_s"]["libero_goal_task"] == 120.0
    assert [(t["suite"], t["source"]) for t in data["transfer"]] == [("libero_goal", "libero_goal_task/9"),
                                                                     ("libero_goal_lan", "libero_goal_task/9")]
    assert data["wall_s"]["transfer"] == 70.0 and set(data["rollouts_by_purpose"]) >= {"transfer-libero_goal",
                                                                                       "transfer-libero_goal_lan"}
    path = results.write(tmp_path / "results.json", data)
    text = results.render(json.loads(path.read_text()))
    assert "commit `abc123def456`" in text and "checkpoint sha256 `ffffffffffffffff`" in text
    assert "| 9 | 0/10 = 0% [0%, 28%] | 10/10 = 100% [72%, 100%] | +100% | 0/10 = 0% [0%, 28%] | 25% | 90% | e-9@1 |" \
        in text
    assert "| **mean** | 0.0% | 50.0% | +50.0% | 0.0% |" in text
    assert "| libero_goal | 9 | e-9@1 (libero_goal_task/9) | 3/10 = 30%" in text
    assert "| libero_goal_lan | 9 | e-9@1 (libero_goal_task/9) | 2/10 = 20%" in text
    gain = next(g for g in data["goals"] if g["goal"].startswith("zero-shot transfer"))
    assert gain["value"] == pytest.approx(0.35)  # both transfer suites' rows: (5 + 7 - 3 - 2) / 20


def test_goals_about_harnesses_are_not_measured_when_none_was_admitted() -> None:
    """A bare row has no recoveries and no control: with nothing admitted, the control, recoveries
    and transfer goals say "not measured", never "met"."""
    seeds = list(range(1, 21))
    arms = {"bare": _arm(2, 20, seeds), "final": _arm(2, 20, seeds), "control": _arm(0, 20, seeds)}
    data = {"suites": {"libero_goal_task": {"tasks": [{"task": "7", "harness": "bare", "arms": arms}],
                                            "mean": {"bare": 0.1, "final": 0.1, "control": 0.0}}}, "transfer": []}
    by_goal = {g["goal"]: g for g in results.goals(data)}
    for goal in ("do-nothing control of every admitted harness",
                 "recoveries' share of actions over successful test episodes",
                 "zero-shot transfer gain over the bare policy"):
        assert by_goal[goal]["value"] is None and by_goal[goal]["gap"] is None, goal
    assert by_goal["recoveries' share of actions over successful test episodes"]["detail"] == "no harness was admitted"
    assert by_goal["harness mean test success, libero_goal_task (Goal-T)"]["value"] == pytest.approx(0.1)


def test_the_published_page_is_generated_from_the_results_file() -> None:
    """docs/results/evolution.md: the common generated head (command, commit) above the tables."""
    data = {"schema": 1, "policy": {"model": "m"}, "source": {"commit": "c0ffee", "dirty": False},
            "command": "zetta evolve experiment --tasks 6", "suites": {}, "transfer": []}
    page = results.page(data)
    assert page.startswith("# Evolution: bare policy, evolved harness, do-nothing control (generated)")
    assert "measured by: `zetta evolve experiment --tasks 6`" in page and "commit: `c0ffee`" in page
    assert "policy `m`" in page


def test_a_suite_evolved_on_is_no_transfer_suite() -> None:
    """Transfer measures suites the harness never saw: naming an evolved suite among them stops the
    command before any stack starts."""
    from services.evolver.cmd_experiment import main

    with pytest.raises(SystemExit, match="libero_goal_swap is both evolved on and a transfer suite"):
        main(["--suites", "libero_goal_swap", "--transfer-suites", "libero_goal_lan,libero_goal_swap"])


def test_nominal_seeds_that_would_share_a_reported_layout_are_refused() -> None:
    """The nominal reference takes the last initial states, test and transfer seeds the first: a
    budget where they would meet stops the command before any stack starts."""
    from services.evolver.cmd_experiment import main

    with pytest.raises(SystemExit, match="--nominal-seeds 5 \\+ test or transfer seeds 46 exceed"):
        main(["--nominal-seeds", "5", "--transfer-seeds", "46"])
