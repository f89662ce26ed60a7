"""Publishing an experiment packs its stores beside its page: the archives hold every rollout the
results file counts, replace the page's older ones, and stay under the stated size in all."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.evolver import history, store_archive
from services.evolver.store import EpisodeKey, RolloutStore
from tests.unit.test_evolver_store import outcome
from tests.unit.test_results_pages import RESULTS, gen


def _run(root: Path) -> dict:
    """A run dir with one evolved suite's store (3 profile + 1 test rollouts) and an empty transfer store."""
    store = RolloutStore(root / "libero_goal_task")
    dev, _ = store.assign_splits("libero_goal_task", "5", dev=3, heldout=1, test=1)
    for seed in dev:
        store.add(EpisodeKey("libero_goal_task", "5", seed, "", "profile"), outcome("miss", seed))
    test = store.seeds("libero_goal_task", "5", "test")[0]
    store.add(EpisodeKey("libero_goal_task", "5", test, "e-5@1", "test"), outcome("success", test))
    store.record("final", {"suite": "libero_goal_task", "task": "5"})
    empty = RolloutStore(root / "transfer-libero_goal_lan")
    doc = {"rollouts_by_purpose": {"libero_goal_task": history.rollout_counts(store),
                                   "transfer-libero_goal_lan": history.rollout_counts(empty)}}
    store.close()
    empty.close()
    return doc


def test_a_published_run_s_archives_hold_what_its_results_file_counts(tmp_path: Path) -> None:
    doc = _run(tmp_path / "run")
    results = tmp_path / "results"
    (results / "evolution-stores").mkdir(parents=True)
    (results / "evolution-stores" / f"libero_goal_swap{store_archive.SUFFIX}").write_bytes(b"an older run's")
    (results / "evolution-goal-stores").mkdir()
    (results / "evolution-goal-stores" / f"libero_goal{store_archive.SUFFIX}").write_bytes(b"another page's")
    written = store_archive.pack(tmp_path / "run", doc, results, "evolution")
    assert [p.name for p in written] == [f"libero_goal_task{store_archive.SUFFIX}"], "a store that ran nothing is left out"
    assert sorted(p.name for p in (results / "evolution-stores").iterdir()) == [p.name for p in written]
    assert store_archive.rollout_counts(written[0]) == {"profile": 3, "test": 1}
    assert (results / "evolution-goal-stores" / f"libero_goal{store_archive.SUFFIX}").read_bytes() == b"another page's"


def test_archives_over_the_limit_or_a_missing_store_write_nothing(tmp_path: Path, monkeypatch) -> None:
    doc = _run(tmp_path / "run")
    results = tmp_path / "results"
    old = results / "evolution-stores" / f"libero_goal_swap{store_archive.SUFFIX}"
    old.parent.mkdir(parents=True)
    old.write_bytes(b"kept")
    monkeypatch.setattr(store_archive, "LIMIT_BYTES", 100)
    with pytest.raises(ValueError, match="over the 100 limit"):
        store_archive.pack(tmp_path / "run", doc, results, "evolution")
    assert old.read_bytes() == b"kept"
    monkeypatch.undo()
    with pytest.raises(ValueError, match="not beside its results file"):
        store_archive.pack(tmp_path / "elsewhere", doc, results, "evolution")
    assert old.read_bytes() == b"kept"


def test_publishing_without_the_run_s_stores_is_a_usage_error(tmp_path: Path, capsys) -> None:
    """gen_results.py evolution --from a results file whose stores are not beside it publishes nothing."""
    doc = _run(tmp_path / "run")
    source = tmp_path / "copied" / "results.json"
    source.parent.mkdir()
    source.write_text(json.dumps(doc))
    results = tmp_path / "results"
    results.mkdir()
    with pytest.raises(SystemExit) as exc:
        gen.main(["--results-dir", str(results), "evolution", "--from", str(source)])
    assert exc.value.code == 2 and "not beside its results file" in capsys.readouterr().err
    assert list(results.iterdir()) == []


@pytest.mark.parametrize("topic", gen.STORE_TOPICS)
def test_the_committed_archives_are_the_published_runs(topic: str) -> None:
    """Each page's archives are its run's stores, with the rollouts its results file counts."""
    doc = json.loads((RESULTS / f"{topic}.json").read_text())
    folder = store_archive.stores_dir(RESULTS, topic)
    names = store_archive.published_stores(doc)
    assert sorted(p.name for p in folder.glob(f"*{store_archive.SUFFIX}")) == [f"{n}{store_archive.SUFFIX}"
                                                                               for n in names]
    for name in names:
        want = {p: c["rollouts"] for p, c in doc["rollouts_by_purpose"][name]["purposes"].items()}
        assert store_archive.rollout_counts(folder / f"{name}{store_archive.SUFFIX}") == want, name


def test_the_committed_archives_stay_under_the_stated_size() -> None:
    total = sum(f.stat().st_size for f in RESULTS.glob(f"*-stores/*{store_archive.SUFFIX}"))
    assert 0 < total <= store_archive.LIMIT_BYTES
    assert f"under {store_archive.LIMIT_BYTES // 1000} KB in all" in (RESULTS / "README.md").read_text()
