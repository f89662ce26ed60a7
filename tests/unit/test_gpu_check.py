"""bench/gpu_check.py without a GPU: the tiny profile runs, lists what it skipped and why, keeps a
step to its time limit, and exits 0; the scale-out predictions it compares with are found in the docs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "bench"))

import gpu_report  # noqa: E402


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the no-GPU path")
def test_tiny_run_without_a_gpu_lists_its_skips_and_exits_0(tmp_path: Path) -> None:
    results = tmp_path / "results"
    proc = subprocess.run([sys.executable, str(ROOT / "bench" / "gpu_check.py"), "--profile", "tiny", "--no-install",
                           "--results", str(results), "--limit", "serving=2", "--limit", "batch=200"],
                          cwd=ROOT, capture_output=True, text=True, timeout=400)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    doc = json.loads((results / "results.json").read_text())
    steps = doc["steps"]
    assert doc["profile"] == "tiny" and doc["checkpoint_why"]
    assert steps["setup"]["status"] in ("ran", "partial") and "torch" in steps["setup"]["note"]
    batch = steps["batch"]
    assert batch["status"] == "partial" and "no CUDA device" in batch["note"]
    assert set(batch["data"]["ms"]) == {"fp32 (cpu)", "w8a8 (cpu)"} and set(batch["data"]["ms"]["w8a8 (cpu)"]) == {"1", "8"}
    assert steps["serving"]["status"] == "timed out" and steps["serving"]["limit_s"] == 2
    for name in ("render", "rollout", "scale-out"):
        assert steps[name]["status"] == "skipped" and steps[name]["note"]
    summary = (results / "summary.md").read_text()
    listed = summary.split("## Skipped or incomplete")[1]
    for name in ("batch", "serving", "render", "rollout", "scale-out"):
        assert f"- {name}: " in listed


def test_scale_out_predictions_are_read_from_the_docs() -> None:
    pred = gpu_report.doc_predictions(ROOT / "docs" / "throughput.md")
    assert {"per_core_steps", "steps_per_episode", "gpu_batch_ms", "cores16_episodes_per_min"} <= set(pred)
    assert all(pred[k] > 0 for k in ("per_core_steps", "steps_per_episode", "gpu_batch_ms"))
