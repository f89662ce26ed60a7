"""`zetta train`'s pipeline on the real simulator and the real oracle, shrunk to seconds: teacher
demos on sampled layouts count no benchmark init state as trained on, and a rerun of the same
pipeline reuses its sets and its stage instead of collecting and training again."""

from __future__ import annotations

import json

from services.common.policies import SAMPLED_LAYOUTS, training_init_states
from services.policy_worker.vla.model import VLAConfig
from services.policy_worker.vla.train import PipelineConfig, TrainConfig, run_pipeline


def test_sampled_teacher_layouts_train_on_no_benchmark_state_and_a_rerun_reuses_everything(tmp_path) -> None:
    pipe = PipelineConfig(clean_episodes=2, noisy_episodes=0, teacher_layouts="sampled", steps=2, dagger_rounds=0,
                          execute_steps=4)
    model = VLAConfig(image_size=32, width=16, prefix_hidden=32, expert_hidden=16, expert_blocks=1)
    train = TrainConfig(steps=2, batch_size=4, warmup=1)
    out, demos = str(tmp_path / "ck"), str(tmp_path / "demos")
    logs: list[str] = []
    run_pipeline(out, pipe, "oracle", [1], 1, train, model, demo_dir=demos, log=lambda m: logs.append(str(m)))
    recipe = json.loads((tmp_path / "demos" / "clean.npz.json").read_text())
    assert recipe["recipe"]["init_states"] == SAMPLED_LAYOUTS and recipe["demos_kept"] >= 1, recipe
    config = json.loads((tmp_path / "ck" / "config.json").read_text())
    assert config["pipeline"]["teacher_layouts"] == "sampled"
    assert training_init_states(tmp_path / "ck") == {}, "sampled layouts are none of the benchmark's"
    logs.clear()
    run_pipeline(out, pipe, "oracle", [1], 1, train, model, demo_dir=demos, log=lambda m: logs.append(str(m)))
    assert any("reusing" in m and "ck" in m for m in logs), logs
    assert not any("demos_kept" in m for m in logs), "nothing is collected again"
