"""Per-step cost of a 10-critic harness next to the env step it watches: package code in-process
at every step (the runtime before code critics had a cadence), in its sandbox child at every step,
and in its sandbox child at the default cadence, side by side in one run.

One real LIBERO slot runs the scripted pick-and-place policy; each episode is run four times with
the same key: plain (the env worker's step loop without a harness), then through the harness loop
(services/env_worker/harness_loop.SlotHarness.run_chunk) with the same package three times: its
code run in this process (``ZETTA_HARNESS_SANDBOX=off``, the trusted-code opt-in) with
``ZETTA_CODE_CRITIC_EVERY=1``, in a sandbox child (the default; services/harness/sandbox/) with
``ZETTA_CODE_CRITIC_EVERY=1``, and in a sandbox child at the default cadence (evaluated every 4th
step over a window of every step; the frames between travel with the next call). The package has 10
package-code critics (tools/critics.py, each calling one library predicate) and no adjudication
rule, so the critics never take control and every run executes the same actions. Printed per mode:
median env step time, harness time per step (critics, window, bookkeeping and, sandboxed, the round
trips to the child: the mean per episode, median over episodes, since at a cadence most steps cost
little and some cost a round trip) and their ratio, episodes alternated so machine load hits all
modes alike. Wall and CPU times are both printed; the sandboxed CPU time adds the child's CPU (from
/proc) to the host thread's, and how long the child waited for a core (runnable, not running) is
printed apart. Target: harness < 5% of the env step at the default settings, sandboxed.

    python bench/bench_harness.py [--episodes 4] [--steps 150] [--suite libero_goal] [--task 6] [--camera-size 64]
    python bench/bench_harness.py --write-docs   # also docs/results/harness-cost.json and .md
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

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from services.common.policies import EXECUTE_STEPS
from services.common.provenance import page_header, publish
from services.harness.runtime.budget import CODE_CRITIC_EVERY

if TYPE_CHECKING:  # the env worker's modules load LIBERO: imported when a run starts, not for a page
    from services.env_worker.harness_loop import SlotHarness

TOPIC = "harness-cost"
TITLE = "Harness cost per env step: 10 package-code critics in-process and sandboxed"

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
    while n < steps:
        chunk = policy.infer({k: v[None] for k, v in obs.items()}, [""])[0]
        for i, action in enumerate(chunk):
            out = slot.step(action, render=i == len(chunk) - 1)  # as run_chunk renders the last action of a chunk
            obs, n = out.observation, n + 1
            if out.terminated or out.truncated:
                return n, (time.perf_counter() - start) / max(1, n)
    return n, (time.perf_counter() - start) / max(1, n)


def timed(fn, wall: list[float], cpu: list[float], rendered: list[bool] | None = None):
    """``fn`` wrapped to record its wall and thread CPU time per call (and, for env steps,
    whether the call rendered)."""
    def wrapper(*args, **kwargs):
        w, c = time.perf_counter(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            wall.append(time.perf_counter() - w)
            cpu.append(time.thread_time() - c)
            if rendered is not None:
                rendered.append(bool(kwargs.get("render")))
    return wrapper


def run_harnessed(slot, policy, obs, steps: int, harness: SlotHarness) -> tuple[dict[str, list[float]], float]:
    """The harness loop; per step the env step's and the harness's wall and CPU times."""
    t: dict[str, list] = {"env_wall": [], "env_cpu": [], "h_wall": [], "h_cpu": [], "render": []}
    step, decide = slot.step, harness.runtime.step
    slot.step = timed(step, t["env_wall"], t["env_cpu"], t["render"])
    harness.runtime.step = timed(decide, t["h_wall"], t["h_cpu"])
    start = time.perf_counter()
    n = 0
    try:
        while n < steps:
            action = policy.infer({k: v[None] for k, v in obs.items()}, [""])[0]
            out, executed, _, _ = harness.run_chunk(slot, action, 10_000, _Hist())
            obs = out.observation
            n += len(executed)
            if out.terminated or out.truncated:
                break
    finally:
        slot.step, harness.runtime.step = step, decide
    return t, (time.perf_counter() - start) / max(1, n)


#: Label, sandboxed, ZETTA_CODE_CRITIC_EVERY, ZETTA_CODE_CRITIC_PIPELINE.
MODES = (("in-process, every step", False, 1, False), ("sandboxed, every step", True, 1, False),
         (f"sandboxed, default (every {CODE_CRITIC_EVERY}, pipelined)", True, CODE_CRITIC_EVERY, True))


def harness_for(pkg_dir: Path, sandboxed: bool, every: int, pipelined: bool) -> SlotHarness:
    """The package's harness as the env worker builds it, under ``ZETTA_CODE_CRITIC_EVERY=every``
    and ``ZETTA_CODE_CRITIC_PIPELINE=pipelined``."""
    from services.env_worker.harness_loop import SlotHarness
    from services.harness.package.loader import load_package

    settings = {"ZETTA_CODE_CRITIC_EVERY": str(every), "ZETTA_CODE_CRITIC_PIPELINE": "1" if pipelined else "0"}
    before = {k: os.environ.get(k) for k in settings}
    os.environ.update(settings)
    try:
        harness = SlotHarness(load_package(pkg_dir, import_tools=not sandboxed))  # sandboxed: never imported here
    finally:
        for k, v in before.items():
            if v is None:
                del os.environ[k]
            else:
                os.environ[k] = v
    rt = harness.runtime
    assert (rt.sandbox is not None) == sandboxed and rt.code_every == every and rt.code_pipelined == pipelined
    return harness


def report(doc: Mapping[str, Any]) -> list[str]:
    """The table a run prints (and its page shows), from its per-episode measurements."""
    eps: Mapping[str, list[Mapping[str, float]]] = doc["modes"]
    labels = list(eps)
    cam = f"agentview {doc['camera_size']} px rendered at each chunk's end" if doc["camera_size"] else "no camera"
    out = [f"load: {doc['load']:.1f} (1-min average); {doc['episodes']} episodes x {doc['steps']} steps per mode, "
           f"{doc['suite']} task {doc['task']}, chunks of {doc['chunk']} actions, {cam}, 10 package-code critics; "
           f"sandbox: {doc['sandbox']}",
           "per episode: mean per step; printed: the median over episodes (ratios: of each episode's ratio)"]
    width = max(len(m) for m in labels) + 2
    out.append(f"{'':40s} " + " ".join(f"{m:>{width}s}" for m in labels))

    def med(m: str, key: str) -> float:
        return statistics.median(e[key] for e in eps[m])

    def ratio(m: str, key: str, env: str) -> float:
        return statistics.median(e[key] / e[env] for e in eps[m])

    def row(label: str, values: list[str]) -> None:
        out.append(f"{label:40s} " + " ".join(f"{v:>{width}s}" for v in values))

    row("env step wall / CPU (ms)", [f"{med(m, 'env_wall') * 1e3:.3f} / {med(m, 'env_cpu') * 1e3:.3f}" for m in labels])
    row("  CPU of steps without a render (ms)", [f"{med(m, 'physics_cpu') * 1e3:.3f}" for m in labels])
    row("harness per step wall / CPU (ms)", [f"{med(m, 'h_wall') * 1e3:.3f} / {med(m, 'h_cpu') * 1e3:.3f}" for m in labels])
    row("  of which the sandbox child CPU (ms)", [f"{med(m, 'child_cpu') * 1e3:.3f}" for m in labels])
    row("  child waiting for a core (ms)", [f"{med(m, 'child_wait') * 1e3:.3f}" for m in labels])
    row("harness p90 wall per step (ms)", [f"{med(m, 'h_p90') * 1e3:.3f}" for m in labels])
    row("harness / env step, wall / CPU", [f"{ratio(m, 'h_wall', 'env_wall'):.2%} / {ratio(m, 'h_cpu', 'env_cpu'):.2%}"
                                          for m in labels])
    row("harness / step without a render, CPU", [f"{ratio(m, 'h_cpu', 'physics_cpu'):.2%}" for m in labels])
    row("loop per step (ms)", [f"{med(m, 'loop') * 1e3:.3f}" for m in labels])
    base, default = labels[0], labels[-1]
    share, physics = ratio(default, "h_cpu", "env_cpu"), ratio(default, "h_cpu", "physics_cpu")
    out.append(f"plain loop per step: {statistics.median(doc['plain']) * 1e3:.3f} ms (scripted policy included); "
               f"default sandboxed vs in-process at every step, harness CPU: "
               f"{med(default, 'h_cpu') / med(base, 'h_cpu'):.2f}x")
    out.append(f"target: harness < 5% of an env step (CPU), default settings: {share:.2%} of the env step "
               f"({'met' if share < 0.05 else 'NOT met'}), {physics:.2%} of a step without a render "
               f"({'met' if physics < 0.05 else 'NOT met'})")
    return out


def page(doc: Mapping[str, Any]) -> str:
    """docs/results/harness-cost.md from its results file."""
    return page_header(TOPIC, TITLE, doc) + (
        "\nWhat the columns are and how to read them: [docs/security.md](../security.md), "
        "\"What the sandbox costs\".\n\n```\n" + "\n".join(report(doc)) + "\n```\n")


def measure(a: argparse.Namespace) -> dict[str, Any]:
    """Run the episodes; the results file's measurements."""
    from services.env_worker.families import ResetSpec, get_family
    from services.policy_worker.models.scripted import ScriptedPickPlacePolicy

    fam_cls = get_family("libero")
    cameras = {"cameras": ["agentview"], "camera_size": a.camera_size, "reflections": False} if a.camera_size else {"cameras": []}
    family = fam_cls(fam_cls.canonical_config({"suite": a.suite, **cameras}))
    slot = family.init()
    policy = ScriptedPickPlacePolicy(chunk_size=EXECUTE_STEPS)  # the shipped VLA's chunk: 4 actions per call
    pkg_dir = write_package(Path(tempfile.mkdtemp(prefix="bench-harness-")) / "pkg")
    labels = [label for label, *_ in MODES]
    harnesses = {label: harness_for(pkg_dir, *settings) for label, *settings in MODES}
    for h in harnesses.values():
        assert len(h.runtime.critics) == 10
    #: Per mode, per episode: mean env step wall and CPU, mean harness wall and CPU per step (the
    #: child's CPU included), the child's wait for a core per step, and the loop's time per step.
    eps: dict[str, list[dict[str, float]]] = {m: [] for m in labels}
    plain: list[float] = []
    for ep in range(a.episodes):
        spec = ResetSpec(task=a.task, seed=ep, init_state_index=ep % 50)
        obs, _ = slot.reset(spec)
        _, per = run_plain(slot, policy, obs, a.steps)
        plain.append(per)
        for mode in (labels if ep % 2 == 0 else labels[::-1]):
            harness = harnesses[mode]
            sandbox = harness.runtime.sandbox
            obs, instruction = slot.reset(spec)
            harness.reset(obs, instruction, slot.milestone_names())
            c0, w0 = child_sched_s(sandbox.pid) if sandbox is not None else (0.0, 0.0)
            t, per = run_harnessed(slot, policy, obs, a.steps, harness)
            c1, w1 = child_sched_s(sandbox.pid) if sandbox is not None else (0.0, 0.0)
            n = max(1, len(t["h_wall"]))
            physics = [c for c, r in zip(t["env_cpu"], t["render"]) if not r]
            eps[mode].append({"env_wall": statistics.fmean(t["env_wall"]), "env_cpu": statistics.fmean(t["env_cpu"]),
                              "physics_cpu": statistics.fmean(physics),
                              "h_wall": statistics.fmean(t["h_wall"]),
                              "h_cpu": statistics.fmean(t["h_cpu"]) + (c1 - c0) / n,
                              "child_cpu": (c1 - c0) / n, "child_wait": (w1 - w0) / n, "loop": per,
                              "h_p90": float(np.percentile(t["h_wall"], 90))})
            disabled = harness.runtime.report.disabled_critics
            assert not disabled, disabled
    sandbox = harnesses[labels[-1]].runtime.sandbox
    assert sandbox is not None
    isolation = f"uid {sandbox.isolation.get('uid')}, degraded: {sandbox.isolation.get('degraded') or 'no'}"
    for h in harnesses.values():
        h.close()
    slot.close()
    family.close()  # its render contexts, before the interpreter tears EGL down
    return {"load": os.getloadavg()[0], "episodes": a.episodes, "steps": a.steps, "suite": a.suite, "task": a.task,
            "chunk": EXECUTE_STEPS, "camera_size": a.camera_size, "sandbox": isolation, "plain": plain, "modes": eps}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--steps", type=int, default=150)
    p.add_argument("--suite", default="libero_goal")
    p.add_argument("--task", default="6")
    p.add_argument("--camera-size", type=int, default=64,
                   help="agentview rendered at the end of each chunk, as for the shipped VLA (64 px); 0: no camera")
    p.add_argument("--write-docs", action="store_true", help=f"also write docs/results/{TOPIC}.json and .md")
    a = p.parse_args(argv)
    doc = measure(a)
    print("\n".join(report(doc)))
    if a.write_docs:
        args = list(argv if argv is not None else sys.argv[1:])
        for path in publish(TOPIC, TITLE, "bench/bench_harness.py", args, doc, page, Path(__file__).resolve().parents[1]):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
