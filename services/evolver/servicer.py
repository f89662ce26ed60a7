"""EvolverService over gRPC: start, inspect, list and cancel evolution jobs."""

from __future__ import annotations

import asyncio

import grpc

from services.common import grpc_errors as ge
from services.evolver.evolve import EvolveConfig
from services.evolver.jobs import Job, JobError, JobManager, success_counts
from services.evolver.store import RolloutStore
from zetta_wire.v1 import evolver_pb2, evolver_pb2_grpc

_STATE = {"pending": evolver_pb2.EVOLUTION_STATE_PENDING, "running": evolver_pb2.EVOLUTION_STATE_RUNNING,
          "succeeded": evolver_pb2.EVOLUTION_STATE_SUCCEEDED, "failed": evolver_pb2.EVOLUTION_STATE_FAILED,
          "cancelled": evolver_pb2.EVOLUTION_STATE_CANCELLED}
_CODES = {"invalid": grpc.StatusCode.INVALID_ARGUMENT, "not_found": grpc.StatusCode.NOT_FOUND,
          "exists": grpc.StatusCode.ALREADY_EXISTS, "exhausted": grpc.StatusCode.RESOURCE_EXHAUSTED,
          "unavailable": grpc.StatusCode.UNAVAILABLE, "precondition": grpc.StatusCode.FAILED_PRECONDITION}


def _spec_dict(spec: evolver_pb2.EvolutionSpec) -> dict[str, object]:
    return {"suite": spec.suite, "tasks": list(spec.tasks), "rounds": spec.rounds, "dev_seeds": spec.dev_seeds,
            "heldout_seeds": spec.heldout_seeds, "model": spec.model, "execute_steps": spec.execute_steps,
            "max_steps": spec.max_steps, "concurrency": spec.concurrency, "name": spec.name,
            "regression_min": spec.regression_min, "max_clusters": spec.max_clusters,
            "max_candidates": spec.max_candidates, "max_depth": spec.max_depth, "test_seeds": spec.test_seeds,
            "llm": spec.llm, "nominal_seeds": spec.nominal_seeds if spec.HasField("nominal_seeds") else None,
            "require_hand_back": spec.require_hand_back}


def status_of(job: Job) -> evolver_pb2.EvolutionStatus:
    """A job's status message, read from its store (a connection of its own)."""
    s = job.spec
    out = evolver_pb2.EvolutionStatus(
        job_id=job.job_id, state=_STATE[job.state], phase=job.phase, phase_done=job.done, phase_total=job.total,
        report_path=job.report, error=job.error, store_path=str(job.root / "store"),
        spec=evolver_pb2.EvolutionSpec(
            suite=str(s["suite"]), tasks=list(s["tasks"]), rounds=int(s["rounds"]), dev_seeds=int(s["dev_seeds"]),
            heldout_seeds=int(s["heldout_seeds"]), model=str(s["model"]), execute_steps=int(s["execute_steps"]),
            max_steps=int(s["max_steps"]), concurrency=int(s["concurrency"]), name=str(s["name"]),
            regression_min=float(s["regression_min"]), max_clusters=int(s["max_clusters"]),
            max_candidates=int(s["max_candidates"]), max_depth=int(s.get("max_depth", EvolveConfig.max_depth)),
            test_seeds=int(s.get("test_seeds", EvolveConfig.test_seeds)), llm=bool(s.get("llm", False)),
            nominal_seeds=int(s.get("nominal_seeds", EvolveConfig.nominal_seeds)),
            require_hand_back=bool(s.get("require_hand_back", False))))
    if (job.root / "store" / "index.sqlite").exists():
        store = RolloutStore(job.root / "store")
        try:
            out.rollouts = len(store.query())
            out.admitted.extend(a["ref"] for a in store.events("admitted"))
            for c in success_counts(store):
                out.success.append(evolver_pb2.SuccessCount(**c))
        finally:
            store.close()
    return out


class EvolverServicer(evolver_pb2_grpc.EvolverServiceServicer):
    """Maps the RPCs onto the job manager; refusals become clear gRPC statuses."""

    def __init__(self, jobs: JobManager) -> None:
        self.jobs = jobs

    async def _call(self, fn, *args):
        try:
            return await asyncio.to_thread(fn, *args)
        except JobError as exc:
            raise ge.ServiceError(_CODES[exc.kind], str(exc)) from None

    @ge.timed_unary("evolver", "StartEvolution")
    async def StartEvolution(self, request, context) -> evolver_pb2.StartEvolutionResponse:
        job = await self._call(self.jobs.start, request.job_id, _spec_dict(request.spec))
        return evolver_pb2.StartEvolutionResponse(status=await asyncio.to_thread(status_of, job))

    @ge.timed_unary("evolver", "GetEvolution")
    async def GetEvolution(self, request, context) -> evolver_pb2.GetEvolutionResponse:
        job = await self._call(self.jobs.get, request.job_id)
        return evolver_pb2.GetEvolutionResponse(status=await asyncio.to_thread(status_of, job))

    @ge.timed_unary("evolver", "ListEvolutions")
    async def ListEvolutions(self, request, context) -> evolver_pb2.ListEvolutionsResponse:
        jobs = list(self.jobs.jobs.values())
        return evolver_pb2.ListEvolutionsResponse(jobs=[await asyncio.to_thread(status_of, j) for j in jobs])

    @ge.timed_unary("evolver", "CancelEvolution")
    async def CancelEvolution(self, request, context) -> evolver_pb2.CancelEvolutionResponse:
        job = await self._call(self.jobs.cancel, request.job_id)
        return evolver_pb2.CancelEvolutionResponse(status=await asyncio.to_thread(status_of, job))
