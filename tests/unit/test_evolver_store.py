"""The rollout store: append-only, invalid attempts kept apart, the dev/held-out split enforced."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from services.evolver.store import DEV, HELDOUT, INIT_STATES, TEST, EpisodeKey, Outcome, RolloutStore, StoreError
from tests.unit.test_evolver_fixtures import make_trace


def outcome(kind: str, seed: int = 0) -> Outcome:
    tr = make_trace(kind, seed)
    return Outcome(success=kind == "success", steps=int(tr.frame_step[-1]), first_missing="" if kind == "success" else
                   "on(a,b)", milestones_reached=["reached(a)"], trace=tr, video_path="", wall_s=0.1)


def test_splits_are_disjoint_stable_and_growable(tmp_path: Path) -> None:
    """Held-out seeds are 1..H, dev the next ones; asking again keeps them; a seed is in one split."""
    s = RolloutStore(tmp_path)
    dev, held = s.assign_splits("libero_goal", "6", dev=5, heldout=3)
    assert held == [1, 2, 3] and dev == [4, 5, 6, 7, 8]
    assert s.assign_splits("libero_goal", "6", dev=5, heldout=3) == (dev, held)
    dev2, held2 = s.assign_splits("libero_goal", "6", dev=7, heldout=3)
    assert held2 == held and dev2[:5] == dev and len(dev2) == 7
    assert not set(dev2) & set(held2)
    # Another task has its own split.
    assert s.assign_splits("libero_goal", "9", dev=1, heldout=1) == ([2], [1])


def test_three_splits_sit_on_disjoint_initial_states_and_refuse_budgets_that_cannot(tmp_path: Path) -> None:
    """Test seeds first, then gate, then dev; no two seeds of a task share an initial state (seed % 50);
    a budget over LIBERO's 50 initial states is refused with a message naming the budgets."""
    s = RolloutStore(tmp_path)
    dev, held = s.assign_splits("g", "6", dev=20, heldout=10, test=20)
    test = s.seeds("g", "6", TEST)
    assert test == list(range(1, 21)) and held == list(range(21, 31)) and dev == list(range(31, 51))
    assert len({x % INIT_STATES for x in dev + held + test}) == 50
    with pytest.raises(StoreError, match="dev 20 \\+ gate 10 \\+ test 21 = 51 seeds"):
        s.assign_splits("g", "6", dev=20, heldout=10, test=21)
    with pytest.raises(StoreError, match="50 initial states"):
        s.assign_splits("g", "9", dev=50, heldout=20)
    # Every initial state is taken: a gate seed that moves to dev is not replaced, and that is recorded.
    assert s.move_to_dev("g", "6", 21, "triggered a change") is None
    assert "no initial state left" in s.split_moves()[-1]["reason"] and s.seeds("g", "6", HELDOUT) == held[1:]


def test_test_seeds_take_only_the_final_measurement(tmp_path: Path) -> None:
    """No decision reads a test outcome: the store refuses a profile, regression or gate rollout on a
    test seed, and a final measurement on any other seed."""
    s = RolloutStore(tmp_path)
    s.assign_splits("g", "6", dev=1, heldout=1, test=1)
    for purpose in ("profile", "regress", "heldout", "control"):
        with pytest.raises(StoreError, match="test seeds take only the final measurement"):
            s.add(EpisodeKey("g", "6", 1, "", purpose), outcome("miss"))
    with pytest.raises(StoreError, match="test seeds take only"):
        s.add(EpisodeKey("g", "6", 3, "", "test"), outcome("miss"))
    assert s.add(EpisodeKey("g", "6", 1, "h@1", "control-test"), outcome("miss")).split == TEST


def test_move_to_dev_is_recorded_and_draws_a_fresh_heldout_seed(tmp_path: Path) -> None:
    """Only a held-out seed can move; the move is logged and a seed on an unused initial state replaces it."""
    s = RolloutStore(tmp_path)
    dev, held = s.assign_splits("g", "6", dev=2, heldout=2)
    fresh = s.move_to_dev("g", "6", 1, "triggered a change in round 1")
    assert s.split_of("g", "6", 1) == DEV
    assert fresh not in dev + held and s.split_of("g", "6", fresh) == HELDOUT
    assert s.seeds("g", "6", HELDOUT) == sorted([2, fresh])
    moves = s.split_moves()
    assert len(moves) == 1 and moves[0]["seed"] == 1 and moves[0]["reason"].startswith("triggered")
    assert s.split_manifest("g", "6")["moves"][0]["to_split"] == DEV
    with pytest.raises(StoreError):
        s.move_to_dev("g", "6", dev[0], "dev seeds cannot move")


def test_append_only_and_query(tmp_path: Path) -> None:
    """A key is filed once; traces round-trip; the index answers by task, harness, outcome, split."""
    s = RolloutStore(tmp_path)
    s.assign_splits("g", "6", dev=3, heldout=1)
    k_ok = EpisodeKey("g", "6", 2, "", "profile")
    k_bad = EpisodeKey("g", "6", 3, "", "profile")
    r = s.add(k_ok, outcome("success"))
    s.add(k_bad, outcome("drop", 3))
    assert r.init_state == 2 and r.split == DEV and r.success
    with pytest.raises(StoreError, match="append-only"):
        s.add(k_ok, outcome("drop"))
    assert [x.seed for x in s.query(task="6", success=False)] == [3]
    assert len(s.query(harness="")) == 2 and s.query(harness="h@1") == []
    assert [x.seed for x in s.query(split=DEV)] == [2, 3]
    back = s.trace(s.get(k_bad))
    np.testing.assert_array_equal(back.obs["robot0_eef_pos"], make_trace("drop", 3).obs["robot0_eef_pos"])
    # A seed outside the task's splits is refused.
    with pytest.raises(StoreError, match="no split"):
        s.add(EpisodeKey("g", "6", 99, "", "profile"), outcome("success"))
    # A reopened store sees the same rows (the store is the checkpoint).
    s.close()
    assert RolloutStore(tmp_path).get(k_ok) is not None


def test_invalid_attempts_never_mix_with_rollouts(tmp_path: Path) -> None:
    """Invalid attempts are logged under their key and are not rollouts; the valid rerun is."""
    s = RolloutStore(tmp_path)
    s.assign_splits("g", "6", dev=1, heldout=1)
    key = EpisodeKey("g", "6", 2, "", "profile")
    s.log_invalid(key, "attempt 1: FAILED_PRECONDITION: session LOST")
    s.log_invalid(key, "attempt 2: UNAVAILABLE")
    assert s.get(key) is None and s.query() == []
    s.add(key, outcome("success"))
    assert len(s.query()) == 1 and len(s.invalid_attempts(key)) == 2


def test_rejected_buffer_and_events(tmp_path: Path) -> None:
    """Rejected fingerprints stay rejected across reopenings; events keep their order."""
    s = RolloutStore(tmp_path)
    s.reject("abc", "6/r1/K1", "held-out not improved")
    s.record("round_done", {"round": 1})
    s.record("round_done", {"round": 2})
    s.close()
    s = RolloutStore(tmp_path)
    assert s.is_rejected("abc") and not s.is_rejected("abd")
    assert [e["round"] for e in s.events("round_done")] == [1, 2]


def test_events_with_an_ident_read_back_latest_only(tmp_path: Path) -> None:
    """A resumed round that records its profile again does not double it in reports; both rows stay."""
    s = RolloutStore(tmp_path)
    s.record("profile", {"round": 1, "successes": 0}, ident="g/6/1")
    s.record("profile", {"round": 1, "successes": 2}, ident="g/6/1")
    s.record("profile", {"round": 2, "successes": 3}, ident="g/6/2")
    assert [(e["round"], e["successes"]) for e in s.events("profile")] == [(1, 2), (2, 3)]
    assert s._db.execute("SELECT COUNT(*) FROM events").fetchone()[0] == 3


def test_test_seeds_take_layouts_the_policy_never_trained_on(tmp_path) -> None:
    """The reported number starts from init states outside the policy's demonstrations; the
    decision splits take the rest."""
    s = RolloutStore(tmp_path / "store")
    dev, held = s.assign_splits("libero_goal_swap", "3", dev=10, heldout=10, test=20, trained=range(30))
    test = s.seeds("libero_goal_swap", "3", "test")
    assert sorted(t % 50 for t in test) == list(range(30, 50))
    assert not {d % 50 for d in dev + held} & {t % 50 for t in test}
    assert s.assign_splits("libero_goal_swap", "3", dev=10, heldout=10, test=20, trained=range(30)) == (dev, held)
    # More test seeds than unseen layouts: the rest come from the others, still disjoint.
    s.assign_splits("libero_goal_swap", "4", dev=0, heldout=0, test=25, trained=range(30))
    assert len({t % 50 for t in s.seeds("libero_goal_swap", "4", "test")}) == 25


def test_a_success_an_intervention_finished_is_flagged_and_not_credited(tmp_path: Path) -> None:
    """The store flags a success whose trace has an intervention still in control at the success
    step; such a rollout is a success but not a credited one. A store written before the flag had
    a column gets it when opened, filled from its traces."""
    s = RolloutStore(tmp_path)
    s.assign_splits("g", "6", dev=3, heldout=1)
    held = {"id": "iv1", "recovery": "fine_alignment", "outcome": "in_control_at_success", "actions": 9}
    handed = {"id": "iv1", "recovery": "regrasp", "outcome": "done", "actions": 9}
    finished = dataclasses.replace(outcome("success"), trace=dataclasses.replace(make_trace("success"),
                                                                                 interventions=[held]))
    cleared = dataclasses.replace(outcome("success"), trace=dataclasses.replace(make_trace("success"),
                                                                                interventions=[handed]))
    a = s.add(EpisodeKey("g", "6", 2, "h@1", "profile"), finished)
    b = s.add(EpisodeKey("g", "6", 3, "h@1", "profile"), cleared)
    assert a.success and a.in_control_at_success and not a.credited
    assert b.success and not b.in_control_at_success and b.credited
    s.close()
    db = sqlite3.connect(tmp_path / "index.sqlite")
    db.execute("ALTER TABLE rollouts DROP COLUMN in_control_at_success")
    db.commit()
    db.close()
    again = RolloutStore(tmp_path)
    assert [r.in_control_at_success for r in again.query(harness="h@1")] == [True, False]
