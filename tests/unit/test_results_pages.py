"""docs/results/: every page is what its results file renders (regenerated in a temp dir and
compared), every results file belongs to a known topic, and each topic's renderer works on a
results file of the shape its command writes."""

from __future__ import annotations

import importlib.util
import json
import platform
import shutil
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "docs" / "results"


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"_test_{name}", ROOT / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gen = _script("gen_results")


def test_every_results_file_has_a_topic_and_a_page() -> None:
    files = sorted(RESULTS.glob("*.json"))
    assert files, "docs/results/ holds no results file"
    for f in files:
        assert f.stem in gen.TOPICS, f"{f.name}: no topic renders it (scripts/gen_results.py TOPICS)"
        assert f.with_suffix(".md").exists(), f"{f.name}: its page {f.stem}.md is missing"
        doc = json.loads(f.read_text())
        assert doc.get("command"), f"{f.name} does not say which command measured it"
    for page in RESULTS.glob("*.md"):
        assert page.name == "README.md" or page.with_suffix(".json").exists(), f"{page.name} has no results file"


def test_the_pages_are_up_to_date_with_their_results_files(tmp_path: Path) -> None:
    assert gen.main(["--out-dir", str(tmp_path)]) == 0
    for f in sorted(RESULTS.glob("*.json")):
        fresh = (tmp_path / f"{f.stem}.md").read_text()
        assert fresh == f.with_suffix(".md").read_text(), (
            f"docs/results/{f.stem}.md is out of date with {f.name}: run python scripts/gen_results.py {f.stem}")
        assert "(generated)" in fresh.split("\n", 1)[0] and "do not edit by hand" in fresh


def test_check_finds_a_stale_page_and_from_publishes_a_file(tmp_path: Path) -> None:
    results = tmp_path / "results"
    shutil.copytree(RESULTS, results)
    assert gen.main(["--results-dir", str(results), "--check"]) == 0
    (results / "oracle.md").write_text("typed by hand\n")
    assert gen.main(["--results-dir", str(results), "--check"]) == 1
    doc = json.loads((results / "oracle.json").read_text())
    doc["episodes"] = doc["episodes"][:3]
    (tmp_path / "run.json").write_text(json.dumps(doc))
    assert gen.main(["--results-dir", str(results), "oracle", "--from", str(tmp_path / "run.json")]) == 0
    assert "Episodes run: 3 of 1500 planned" in (results / "oracle.md").read_text()
    (results / "stray.json").write_text("{}")
    with pytest.raises(SystemExit):
        gen.main(["--results-dir", str(results), "--check"])


_SOURCE = {"command": "c", "source": {"commit": "0123456789abcdef", "dirty": True}, "date": "d"}


def test_the_oracle_page_counts_per_task_and_suite() -> None:
    rows = [{"suite": "libero_goal", "task": 0, "init": i, "seed": 0, "instruction": "open it", "success": i != 1,
             "steps": 100 + i, "first_missing": "" if i != 1 else "open(x)", "wall_s": 1.0} for i in range(3)]
    page = gen.render("oracle", {**_SOURCE, "planned": 3, "seed": 0, "episodes": rows})
    assert "| libero_goal | 0 | open it | 2/3 |" in page and "`open(x)` (1)" in page
    assert "commit: `0123456789ab` (with uncommitted changes), d" in page


def test_the_harness_page_pairs_the_conditions() -> None:
    def row(cond: str, success: bool) -> dict:
        return {"suite": "libero_goal", "task": 6, "seed": 1, "condition": cond, "success": success,
                "first_missing_milestone": "" if success else "grasped(x)", "policy_actions": 30,
                "recovery_actions": 10 if cond == "harness" else 0, "kinds": ["regrasp"] if cond == "harness" else [],
                "outcomes": ["handed_back: ok"] if cond == "harness" else [],
                "interventions_by_kind": {"regrasp": 1} if cond == "harness" else {}}

    doc = {**_SOURCE, "harness": "examples/h", "content_hash": "ab" * 32, "model": "m", "checkpoint": "ck",
           "execute_steps": 4, "seeds": "1", "wall_s": 60.0, "rows": [row("bare", False), row("harness", True)]}
    page = gen.render("harness", doc)
    assert "| libero_goal | 6 | harness | 1/1 |" in page and "| libero_goal | 6 | 1 | no | grasped(x) | yes | - | 30/40 |" in page


def test_the_bench_rollout_page_from_its_episodes() -> None:
    def run(wall: float, n: int) -> dict:
        return {"wall_s": wall, "episodes": [{"index": i, "success": True, "steps": 100, "latency_s": 1.0,
                                              "build_s": 0.0} for i in range(n)]}

    doc = {**_SOURCE, "machine": "m", "load": [1.0, 2.0], "setup": {"stack_up_s": 5.0}, "max_steps": 300,
           "episodes_per_point": 4, "naive_episodes": 2, "repeats": 1,
           "points": [{"mode": "naive", "concurrency": 1, "runs": [run(4.0, 2)]},
                      {"mode": "run_episode", "concurrency": 4, "runs": [run(2.0, 4)]}]}
    page = gen.render("bench-rollout", doc)
    assert "| naive | 1 | 2 | 100% (2/2) | 30.0 | 1.00x |" in page and "| run_episode | 4 | 4 |" in page


def test_published_policy_figures_are_of_the_shipped_weights() -> None:
    """A figure measured on other weights no longer reproduces with the shipped checkpoint: re-measure
    it (or remove it) when the checkpoint changes. Every results file names its weights the same way.
    Until a long run is re-measured its file may say, and its page show at the top, that it is of
    the earlier weights; vla.json and demo.json, the policy's own figures, never wait."""
    from services.common.policies import checkpoint_dir
    from services.common.provenance import weights_sha256

    found = set()
    for f in sorted(RESULTS.glob("*.json")):
        doc = json.loads(f.read_text())
        policy = doc.get("policy") if isinstance(doc.get("policy"), dict) else doc
        sha, model = policy.get("checkpoint_sha256"), policy.get("model")
        if not sha or not isinstance(model, str) or checkpoint_dir(model) is None:
            continue
        shipped = weights_sha256(checkpoint_dir(model))
        if sha == shipped:
            found.add(f.name)
            continue
        note = doc.get("superseded") or {}
        assert f.name not in ("vla.json", "demo.json") and note.get("measured_sha256") == sha and \
            note.get("shipped_sha256") == shipped, (
            f"{f.name}: measured on {model} weights {sha[:12]}..., the shipped checkpoint's are {shipped[:12]}...: "
            f"re-measure (or, for a long run, `python scripts/gen_results.py {f.stem} --superseded NOTE`)")
        assert "Measured with earlier weights" in f.with_suffix(".md").read_text()
    assert {"vla.json", "demo.json"} <= found, "vla.json and demo.json name the weights they measured"


def test_the_policy_figures_are_measured_as_the_policy_is_served() -> None:
    """vla.json and demo.json are what a user gets from the default commands: measured at the
    actions per call every command defaults to, so changing EXECUTE_STEPS means re-measuring them."""
    from services.common.policies import EXECUTE_STEPS

    for name in ("vla.json", "demo.json"):
        doc = json.loads((RESULTS / name).read_text())
        assert doc["execute_steps"] == EXECUTE_STEPS, (
            f"{name} was measured at {doc['execute_steps']} actions per call, the default is {EXECUTE_STEPS}: re-measure it")


def test_a_superseded_results_file_says_so_at_the_top_of_its_page() -> None:
    from services.common.provenance import superseded

    doc = {**_SOURCE, "rendered": "table", "policy": {"model": "zetta-vla-image", "checkpoint_sha256": "a" * 64}}
    page = gen.render("harness-cost", superseded(doc, "b" * 64, "rerun: zetta x"))
    assert "**Measured with earlier weights** (model.pt sha256 `aaaaaaaaaaaa`)" in page and "rerun: zetta x" in page
    with pytest.raises(ValueError):
        superseded(doc, "a" * 64)


def test_a_result_whose_code_changed_says_so_at_the_top_of_its_page() -> None:
    from services.common.provenance import code_changed

    doc = {**_SOURCE, "rendered": "table"}
    measured = doc["source"]["commit"]
    page = gen.render("harness-cost", code_changed(doc, "c" * 40, "rerun: zetta y"))
    assert (f"**The code that measures it changed after this run** (at commit `cccccccccccc`): the figures "
            f"were measured at commit `{measured[:12]}`") in page and "rerun: zetta y" in page
    with pytest.raises(ValueError):
        code_changed(doc, measured)


def test_a_results_file_names_the_cpu_whose_kernels_made_its_floats(tmp_path: Path) -> None:
    """Episodes replay on the same kind of CPU only, so every run records which one and its page says it."""
    import os

    import torch

    from services.common.provenance import provenance

    doc = provenance("zetta x", tmp_path)
    cpus = len(os.sched_getaffinity(0))
    assert doc["machine"].startswith(f"{platform.machine()}, {cpus} CPUs")
    assert doc["machine"].endswith(f"torch CPU kernels {torch.backends.cpu.get_cpu_capability()}")
    page = gen.render("harness-cost", {**_SOURCE, "rendered": "table", "machine": doc["machine"]})
    assert f", on {doc['machine']}" in page.splitlines()[5]


def test_a_published_bench_names_the_command_that_reruns_it(tmp_path: Path) -> None:
    from services.common.provenance import page_header, publish

    paths = publish("x-bench", "X bench", "bench/x.py", ["--write-docs", "--n", "3"], {"rows": [1]},
                    lambda d: page_header("x-bench", d["title"], d), ROOT, tmp_path)
    doc = json.loads((tmp_path / "x-bench.json").read_text())
    assert paths == [tmp_path / "x-bench.json", tmp_path / "x-bench.md"]
    assert doc["command"] == "python bench/x.py --write-docs --n 3" and doc["rows"] == [1] and doc["title"] == "X bench"
    assert len(doc["source"]["commit"]) == 40
    assert "`python bench/x.py --write-docs --n 3`" in (tmp_path / "x-bench.md").read_text()
