"""Evolution jobs of the service: each runs :class:`Evolution` on a thread of its own, with its own
rollout store under the service's store directory (so a job started again resumes it).

Status is derived from the job's store (what was recorded) plus the phase the job reports while it
runs. A cancel request is honoured at the next finished episode: the progress callback raises
:class:`Cancelled`, the rollouts in flight are abandoned, the finished ones stay filed.
"""

from __future__ import annotations

import json
import logging
import re
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS
from services.evolver import metrics
from services.evolver.evolve import EvolveConfig, Evolution
from services.evolver.gate import GateParams
from services.evolver.llm import LLMConfig, LLMError, config_from_env
from services.evolver.registry_client import RegistryClient
from services.evolver.report import write_report
from services.evolver.repair import SearchParams
from services.evolver.rollout import RunConfig
from services.evolver.stack import policy_instructions
from services.evolver.store import INIT_STATES, RolloutStore

log = logging.getLogger("evolver.jobs")
JOB_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
STATES = ("pending", "running", "succeeded", "failed", "cancelled")


class Cancelled(Exception):
    """Raised from the progress callback to stop a job."""


class JobError(ValueError):
    """A request the job manager refuses; ``kind`` names the gRPC status it maps to."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass
class Job:
    """One job's mutable state."""

    job_id: str
    spec: dict[str, Any]
    root: Path
    state: str = "pending"
    phase: str = ""
    done: int = 0
    total: int = 0
    error: str = ""
    report: str = ""
    cancel: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None

    def save(self) -> None:
        """Persist the spec and state next to the store (what a restarted service lists)."""
        (self.root / "job.json").write_text(json.dumps({"job_id": self.job_id, "spec": self.spec, "state": self.state,
                                                        "error": self.error, "report": self.report}, indent=2))


def _llm() -> LLMConfig | None:
    """The service's LLM backend, as the CLI reads it (a misconfiguration is a precondition failure)."""
    try:
        return config_from_env()
    except LLMError as exc:
        raise JobError("precondition", str(exc)) from None


def check_spec(spec: dict[str, Any]) -> dict[str, Any]:
    """Defaults applied, bad values refused with a message naming the field."""
    tasks = [str(t) for t in spec.get("tasks", []) if str(t)]
    if not spec.get("suite"):
        raise JobError("invalid", "spec.suite is required (e.g. libero_goal_task)")
    if not tasks:
        raise JobError("invalid", "spec.tasks must name at least one task")
    for key in ("rounds", "dev_seeds", "heldout_seeds"):
        if int(spec.get(key, 0)) < 1:
            raise JobError("invalid", f"spec.{key} must be at least 1, got {spec.get(key, 0)}")
    for key in ("execute_steps", "max_steps", "concurrency", "max_clusters", "max_candidates", "max_depth"):
        if int(spec.get(key, 0)) < 0:
            raise JobError("invalid", f"spec.{key} must not be negative")
    if not 0.0 <= float(spec.get("regression_min", 0.0)) <= 1.0:
        raise JobError("invalid", "spec.regression_min must be in [0, 1]")
    test = int(spec.get("test_seeds") or EvolveConfig.test_seeds)
    total = int(spec["dev_seeds"]) + int(spec["heldout_seeds"]) + test
    if test < 0 or total > INIT_STATES:
        raise JobError("invalid", f"spec.dev_seeds + heldout_seeds + test_seeds = {total}: the three splits must sit on "
                                  f"disjoint initial states and a task has {INIT_STATES}")
    nominal = EvolveConfig.nominal_seeds if spec.get("nominal_seeds") is None else int(spec["nominal_seeds"])
    if nominal < 0 or nominal + test > INIT_STATES:
        raise JobError("invalid", f"spec.nominal_seeds {nominal} + test_seeds {test}: the nominal reference takes the "
                                  f"last initial states and the test seeds the first, {INIT_STATES} in all")
    if spec.get("llm") and _llm() is None:
        raise JobError("precondition", "spec.llm asks for the LLM backend but this evolver service has no "
                                       "ZETTA_EVOLVER_LLM_URL configured")
    return {"suite": spec["suite"], "tasks": tasks, "rounds": int(spec["rounds"]), "dev_seeds": int(spec["dev_seeds"]),
            "heldout_seeds": int(spec["heldout_seeds"]), "model": spec.get("model") or DEFAULT_POLICY,
            "execute_steps": int(spec.get("execute_steps") or EXECUTE_STEPS), "max_steps": int(spec.get("max_steps") or 0),
            "concurrency": int(spec.get("concurrency") or 2), "name": spec.get("name") or "evolved",
            "regression_min": float(spec.get("regression_min") or 1.0),
            "max_clusters": int(spec.get("max_clusters") or EvolveConfig.max_clusters),
            "max_candidates": int(spec.get("max_candidates") or SearchParams.max_candidates),
            "max_depth": int(spec.get("max_depth") or EvolveConfig.max_depth), "test_seeds": test,
            "llm": bool(spec.get("llm", False)), "nominal_seeds": nominal,
            "require_hand_back": bool(spec.get("require_hand_back", False))}


class JobManager:
    """Starts, tracks and stops jobs; thread-safe."""

    def __init__(self, root: Path, gateway: str, registry: str, max_jobs: int, policy_worker: str = "") -> None:
        self.root = root
        self.root.mkdir(parents=True, exist_ok=True)
        self.gateway = gateway
        self.registry = registry
        self.policy_worker = policy_worker
        self.max_jobs = max_jobs
        self.draining = False
        self._lock = threading.Lock()
        self.jobs: dict[str, Job] = {}
        for path in sorted(self.root.glob("*/job.json")):
            body = json.loads(path.read_text())
            state = body["state"] if body["state"] in ("succeeded", "failed") else "cancelled"
            self.jobs[body["job_id"]] = Job(body["job_id"], body["spec"], path.parent, state, error=body.get("error", ""),
                                            report=body.get("report", ""))
        self._gauges()

    def start(self, job_id: str, spec: dict[str, Any]) -> Job:
        """Accept a job (or resume one) and start its thread."""
        if self.draining:
            raise JobError("unavailable", "the evolver is draining; start the job on another instance")
        job_id = job_id or uuid.uuid4().hex[:12]
        if not JOB_ID.match(job_id):
            raise JobError("invalid", f"job_id {job_id!r}: use 1-64 letters, digits, '-' or '_'")
        clean = check_spec(spec)
        with self._lock:
            old = self.jobs.get(job_id)
            if old is not None and old.state in ("pending", "running"):
                raise JobError("exists", f"job {job_id} is {old.state}")
            if old is not None and old.spec != clean:
                raise JobError("invalid", f"job {job_id} exists with another spec; resume it with the same spec")
            if sum(j.state in ("pending", "running") for j in self.jobs.values()) >= self.max_jobs:
                raise JobError("exhausted", f"{self.max_jobs} job(s) already running (ZETTA_EVOLVER_MAX_JOBS)")
            job = Job(job_id, clean, self.root / job_id)
            job.root.mkdir(parents=True, exist_ok=True)
            job.save()
            self.jobs[job_id] = job
            job.thread = threading.Thread(target=self._run, args=(job,), name=f"evolve-{job_id}", daemon=True)
            job.thread.start()
        self._gauges()
        return job

    def get(self, job_id: str) -> Job:
        """A known job, or JobError('not_found')."""
        job = self.jobs.get(job_id)
        if job is None:
            raise JobError("not_found", f"no evolution job {job_id!r}")
        return job

    def cancel(self, job_id: str) -> Job:
        """Ask a job to stop at its next finished episode."""
        job = self.get(job_id)
        job.cancel.set()
        return job

    def drain(self, timeout: float) -> None:
        """Refuse new jobs, cancel running ones, wait for their threads."""
        self.draining = True
        for job in list(self.jobs.values()):
            job.cancel.set()
        deadline = time.monotonic() + timeout
        for job in list(self.jobs.values()):
            if job.thread is not None:
                job.thread.join(max(0.0, deadline - time.monotonic()))

    def _gauges(self) -> None:
        for s in STATES:
            metrics.JOBS.labels(s).set(sum(j.state == s for j in self.jobs.values()))

    def _progress(self, job: Job, store: RolloutStore):
        def update(phase: str, done: int, total: int) -> None:
            if job.cancel.is_set():
                raise Cancelled(f"job {job.job_id} cancelled")
            if phase != job.phase:
                refresh_success(job.job_id, store)
                m = re.match(r"r(\d+) ", phase)
                metrics.ROUND.labels(job.job_id).set(int(m.group(1)) if m else 0)
            elif done > job.done:
                metrics.EPISODES.labels(job.job_id).inc(done - job.done)
            job.phase, job.done, job.total = phase, done, total
            metrics.PHASE_PROGRESS.labels(job.job_id).set(done / total if total else 0.0)

        return update

    def _run(self, job: Job) -> None:
        spec = job.spec
        store = RolloutStore(job.root / "store")
        job.state = "running"
        job.save()
        self._gauges()
        log.info("job started", extra={"fields": {"job": job.job_id, **{k: spec[k] for k in ("suite", "tasks", "rounds")}}})
        registry = RegistryClient(self.registry)
        t0 = time.time()
        try:
            cfg = EvolveConfig(suite=spec["suite"], tasks=tuple(spec["tasks"]), rounds=spec["rounds"],
                               dev_seeds=spec["dev_seeds"], heldout_seeds=spec["heldout_seeds"], name=spec["name"],
                               max_clusters=spec["max_clusters"], search=SearchParams(max_candidates=spec["max_candidates"]),
                               gate=GateParams(spec["regression_min"], require_hand_back=bool(spec.get("require_hand_back", False))), max_depth=spec["max_depth"],
                               test_seeds=int(spec.get("test_seeds") or EvolveConfig.test_seeds),
                               llm=_llm() if spec.get("llm") else None,
                               nominal_seeds=int(spec.get("nominal_seeds", EvolveConfig.nominal_seeds)),
                               policy_instructions=policy_instructions(self.policy_worker, spec["model"]))
            run = RunConfig(gateway=self.gateway, model=spec["model"], execute_steps=spec["execute_steps"],
                            max_steps=spec["max_steps"], concurrency=spec["concurrency"])
            Evolution(cfg, store, run, registry, self._progress(job, store)).run()
            store.record("wall", {"command": "service", "wall_s": time.time() - t0})
            job.report = str(write_report(store, job.root / "report", f"Evolution job {job.job_id}", time.time() - t0))
            job.state = "succeeded"
        except Cancelled:
            job.state = "cancelled"
        except Exception as exc:  # noqa: BLE001 - a job's failure is its status, the service goes on
            job.state, job.error = "failed", f"{type(exc).__name__}: {exc}"
        finally:
            registry.close()
            refresh_success(job.job_id, store)
            metrics.ADMITTED.labels(job.job_id).set(len(store.events("admitted")))
            log.log(logging.ERROR if job.state == "failed" else logging.INFO, "job ended",
                    extra={"fields": {"job": job.job_id, "state": job.state, "error": job.error,
                                      "rollouts": len(store.query()), "wall_s": round(time.time() - t0, 1)}})
            store.close()
            job.save()
            self._gauges()


def success_counts(store: RolloutStore) -> list[dict[str, Any]]:
    """Dev success per round and the final test success (bare, harness, do-nothing control), from the store's events."""
    out = [{"task": p["task"], "round": p["round"], "harness": p["harness"], "successes": p["successes"],
            "episodes": p["episodes"], "arm": "dev"} for p in store.events("profile")]
    for f in store.events("final"):
        out.append({"task": f["task"], "round": 0, "harness": "bare", "successes": f["bare"][0],
                    "episodes": f["bare"][1], "arm": "test_bare"})
        out.append({"task": f["task"], "round": 0, "harness": f["harness"], "successes": f["final"][0],
                    "episodes": f["final"][1], "arm": "test_final"})
        control = f.get("arms", {}).get("control")
        if control:
            out.append({"task": f["task"], "round": 0, "harness": f["harness"], "successes": control["successes"],
                        "episodes": control["episodes"], "arm": "test_control"})
    return out


def refresh_success(job_id: str, store: RolloutStore) -> None:
    """Set the success gauges from the store."""
    for c in success_counts(store):
        metrics.SUCCESS.labels(job_id, c["task"], str(c["round"]), c["arm"]).set(
            c["successes"] / c["episodes"] if c["episodes"] else 0.0)
