"""What the evolver's commands share: their common options, the rollout settings they give,
the optional LLM backend and publishing a package directory to a registry.

`zetta evolve`, `zetta eval` and `zetta evolve experiment` each import this module and none of
the others, so the commands do not import each other.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.common.policies import DEFAULT_POLICY
from services.common.progress import add_progress_option
from services.evolver.llm import LLMConfig, LLMError, config_from_env
from services.evolver.rollout import RunConfig


def add_run_args(p: argparse.ArgumentParser) -> None:
    """Options shared by `zetta evolve` and `zetta eval`: the stack, the policy and the store."""
    p.add_argument("--suite", required=True, help="LIBERO suite, e.g. libero_goal_task or libero_goal_swap")
    p.add_argument("--tasks", required=True, help="comma-separated task indices or names, e.g. 6,9")
    p.add_argument("--store", type=Path, default=None, help="rollout store directory (default runs/<command>-<suite>)")
    p.add_argument("--report", type=Path, default=None, help="report directory (default <store>/report)")
    p.add_argument("--gateway", default=None, help="use a running stack's gateway (with --registry)")
    p.add_argument("--registry", default=None, help="critic service address of that stack")
    p.add_argument("--model", default=DEFAULT_POLICY, help=f"the frozen policy (default {DEFAULT_POLICY})")
    p.add_argument("--execute-steps", type=int, default=2, help="actions of each chunk executed per policy call")
    p.add_argument("--max-steps", type=int, default=0, help="episode budget (default: the suite's)")
    p.add_argument("--concurrency", type=int, default=2, help="episodes in flight")
    p.add_argument("--env-workers", type=int, default=2, help="env workers of the local stack")
    p.add_argument("--video", action="store_true", help="record every rollout's video (slower: renders each step)")
    add_progress_option(p)


def tasks_of(text: str) -> tuple[str, ...]:
    """'6,9' -> ('6', '9')."""
    out = tuple(t.strip() for t in text.split(",") if t.strip())
    if not out:
        raise SystemExit("--tasks: give at least one task")
    return out


def run_config(args: argparse.Namespace, gateway: str) -> RunConfig:
    """The rollout settings of the parsed arguments."""
    return RunConfig(gateway=gateway, model=args.model, execute_steps=args.execute_steps, max_steps=args.max_steps,
                     record_video=args.video, concurrency=args.concurrency)


def llm_from_env() -> LLMConfig | None:
    """The optional LLM backend: ZETTA_EVOLVER_LLM_URL (+ _MODEL, _API_KEY); unset means offline only."""
    try:
        return config_from_env()
    except LLMError as exc:
        raise SystemExit(str(exc)) from None


def publish_dir(registry: str, path: Path) -> str:
    """Publish a package directory (a harness from another stack) and return its reference."""
    from services.common.tls import sync_channel
    from services.harness.package.format import read_tree
    from zetta_wire.v1 import critic_pb2, critic_pb2_grpc

    with sync_channel(registry) as ch:  # mutual TLS when ZETTA_TLS_* are set, as RegistryClient
        files = {k: v for k, v in read_tree(path).items() if k != "manifest.json"}
        m = critic_pb2_grpc.HarnessRegistryServiceStub(ch).Publish(critic_pb2.PublishRequest(files=files), timeout=30)
    return f"{m.manifest.name}@{m.manifest.version}"
