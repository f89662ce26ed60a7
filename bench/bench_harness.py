"""Per-step cost of a 10-critic harness next to the env step it watches, side by side in one run.

One real LIBERO slot runs the scripted pick-and-place policy; each episode is run twice with the
same key: once plain (the env worker's step loop without a harness) and once through the harness
loop (services/env_worker/harness_loop.SlotHarness.run_chunk) with a package of 10 library
critics and no adjudication rule, so the critics all run at every step but never take control
and both runs execute the same actions. Printed: median env step time, median harness time per
step (critics, window and bookkeeping) and their ratio, plus the plain vs harnessed loop time per
step, episode by episode alternated so machine load hits both alike. Wall and thread CPU times
are both printed: on a shared machine the CPU times are the stable ones. Target: harness < 5% of
the env step.

    python bench/bench_harness.py [--episodes 4] [--steps 150] [--suite libero_goal] [--task 6]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "clients" / "python"))

from services.harness.package.loader import load_package
from services.env_worker.families import ResetSpec, get_family
from services.env_worker.harness_loop import SlotHarness
from services.policy_worker.models.scripted import ScriptedPickPlacePolicy

CRITICS = [
    ("non_approach", {}), ("approach_wrong_object", {}), ("failed_acquisition", {}), ("grasp_lost", {}),
    ("drift", {}), ("held_near_target", {}), ("held_stalled_transport", {}), ("supported_placement", {}),
    ("stalled_progress", {}), ("blocked_motion", {}),
]

SKILL = "+++\n" + 'name = "bench-10-critics"\ndescription = "10 library critics, no rule: they only watch"\n' + "".join(
    f'\n[[critics]]\nname = "c{i}_{name}"\npredicate = "{name}"\nevidence = "{name}"\n' for i, (name, _) in enumerate(CRITICS)
) + "+++\nbench harness\n"


def write_package(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "SKILL.md").write_text(SKILL)
    return root


class _Hist:
    """Collects the env step times run_chunk reports (it observes a Prometheus histogram)."""

    def __init__(self) -> None:
        self.values: list[float] = []

    def observe(self, v: float) -> None:
        self.values.append(v)


def run_plain(slot, policy, obs, steps: int) -> tuple[int, float]:
    """The plain loop: steps taken and wall time per step."""
    start = time.perf_counter()
    n = 0
    for _ in range(steps):
        action = policy.infer({k: v[None] for k, v in obs.items()}, [""])[0]
        out = slot.step(action[0], render=True)  # as run_chunk renders the last action of each chunk
        obs, n = out.observation, n + 1
        if out.terminated or out.truncated:
            break
    return n, (time.perf_counter() - start) / max(1, n)


def timed(fn, wall: list[float], cpu: list[float]):
    """``fn`` wrapped to record its wall and thread CPU time per call."""
    def wrapper(*args, **kwargs):
        w, c = time.perf_counter(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            wall.append(time.perf_counter() - w)
            cpu.append(time.thread_time() - c)
    return wrapper


def run_harnessed(slot, policy, obs, steps: int, harness: SlotHarness) -> tuple[dict[str, list[float]], float]:
    """The harness loop; per step the env step's and the harness's wall and CPU times."""
    t: dict[str, list[float]] = {"env_wall": [], "env_cpu": [], "h_wall": [], "h_cpu": []}
    step, decide = slot.step, harness.runtime.step
    slot.step = timed(step, t["env_wall"], t["env_cpu"])
    harness.runtime.step = timed(decide, t["h_wall"], t["h_cpu"])
    start = time.perf_counter()
    n = 0
    try:
        while n < steps:
            action = policy.infer({k: v[None] for k, v in obs.items()}, [""])[0]
            out, executed, _, _ = harness.run_chunk(slot, action[:1], 10_000, _Hist())
            obs = out.observation
            n += len(executed)
            if out.terminated or out.truncated:
                break
    finally:
        slot.step, harness.runtime.step = step, decide
    return t, (time.perf_counter() - start) / max(1, n)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--suite", default="libero_goal")
    p.add_argument("--task", default="6")
    a = p.parse_args(argv)
    fam_cls = get_family("libero")
    family = fam_cls(fam_cls.canonical_config({"suite": a.suite, "cameras": []}))
    slot = family.init()
    policy = ScriptedPickPlacePolicy()
    pkg_dir = write_package(Path(tempfile.mkdtemp(prefix="bench-harness-")) / "pkg")
    harness = SlotHarness(load_package(pkg_dir))
    assert len(harness.runtime.critics) == 10
    times: dict[str, list[float]] = {"env_wall": [], "env_cpu": [], "h_wall": [], "h_cpu": []}
    loop_plain: list[float] = []
    loop_h: list[float] = []
    for ep in range(a.episodes):
        spec = ResetSpec(task=a.task, seed=ep, init_state_index=ep % 50)
        obs, _ = slot.reset(spec)
        _, per = run_plain(slot, policy, obs, a.steps)
        loop_plain.append(per)
        obs, instruction = slot.reset(spec)
        harness.reset(obs, instruction, slot.milestone_names())
        t, per = run_harnessed(slot, policy, obs, a.steps, harness)
        for k, v in t.items():
            times[k] += v
        loop_h.append(per)
        disabled = harness.runtime.report.disabled_critics
        assert not disabled, disabled
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"load: {os.getloadavg()[0]:.1f} (1-min average); {a.episodes} episodes x {a.steps} steps, "
          f"{a.suite} task {a.task}, 10 critics, {len(times['h_wall'])} harnessed steps")
    print(f"env step, median wall / CPU      : {med['env_wall'] * 1000:7.3f} / {med['env_cpu'] * 1000:7.3f} ms")
    print(f"harness step, median wall / CPU  : {med['h_wall'] * 1000:7.3f} / {med['h_cpu'] * 1000:7.3f} ms "
          f"(p90 wall {np.percentile(times['h_wall'], 90) * 1000:.3f} ms)")
    print(f"harness / env step, wall / CPU   : {med['h_wall'] / med['env_wall']:7.2%} / "
          f"{med['h_cpu'] / med['env_cpu']:7.2%}   (target < 5%)")
    print(f"loop per step, plain / harness   : {statistics.median(loop_plain) * 1000:.3f} / "
          f"{statistics.median(loop_h) * 1000:.3f} ms (median over episodes; scripted policy included)")
    slot.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
