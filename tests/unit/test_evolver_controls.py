"""One arm's numbers from a real rollout store: success with its interval, the recoveries' share
of the actions of successful episodes (the policy's actions under a redirected instruction
included, and counted apart), and the share of successes the policy was in control at."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from services.evolver.controls import arm
from services.evolver.store import EpisodeKey, RolloutStore
from tests.unit.test_evolver_store import outcome


def _with(kind: str, seed: int, interventions: list[dict], recovery_steps: int):
    out = outcome(kind, seed)
    trace = dataclasses.replace(out.trace, interventions=interventions, recovery_steps=recovery_steps)
    return dataclasses.replace(out, trace=trace)


def test_an_arm_counts_recoveries_redirections_and_who_was_in_control(tmp_path: Path) -> None:
    store = RolloutStore(tmp_path)
    redirect = {"id": "iv1", "recovery": "redirect", "actions": 10, "outcome": "reentered",
                "instruction": "put the wine bottle on the rack"}
    place = {"id": "iv2", "recovery": "place", "actions": 6, "outcome": "in_control_at_success", "instruction": ""}
    rows = [
        (1, _with("success", 1, [redirect, place], 16)),  # the place recovery finished it
        (2, _with("success", 2, [redirect], 10)),  # the policy finished it after a redirection
        (3, _with("success", 3, [], 0)),
        (4, _with("miss", 4, [redirect], 10)),  # failures count in the rate only
    ]
    store.assign_splits("libero_goal_task", "8", dev=1, heldout=1, test=4)
    for seed, out in rows:
        store.add(EpisodeKey("libero_goal_task", "8", seed, "h@1", "test"), out)
    got = arm(store, store.query(suite="libero_goal_task", task="8", harness="h@1", purpose="test"))
    wins = [out for _, out in rows if out.success]
    actions = sum(o.steps for o in wins)
    assert (got["successes"], got["episodes"], got["seeds"]) == (3, 4, [1, 2, 3, 4])
    assert got["rate"] == 0.75 and got["wilson95"][0] < 0.75 < got["wilson95"][1]
    assert got["recovery_share"] == pytest.approx(26 / actions)
    assert got["redirected_share"] == pytest.approx(20 / actions)
    assert got["policy_in_control_at_success"] == pytest.approx(2 / 3)
