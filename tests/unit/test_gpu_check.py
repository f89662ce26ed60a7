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
@pytest.mark.timeout(420)
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
    pred = gpu_report.doc_predictions(ROOT / "docs" / "results" / "throughput.md")
    assert {"per_core_steps", "steps_per_episode", "gpu_batch_ms", "cores16_episodes_per_min"} <= set(pred)
    assert all(pred[k] > 0 for k in ("per_core_steps", "steps_per_episode", "gpu_batch_ms"))


def _rollout_doc() -> dict:
    """A `zetta bench rollout --json` document: 14 env workers, stack points at 8 and 32, the policy on a GPU."""
    from bench import sweep_results as bs

    def row(mode: str, c: int, latency: float, wall: float) -> bs.Row:
        usage = bs.Usage(100.0, 90.0, 5.0, 1.0, cpu_s=0.3 * c, cpu_s_by_process={"env-0": 0.28 * c, "policy-0": 0.02 * c})
        return bs.Row(mode, c, [bs.Episode(i, True, 100, latency) for i in range(c)], wall, usage, batch_mean=8.0)

    res = bs.Results({"env_workers": 14, "model": "zetta-vla-image", "max_steps": 120}, "m", "now", 0.0,
                     rows=[row("limit-obs", 16, 0.3, 1.0), row("stack", 8, 4.0, 10.0), row("stack", 32, 6.0, 10.0)],
                     inference_ms={1: 2.0, 64: 6.0}, policy_ops=500, chunk=8)
    return {**res.to_json(), "policy_device": "cuda", "command": "python -m zetta.cli bench rollout"}


def test_rollout_and_scale_out_sections() -> None:
    """The 32-vs-8 latency ratio against the 2x target; the docs' per-core figure scaled to the env
    workers run against the measured steps/s; the GPU batch time against the docs' PREDICTED one."""
    rollout = _rollout_doc()
    growth = gpu_report.latency_growth(rollout)
    assert growth is not None and growth["p50_ratio"] == pytest.approx(1.5)
    batch = type("Step", (), {"data": {"device": "cuda", "ms": {"fp32 (gpu)": {"64": 2.0}}}})()
    comparison = gpu_report.scale_out_comparison(rollout, batch, ROOT / "docs" / "results" / "throughput.md")
    pred = gpu_report.doc_predictions(ROOT / "docs" / "results" / "throughput.md")
    rows = {r["quantity"].split(" (")[0]: r for r in comparison["rows"]}
    steps = rows["stack steps/s with 14 env workers"]
    assert steps["predicted"] == pytest.approx(14 * pred["per_core_steps"]) and steps["measured"] == pytest.approx(320.0)
    gpu = rows["policy inference on the GPU, batch 64"]
    assert gpu["predicted"] == pred["gpu_batch_ms"] and gpu["measured"] == 2.0
    doc = {"started": "now", "finished": "now", "command": "c", "machine": "m", "gpu": "H200", "profile": "gpu",
           "python": "p", "checkpoint": "ck", "checkpoint_why": "w", "rollout_model": "zetta-vla-image",
           "steps": {"setup": {"status": "ran", "seconds": 1, "limit_s": 60, "note": "n", "data": {}},
                     "rollout": {"status": "ran", "seconds": 1, "limit_s": 1, "note": "", "data": rollout},
                     "scale-out": {"status": "ran", "seconds": 0, "limit_s": 0, "note": "", "data": comparison}}}
    text = gpu_report.summary(doc)
    assert "p50 1.50x" in text and "target under 2x: met" in text and "figures unreadable" not in text
    assert "| policy inference on the GPU, batch 64 (ms) |" in text
