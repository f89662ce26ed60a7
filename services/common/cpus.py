"""How many CPUs this process may really use: its affinity mask, capped by a cgroup CPU quota.

``os.cpu_count()`` counts the host's CPUs. A container started with ``--cpus 2`` or a pod with a
CPU limit of 2 on a 64-core host may run on every core but gets two cores' worth of time, and
work sized for 64 threads only contends there. The env worker sizes how many slots step at once
from this (services/env_worker/slots.SlotActivity); LocalStack divides it among its workers.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

#: Where cgroup v2 and v1 keep the CPU quota of the process's own group (inside a container, the
#: container's group is mounted at /sys/fs/cgroup).
CGROUP_ROOT = Path("/sys/fs/cgroup")


def usable_cpus(cgroup_root: Path = CGROUP_ROOT) -> int:
    """CPUs of the affinity mask, at most the cgroup quota rounded up; at least 1."""
    try:
        count = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # no affinity call (macOS)
        count = os.cpu_count() or 1
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
