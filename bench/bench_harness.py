"""Per-step cost of a 10-critic harness next to the env step it watches: package code in-process
vs in its sandbox child, side by side in one run.

One real LIBERO slot runs the scripted pick-and-place policy; each episode is run three times with
the same key: plain (the env worker's step loop without a harness), then through the harness loop
(services/env_worker/harness_loop.SlotHarness.run_chunk) with the same package twice: its code run
in this process (``ZETTA_HARNESS_SANDBOX=off``, the trusted-code opt-in) and in a sandbox child
(the default; services/harness/sandbox/). The package has 10 package-code critics (tools/critics.py,
each calling one library predicate) and no adjudication rule, so the critics all run at every step
but never take control and every run executes the same actions. Printed per mode: median env step
time, median harness time per step (critics, window, bookkeeping and, sandboxed, the round trip to
the child) and their ratio, episodes alternated so machine load hits all modes alike. Wall and CPU
times are both printed; the sandboxed CPU time adds the child's CPU (from /proc) to the host
thread's, and how long the child waited for a core (runnable, not running) is printed apart: on a
loaded machine it is most of the sandboxed wall time. Target: harness < 5% of the env step, sandboxed included.

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

SKILL = ('+++\nname = "bench-10-critics"\ndescription = "10 package-code critics, no rule: they only watch"\n'
         "+++\nbench harness\n")

TOOLS = """from services.harness.runtime.api import Proposal
from services.harness.runtime.library import PREDICATES, resolve

NAMES = [%s]
PARAMS = {n: resolve(PREDICATES[n].params, {}, n) for n in NAMES}


def _run(name, window):
    details = PREDICATES[name].fn(window, PARAMS[name])
    return None if details is None else Proposal("critics." + name, name, "", details)
""" % ", ".join(repr(n) for n, _ in CRITICS) + "".join(
    f"\n\ndef critic_{name}(window, params):\n    return _run({name!r}, window)\n" for name, _ in CRITICS)


def write_package(root: Path) -> Path:
    (root / "tools").mkdir(parents=True, exist_ok=True)
    (root / "SKILL.md").write_text(SKILL)
    (root / "tools" / "critics.py").write_text(TOOLS)
    return root


def child_cpu_s(pid: int) -> float:
    """CPU seconds a process (the sandbox child) has run, from /proc/PID/schedstat (ns)."""
    return child_sched_s(pid)[0]


def child_sched_s(pid: int) -> tuple[float, float]:
    """Seconds a process has run and has waited on a run queue (runnable, no core free for it),
    from /proc/PID/schedstat (ns)."""
    ran, waited = Path(f"/proc/{pid}/schedstat").read_text().split()[:2]
    return int(ran) / 1e9, int(waited) / 1e9


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


MODES = ("in-process", "sandboxed")


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
    harnesses = {
        "in-process": SlotHarness(load_package(pkg_dir, import_tools=True)),
        "sandboxed": SlotHarness(load_package(pkg_dir, import_tools=False)),  # tools never imported here
    }
    assert harnesses["in-process"].runtime.sandbox is None
    sandbox = harnesses["sandboxed"].runtime.sandbox
    assert sandbox is not None
    for h in harnesses.values():
        assert len(h.runtime.critics) == 10
    keys = ("env_wall", "env_cpu", "h_wall", "h_cpu")
    times = {m: {k: [] for k in keys} for m in MODES}
    child_cpu: list[float] = []
    child_wait: list[float] = []
    loop = {m: [] for m in ("plain", *MODES)}
    for ep in range(a.episodes):
        spec = ResetSpec(task=a.task, seed=ep, init_state_index=ep % 50)
        obs, _ = slot.reset(spec)
        _, per = run_plain(slot, policy, obs, a.steps)
        loop["plain"].append(per)
        for mode in (MODES if ep % 2 == 0 else MODES[::-1]):
            harness = harnesses[mode]
            obs, instruction = slot.reset(spec)
            harness.reset(obs, instruction, slot.milestone_names())
            c0, w0 = child_sched_s(sandbox.pid) if mode == "sandboxed" else (0.0, 0.0)
            t, per = run_harnessed(slot, policy, obs, a.steps, harness)
            if mode == "sandboxed":
                c1, w1 = child_sched_s(sandbox.pid)
                child_cpu.append((c1 - c0) / max(1, len(t["h_wall"])))
                child_wait.append((w1 - w0) / max(1, len(t["h_wall"])))
            for k, v in t.items():
                times[mode][k] += v
            loop[mode].append(per)
            disabled = harness.runtime.report.disabled_critics
            assert not disabled, disabled
    print(f"load: {os.getloadavg()[0]:.1f} (1-min average); {a.episodes} episodes x {a.steps} steps per mode, "
          f"{a.suite} task {a.task}, 10 package-code critics; sandbox: uid {sandbox.isolation.get('uid')}, "
          f"degraded: {sandbox.isolation.get('degraded') or 'no'}")
    print(f"{'':34s} {'in-process':>22s} {'sandboxed':>22s}")
    med = {m: {k: statistics.median(v) for k, v in times[m].items()} for m in MODES}
    child = statistics.median(child_cpu) if child_cpu else 0.0

    def row(label: str, values: list[str]) -> None:
        print(f"{label:34s} " + " ".join(f"{v:>22s}" for v in values))

    row("env step, median wall / CPU (ms)", [f"{med[m]['env_wall'] * 1e3:.3f} / {med[m]['env_cpu'] * 1e3:.3f}" for m in MODES])
    cpu = {"in-process": med["in-process"]["h_cpu"], "sandboxed": med["sandboxed"]["h_cpu"] + child}
    row("harness step, median wall / CPU (ms)", [f"{med[m]['h_wall'] * 1e3:.3f} / {cpu[m] * 1e3:.3f}" for m in MODES])
    row("harness p90 wall (ms)", [f"{np.percentile(times[m]['h_wall'], 90) * 1e3:.3f}" for m in MODES])
    row("harness / env step, wall / CPU", [f"{med[m]['h_wall'] / med[m]['env_wall']:.2%} / {cpu[m] / med[m]['env_cpu']:.2%}"
                                          for m in MODES])
    row("loop per step, median (ms)", [f"{statistics.median(loop[m]) * 1e3:.3f}" for m in MODES])
    print(f"plain loop per step, median: {statistics.median(loop['plain']) * 1e3:.3f} ms (scripted policy included); "
          f"sandbox child CPU per step: {child * 1e3:.3f} ms (in the sandboxed CPU column); target: harness < 5% of an env step")
    print(f"sandbox child waiting for a core (runnable, not running) per step: {statistics.median(child_wait) * 1e3:.3f} ms "
          "(mean per episode, median over episodes; part of the sandboxed wall column)")
    for h in harnesses.values():
        h.close()
    slot.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
