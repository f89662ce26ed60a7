"""The front-door demo over the real stack: the shipped image VLA bare, under the example harness,
and the harness around the do-nothing policy, on the same seed; its report names what ran."""

from __future__ import annotations

import hashlib
import json

from services.common.policies import DEFAULT_POLICY, default_checkpoint
from services.ops.mission_demo import CONDITIONS, LABELS, MissionSpec, run_mission, summary


async def test_three_conditions_on_the_same_seed_and_a_report(stack_factory, tmp_path) -> None:
    videos = tmp_path / "videos"
    videos.mkdir()
    stack = stack_factory(env_workers=1, slots=1, families=("libero",), models=(DEFAULT_POLICY, "do-nothing"),
                          heartbeat_timeout_ms=15000, extra_env={"ZETTA_VIDEO_DIR": str(videos)})
    spec = MissionSpec(seeds=(3,), max_steps=24, out_dir=tmp_path / "demo")
    res = await run_mission(stack.gateway_address, spec, log=lambda *_: None)

    assert list(res.conditions) == list(CONDITIONS)
    for name, cond in res.conditions.items():
        assert len(cond.episodes) == 1 and cond.episodes[0].steps <= 24
        assert (cond.episodes[0].harness_report is None) == (name == "bare")
    doc = json.loads(res.report_path.read_text())
    assert [r["condition"] for r in doc["episodes"]] == list(CONDITIONS)
    assert {r["seed"] for r in doc["episodes"]} == {3} and doc["suite"] == "libero_goal_lan"
    expected = hashlib.sha256((default_checkpoint() / "model.pt").read_bytes()).hexdigest()
    assert doc["checkpoint_sha256"] == expected and len(doc["harness_content_hash"]) == 64
    text = summary(doc, res.report_path)
    for label in LABELS.values():
        assert label in text
    assert str(res.report_path) in text
