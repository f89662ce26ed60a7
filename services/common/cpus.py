"""Which CPUs a process may really use, and pinning a process to some of them.

``os.cpu_count()`` counts the host's CPUs. A container started with ``--cpus 2`` or a pod with a
CPU limit of 2 on a 64-core host may run on every core but gets two cores' worth of time, and
work sized for 64 threads only contends there. The env worker sizes how many slots step at once
from this (services/env_worker/slots.SlotActivity); LocalStack divides it among its workers.

``ZETTA_CPUS`` pins a worker to a CPU list. Left to the scheduler, an env worker's stepping thread
is moved between cores whenever the policy worker or another worker wakes up, and finds its
simulation state in the other core's cold cache; pinned, each worker's physics stays warm on its
own cores (docs/throughput.md measures what that gives; LocalStack pins its env workers).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence, Set
from pathlib import Path

#: Where cgroup v2 and v1 keep the CPU quota of the process's own group (inside a container, the
#: container's group is mounted at /sys/fs/cgroup).
CGROUP_ROOT = Path("/sys/fs/cgroup")


def usable_cpus(cgroup_root: Path = CGROUP_ROOT, mask: Set[int] | None = None) -> int:
    """CPUs of the affinity mask (``mask``, or this process's), at most the cgroup quota rounded
    up; at least 1."""
    if mask is None:
        mask = allowed_cpus()
    count = len(mask) if mask is not None else os.cpu_count() or 1
    quota = cgroup_cpu_quota(cgroup_root)
    if quota is not None:
        count = min(count, math.ceil(quota))
    return max(1, count)


def cgroup_cpu_quota(root: Path = CGROUP_ROOT) -> float | None:
    """The group's CPU quota in CPUs (``cpu.max`` of cgroup v2, ``cpu.cfs_quota_us`` of v1); None
    when there is none or it cannot be read."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        if quota != "max":
            return int(quota) / int(period)
        return None
    except (OSError, ValueError):
        pass
    try:
        quota_us = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period_us = int((root / "cpu" / "cpu.cfs_period_us").read_text())
    except (OSError, ValueError):
        return None
    return quota_us / period_us if quota_us > 0 and period_us > 0 else None


def allowed_cpus() -> frozenset[int] | None:
    """The CPUs this process may run on (its affinity mask); None where the OS has no such call (macOS)."""
    try:
        return frozenset(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def parse_cpu_list(text: str) -> frozenset[int]:
    """A CPU list in the kernel's syntax, as ``taskset -c`` and ``docker --cpuset-cpus`` take it:
    ``"0-3,8"`` is CPUs 0, 1, 2, 3 and 8. Raises ValueError saying what is wrong."""
    cpus: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        first, sep, last = part.partition("-")
        if not first.strip().isdigit() or (sep and not last.strip().isdigit()):
            raise ValueError(f"{part!r} is not a CPU number or a range like 0-3")
        lo, hi = int(first), int(last) if sep else int(first)
        if hi < lo:
            raise ValueError(f"range {part!r} runs backwards")
        cpus.update(range(lo, hi + 1))
    return frozenset(cpus)


def format_cpu_list(cpus: Set[int]) -> str:
    """The shortest CPU list for ``cpus`` (``{0, 1, 2, 5}`` is ``"0-2,5"``)."""
    ordered = sorted(cpus)
    parts: list[str] = []
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        parts.append(str(ordered[i]) if i == j else f"{ordered[i]}-{ordered[j]}")
        i = j + 1
    return ",".join(parts)


def split_cpus(cpus: Sequence[int], parts: int) -> list[list[int]]:
    """``parts`` groups of ``cpus`` for as many workers: contiguous blocks whose sizes differ by at
    most one; with more workers than CPUs, one CPU each, in turn."""
    n = len(cpus)
    if parts > n:
        return [[cpus[i % n]] for i in range(parts)]
    return [list(cpus[i * n // parts:(i + 1) * n // parts]) for i in range(parts)]


def pin_process(cpus: Set[int]) -> None:
    """Run every thread of this process (those already started too: libraries start pools at
    import) and every thread started later on ``cpus`` only."""
    try:
        threads = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:  # no procfs: the calling thread, which later threads inherit from
        threads = [0]
    for tid in threads:
        try:
            os.sched_setaffinity(tid, cpus)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
