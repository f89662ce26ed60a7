"""Which CPUs a process may use and pinning to them (services/common/cpus.py), and how LocalStack shares them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from services.common.config import ConfigError
from services.common.cpus import cgroup_cpu_quota, format_cpu_list, parse_cpu_list, split_cpus, usable_cpus
from services.env_worker.config import EnvWorkerConfig
from services.policy_worker.config import PolicyWorkerConfig
from services.ops.local_stack import LocalStack


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


def test_cpu_lists_parse_and_format_like_taskset() -> None:
    """The kernel's list syntax both ways; ranges and single CPUs mix, order does not matter."""
    assert parse_cpu_list("0-3,8") == {0, 1, 2, 3, 8}
    assert parse_cpu_list(" 5 , 1-2") == {1, 2, 5}
    assert format_cpu_list({0, 1, 2, 5, 7, 8}) == "0-2,5,7-8"
    assert parse_cpu_list(format_cpu_list({3, 4, 9})) == {3, 4, 9}


@pytest.mark.parametrize("text, why", [("a", "'a' is not a CPU number"), ("3-1", "runs backwards"),
                                       ("1,,2", "'' is not a CPU number"), ("-2", "'-2' is not"),
                                       ("1-", "'1-' is not")])
def test_bad_cpu_lists_say_what_is_wrong(text: str, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        parse_cpu_list(text)


def test_cpus_split_into_contiguous_blocks_or_one_each_in_turn() -> None:
    assert split_cpus([0, 1, 2, 3], 2) == [[0, 1], [2, 3]]
    assert split_cpus([0, 1, 2, 3, 4], 2) == [[0, 1], [2, 3, 4]]
    assert split_cpus([4, 6], 1) == [[4, 6]]
    assert split_cpus([0, 1], 3) == [[0], [1], [0]]


def test_zetta_cpus_is_checked_against_the_cpus_the_process_may_use() -> None:
    """A malformed list or a CPU outside the affinity mask stops the worker with the variable named;
    a good list also sizes the default step concurrency."""
    allowed = sorted(os.sched_getaffinity(0))
    base = {"ZETTA_GATEWAY_ADDRESS": "g:1"}
    with pytest.raises(ConfigError, match=r"ZETTA_CPUS='0-x' is not a CPU list"):
        EnvWorkerConfig.from_env({**base, "ZETTA_CPUS": "0-x"})
    outside = max(allowed) + 1
    with pytest.raises(ConfigError, match=rf"ZETTA_CPUS='{outside}' names CPUs this process may not run on \({outside}\)"):
        EnvWorkerConfig.from_env({**base, "ZETTA_CPUS": str(outside)})
    with pytest.raises(ConfigError, match="ZETTA_CPUS"):
        PolicyWorkerConfig.from_env({"ZETTA_CPUS": str(outside)})
    cfg = EnvWorkerConfig.from_env({**base, "ZETTA_CPUS": str(allowed[0])})
    assert cfg.cpus == {allowed[0]} and cfg.step_concurrency == 1
    assert EnvWorkerConfig.from_env(base).cpus is None
    assert PolicyWorkerConfig.from_env({"ZETTA_CPUS": str(allowed[-1])}).cpus == {allowed[-1]}


_PIN_CHILD = """
import os, threading, sys
from services.common.cpus import pin_process
cpu = int(sys.argv[1])
started = threading.Event(); done = threading.Event(); seen = {}
def before():  # a thread already running when the process pins itself (a library's pool)
    started.set(); done.wait(); seen["before"] = os.sched_getaffinity(0)
t = threading.Thread(target=before); t.start(); started.wait()
pin_process({cpu})
after = threading.Thread(target=lambda: seen.__setitem__("after", os.sched_getaffinity(0))); after.start(); after.join()
done.set(); t.join()
print(sorted(os.sched_getaffinity(0)), sorted(seen["before"]), sorted(seen["after"]))
"""


def test_pin_process_moves_running_and_later_threads(tmp_path: Path) -> None:
    """Pinning reaches threads started before it and after it, not only the caller."""
    cpu = max(os.sched_getaffinity(0))
    out = subprocess.run([sys.executable, "-c", _PIN_CHILD, str(cpu)], capture_output=True, text=True, timeout=60,
                         cwd=Path(__file__).resolve().parents[2], check=True).stdout.split("\n")[0]
    assert out == f"[{cpu}] [{cpu}] [{cpu}]"


def test_local_stack_pins_each_env_worker_to_its_own_cpus(monkeypatch: pytest.MonkeyPatch) -> None:
    """Blocks of the machine's CPUs, one each in turn with more workers than CPUs; unpinned when
    switched off or when one worker has every CPU anyway; the caller's ZETTA_CPUS wins."""
    monkeypatch.delenv("ZETTA_CPUS", raising=False)
    allowed = sorted(os.sched_getaffinity(0))
    if usable_cpus() < len(allowed):
        pytest.skip("a CPU quota below the affinity mask: LocalStack does not pin here")
    assert LocalStack(env_workers=1).env_worker_cpus(0) == ""
    assert LocalStack(env_workers=2, pin_env_workers=False).env_worker_cpus(1) == ""
    many = LocalStack(env_workers=len(allowed) + 1)
    assert [many.env_worker_cpus(i) for i in range(len(allowed) + 1)] == [str(c) for c in allowed + allowed[:1]]
    if len(allowed) >= 2:
        two = LocalStack(env_workers=2)
        assert parse_cpu_list(two.env_worker_cpus(0)) | parse_cpu_list(two.env_worker_cpus(1)) == set(allowed)
        assert not parse_cpu_list(two.env_worker_cpus(0)) & parse_cpu_list(two.env_worker_cpus(1))
    assert LocalStack(env_workers=2, extra_env={"ZETTA_CPUS": "0"}).env_worker_cpus(1) == "0"
