"""The evolution loops against the real stack: gateway, env workers running harnesses from the
critic service's registry, a policy worker, Redis, all over gRPC on loopback, real MuJoCo.

The frozen policy is deliberately weak ("scripted-pick-place-weak" closes its gripper 4 cm above
the grasp point, without a hold, and retries the same way): a known failure that a bounded regrasp
fixes, after which the policy carries and places the object itself. The end-to-end test therefore
fails when the loops find, validate or admit nothing, when the admitted harness does not beat the
bare policy on test seeds, or when it succeeds around a do-nothing policy.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import threading
from http.server import BaseHTTPRequestHandler, HTTPServer
from collections.abc import Iterator
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.lerobot_export import export_lerobot
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.repair import SearchParams
from services.evolver.rollout import Runner, RunConfig
from services.evolver.stack import Endpoints, endpoints
from services.evolver.store import DEV, HELDOUT, INIT_STATES, TEST, EpisodeKey, RolloutStore
from tests.conftest import new_stack

pytestmark = pytest.mark.slow

TASK = "put_the_cream_cheese_in_the_bowl"
WEAK = "scripted-pick-place-weak"
#: Enough for the policy's approach, an 80-action regrasp, and the policy's carry and placement.
MAX_STEPS = 280
#: Purposes by split: dev feeds every decision, the gate admission, test only the final measurement.
PURPOSES = {DEV: {"profile", "validate", "regress", "control"}, HELDOUT: {"heldout"}, TEST: {"test", "control-test"}}


@pytest.fixture(scope="module")
def evo_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Endpoints]:
    """A local stack serving the weak policy and the do-nothing control; env workers load harness
    versions from its critic service."""
    with endpoints(None, None, WEAK, env_workers=1, slots=2,
                   workdir=tmp_path_factory.mktemp("evo-stack"), video=True) as ep:
        yield ep


def config() -> EvolveConfig:
    return EvolveConfig(suite="libero_goal", tasks=(TASK,), rounds=1, dev_seeds=3, heldout_seeds=2, test_seeds=2,
                        name="it", max_clusters=1, search=SearchParams(max_candidates=3))


@pytest.mark.timeout(1800)  # about 40 episodes of up to 280 steps on a shared 2-core machine
def test_a_repair_that_helps_is_validated_admitted_and_measured_on_test_seeds(evo_stack: Endpoints,
                                                                               tmp_path: Path) -> None:
    """Profile, cluster, diagnose, repair, validate as a real harness, regress on the whole cluster, the
    do-nothing control, gate, final measurement on test seeds only; a resumed run reruns nothing."""
    store = RolloutStore(tmp_path / "store")
    run = RunConfig(gateway=evo_stack.gateway, model=WEAK, max_steps=MAX_STEPS, concurrency=2)
    registry = RegistryClient(evo_stack.registry)
    Evolution(config(), store, run, registry).run()

    dev, gate, test = (store.seeds("libero_goal", TASK, s) for s in (DEV, HELDOUT, TEST))
    assert (len(dev), len(gate), len(test)) == (3, 2, 2)
    assert len({s % INIT_STATES for s in dev + gate + test}) == 7
    for r in store.query():
        assert r.purpose in PURPOSES[r.split], r.key
    profile = store.query(purpose="profile")
    assert sorted(r.seed for r in profile) == dev and not any(r.success for r in profile)
    assert {r.first_missing for r in profile} == {"lifted(cream_cheese_1)"}  # it touches the object, never holds it
    assert any(v["medoid_success"] for v in store.events("validation")), store.events("validation")
    (admitted,) = store.events("admitted")
    verdict = admitted["verdict"]
    assert verdict["regression"]["episodes"] >= 3 and verdict["regression"]["successes"] == verdict["regression"]["episodes"]
    assert verdict["control"] == {**verdict["control"], "successes": 0, "episodes": 3}
    assert verdict["heldout"]["successes"] > verdict["current"]["successes"]
    assert registry.manifest(admitted["ref"]).content_hash
    (final,) = store.events("final")
    arms = final["arms"]
    assert final["seeds"] == test and arms["final"]["seeds"] == test and arms["control"]["seeds"] == test
    assert arms["final"]["successes"] > arms["bare"]["successes"] == 0
    assert arms["control"]["successes"] == 0
    # The regrasp hands back; the policy carries and places: it is in control at every success.
    assert arms["final"]["policy_in_control_at_success"] == 1.0 and arms["final"]["recovery_share"] < 0.5

    before, invalid = len(store.query()), store.invalid_attempts()
    Evolution(config(), store, run, registry).run()
    assert len(store.query()) == before and store.invalid_attempts() == invalid  # nothing ran again

    report = write_report(store, tmp_path / "report", "integration").read_text()
    assert "Dev success per round" in report and "Test success" in report
    info = export_lerobot(store, profile, tmp_path / "dataset")
    assert info["total_frames"] == sum(r.steps for r in profile)
    episodes = pq.read_table(tmp_path / "dataset" / "meta" / "episodes" / "chunk-000" / "file-000.parquet")
    assert episodes.column("length")[0].as_py() == MAX_STEPS
    registry.close()


#: The critic an LLM writes for the weak policy: fingers shut near the (perceived) object, no grasp.
CLOSED_ON_NOTHING = '''
from services.harness.runtime.library import tools


def detect(window, params):
    now = window.now
    if tools.grasped(now) or tools.scalar(now, "phi_gripper_aperture") > params["closed_gap"]:
        return None
    dist = tools.eef_object_dist(now)
    if dist is None or dist > params["near"]:
        return None
    return {"eef_object_dist": dist, "aperture": tools.scalar(now, "phi_gripper_aperture")}
'''


class _LLM(BaseHTTPRequestHandler):
    """An OpenAI-compatible chat endpoint that answers every request with one critic-code patch."""

    requests: list[dict] = []

    def do_POST(self) -> None:
        _LLM.requests.append(json.loads(self.rfile.read(int(self.headers["Content-Length"]))))
        patch = {"critic": {"code": CLOSED_ON_NOTHING, "params": {"closed_gap": 0.01, "near": 0.06},
                            "evidence": "closed_on_nothing"}, "recovery": {"template": "acquire"}}
        out = json.dumps({"choices": [{"message": {"role": "assistant",
                                                   "content": json.dumps({"patches": [patch]})}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(out)))
        self.end_headers()
        self.wfile.write(out)

    def log_message(self, *args: object) -> None:
        return None


@pytest.mark.timeout(1800)
def test_zetta_evolve_admits_critic_code_an_llm_wrote(evo_stack: Endpoints, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """`zetta evolve` with an OpenAI-compatible server on loopback: its critic code is loaded through the
    package checks, replayed, validated closed-loop, regressed, controlled and gated like any patch,
    and admitted; the admitted package holds the code."""
    from services.evolver.cmd_evolve import main as evolve_main

    server = HTTPServer(("127.0.0.1", 0), _LLM)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    monkeypatch.setenv("ZETTA_EVOLVER_LLM_URL", f"http://127.0.0.1:{server.server_address[1]}/v1")
    monkeypatch.setenv("ZETTA_EVOLVER_LLM_MODEL", "loopback")
    try:
        code = evolve_main(["--suite", "libero_goal", "--tasks", TASK, "--dev-seeds", "3", "--heldout-seeds", "2",
                            "--test-seeds", "2", "--max-clusters", "1", "--max-candidates", "1", "--name", "llm",
                            "--model", WEAK, "--max-steps", str(MAX_STEPS), "--gateway", evo_stack.gateway,
                            "--registry", evo_stack.registry, "--store", str(tmp_path / "store"), "--no-progress"])
    finally:
        server.shutdown()
        server.server_close()
    assert code == 0 and _LLM.requests
    store = RolloutStore(tmp_path / "store")
    assert [e["accepted"] for e in store.events("llm")][:1] == [1], store.events("llm")
    (admitted,) = store.events("admitted")
    (patch,) = admitted["patches"]
    assert patch["source"] == "llm" and patch["template"] == "code"
    assert admitted["verdict"]["control"]["successes"] == 0
    tools = list((store.root / "harness" / admitted["ref"] / "tools").glob("c_llm_*.py"))
    assert len(tools) == 1 and "def detect(window, params)" in tools[0].read_text()
    (final,) = store.events("final")
    assert final["arms"]["final"]["successes"] > final["arms"]["bare"]["successes"]


async def test_rollout_video_is_filed_and_exported(evo_stack: Endpoints, tmp_path: Path) -> None:
    """With videos on, the env worker's MP4 is copied into the store and into the exported dataset."""
    store = RolloutStore(tmp_path / "store")
    store.assign_splits("libero_goal", TASK, dev=1, heldout=0)
    key = EpisodeKey("libero_goal", TASK, 1, "", "profile")
    runner = Runner(store, RunConfig(gateway=evo_stack.gateway, model=WEAK, max_steps=20,
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
    the harness and its do-nothing control on the same test seeds of a task it was not evolved on, with a report."""
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
                      "--registry", evo_stack.registry, "--model", WEAK, "--max-steps", "30",
                      "--store", str(tmp_path / "store"), "--no-progress"])
    assert code == 0
    store = RolloutStore(tmp_path / "store")
    final = store.events("final")
    assert len(final) == 1 and final[0]["transfer"] and final[0]["harness"] == "transfer-probe@1"
    arms = {h: sorted(r.seed for r in store.query(harness=h, purpose="test")) for h in ("", "transfer-probe@1")}
    control = sorted(r.seed for r in store.query(harness="transfer-probe@1", purpose="control-test"))
    assert arms[""] == arms["transfer-probe@1"] == control == store.seeds("libero_goal", "put_the_bowl_on_the_plate", TEST)
    assert "zero-shot transfer" in (tmp_path / "store" / "report" / "report.md").read_text()


def test_nominal_reference_runs_once_on_the_original_suite(evo_stack: Endpoints, tmp_path: Path) -> None:
    """An evolution on a LIBERO-PRO variant first runs the bare policy on every task of the original
    suite (dev seed 49 of libero_goal's ten, purpose nominal), records what it found, and a resumed run reads it back;
    the variant's own splits hold no nominal rollout."""
    store = RolloutStore(tmp_path / "store")
    run = RunConfig(gateway=evo_stack.gateway, model=WEAK, max_steps=10, concurrency=2)
    cfg = EvolveConfig(suite="libero_goal_lan", tasks=("8",), nominal_seeds=1, name="nominal")
    evo = Evolution(cfg, store, run, None)
    assert evo.nominal_successes() == []  # nothing completes a LIBERO-Goal task in 10 steps
    rows = store.query(purpose="nominal")
    tasks = [str(t) for t in range(10)]
    assert sorted((r.suite, r.task, r.seed, r.split, r.harness) for r in rows) == [
        ("libero_goal", t, 49, DEV, "") for t in tasks]
    assert all(r.steps == 10 for r in rows)
    (event,) = store.events("nominal")
    assert event == {"kind": "nominal", "for_suite": "libero_goal_lan", "suite": "libero_goal", "tasks": tasks,
                     "seeds_per_task": 1, "seeds": [49], "episodes": 10, "successes": 0}
    assert not store.query(suite="libero_goal_lan")
    Evolution(cfg, store, run, None).nominal_successes()
    assert len(store.query()) == 10  # read back, not run again


@pytest.mark.timeout(1800)
def test_the_evolver_service_admits_critic_code_an_llm_wrote(evo_stack: Endpoints, tmp_path: Path) -> None:
    """The same loopback LLM through the evolver service: a job with ``spec.llm`` on a service started
    with ZETTA_EVOLVER_LLM_URL runs to SUCCEEDED, and its store holds the admitted LLM-written critic."""
    import subprocess
    import sys

    import grpc

    from services.ops.local_stack import free_port, wait_healthy
    from tests.integration.test_evolver_service import service_env, wait_job
    from zetta_wire.v1 import evolver_pb2, evolver_pb2_grpc

    server = HTTPServer(("127.0.0.1", 0), _LLM)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    port = free_port()
    log = open(tmp_path / "evolver.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "services.evolver.main"], stdout=log, stderr=subprocess.STDOUT,
                            env=service_env(ZETTA_EVOLVER_PORT=str(port), ZETTA_METRICS_PORT="-1",
                                            ZETTA_GATEWAY_ADDRESS=evo_stack.gateway, ZETTA_CRITIC_ADDR=evo_stack.registry,
                                            ZETTA_POLICY_WORKER_ADDR=evo_stack.policy,
                                            ZETTA_EVOLVER_STORE=str(tmp_path / "jobs"),
                                            ZETTA_EVOLVER_LLM_URL=f"http://127.0.0.1:{server.server_address[1]}/v1",
                                            ZETTA_EVOLVER_LLM_MODEL="loopback"),
                            start_new_session=True)
    asked = len(_LLM.requests)
    try:
        wait_healthy(f"127.0.0.1:{port}", timeout=60, proc=proc, log=tmp_path / "evolver.log")
        spec = evolver_pb2.EvolutionSpec(suite="libero_goal", tasks=[TASK], rounds=1, dev_seeds=3, heldout_seeds=2,
                                         test_seeds=2, model=WEAK, max_steps=MAX_STEPS, max_clusters=1,
                                         max_candidates=1, name="svc-llm", llm=True)
        with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
            stub = evolver_pb2_grpc.EvolverServiceStub(ch)
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(job_id="llm", spec=spec), timeout=30)
            status = wait_job(stub, "llm", 1500)
        assert status.state == evolver_pb2.EVOLUTION_STATE_SUCCEEDED, status.error
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=60)
        log.close()
        server.shutdown()
        server.server_close()
    assert len(_LLM.requests) > asked, "the service asked the LLM"
    store = RolloutStore(status.store_path)
    (admitted,) = store.events("admitted")
    (patch,) = admitted["patches"]
    assert patch["source"] == "llm" and patch["template"] == "code"
    assert admitted["verdict"]["control"]["successes"] == 0
