"""The results page's sections beyond the test tables, each from constructed store records: goals and
their gaps, budgets and splits, the history per task and round, the internal-version curves, the
rollouts by purpose and the wall time per phase; and a schema 1 file still renders."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from services.evolver import results
from services.evolver.gate import Verdict
from services.evolver.store import EpisodeKey, RolloutStore
from tests.unit.test_evolver_experiment import _arm
from tests.unit.test_evolver_store import outcome

SUITE = "libero_goal_task"
SEEDS = list(range(1, 11))


def _final(store: RolloutStore, task: str, ref: str, bare: int, final: int, control: int, share: float) -> None:
    store.record("final", {"suite": SUITE, "task": task, "harness": ref, "split": store.split_manifest(SUITE, task),
                           "wall_s": 30.0, "arms": {"bare": _arm(bare, 10, SEEDS), "control": _arm(control, 10, SEEDS),
                                                    "final": _arm(final, 10, SEEDS, share, 0.8)}},
                 ident=f"{SUITE}/{task}")


def _round_one(store: RolloutStore) -> None:
    """Task 6, round 1: two clusters, one repaired and solved by v2; three candidates (one validated);
    a merge refused; the gate admits e-6@1; a held-out failure moves to dev."""
    store.record("profile", {"suite": SUITE, "task": "6", "round": 1, "harness": "bare", "successes": 1,
                             "episodes": 4})
    for cid, seeds in (("6/r1/K1", [12, 13, 14]), ("6/r1/K2", [15])):
        store.record("cluster", {"suite": SUITE, "task": "6", "round": 1, "cluster": cid, "seeds": seeds},
                     ident=cid)
    store.record("cluster_versions", {"suite": SUITE, "task": "6", "round": 1, "cluster": "6/r1/K1", "tried": 3,
                                      "versions": [{"version": "v0", "harness": "bare", "successes": 0, "episodes": 3},
                                                   {"version": "v1", "harness": "c@1", "successes": 0, "episodes": 3,
                                                    "validated": False},
                                                   {"version": "v2", "harness": "c@2", "successes": 3, "episodes": 3,
                                                    "validated": True}]}, ident="6/r1/K1")
    for ref, ok in (("c@1", False), ("c@2", True), ("c@3", False)):
        store.record("validation", {"cluster": "6/r1/K1", "ref": ref, "medoid_success": ok}, ident=f"6/r1/K1/{ref}")
    store.record("validation", {"cluster": "6/r1/K1", "ref": "c@4", "medoid_success": True,
                                "in_control_at_success": True, "validated": False},
                 ident="6/r1/K1/c@4")  # its recovery finished it, in a run that required a hand-back
    store.record("validation", {"cluster": "9/r1/K1", "ref": "x@1", "medoid_success": True})  # another task's
    store.record("consolidation", {"suite": SUITE, "task": "6", "round": 1, "cluster": "6/r1/K2", "joined": False,
                                   "reason": "historical regression 3/4 below 100%"})
    verdict = Verdict(True, "held-out 3/3 > current 1/3", (3, 3), (3, 3), (1, 3), (1, 3), (0, 4)).to_dict()
    store.record("gate", {"suite": SUITE, "task": "6", "round": 1, "candidate": "c@2", "verdict": verdict},
                 ident="fp1")
    store.record("admitted", {"suite": SUITE, "task": "6", "round": 1, "ref": "e-6@1", "verdict": verdict})
    store.move_to_dev(SUITE, "6", store.seeds(SUITE, "6", "heldout")[0], "held-out failure of e-6@1 (round 1)")
    store.record("round_done", {"suite": SUITE, "task": "6", "round": 1, "wall_s": 100.0,
                                "phases_s": {"profile": 20.0, "repair": 50.0, "gate": 30.0}})


def _round_two(store: RolloutStore) -> None:
    """Task 6, round 2: two clusters under the gate's minimum are left; the gate refuses a candidate
    whose held-out success is no better."""
    store.record("profile", {"suite": SUITE, "task": "6", "round": 2, "harness": "e-6@1", "successes": 3,
                             "episodes": 5})
    verdict = Verdict(False, "held-out 2/3 is not a strict improvement over the current harness's 2/3",
                      (3, 3), (2, 3), (2, 3), (1, 3), (0, 5)).to_dict()
    store.record("gate", {"suite": SUITE, "task": "6", "round": 2, "candidate": "c@5", "verdict": verdict},
                 ident="fp2")
    store.record("round_done", {"suite": SUITE, "task": "6", "round": 2, "wall_s": 40.0,
                                "phases_s": {"profile": 10.0, "repair": 20.0, "gate": 10.0},
                                "skipped_clusters": [[16, 17], [18]]})


def experiment(tmp_path: Path, transfer: bool = True) -> dict[str, Any]:
    """An experiment directory with one evolved suite (task 6 admitted, task 9 bare) and a transfer
    store, collected and read back from its results file."""
    store = RolloutStore(tmp_path / SUITE)
    for task in ("6", "9"):
        store.assign_splits(SUITE, task, dev=4, heldout=3, test=2)
    store.add(EpisodeKey(SUITE, "6", 6, "", "profile"), outcome("miss", 1), 1)
    store.add(EpisodeKey(SUITE, "6", 7, "", "profile"), outcome("success", 2), 1)
    store.add(EpisodeKey(SUITE, "6", 6, "c@1", "validate"), outcome("miss", 3), 1)
    store.log_invalid(EpisodeKey(SUITE, "6", 6, "c@1", "validate"), "UNAVAILABLE")
    _round_one(store)
    _round_two(store)
    _final(store, "6", "e-6@1", 2, 7, 1, 0.4)
    _final(store, "9", "bare", 3, 3, 0, 0.0)
    store.close()
    if transfer:
        tstore = RolloutStore(tmp_path / "transfer-libero_goal")
        tstore.record("transfer_source", {"suite": "libero_goal", "task": "6", "harness": "e-6@1",
                                          "source": f"{SUITE}/6", "arms": {"bare": _arm(2, 10, SEEDS),
                                                                           "final": _arm(5, 10, SEEDS),
                                                                           "control": _arm(0, 10, SEEDS)}})
        tstore.record("wall", {"command": "experiment transfer", "wall_s": 50.0})
        tstore.close()
    meta = {"command": "zetta evolve experiment", "source": {"commit": "abc"}, "policy": {"model": "m"},
            "budgets": {"rounds": 2, "dev_seeds": 4, "heldout_seeds": 3, "test_seeds": 2, "max_depth": 3}}
    data = results.collect(tmp_path, [SUITE], ["libero_goal"] if transfer else [], meta)
    assert data["schema"] == 2
    return dict(json.loads(results.write(tmp_path / "results.json", data).read_text()))


def test_goals_give_each_measured_value_and_its_gap(tmp_path: Path) -> None:
    """Mean harness success 50 % misses 90 % by 40 points (with the paper's Goal-T figures beside
    it); the admitted harness's control (10 %) misses 5 % and its recoveries' share (40 %) misses
    30 %; the transfer gain of +30 points meets +20."""
    data = experiment(tmp_path)
    goals = {g["goal"].split(",")[0]: g for g in data["goals"]}
    success = goals["harness mean test success"]
    assert success["value"] == pytest.approx(0.5) and success["gap"] == pytest.approx(-0.4) and not success["met"]
    assert goals["do-nothing control of every admitted harness"]["value"] == pytest.approx(0.1)
    assert goals["zero-shot transfer gain over the bare policy"]["met"] is True
    text = results.render(data)
    assert ("| harness mean test success, libero_goal_task (Goal-T) | ≥ 90.0% | 50.0% | **missed by 40.0 points** | "
            "1 of 2 tasks with an admitted harness; bare mean 25.0% | paper (Goal-T, frozen pi0.5): 31.0% -> 92.5% |"
            in text)
    assert "| ≤ 5.0% | 10.0% | **missed by 5.0 points** | highest: libero_goal_task/6 |" in text
    assert "| ≤ 30.0% | 40.0% | **missed by 10.0 points** | largest: libero_goal_task/6 |" in text
    assert "| ≥ +20.0 points | +30.0 points | met (margin 10.0 points) |" in text
    assert "What limits it" not in text
    limited = results.render({**data, "limits": "the VLA never lifts the bowl on 8 of 10 tasks"})
    assert "**What limits it** (the publisher's note): the VLA never lifts the bowl on 8 of 10 tasks" in limited


def test_unmeasured_goals_say_so(tmp_path: Path) -> None:
    """No transfer run: its goal is not measured, and says why."""
    text = results.render(experiment(tmp_path, transfer=False))
    assert "| - | not measured | no admitted harness was run zero-shot | paper: +16 to +20 points |" in text


def test_budgets_and_splits_show_seeds_init_states_and_moves(tmp_path: Path) -> None:
    data = experiment(tmp_path)
    six = data["suites"][SUITE]["tasks"][0]
    assert six["init_states"]["test"] == [s % 50 for s in six["split"]["test"]]
    text = results.render(data)
    assert "Budgets: `dev_seeds` 4, `heldout_seeds` 3, `max_depth` 3, `rounds` 2, `test_seeds` 2." in text
    # Task 6: test 1-2, gate 3-5 then 3 moved to dev and 19 drawn; task 9 draws its own seeds.
    assert "| libero_goal_task | 6 | 3, 6-9 (init 3, 6-9) | 4-5, 10 (init 4-5, 10) | 1-2 (init 1-2) | 3 | yes |" in text
    assert "- libero_goal_task/6 seed 3: held-out failure of e-6@1 (round 1)" in text


def test_history_per_task_and_round_from_the_recorded_events(tmp_path: Path) -> None:
    """Dev profile, clusters repaired and solved, candidates validated and refused by kind, the gate's
    numbers, the admitted version and the wall time per phase; another task's validations stay out."""
    data = experiment(tmp_path)
    first, second = data["suites"][SUITE]["history"]
    assert (first["round"], first["profile"], first["clusters"], first["repaired"], first["solved"]) == (1, [1, 4], 2, 1, 1)
    assert first["candidates"] == {"run": 4, "validated": 1,
                                   "refused": {"validation": 2, "no hand-back": 1, "consolidation": 1}}
    assert first["gate"]["control"] == [0, 4] and first["gate"]["heldout"] == [3, 3] and first["admitted"] == "e-6@1"
    assert second["gate"]["refusal"] == "held-out" and second["candidates"]["refused"] == {"held-out": 1}
    text = results.render(data)
    assert ("| libero_goal_task | 6 | 1 | bare | 1/4 | 2 | 1 / 1 | 4 run: 1 validated; refused: consolidation 1, "
            "no hand-back 1, validation 2 | regression 3/3, control (dev) 0/4, held-out 3/3 vs current 1/3 (bare 1/3): admitted | "
            "e-6@1 | 100 (20 / 50 / 30) |") in text
    assert (first["small"], second["small"]) == (0, 2)
    assert "| libero_goal_task | 6 | 2 | e-6@1 | 3/5 | 0 (+2 small) | 0 / 0 |" in text
    assert "held-out 2/3 vs current 2/3 (bare 1/3): refused (held-out) | - | 40 (10 / 20 / 10) |" in text


def test_aha_curves_list_every_internal_version(tmp_path: Path) -> None:
    text = results.render(experiment(tmp_path))
    assert "| libero_goal_task | 6 | 1 | 6/r1/K1 | 12-14 | v0 0/3 → v1 0/3 → v2 3/3 ✓ | ▁▁█ | 3 |" in text


def test_rollouts_by_purpose_and_wall_time_per_phase(tmp_path: Path) -> None:
    data = experiment(tmp_path)
    counts = data["rollouts_by_purpose"][SUITE]
    assert counts["purposes"]["profile"] == {"rollouts": 2, "episode_s": pytest.approx(0.2)}
    assert counts["invalid"] == 1 and data["suites"][SUITE]["phases_s"] == {"profile": 30.0, "repair": 70.0,
                                                                           "gate": 40.0, "final": 60.0}
    text = results.render(data)
    assert "| store | profile | validate | invalid attempts |" in text
    assert "| libero_goal_task | 2 (0 s) | 1 (0 s) | 1 |" in text and "| transfer-libero_goal | - | - | 0 |" in text
    assert "| libero_goal_task | 30 | 70 | 40 | 60 | 0 |" in text and "| transfer | - | - | - | - | 50 |" in text


def test_a_schema_1_file_still_renders(tmp_path: Path) -> None:
    """An older results file: goals computed from its tables, its splits without initial states, no
    history sections."""
    data = experiment(tmp_path)
    old = {k: v for k, v in data.items() if k not in ("goals", "rollouts_by_purpose")} | {"schema": 1}
    old["suites"] = {SUITE: {k: v for k, v in data["suites"][SUITE].items() if k not in ("history", "curves",
                                                                                       "phases_s")}}
    for t in old["suites"][SUITE]["tasks"]:
        t.pop("init_states")
    text = results.page(old)
    assert "**missed by 40.0 points**" in text and "| libero_goal_task | 6 | 3, 6-9 | 4-5, 10 | 1-2 | 3 | yes |" in text
    assert "Evolution history" not in text and "aha curves" not in text and "Rollouts and wall time" not in text
