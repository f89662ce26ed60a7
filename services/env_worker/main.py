"""Env worker process: `python -m services.env_worker.main` (configuration in ZETTA_* variables)."""

from __future__ import annotations

import asyncio
import logging
import threading

from services.common.config import ConfigError
from services.common.cpus import format_cpu_list, pin_process
from services.common.logs import setup_logging
from services.common.server import Registration, ServiceRunner, run_service
from services.harness.runtime.budget import PlatformLimits
from services.harness.sandbox import client as sandbox
from services.harness.sandbox.client import SandboxLimits
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.families import UnknownFamilyError, get_family
from services.env_worker.membership import Membership
from services.env_worker.policy_client import PolicyClient
from services.env_worker.rendering import gl_backend_choice, gl_renderer_string, select_gl_backend
from services.env_worker.servicer import EnvWorkerServicer
from services.env_worker.slots import SlotTable
from zetta_wire.v1 import env_worker_pb2, env_worker_pb2_grpc

log = logging.getLogger(__name__)


def _warm_compiled(fast_step_kernel: bool) -> None:
    """Compile (or load from numba's cache) the step path's kernels before the worker serves: a
    compile holds the GIL, which on a slot's first step would stall the event loop and heartbeats.
    The geom box kernel serves every family's task tensors; the fast step's only libero and robosuite."""
    from services.env_worker.families import task_state

    if fast_step_kernel:
        from services.env_worker import fast_step

        log.info("fast step kernel ready in %.1f s", fast_step.warm_up())
    log.info("geom box kernel ready in %.1f s", task_state.warm_up())


def _gl_renderer() -> str:
    """The OpenGL implementation frames will come from (GPU or llvmpipe), checked once at start."""
    if not gl_backend_choice().backend:
        return "none"
    try:
        return gl_renderer_string()
    except Exception as exc:  # noqa: BLE001 - state-only sessions still work; camera configs will fail
        log.warning("rendering: cannot make a GL context: %s", exc)
        return f"unavailable ({exc})"


async def main() -> None:
    """Serve the slots, register with the gateway, heartbeat; on SIGTERM drain and deregister."""
    setup_logging("env_worker")
    cfg = EnvWorkerConfig.from_env()
    PlatformLimits.from_env()  # the harness time limits fail fast here, not at the first reset
    SandboxLimits.from_env()
    if sandbox.enabled():
        # Before any family import and before threads: the zygote every harness sandbox child is
        # forked from, launched now: it imports numpy and the runtime (1-3 s) while the worker starts.
        sandbox.start_zygote()
    else:
        log.warning("ZETTA_HARNESS_SANDBOX=off: harness package code runs inside this process (trusted code only)")
    # Before any family import: MuJoCo and robosuite read MUJOCO_GL when they are imported.
    select_gl_backend()
    log.info("rendering: %s; OpenGL renderer: %s", gl_backend_choice().describe(), _gl_renderer())
    log.info("episode videos: %s", cfg.video_dir or "off (ZETTA_VIDEO_DIR unset)")
    if cfg.cpus is not None:
        # After the GL probe: Mesa's queue threads give themselves every CPU when they start, so
        # they are pinned with the rest; threads started from here on inherit the mask.
        pin_process(cfg.cpus)
    log.info("CPUs: %s; %s slot(s) step at once", format_cpu_list(cfg.cpus) + " (pinned, ZETTA_CPUS)"
             if cfg.cpus is not None else "not pinned", cfg.step_concurrency or "any number of")
    for name in cfg.families:
        try:
            reason = get_family(name).unavailable_reason()
        except UnknownFamilyError as exc:
            raise ConfigError(f"env worker: ZETTA_ENV_FAMILIES: {exc}") from None
        if reason:
            raise ConfigError(f"env worker: ZETTA_ENV_FAMILIES names {name!r}, which cannot run here: {reason}")
    fast_step_kernel = bool({"libero", "robosuite"} & set(cfg.families))  # their fast step path is compiled
    warming = threading.Thread(target=_warm_compiled, args=(fast_step_kernel,), name="kernel-warm-up", daemon=True)
    warming.start()
    table = SlotTable(cfg.slots, cfg.families, cfg.step_concurrency)
    policy = PolicyClient(cfg.policy_addresses, cfg.default_policy_timeout_ms, cfg.infer_hold,
                          busy=lambda: table.activity.busy)
    table.activity.listen(policy.slot_finished)
    servicer = EnvWorkerServicer(table, policy, video_dir=cfg.video_dir, resource_sharing=cfg.resource_sharing,
                                 critic_address=cfg.critic_address)
    membership: Membership | None = None

    async def drain() -> None:
        await servicer.wait_idle()
        if membership is not None:
            await membership.stop(deregister=True)

    runner = ServiceRunner(
        name="env_worker",
        host=cfg.host,
        port=cfg.port,
        metrics_port=cfg.metrics_port,
        registrations=[
            Registration(
                env_worker_pb2_grpc.add_EnvWorkerServiceServicer_to_server,
                servicer,
                env_worker_pb2.DESCRIPTOR.services_by_name["EnvWorkerService"].full_name,
            )
        ],
        grace_seconds=cfg.grace_seconds,
        on_drain=drain,
    )
    # SERVING (and registration) only once the kernels are compiled: a session's first step must
    # not wait for a compile (62.7 s with a cold numba cache on a busy node).
    await asyncio.to_thread(warming.join)
    await runner.start()
    cfg = cfg.resolved(runner.bound_port)
    servicer.worker_id = cfg.worker_id
    membership = Membership(cfg, table.session_ids, servicer.close_all)
    await membership.register()
    membership.start()
    try:
        await runner.run_until_signalled()
    finally:
        await policy.close()
        table.shutdown()


if __name__ == "__main__":
    run_service(main, "env_worker")
