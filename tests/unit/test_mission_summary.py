"""The mission demo's arithmetic and its printed rows, from a report document."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.ops.mission_demo import recovered, recovery_share, summary
from zetta.client import EpisodeSummary, HarnessReport

ROOT = Path(__file__).resolve().parents[2]


def _row(condition: str, seed: int, success: bool, policy: int, recovery: int, kinds: tuple[str, ...] = ()) -> dict:
    return {"condition": condition, "seed": seed, "success": success, "policy_actions": policy,
            "recovery_actions": recovery, "interventions": [{"kind": k, "outcome": "reentered"} for k in kinds]}


DOC = {"suite": "libero_goal_swap", "task": "t", "seeds": [0, 1], "model": "m", "checkpoint_sha256": "ab" * 32,
       "harness": "h", "harness_content_hash": "cd" * 32, "execute_steps": 4, "wall_s": 12.0,
       "video": "out/demo/videos/e.mp4", "video_seed": 0, "episodes": [
           _row("bare", 0, False, 300, 0), _row("bare", 1, True, 120, 0),
           _row("harness", 0, True, 90, 10, ("acquire",)), _row("harness", 1, True, 100, 0),
           _row("control", 0, False, 240, 60, ("redirect", "redirect")),
           _row("control", 1, False, 240, 60, ("redirect", "redirect"))]}


def test_recovery_share_counts_actions() -> None:
    assert recovery_share(DOC["episodes"][2:4]) == 10 / 200
    assert recovery_share([]) == 0.0


def test_recovered_needs_a_success_with_recovery_actions() -> None:
    def episode(success: bool, recovery: int) -> EpisodeSummary:
        report = HarnessReport(harness="h", version="", content_hash="x", policy_actions=10, recovery_actions=recovery,
                               actions_by_mode={}, interventions=[], interventions_by_kind={}, disabled_critics=[],
                               proposals=0, rejected=0)
        return EpisodeSummary("s", "e", 10, 0.0, success, "", 0.0, 0, harness_report=report)

    assert recovered(episode(True, 5)) and not recovered(episode(True, 0)) and not recovered(episode(False, 5))


def test_summary_prints_every_condition_with_its_interval() -> None:
    lines = summary(DOC, "out/demo/report.json").splitlines()
    bare = next(line for line in lines if line.startswith("frozen policy alone"))
    assert "1/2" in bare and "50%" in bare and "9%-91%" in bare
    control = next(line for line in lines if line.startswith("do-nothing policy + harness"))
    assert "0/2" in control and "20%" in control and "redirect: 4" in control
    assert any("successful harness episodes: 5%" in line for line in lines)
    assert "video of a recovered episode (seed 0): out/demo/videos/e.mp4" in lines


def test_readme_shows_the_published_demo_report() -> None:
    results = ROOT / "docs" / "results" / "demo.json"
    if not results.exists():
        pytest.skip("no published demo report yet (docs/results/demo.json)")
    sys_path = str(ROOT / "scripts")
    import sys

    sys.path.insert(0, sys_path)
    try:
        from gen_readme_demo import render
    finally:
        sys.path.remove(sys_path)
    readme = (ROOT / "README.md").read_text()
    assert render(readme, json.loads(results.read_text())) == readme, "run scripts/gen_readme_demo.py"
