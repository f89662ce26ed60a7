"""LocalStack's env workers really run pinned: every thread of each worker (gRPC's, the slot
threads', the event loop's) on its own block of CPUs, the blocks disjoint (services/common/cpus.py)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.common.cpus import parse_cpu_list, usable_cpus
from services.ops.local_stack import LocalStack


def _thread_cpus(pid: int) -> dict[int, frozenset[int]]:
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        status = Path(f"/proc/{pid}/task/{tid}/status").read_text()
        allowed = next(line for line in status.splitlines() if line.startswith("Cpus_allowed_list:"))
        out[int(tid)] = parse_cpu_list(allowed.split(":", 1)[1])
    return out


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2 or usable_cpus() < len(os.sched_getaffinity(0)),
                    reason="needs 2 CPUs and no CPU quota below them")
def test_env_workers_run_on_disjoint_cpu_blocks(stack: LocalStack) -> None:
    blocks = []
    for i in range(stack.env_workers):
        svc = stack.services[f"env-{i}"]
        expected = parse_cpu_list(stack.env_worker_cpus(i))
        threads = _thread_cpus(svc.proc.pid)
        assert len(threads) > 3  # gRPC and slot threads started after the pinning are covered too
        assert set(threads.values()) == {expected}, f"env-{i}: {threads}"
        blocks.append(expected)
    assert not blocks[0] & blocks[1]
    assert _thread_cpus(stack.services["policy-0"].proc.pid)[stack.services["policy-0"].proc.pid] == \
        frozenset(os.sched_getaffinity(0))  # the policy worker is left to the scheduler


def test_policy_worker_pins_itself_to_zetta_cpus(tmp_path: Path) -> None:
    """ZETTA_CPUS on a policy worker: every thread of it (the model's, gRPC's) runs on that list."""
    cpu = max(os.sched_getaffinity(0))
    with LocalStack(env_workers=0, policy_workers=1, critic=False, workdir=tmp_path,
                    extra_env={"ZETTA_CPUS": str(cpu)}) as stack:
        threads = _thread_cpus(stack.services["policy-0"].proc.pid)
    assert len(threads) > 1 and set(threads.values()) == {frozenset({cpu})}, threads
