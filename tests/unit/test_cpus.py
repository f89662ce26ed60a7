"""How many CPUs a process may use (services/common/cpus.py), and how LocalStack shares them."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.common.cpus import cgroup_cpu_quota, usable_cpus
from services.env_worker.config import EnvWorkerConfig
from zetta.local_stack import LocalStack


def _affinity() -> int:
    return len(os.sched_getaffinity(0))


def test_cgroup_v2_quota(tmp_path: Path) -> None:
    """cpu.max "quota period" is quota/period CPUs; "max" is no quota."""
    (tmp_path / "cpu.max").write_text("150000 100000\n")
    assert cgroup_cpu_quota(tmp_path) == 1.5
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_cgroup_v1_quota(tmp_path: Path) -> None:
    """cfs_quota_us / cfs_period_us; -1 is no quota."""
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")
    assert cgroup_cpu_quota(tmp_path) == 3.0
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_quota(tmp_path) is None


def test_no_or_unreadable_cgroup_is_no_quota(tmp_path: Path) -> None:
    assert cgroup_cpu_quota(tmp_path) is None
    (tmp_path / "cpu.max").write_text("garbage")
    assert cgroup_cpu_quota(tmp_path) is None


def test_usable_cpus_is_the_affinity_capped_by_the_quota(tmp_path: Path) -> None:
    """A quota below the affinity mask caps it (rounded up, never below one CPU)."""
    assert usable_cpus(tmp_path) == _affinity()
    (tmp_path / "cpu.max").write_text("50000 100000\n")
    assert usable_cpus(tmp_path) == 1
    (tmp_path / "cpu.max").write_text(f"{100000 * (_affinity() + 4)} 100000\n")
    assert usable_cpus(tmp_path) == _affinity()


def test_env_worker_steps_as_many_slots_at_once_as_it_has_cpus() -> None:
    """Unset, ZETTA_STEP_CONCURRENCY is the CPUs the worker may use; 0 lifts the bound."""
    cfg = EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1"})
    assert cfg.step_concurrency == usable_cpus()
    assert EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1", "ZETTA_STEP_CONCURRENCY": "0"}).step_concurrency == 0


def test_local_stack_shares_the_cpus_among_its_env_workers(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every worker of a LocalStack runs on the same cores: each gets its share, at least one;
    a value the caller sets wins."""
    monkeypatch.delenv("ZETTA_STEP_CONCURRENCY", raising=False)
    cpus = usable_cpus()
    assert LocalStack(env_workers=1).step_concurrency() == str(cpus)
    assert LocalStack(env_workers=2).step_concurrency() == str(max(1, cpus // 2))
    assert LocalStack(env_workers=4 * cpus).step_concurrency() == "1"
    assert LocalStack(env_workers=2, extra_env={"ZETTA_STEP_CONCURRENCY": "0"}).step_concurrency() == "0"
    monkeypatch.setenv("ZETTA_STEP_CONCURRENCY", "3")
    assert LocalStack(env_workers=2).step_concurrency() == "3"
