"""Measure what one session costs an env worker and one inference costs a policy worker.

    .venv/bin/python deploy/tools/measure_costs.py            # about 3 minutes on 2 cores
    .venv/bin/python deploy/tools/measure_costs.py --quick    # fewer points

Starts a LocalStack with one env worker (8 slots) and one policy worker, then for each workload
(LIBERO-Goal state-only, LIBERO-Goal with two 128x128 cameras, robosuite Lift) and each number of
concurrent sessions drives policy_step over the gateway for a fixed time and reads:

- env worker CPU seconds per environment step (from /proc: user + system time of the process),
  which sets how many steps/s a core sustains, whatever else runs on the machine;
- env worker resident memory before and after the sessions exist (per-slot memory);
- policy worker CPU seconds per inference item and the batch sizes it formed;
- gateway CPU seconds per environment step it routed;
- steps/s on this machine (every process shares its cores, so this is a floor).

docs/deploy.md ("Sizing") turns these numbers into sessions per env worker and policy workers per
env worker.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

from prometheus_client.parser import text_string_to_metric_families  # noqa: E402

from zetta import Gateway  # noqa: E402
from services.ops.local_stack import LocalStack  # noqa: E402

TICKS = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")

WORKLOADS = {
    "libero-goal state": ("libero", {"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl"}),
    "libero-goal 2 cams": ("libero", {"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl",
                                      "cameras": ["agentview", "robot0_eye_in_hand"], "camera_size": 128}),
    "robosuite lift": ("robosuite", {"env_name": "Lift"}),
}


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICKS


def rss_bytes(pid: int) -> int:
    """Resident memory of a process."""
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE


def counter(url: str, name: str) -> float:
    """Sum of a counter's samples in a /metrics page."""
    text = urllib.request.urlopen(url, timeout=5).read().decode()  # loopback
    total = 0.0
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name == name:
                total += s.value
    return total


@dataclass
class Point:
    workload: str
    sessions: int
    steps: int
    seconds: float
    env_cpu_per_step_ms: float
    env_rss_before_mb: float
    env_rss_after_mb: float
    policy_cpu_per_item_ms: float
    mean_batch: float
    gateway_cpu_per_step_ms: float


async def measure(stack: LocalStack, workload: str, n: int, seconds: float) -> Point:
    family, config = WORKLOADS[workload]
    env, policy, gateway = stack.services["env-0"], stack.services["policy-0"], stack.services["gateway"]
    async with Gateway(stack.gateway_address) as gw:
        rss0 = rss_bytes(env.proc.pid)
        group = await gw.create_sessions(family, n=n, env_config=config)
        await group.reset(seed=list(range(n)), init_state_index=list(range(n)) if family == "libero" else 0)
        await group.policy_step()  # warm
        rss1 = rss_bytes(env.proc.pid)
        steps0 = counter(env.metrics_url, "zetta_env_steps_total")
        items0 = counter(policy.metrics_url, "zetta_policy_items_total")
        batches0 = counter(policy.metrics_url, "zetta_policy_batch_size_count")
        cpu_env0, cpu_pol0 = cpu_seconds(env.proc.pid), cpu_seconds(policy.proc.pid)
        cpu_gw0 = cpu_seconds(gateway.proc.pid)
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            results = await group.policy_step()
            done = [r.session_id for r in results if r.done]
            if done:
                await group.subset(done).reset()
        wall = time.monotonic() - t0
        steps = counter(env.metrics_url, "zetta_env_steps_total") - steps0
        items = counter(policy.metrics_url, "zetta_policy_items_total") - items0
        batches = counter(policy.metrics_url, "zetta_policy_batch_size_count") - batches0
        cpu_env = cpu_seconds(env.proc.pid) - cpu_env0
        cpu_pol = cpu_seconds(policy.proc.pid) - cpu_pol0
        cpu_gw = cpu_seconds(gateway.proc.pid) - cpu_gw0
        rss2 = max(rss1, rss_bytes(env.proc.pid))
        await group.close()
    return Point(workload, n, int(steps), wall, 1000 * cpu_env / max(steps, 1), rss0 / 2**20, rss2 / 2**20,
                 1000 * cpu_pol / max(items, 1), items / max(batches, 1), 1000 * cpu_gw / max(steps, 1))


async def run(points: list[tuple[str, int]], seconds: float, model: str) -> list[Point]:
    out = []
    with LocalStack(env_workers=1, slots=8, policy_workers=1, models=(model,)) as stack:
        for workload, n in points:
            p = await measure(stack, workload, n, seconds)
            out.append(p)
            print(f"{p.workload:20s} {p.sessions:2d} sessions: {p.steps / p.seconds:6.1f} steps/s, "
                  f"env worker {p.env_cpu_per_step_ms:5.1f} CPU-ms/step, RSS {p.env_rss_before_mb:6.0f} -> "
                  f"{p.env_rss_after_mb:6.0f} MiB, policy {p.policy_cpu_per_item_ms:5.2f} CPU-ms/item, "
                  f"mean batch {p.mean_batch:4.1f}, gateway {p.gateway_cpu_per_step_ms:4.2f} CPU-ms/step",
                  flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seconds", type=float, default=12.0)
    parser.add_argument("--model", default="scripted-pick-place", help="served model (ZETTA_MODELS)")
    args = parser.parse_args()
    if args.quick:
        points = [("libero-goal state", 4), ("robosuite lift", 4)]
    else:
        points = [("libero-goal state", 1), ("libero-goal state", 4), ("libero-goal state", 8),
                  ("libero-goal 2 cams", 4), ("robosuite lift", 8)]
    print(f"machine: {os.cpu_count()} cores; one env worker (8 slots), one policy worker serving {args.model}, "
          "all on this machine")
    asyncio.run(run(points, args.seconds, args.model))
    return 0


if __name__ == "__main__":
    sys.exit(main())
