"""The VLA's results file and its generated page: numbers with their seeds, intervals and
provenance, and a refusal to publish episodes from init states the checkpoint trained on."""

from __future__ import annotations

import json

import pytest

from services.policy_worker.vla.evaluate import done_rows
from services.common.policies import SAMPLED_LAYOUTS, training_init_states
from services.policy_worker.vla.results import _ranges, render, summarize, write_results


def _checkpoint(tmp_path, seed_offset: int = 1000, seeds_per_task: int = 30):
    ck = tmp_path / "ck"
    ck.mkdir()
    (ck / "model.pt").write_bytes(b"weights")
    recipe = {"suite": "libero_goal", "tasks": list(range(10)), "seed_offset": seed_offset,
              "seeds_per_task": seeds_per_task, "max_episodes": 10 * seeds_per_task}
    (ck / "config.json").write_text(json.dumps({"data": {"recipes": [{"recipe": recipe}]}}))
    return ck


def _rows(suite: str, seeds: range, successes: set[tuple[int, int]]) -> list[dict]:
    return [{"suite": suite, "task": t, "seed": s, "init_state_index": s % 50, "instruction": f"task {t}",
             "success": (t, s) in successes} for t in (0, 1) for s in seeds]


def test_summary_counts_and_intervals() -> None:
    rows = _rows("libero_goal", range(30, 40), {(0, 30), (0, 31), (1, 30)}) + [{"suite": "libero_goal", "error": "x"}]
    s = summarize(rows)["libero_goal"]
    assert s["tasks"]["0"]["successes"] == 2 and s["tasks"]["0"]["episodes"] == 10
    assert s["total"] == {"successes": 3, "episodes": 20, "wilson95": s["total"]["wilson95"]}
    lo, hi = s["total"]["wilson95"]
    assert 0.04 < lo < 0.06 and 0.35 < hi < 0.38
    assert s["init_states"] == list(range(30, 40))


def test_training_init_states_come_from_the_recipes(tmp_path) -> None:
    ck = _checkpoint(tmp_path)
    assert training_init_states(ck) == {"libero_goal": list(range(30))}
    doc = json.loads((ck / "config.json").read_text())
    sampled = {**doc["data"]["recipes"][0]["recipe"], "seed_offset": 5030, "init_states": SAMPLED_LAYOUTS}
    doc["data"]["recipes"].append({"recipe": sampled})  # its seeds map to no benchmark state
    (ck / "config.json").write_text(json.dumps(doc))
    assert training_init_states(ck) == {"libero_goal": list(range(30))}


def test_results_refuse_init_states_the_checkpoint_trained_on(tmp_path) -> None:
    ck = _checkpoint(tmp_path)
    with pytest.raises(ValueError, match=r"libero_goal_swap: init states \[20, 21"):
        write_results(tmp_path / "r.json", _rows("libero_goal_swap", range(20, 40), set()), model="m",
                      checkpoint=ck, execute_steps=4, command=["zetta"], wall_s=1.0)
    doc = write_results(tmp_path / "r.json", _rows("libero_goal", range(30, 50), {(1, 49)}), model="m",
                        checkpoint=ck, execute_steps=4, command=["zetta", "eval-policy"], wall_s=61.0)
    assert len(doc["checkpoint_sha256"]) == 64 and doc["command"] == "zetta eval-policy"
    page = render(json.loads((tmp_path / "r.json").read_text()))
    assert "| libero_goal | 1/40 | 2% |" in page and "init states 0-29" in page and "30-49" in page


def test_a_run_keeps_suites_measured_on_the_same_weights_and_drops_others(tmp_path) -> None:
    ck, out = _checkpoint(tmp_path), tmp_path / "r.json"
    common = {"model": "m", "checkpoint": ck, "execute_steps": 4, "wall_s": 1.0}
    write_results(out, _rows("libero_goal", range(30, 50), set()), command=["first"], **common)
    doc = write_results(out, _rows("libero_goal_lan", range(30, 50), {(0, 30)}), command=["second"], **common)
    assert list(doc["suites"]) == ["libero_goal", "libero_goal_lan"]
    assert [(r["command"], r["suites"]) for r in doc["runs"]] == [("second", ["libero_goal_lan"]),
                                                                   ("first", ["libero_goal"])]
    page = render(doc)
    assert "- libero_goal_lan: `second`" in page and "- libero_goal: `first`" in page
    doc = write_results(out, _rows("libero_goal", range(30, 50), {(0, 31)}), command=["third"], **common)
    assert doc["suites"]["libero_goal"]["total"]["successes"] == 1 and len(doc["runs"]) == 2
    (ck / "model.pt").write_bytes(b"other weights")
    doc = write_results(out, _rows("libero_goal_swap", range(30, 50), set()), command=["fourth"], **common)
    assert list(doc["suites"]) == ["libero_goal_swap"] and len(doc["runs"]) == 1
    doc = write_results(out, _rows("libero_goal", range(30, 50), set()), command=["fifth"], **{**common, "execute_steps": 2})
    assert list(doc["suites"]) == ["libero_goal"]


def test_ranges() -> None:
    assert _ranges([0, 1, 2, 5, 7, 8]) == "0-2, 5, 7-8" and _ranges([]) == "none"


def test_an_evaluation_resumes_from_its_rows(tmp_path) -> None:
    path = tmp_path / "e.jsonl"
    same = {"model": "m", "suite": "s", "execute_steps": 4, "env": {}}
    lines = [{**same, "task": 0, "seed": 1, "success": True}, {**same, "task": 0, "seed": 2, "error": "boom"},
             {**same, "execute_steps": 2, "task": 0, "seed": 3, "success": True}]
    path.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    assert list(done_rows(str(path), "m", "s", 4, {})) == [(0, 1, 1)]
    assert done_rows(str(tmp_path / "none.jsonl"), "m", "s", 4, {}) == {}


def test_a_sampled_layout_row_is_not_the_benchmark_episode_of_its_seed(tmp_path) -> None:
    """Rows are done by (task, seed, init state): an evaluation on sampled layouts (init -1) and one
    on the benchmark's states resume from their own rows in a shared file."""
    path = tmp_path / "e.jsonl"
    same = {"model": "m", "suite": "s", "execute_steps": 4, "env": {}, "task": 0, "success": True}
    lines = [{**same, "seed": 51, "init_state_index": -1}, {**same, "seed": 52, "init_state_index": 2}]
    path.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    assert sorted(done_rows(str(path), "m", "s", 4, {})) == [(0, 51, -1), (0, 52, 2)]


def test_sampled_layouts_are_never_published(tmp_path, capsys) -> None:
    """A results page reports benchmark init states: eval-policy refuses to publish sampled layouts."""
    from services.policy_worker.vla.evaluate import main

    with pytest.raises(SystemExit) as exc:
        main(["--sampled-layouts", "--results", str(tmp_path / "vla.json"), "--out", str(tmp_path / "e.jsonl")])
    assert exc.value.code == 2 and "publish nothing" in capsys.readouterr().err
    assert not (tmp_path / "e.jsonl").exists()
