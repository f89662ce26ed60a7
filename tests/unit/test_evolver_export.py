"""The Markdown report, from a store filled with constructed rollouts (the export: test_lerobot_export.py)."""

from __future__ import annotations

from pathlib import Path


from services.evolver.report import write_report
from services.evolver.store import EpisodeKey, Outcome, RolloutStore
from tests.unit.test_evolver_fixtures import make_trace


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
