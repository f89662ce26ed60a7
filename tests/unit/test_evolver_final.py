"""The final measurement's wall time survives a resumed run that reads every rollout back."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.rollout import RunConfig
from services.evolver.store import TEST, EpisodeKey, RolloutStore
from tests.unit.test_evolver_store import outcome

SUITE = "libero_goal"


def test_a_resumed_final_keeps_the_time_the_measurement_took(tmp_path: Path) -> None:
    """Every test rollout is in the store (no gateway is reached: the address is closed); the task's
    earlier final event took 120 s, and the re-recorded one still says so, not the ~0 s of the read."""
    store = RolloutStore(tmp_path)
    store.assign_splits(SUITE, "6", dev=2, heldout=2, test=3)
    seeds = store.seeds(SUITE, "6", TEST)
    for s in seeds:
        store.add(EpisodeKey(SUITE, "6", s, "", "test"), outcome("success" if s % 2 else "miss", s))
        store.add(EpisodeKey(SUITE, "6", s, "", "control-test"), outcome("miss", s))
    cfg = EvolveConfig(suite=SUITE, tasks=("6",), dev_seeds=2, heldout_seeds=2, test_seeds=3, nominal_seeds=0)
    evo = Evolution(cfg, store, RunConfig(gateway="127.0.0.1:1", model="do-nothing"), None)
    evo.final_eval("6")
    (first,) = store.events("final")
    assert first["final"] == [2, 3] and first["wall_s"] < 5.0
    store.record("final", {**{k: v for k, v in first.items() if k != "kind"}, "wall_s": 120.0}, ident=f"{SUITE}/6")
    evo.final_eval("6")
    (again,) = store.events("final")
    assert again["wall_s"] == pytest.approx(120.0, abs=5.0) and again["arms"] == first["arms"]
