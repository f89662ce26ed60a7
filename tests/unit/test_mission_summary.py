"""The mission demo's arithmetic: recoveries' share, interventions by kind, the printed rows."""

from __future__ import annotations

from pathlib import Path

from services.ops.mission_demo import ConditionResult, MissionResult, MissionSpec, recovered, summary
from zetta.client import EpisodeSummary, HarnessReport


def _episode(success: bool, policy: int, recovery: int, kinds: dict[str, int] | None) -> EpisodeSummary:
    report = None
    if kinds is not None:
        report = HarnessReport(harness="h", version="", content_hash="x", policy_actions=policy,
                               recovery_actions=recovery, actions_by_mode={}, interventions=[],
                               interventions_by_kind=kinds, disabled_critics=[], proposals=0, rejected=0)
    return EpisodeSummary(session_id="s", episode_id="e", steps=policy + recovery, reward=0.0, success=success,
                          stop_reason="", wall_ms=0.0, policy_calls=0, harness_report=report)


def test_shares_count_actions_and_successes_only_when_asked() -> None:
    cond = ConditionResult("harness", [_episode(True, 90, 10, {"acquire": 1}), _episode(False, 20, 80, {"redirect": 2})])
    assert cond.successes == 1
    assert cond.recovery_share() == 90 / 200
    assert cond.recovery_share(successful_only=True) == 0.1
    assert cond.interventions() == {"acquire": 1, "redirect": 2}
    assert recovered(cond.episodes[0]) and not recovered(cond.episodes[1])
    assert not recovered(_episode(True, 100, 0, {}))


def test_summary_prints_every_condition_with_its_interval() -> None:
    spec = MissionSpec(seeds=(0, 1))
    res = MissionResult(spec, {
        "bare": ConditionResult("bare", [_episode(False, 300, 0, None), _episode(True, 120, 0, None)]),
        "harness": ConditionResult("harness", [_episode(True, 90, 10, {"acquire": 1}), _episode(True, 100, 0, {})]),
        "control": ConditionResult("control", [_episode(False, 240, 60, {"redirect": 2})] * 2),
    }, wall_s=12.0, video="/v/e.mp4", video_seed=0, report_path=Path("out/demo/report.json"))
    lines = summary(res).splitlines()
    bare = next(line for line in lines if line.startswith("frozen policy alone"))
    assert "1/2" in bare and "50%" in bare and "9%-91%" in bare
    control = next(line for line in lines if line.startswith("do-nothing policy + harness"))
    assert "0/2" in control and "20%" in control and "redirect: 4" in control
    assert any("successful harness episodes: 5%" in line for line in lines)
    assert lines[-2].endswith("(seed 0): /v/e.mp4")
