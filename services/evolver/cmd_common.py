"""What the evolver's commands share: their common options, the rollout settings they give,
the optional LLM backend and publishing a package directory to a registry.

`zetta evolve`, `zetta eval` and `zetta evolve experiment` each import this module and none of
the others, so the commands do not import each other.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS
from services.common.progress import add_progress_option
from services.evolver.cluster import ClusterParams
from services.evolver.eod import EODParams
from services.evolver.evolve import EvolveConfig
from services.evolver.gate import GateParams
from services.evolver.llm import LLMConfig, LLMError, config_from_env
from services.evolver.repair import SearchParams
from services.evolver.rollout import RunConfig
from services.evolver.stack import policy_instructions


def add_run_args(p: argparse.ArgumentParser) -> None:
    """Options shared by `zetta evolve` and `zetta eval`: the stack, the policy and the store."""
    p.add_argument("--suite", required=True, help="LIBERO suite, e.g. libero_goal_task or libero_goal_swap")
    p.add_argument("--tasks", required=True, help="comma-separated task indices or names, e.g. 6,9")
    p.add_argument("--store", type=Path, default=None, help="rollout store directory (default runs/<command>-<suite>)")
    p.add_argument("--report", type=Path, default=None, help="report directory (default <store>/report)")
    p.add_argument("--gateway", default=None, help="use a running stack's gateway (with --registry)")
    p.add_argument("--registry", default=None, help="critic service address of that stack")
    p.add_argument("--model", default=DEFAULT_POLICY, help=f"the frozen policy (default {DEFAULT_POLICY})")
    p.add_argument("--execute-steps", type=int, default=EXECUTE_STEPS,
                   help=f"actions of each chunk executed per policy call (default {EXECUTE_STEPS}, the VLA's own)")
    p.add_argument("--max-steps", type=int, default=0, help="episode budget (default: the suite's)")
    p.add_argument("--concurrency", type=int, default=2, help="episodes in flight")
    p.add_argument("--env-workers", type=int, default=2, help="env workers of the local stack")
    p.add_argument("--video", action="store_true", help="record every rollout's video (slower: renders each step)")
    add_progress_option(p)


def add_policy_worker_arg(p: argparse.ArgumentParser) -> None:
    """--policy-worker: where a running stack's frozen policy can be asked what it was trained on."""
    p.add_argument("--policy-worker", default=None,
                   help="a policy worker of that stack (with --gateway): the repair search asks it which "
                        "instructions the policy was trained on (without it, every firing of an instruction "
                        "redirection on a success counts as a false positive)")


def with_policy_instructions(cfg: EvolveConfig, instructions: tuple[str, ...]) -> EvolveConfig:
    """``cfg`` with the instructions the frozen policy was trained on (from :func:`trained_instructions`)."""
    return dataclasses.replace(cfg, policy_instructions=instructions)


def trained_instructions(address: str, model: str) -> tuple[str, ...]:
    """The instructions ``model`` was trained on (ListModels at ``address``), asked once per command."""
    try:
        return policy_instructions(address, model)
    except RuntimeError as exc:
        raise SystemExit(f"zetta evolve: {exc}") from None


def add_search_args(p: argparse.ArgumentParser) -> None:
    """The loops' budgets and thresholds, shared by `zetta evolve` and `zetta evolve experiment`."""
    p.add_argument("--rounds", type=int, default=1)
    p.add_argument("--dev-seeds", type=int, default=EvolveConfig.dev_seeds, help="repair seeds per task")
    p.add_argument("--heldout-seeds", type=int, default=EvolveConfig.heldout_seeds,
                   help="gate (admission) seeds per task")
    p.add_argument("--test-seeds", type=int, default=EvolveConfig.test_seeds,
                   help="seeds of the reported number per task (dev + held-out + test <= 50 initial states)")
    p.add_argument("--max-clusters", type=int, default=EvolveConfig.max_clusters,
                   help="clusters repaired per task and round, largest first")
    p.add_argument("--max-candidates", type=int, default=SearchParams.max_candidates,
                   help="candidate patches validated per cluster and depth")
    p.add_argument("--max-depth", type=int, default=EvolveConfig.max_depth,
                   help="internal versions stacked per cluster until one solves every cluster seed")
    p.add_argument("--regression-min", type=float, default=1.0,
                   help="share of a cluster's seeds a candidate must solve (the paper: 1.0)")
    p.add_argument("--require-hand-back", action="store_true",
                   help="count a success only when the policy was in control at the success step: one an "
                        "intervention finished (a placement recovery still in control) then validates no "
                        "candidate and passes no regression or held-out gate")
    p.add_argument("--nominal-seeds", type=int, default=EvolveConfig.nominal_seeds,
                   help="bare-policy episodes per task on a LIBERO-PRO variant's original suite; a critic that "
                        "fires on their successes counts a false positive (0: none)")
    p.add_argument("--eod-epsilon", type=float, default=EODParams().epsilon)
    p.add_argument("--cluster-radius", type=float, default=ClusterParams().radius)
    p.add_argument("--cluster-max-size", type=int, default=ClusterParams().max_size,
                   help="most failures per cluster (0: no limit)")


def evolve_config(a: argparse.Namespace, suite: str, tasks: tuple[str, ...], name: str) -> EvolveConfig:
    """The evolution a command's parsed options (``add_search_args``) describe for one suite."""
    return EvolveConfig(suite=suite, tasks=tasks, rounds=a.rounds, dev_seeds=a.dev_seeds,
                        heldout_seeds=a.heldout_seeds, test_seeds=a.test_seeds, name=name,
                        max_clusters=a.max_clusters, eod=EODParams(epsilon=a.eod_epsilon),
                        cluster=ClusterParams(radius=a.cluster_radius, max_size=a.cluster_max_size),
                        search=SearchParams(max_candidates=a.max_candidates), gate=GateParams(a.regression_min, require_hand_back=a.require_hand_back),
                        llm=llm_from_env(), max_depth=a.max_depth, nominal_seeds=a.nominal_seeds)


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
