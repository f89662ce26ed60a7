"""LeRobot-style export and the Markdown report, from a store filled with constructed rollouts."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from services.evolver.export import export_lerobot
from services.evolver.report import write_report
from services.evolver.store import EpisodeKey, Outcome, RolloutStore
from tests.unit.test_evolver_fixtures import K, make_trace


def filled(tmp_path: Path) -> RolloutStore:
    s = RolloutStore(tmp_path / "store")
    s.assign_splits("g", "6", dev=2, heldout=1)
    video = tmp_path / "v.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42")
    for seed, kind in ((2, "success"), (3, "drop")):
        tr = make_trace(kind, seed)
        s.add(EpisodeKey("g", "6", seed, "", "profile"),
              Outcome(kind == "success", int(tr.frame_step[-1]), "" if kind == "success" else "on(a,b)", [], tr,
                      str(video) if seed == 2 else "", 1.0))
    return s


def test_export_writes_parquet_videos_and_meta(tmp_path: Path) -> None:
    """One parquet per episode with one row per executed action, the video copied, meta consistent."""
    s = filled(tmp_path)
    info = export_lerobot(s, s.query(), tmp_path / "ds", {"6": "put the a on the b"})
    rows = 2 * (K - 1)
    assert info["total_episodes"] == 2 and info["total_frames"] == 2 * rows and info["total_videos"] == 1
    t = pq.read_table(tmp_path / "ds" / "data" / "chunk-000" / "episode_000001.parquet")
    assert t.num_rows == rows and t.column("index")[0].as_py() == rows
    assert len(t.column("action")[0].as_py()) == 7 and len(t.column("observation.state")[0].as_py()) == 16
    assert t.column("next.done")[-1].as_py() and not t.column("next.success")[-1].as_py()
    assert (tmp_path / "ds" / "videos" / "chunk-000" / "observation.images.agentview" / "episode_000000.mp4").exists()
    meta = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert meta["features"]["action"]["shape"] == [7] and meta["fps"] == 20
    tasks = (tmp_path / "ds" / "meta" / "tasks.jsonl").read_text().splitlines()
    assert json.loads(tasks[0]) == {"task_index": 0, "task": "put the a on the b"}
    with pytest.raises(FileExistsError):
        export_lerobot(s, s.query(), tmp_path / "ds")


def test_report_from_recorded_events(tmp_path: Path) -> None:
    """The report states what the store recorded: per-round success with intervals, version curves,
    the gate decision and the lineage, with its plots written next to it."""
    s = filled(tmp_path)
    s.record("profile", {"suite": "g", "task": "6", "round": 1, "harness": "bare", "successes": 1, "episodes": 2})
    s.record("cluster_versions", {"suite": "g", "task": "6", "round": 1, "cluster": "6/r1/K1",
                                  "versions": [{"version": "v0", "successes": 0, "episodes": 3},
                                               {"version": "v1", "successes": 2, "episodes": 3}]})
    verdict = {"admitted": True, "reason": "held-out 2/2 > current 1/2", "delta_over_bare": 0.5}
    s.record("gate", {"task": "6", "round": 1, "candidate": "e-6-candidate@1", "verdict": verdict})
    s.record("admitted", {"suite": "g", "task": "6", "round": 1, "ref": "e-6@1", "parent": "bare", "verdict": verdict,
                          "patches": [{"critic": "c_grasp_lost", "template": "grasp_lost", "params": {"confirm": 3},
                                       "recovery": "regrasp"}]})
    arm = {"successes": 0, "episodes": 2, "recovery_share": 0.25, "policy_in_control_at_success": 1.0}
    s.record("final", {"suite": "g", "task": "6", "harness": "e-6@1", "bare": [1, 2], "final": [2, 2], "seeds": [1, 4],
                       "arms": {"final": arm, "control": arm}})
    md = write_report(s, tmp_path / "report", "Evolution test", wall_s=12.0).read_text()
    assert "| +50% | 0/2 = 0% [0%, 66%] | 25% | 100% |" in md
    assert "1/2 = 50% [9%, 91%]" in md and "v0 0/3, v1 2/3" in md and "ADMITTED" in md
    assert "e-6@1 (parent bare, round 1): c_grasp_lost(grasp_lost" in md and "+50%" in md
    for png in ("rounds.png", "versions.png", "test.png"):
        assert (tmp_path / "report" / png).stat().st_size > 1000
