"""Where the evolver's rollouts run: a stack that is already up, or a local one it starts and stops.

The local stack is the real one (services.ops.local_stack.LocalStack): Redis, gateway, critic service
(harness registry), one policy worker serving the frozen policy and N env workers that load
harness versions from the critic service. Env workers are started after the critic service so
they can be given its address.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Endpoints:
    """Addresses the evolver dials."""

    gateway: str
    registry: str
    #: A policy worker serving the frozen policy, asked what it was trained on ("": none known).
    policy: str = ""


@contextmanager
def endpoints(gateway: str | None, registry: str | None, model: str, env_workers: int, slots: int,
              workdir: Path, video: bool, policy: str | None = None) -> Iterator[Endpoints]:
    """The given addresses, or a local stack started for the duration of the block."""
    if gateway:
        if not registry:
            raise SystemExit("--gateway needs --registry too (the critic service that serves harness versions)")
        yield Endpoints(gateway, registry, policy or "")
        return
    from services.ops.local_stack import LocalStack

    # Absolute: redis-server changes into its --dir before opening its --logfile.
    workdir = workdir.resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    # Batch-invariant serving unless the caller chose otherwise: with it an episode key replays bit
    # for bit whatever else shares the policy worker's batch, so a medoid's validation rollout, its
    # regression rollout and a resumed run's rollouts are the same episode (docs/evolution.md, "Replays").
    extra = {"ZETTA_TORCH_THREADS": "1", "ZETTA_LOG_LEVEL": "WARNING",
             "ZETTA_VLA_BATCH_INVARIANT": os.environ.get("ZETTA_VLA_BATCH_INVARIANT", "1")}
    if video:
        extra["ZETTA_VIDEO_DIR"] = str(workdir / "videos")
    # The do-nothing policy is served beside the frozen one: every gate and table has its control.
    models = (model,) if model == "do-nothing" else (model, "do-nothing")
    stack = LocalStack(env_workers=0, slots=slots, policy_workers=1, families=("libero",), models=models,
                       workdir=workdir, extra_env=extra, critic=True)
    with stack:
        stack.extra_env = {**extra, "ZETTA_CRITIC_ADDR": stack.critic_address}
        for i in range(env_workers):
            stack.start_env_worker(i)
        stack.wait_workers(env_workers)
        yield Endpoints(stack.gateway_address, stack.critic_address, stack.services["policy-0"].address)


def policy_instructions(address: str, model: str, timeout: float = 30.0) -> tuple[str, ...]:
    """The instructions ``model`` was trained on, from the policy worker at ``address`` (ListModels;
    empty when it lists none, when ``address`` is empty or when the worker does not serve it). The
    repair search needs them to tell which redirections the runtime would not start. An unreachable
    worker is an error: a search without them would count false positives the runtime never makes."""
    if not address:
        return ()
    import grpc

    from services.common.tls import sync_channel
    from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc

    with sync_channel(address) as channel:
        try:
            listing = policy_worker_pb2_grpc.PolicyWorkerServiceStub(channel).ListModels(
                policy_worker_pb2.ListModelsRequest(), timeout=timeout)
        except grpc.RpcError as exc:
            raise RuntimeError(f"the policy worker at {address} did not list its models "
                               f"({exc.code().name}: {exc.details()})") from None
    for m in listing.models:
        if m.name == model or (not model and m.is_default):
            return tuple(m.instructions)
    return ()


@contextmanager
def stop_on_sigterm() -> Iterator[None]:
    """Within the block SIGTERM (kill, a scheduler) stops like Ctrl-C: KeyboardInterrupt unwinds the
    command, so the local stack it started is stopped and nothing is left behind; finished rollouts
    are filed. The previous handlers come back afterwards."""
    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    signal.signal(signal.SIGTERM, interrupt)
    if previous[signal.SIGINT] is signal.SIG_IGN:  # started in the background: honour SIGINT too
        signal.signal(signal.SIGINT, interrupt)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
