"""Policy worker process: `python -m services.policy_worker.main` (configuration in ZETTA_* variables)."""

from __future__ import annotations

import logging

from services.common.config import ConfigError
from services.common.cpus import format_cpu_list, pin_process
from services.common.logs import setup_logging
from services.common.server import Registration, ServiceRunner, run_service
from services.policy_worker.config import PolicyWorkerConfig
from services.policy_worker.input_check import check_models
from services.policy_worker.metrics import PrometheusObserver
from services.policy_worker.models.base import load_model
from services.policy_worker.scheduler import BatchScheduler
from services.policy_worker.servicer import PolicyWorkerServicer
from services.policy_worker.warmup import WarmUpError, warm_up
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc


async def main() -> None:
    """Load the models, serve them through one scheduler, drain the queue on SIGTERM."""
    setup_logging("policy_worker")
    cfg = PolicyWorkerConfig.from_env()
    if cfg.cpus is not None:  # before the models load, so every thread they start stays there too
        pin_process(cfg.cpus)
        logging.getLogger("policy_worker").info("pinned to CPUs %s (ZETTA_CPUS)", format_cpu_list(cfg.cpus))
    try:
        models = {name: load_model(name) for name in cfg.models}
    except ValueError as exc:  # a model's own settings (ZETTA_VLA_*) are wrong for this node
        raise ConfigError(f"policy_worker: {exc}") from None
    for name, model in models.items():
        model.name = name
    if cfg.input_check_family:
        check_models(models, cfg.input_check_family)
    for name, model in models.items():
        try:  # before binding the port: SERVING must mean the first request is served in normal time
            warm_up(name, model)
        except WarmUpError as exc:
            raise ConfigError(f"policy_worker: {exc}") from None
    observer = PrometheusObserver()
    scheduler = BatchScheduler(lambda m, inputs, instr: models[m].infer(inputs, instr), cfg.scheduler, observer)
    if cfg.vla_split:
        # The Zetta VLA's stages in two processes sharing the prefix (docs/policies.md).
        from services.policy_worker.vla.split import wrap_for_split

        scheduler = wrap_for_split(scheduler, models, cfg.scheduler, observer)
    servicer = PolicyWorkerServicer(models, cfg.models[0], scheduler, cfg.default_timeout_ms)
    runner = ServiceRunner(
        name="policy_worker",
        host=cfg.host,
        port=cfg.port,
        metrics_port=cfg.metrics_port,
        registrations=[
            Registration(
                policy_worker_pb2_grpc.add_PolicyWorkerServiceServicer_to_server,
                servicer,
                policy_worker_pb2.DESCRIPTOR.services_by_name["PolicyWorkerService"].full_name,
            )
        ],
        grace_seconds=cfg.grace_seconds,
        on_drain=scheduler.drain,
    )
    await runner.start()
    logging.getLogger("policy_worker").info(
        "models loaded", extra={"fields": {"models": list(models), "scheduler": cfg.scheduler.__dict__}}
    )
    await runner.run_until_signalled()


if __name__ == "__main__":
    run_service(main, "policy_worker")
