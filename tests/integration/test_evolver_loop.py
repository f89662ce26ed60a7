"""The evolution loops against the real stack: gateway, env workers running harnesses from the
critic service's registry, a policy worker, Redis, all over gRPC on loopback.

Budgets are tiny (40-step episodes, 2 dev seeds, 1 held-out seed); the assertions are about what
the system must guarantee whatever the outcomes: rollouts filed with full traces, splits kept
apart, every candidate published and run as a real harness, the report and the export written,
and a resumed run that reruns nothing.
"""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.lerobot_export import export_lerobot
from services.evolver.gate import GateParams
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.repair import SearchParams
from services.evolver.rollout import Runner, RunConfig
from services.evolver.stack import Endpoints, endpoints
from services.evolver.store import DEV, HELDOUT, EpisodeKey, RolloutStore
from tests.conftest import new_stack

pytestmark = pytest.mark.slow

TASK = "put_the_cream_cheese_in_the_bowl"
#: The purposes whose rollouts may only use dev seeds (the held-out set is for gating only).
DEV_PURPOSES = {"profile", "validate", "regress"}


@pytest.fixture(scope="module")
def evo_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Endpoints]:
    """A local stack whose env workers load harness versions from its critic service."""
    with endpoints(None, None, "scripted-pick-place", env_workers=1, slots=2,
                   workdir=tmp_path_factory.mktemp("evo-stack"), video=True) as ep:
        yield ep


def config() -> EvolveConfig:
    return EvolveConfig(suite="libero_goal", tasks=(TASK,), rounds=1, dev_seeds=2, heldout_seeds=1, name="it",
                        max_clusters=1, search=SearchParams(max_candidates=1), gate=GateParams(0.0))


def test_one_round_end_to_end_and_resume(evo_stack: Endpoints, tmp_path: Path) -> None:
    """Profile, cluster, diagnose, repair, validate as a real harness, gate, final evaluation; the
    store keeps dev and held-out apart; running again reruns nothing."""
    store = RolloutStore(tmp_path / "store")
    run = RunConfig(gateway=evo_stack.gateway, model="scripted-pick-place", max_steps=40, concurrency=2)
    registry = RegistryClient(evo_stack.registry)
    phases: list[str] = []
    Evolution(config(), store, run, registry, lambda p, d, t: phases.append(p) if d == 0 else None).run()

    profile = store.query(purpose="profile")
    assert sorted(r.seed for r in profile) == store.seeds("libero_goal", TASK, DEV) == [2, 3]
    assert store.seeds("libero_goal", TASK, HELDOUT) == [1]
    for r in store.query():
        assert (r.split == DEV) == (r.purpose in DEV_PURPOSES), r.key
    tr = store.trace(profile[0])
    # One frame after the reset and one per policy call; every executed action is kept.
    assert len(tr.actions) == 40 and tr.frames - 1 == len(set(tr.action_frame.tolist())) and len(tr.milestone_names) >= 4
    assert {"phi_grasp", "phi_eef_object_dist", "milestones", "task_object_pos"} <= set(tr.obs)
    finals = store.events("final")
    assert len(finals) == 1 and finals[0]["seeds"] == [1] and finals[0]["bare"][1] == 1
    if any(not r.success for r in profile):
        clusters = store.events("cluster")
        assert clusters and clusters[0]["spec"]["layer"] in ("eval", "critic", "state", "plan", "recovery", "param",
                                                              "unexplained")
    # Every candidate that was validated ran as a real harness published in the registry.
    for v in store.events("validation"):
        assert registry.manifest(v["ref"]).content_hash
        assert store.query(harness=v["ref"], purpose="validate")

    before = len(store.query())
    Evolution(config(), store, run, registry).run()
    assert len(store.query()) == before and store.invalid_attempts() == []

    report = write_report(store, tmp_path / "report", "integration").read_text()
    assert "Dev success per round" in report and "Held-out success" in report
    info = export_lerobot(store, profile, tmp_path / "dataset")
    assert info["total_frames"] == sum(r.steps for r in profile)
    episodes = pq.read_table(tmp_path / "dataset" / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert episodes.column("length")[0].as_py() == 40
    registry.close()


async def test_rollout_video_is_filed_and_exported(evo_stack: Endpoints, tmp_path: Path) -> None:
    """With videos on, the env worker's MP4 is copied into the store and into the exported dataset."""
    store = RolloutStore(tmp_path / "store")
    store.assign_splits("libero_goal", TASK, dev=1, heldout=0)
    key = EpisodeKey("libero_goal", TASK, 1, "", "profile")
    runner = Runner(store, RunConfig(gateway=evo_stack.gateway, model="scripted-pick-place", max_steps=20,
                                     record_video=True), {"suite": "libero_goal", "max_steps": 20})
    (rollout,) = await runner.run([key])
    assert rollout.video_path and (store.root / rollout.video_path).stat().st_size > 1000
    info = export_lerobot(store, [rollout], tmp_path / "dataset")
    assert info["features"]["observation.images.agentview"]["info"]["video.codec"] == "h264"
    assert (tmp_path / "dataset" / "videos" / "observation.images.agentview" / "chunk-000" /
            "file-000.mp4").stat().st_size > 1000


async def test_invalid_attempts_are_rerun_on_the_same_key(tmp_path: Path) -> None:
    """Killing an env worker mid-episode makes its sessions' attempts invalid: they are logged, rerun
    on the same episode keys on the surviving worker, and only valid rollouts are filed."""
    stack = new_stack(env_workers=2, slots=2, families=("libero",), critic=False, workdir=tmp_path / "stack")
    stack.start()
    try:
        store = RolloutStore(tmp_path / "store")
        store.assign_splits("libero_goal", TASK, dev=8, heldout=0)
        keys = [EpisodeKey("libero_goal", TASK, s, "", "profile") for s in store.seeds("libero_goal", TASK, DEV)]
        runner = Runner(store, RunConfig(gateway=stack.gateway_address, model="scripted-pick-place", max_steps=300,
                                         concurrency=4), {"suite": "libero_goal"})
        job = asyncio.create_task(runner.run(keys))
        # Kill one worker once the first rollout is filed: the next ones are in flight on both workers
        # (a fixed sleep raced the episodes, which a fast machine finishes first).
        while not store.query() and not job.done():
            await asyncio.sleep(0.1)
        os.killpg(stack.services["env-0"].proc.pid, signal.SIGKILL)
        rollouts = await asyncio.wait_for(job, timeout=240)
        assert [r.key for r in rollouts] == [str(k) for k in keys]
        assert len(store.query()) == 8
        invalid = store.invalid_attempts()
        assert invalid, "killing a worker mid-episode must invalidate the attempts it held"
        assert {k for k, _ in invalid} <= {str(k) for k in keys}
        assert all(store.get(k) is not None for k in keys)
    finally:
        stack.stop()


def test_zero_shot_transfer_command(evo_stack: Endpoints, tmp_path: Path) -> None:
    """`zetta eval` publishes a harness package directory to the registry and runs the bare policy and
    the harness on the same held-out seeds of a task it was not evolved on, with a report."""
    from services.evolver.cmd_eval import main as eval_main
    from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft, render

    draft = HarnessDraft("transfer-probe", ("put_the_cream_cheese_in_the_bowl",)).with_patch(
        {"c_grasp_lost": CriticDraft("grasp_lost", {"confirm": 3, "min_held": 5}, "grasp_lost", "regrasp",
                                     missing=("on",))},
        {"grasp_lost": PlanDraft("regrasp")})
    pkg = tmp_path / "pkg"
    for rel, data in render(draft).items():
        (pkg / rel).parent.mkdir(parents=True, exist_ok=True)
        (pkg / rel).write_bytes(data)
    code = eval_main(["--suite", "libero_goal", "--tasks", "put_the_bowl_on_the_plate", "--seeds", "2",
                      "--harness", "unused", "--harness-dir", str(pkg), "--gateway", evo_stack.gateway,
                      "--registry", evo_stack.registry, "--model", "scripted-pick-place", "--max-steps", "30",
                      "--store", str(tmp_path / "store"), "--no-progress"])
    assert code == 0
    store = RolloutStore(tmp_path / "store")
    final = store.events("final")
    assert len(final) == 1 and final[0]["transfer"] and final[0]["harness"] == "transfer-probe@1"
    arms = {h: sorted(r.seed for r in store.query(harness=h)) for h in ("", "transfer-probe@1")}
    assert arms[""] == arms["transfer-probe@1"] == store.seeds("libero_goal", "put_the_bowl_on_the_plate", HELDOUT)
    assert "zero-shot transfer" in (tmp_path / "store" / "report" / "report.md").read_text()
