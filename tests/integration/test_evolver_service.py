"""The evolver service over real gRPC: health, reflection, jobs, metrics, refusals, drain."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from services.evolver.stack import Endpoints, endpoints
from services.ops.local_stack import free_port, wait_healthy
from zetta_wire.v1 import evolver_pb2, evolver_pb2_grpc

ROOT = Path(__file__).resolve().parents[2]
TASK = "put_the_cream_cheese_in_the_bowl"


def service_env(**settings: str) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")])
    env.update(settings)
    return env


def test_config_fails_fast_with_clear_messages(tmp_path: Path) -> None:
    """Missing or malformed variables are named; an unreachable gateway is reported before serving."""
    out = subprocess.run([sys.executable, "-m", "services.evolver.main"], capture_output=True, text=True, timeout=60,
                         env=service_env(ZETTA_POLICY_WORKER_ADDR="policy-worker"))
    assert out.returncode != 0 and "ZETTA_GATEWAY_ADDRESS" in out.stderr and "ZETTA_EVOLVER_STORE" in out.stderr
    assert "ZETTA_POLICY_WORKER_ADDR='policy-worker' is not a host:port address" in out.stderr
    dead = f"127.0.0.1:{free_port()}"
    out = subprocess.run([sys.executable, "-m", "services.evolver.main"], capture_output=True, text=True, timeout=60,
                         env=service_env(ZETTA_GATEWAY_ADDRESS=dead, ZETTA_CRITIC_ADDR=dead,
                                         ZETTA_EVOLVER_STORE=str(tmp_path), ZETTA_METRICS_PORT="-1"))
    assert out.returncode != 0 and f"ZETTA_GATEWAY_ADDRESS={dead} does not answer" in out.stderr


@pytest.fixture(scope="module")
def evo_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Endpoints]:
    with endpoints(None, None, "scripted-pick-place", env_workers=1, slots=2,
                   workdir=tmp_path_factory.mktemp("evo-svc-stack"), video=False) as ep:
        yield ep


@pytest.fixture
def evolver(evo_stack: Endpoints, tmp_path: Path) -> Iterator[tuple[str, int, subprocess.Popen[bytes]]]:
    port, metrics = free_port(), free_port()
    log = open(tmp_path / "evolver.log", "wb")
    proc = subprocess.Popen([sys.executable, "-m", "services.evolver.main"], stdout=log, stderr=subprocess.STDOUT,
                            env=service_env(ZETTA_EVOLVER_PORT=str(port), ZETTA_METRICS_PORT=str(metrics),
                                            ZETTA_GATEWAY_ADDRESS=evo_stack.gateway,
                                            ZETTA_CRITIC_ADDR=evo_stack.registry,
                                            ZETTA_POLICY_WORKER_ADDR=evo_stack.policy,
                                            ZETTA_EVOLVER_STORE=str(tmp_path / "jobs"), ZETTA_GRACE_SECONDS="20"),
                            start_new_session=True)
    try:
        wait_healthy(f"127.0.0.1:{port}", timeout=60, proc=proc, log=tmp_path / "evolver.log")
        yield f"127.0.0.1:{port}", metrics, proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=60)
        log.close()


def wait_job(stub: evolver_pb2_grpc.EvolverServiceStub, job_id: str, seconds: float) -> evolver_pb2.EvolutionStatus:
    """The job's status once it has left pending and running, or the last one seen after ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        status = stub.GetEvolution(evolver_pb2.GetEvolutionRequest(job_id=job_id), timeout=30).status
        if status.state not in (evolver_pb2.EVOLUTION_STATE_PENDING, evolver_pb2.EVOLUTION_STATE_RUNNING):
            return status
        if time.monotonic() > deadline:
            return status
        time.sleep(1.0)


def spec(**kw: object) -> evolver_pb2.EvolutionSpec:
    base: dict[str, object] = dict(suite="libero_goal", tasks=[TASK], rounds=1, dev_seeds=2, heldout_seeds=1, test_seeds=1,
                                   model="scripted-pick-place", max_steps=30, max_clusters=1, max_candidates=1)
    base.update(kw)
    return evolver_pb2.EvolutionSpec(**base)  # type: ignore[arg-type]


@pytest.mark.slow
def test_job_runs_to_its_report_with_metrics(evolver: tuple[str, int, subprocess.Popen[bytes]]) -> None:
    """A job runs to SUCCEEDED with its report and success counts; bad requests get clear statuses;
    reflection lists the service; /metrics carries the evolution gauges."""
    address, metrics_port, _ = evolver
    with grpc.insecure_channel(address) as ch:
        stub = evolver_pb2_grpc.EvolverServiceStub(ch)
        with pytest.raises(grpc.RpcError) as err:
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(spec=spec(tasks=[])), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "tasks" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(spec=spec(dev_seeds=40, heldout_seeds=10)), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "disjoint initial states" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(spec=spec(nominal_seeds=-1)), timeout=10)
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "nominal_seeds" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(spec=spec(llm=True)), timeout=10)
        assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION and "ZETTA_EVOLVER_LLM_URL" in err.value.details()
        with pytest.raises(grpc.RpcError) as err:
            stub.GetEvolution(evolver_pb2.GetEvolutionRequest(job_id="nope"), timeout=10)
        assert err.value.code() == grpc.StatusCode.NOT_FOUND
        started = stub.StartEvolution(evolver_pb2.StartEvolutionRequest(job_id="j1", spec=spec(require_hand_back=True)),
                                      timeout=30).status
        assert started.job_id == "j1" and started.spec.model == "scripted-pick-place" and started.spec.require_hand_back
        with pytest.raises(grpc.RpcError) as err:
            stub.StartEvolution(evolver_pb2.StartEvolutionRequest(job_id="j1", spec=spec()), timeout=10)
        assert err.value.code() in (grpc.StatusCode.ALREADY_EXISTS, grpc.StatusCode.RESOURCE_EXHAUSTED)
        status = wait_job(stub, "j1", 400)
        assert status.state == evolver_pb2.EVOLUTION_STATE_SUCCEEDED, status.error
        assert status.rollouts >= 4 and Path(status.report_path).exists()  # 2 dev + 1 test + its control at least
        arms = {s.arm for s in status.success}
        assert {"dev", "test_bare", "test_final", "test_control"} <= arms
        assert status.spec.test_seeds == 1 and status.spec.nominal_seeds == 2
        assert [j.job_id for j in stub.ListEvolutions(evolver_pb2.ListEvolutionsRequest(), timeout=10).jobs] == ["j1"]
        refl = reflection_pb2_grpc.ServerReflectionStub(ch)
        names = [s.name for r in refl.ServerReflectionInfo(iter([reflection_pb2.ServerReflectionRequest(list_services="")]))
                 for s in r.list_services_response.service]
        assert "zetta.v1.EvolverService" in names
    text = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5).read().decode()
    assert 'zetta_evolver_success_ratio{arm="dev",job_id="j1"' in text
    assert 'zetta_evolver_jobs{state="succeeded"} 1.0' in text
    assert "zetta_evolver_episodes_total" in text


@pytest.mark.slow
def test_drain_cancels_a_running_job_and_keeps_its_rollouts(evolver: tuple[str, int, subprocess.Popen[bytes]]) -> None:
    """SIGTERM while a job runs: the job is cancelled, the process exits, finished rollouts stay filed
    and the job's state on disk says cancelled (resumable)."""
    address, _, proc = evolver
    with grpc.insecure_channel(address) as ch:
        stub = evolver_pb2_grpc.EvolverServiceStub(ch)
        stub.StartEvolution(evolver_pb2.StartEvolutionRequest(job_id="long", spec=spec(dev_seeds=6, max_steps=60)),
                            timeout=30)
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            st = stub.GetEvolution(evolver_pb2.GetEvolutionRequest(job_id="long"), timeout=30).status
            if st.rollouts >= 1:
                break
            time.sleep(0.5)
        assert st.rollouts >= 1
        store_path = st.store_path
    os.killpg(proc.pid, signal.SIGTERM)
    assert proc.wait(timeout=60) == 0
    job = Path(store_path).parent / "job.json"
    assert '"state": "cancelled"' in job.read_text()
    from services.evolver.store import RolloutStore

    assert len(RolloutStore(store_path).query()) >= 1
