"""Simulation cost: the fast step path, model sharing, and threads vs processes, side by side.

Everything runs in one invocation; each figure is the median over ``--repeats`` rounds, and within
a round the variants run back to back in rotating order, so load that drifts during the run (the
machine is shared) weighs on all of them alike. Ratios are computed from those medians.

steps      steps/s of one LIBERO-Goal slot ("put_the_cream_cheese_in_the_bowl", state only) and of
           one Lift slot, from the same reset state and with the same actions, for
             stock    robosuite's env.step
             fast     FastStepper, compiled substep kernel (the default, ``fast_step: true``)
             fast-py  FastStepper with Python substeps (what runs if numba is unavailable)
             raw      25 bare mujoco.mj_step calls per control step: physics alone, the limit
create     Slot create and reset against a fresh environment build: a cold process (imports,
           compile, build, first reset); a new group in a warm process (compile + build); the
           model copy each env used to make (``copy.copy``) against the GIL-free copy, with the
           longest stall a 1 ms ticker thread saw during each; a new env on the group's shared
           template; a slot from the group's pool; resets with a held seed, a new seed (private
           model rewritten in place), a seed another slot holds (model shared).
resetphases Where one LIBERO-Goal slot reset (fast path) spends its time: robosuite's env.reset(),
           the settle steps, the rest (init state, task state, observation), for keys the group
           has not settled before (settle steps replayed), for a repeated key (its settled
           snapshot restored, families/settled.py) and for a key's first reset on a second slot
           after the first settled it (the group's snapshot restored on another env). Not in the
           default run.
parallel   Aggregate steps/s of N LIBERO-Goal slots stepping at once on this machine: one thread
           stepping them in turn, N threads in one process (the env worker's model: one slot
           thread per slot, one shared model), N processes with one slot each -- for the fast
           path and for stock env.step.

    python bench/bench_sim.py              # about 4 minutes on 2 cores
    python bench/bench_sim.py --quick      # about 2 minutes
    python bench/bench_sim.py --only steps,create
    python bench/bench_sim.py --only resetphases
Rendering cost is measured by bench/bench_render.py.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

TASK = "put_the_cream_cheese_in_the_bowl"
LIBERO = {"suite": "libero_goal", "task": TASK}
LIFT = {"env_name": "Lift"}


def _median(xs: list[float]) -> float:
    return statistics.median(xs) if xs else float("nan")


def _actions(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-0.5, 0.5, size=(n, 7))
    actions[:, 6] = np.where(np.arange(n) % 40 < 20, -1.0, 1.0)
    return actions


def _family(name: str, config: dict[str, Any]) -> Any:
    from services.env_worker.families import get_family

    return get_family(name)(config)


# ---------------------------------------------------------------------------------------------
# reset phases


def bench_reset_phases(repeats: int) -> dict[str, dict[str, float]]:
    """Median ms per phase of a LIBERO slot reset, each phase timed by wrapping the call: a key the
    group has not settled yet (settle steps replayed), a repeated key (settled snapshot restored)
    and a key's first reset on a second slot after the first slot settled it (the group's shared
    snapshot restored on another env)."""
    from services.env_worker.families import settled
    from services.env_worker.families import ResetSpec
    from services.env_worker.fast_step import make_stepper

    family = _family("libero", LIBERO)
    slot, other = family.init(), family.init()
    slot.reset(ResetSpec(TASK, seed=0, init_state_index=0))
    other.reset(ResetSpec(TASK, seed=0, init_state_index=0))
    env = slot._env
    steppers = [make_stepper(s._env, True) for s in (slot, other)]
    spent: dict[str, float] = defaultdict(float)

    def timed(owner: Any, attr: str, phase: str) -> None:
        inner = getattr(owner, attr)

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                spent[phase] += time.perf_counter() - start

        setattr(owner, attr, wrapper)

    for s, stepper in zip((slot, other), steppers, strict=True):
        timed(s._env, "reset", "env.reset")
        timed(stepper, "step", "settle steps")
    rounds = max(repeats, 5) * 2
    out: dict[str, dict[str, float]] = {}
    try:
        for mode in ("replayed", "restored", "shared"):
            rows: dict[str, list[float]] = defaultdict(list)
            for k in range(rounds):
                spec = ResetSpec(TASK, seed=0, init_state_index=1 + k % 40)
                if mode != "restored":
                    settled.forget(env)  # the group's snapshots (both slots share them) dropped
                if mode != "replayed":
                    slot.reset(spec)  # settled on the first slot
                spent.clear()
                target = other if mode == "shared" else slot
                total = _timed(lambda spec=spec, target=target: target.reset(spec))[0] * 1000
                rows["total"].append(total)
                for phase in ("env.reset", "settle steps"):
                    rows[phase].append(spent[phase] * 1000)
                rows["rest"].append(total - 1000 * (spent["env.reset"] + spent["settle steps"]))
            out[mode] = {phase: _median(v) for phase, v in rows.items()}
    finally:
        for s, stepper in zip((slot, other), steppers, strict=True):
            del s._env.reset, stepper.step  # the instance attributes set above
            s.close()
        family.close()
    return out


def print_reset_phases(res: dict[str, dict[str, float]]) -> None:
    print(f"\n== reset phases: one LIBERO-Goal slot, fast path (median ms; load average {os.getloadavg()[0]:.1f})")
    modes = ("replayed", "restored", "shared")
    print(f"{'phase':14}" + "".join(f"{m:>10}" for m in modes))
    for phase in ("env.reset", "settle steps", "rest", "total"):
        print(f"{phase:14}" + "".join(f"{res[m][phase]:10.1f}" for m in modes))
    print(f"replayed / restored: {res['replayed']['total'] / res['restored']['total']:.1f}x, "
          f"replayed / shared (another slot's key): {res['replayed']['total'] / res['shared']['total']:.1f}x")


# ---------------------------------------------------------------------------------------------
# steps


def bench_steps(name: str, config: dict[str, Any], repeats: int, n: int) -> dict[str, Any]:
    import mujoco

    from services.env_worker.families import ResetSpec
    from services.env_worker.fast_step import FastStepper

    family = _family(name, config)
    slot = family.init()
    env = slot._env
    fast = FastStepper(env)
    fast_py = FastStepper(env, compiled=False)
    actions = _actions(n)

    fast_check_contact = env.__dict__.pop("check_contact")  # stock runs robosuite's own contact loop

    def run_stock() -> None:
        env.__dict__.pop("check_contact", None)
        try:
            for a in actions:
                env.step(a)
        finally:
            env.check_contact = fast_check_contact

    def run_fast() -> None:
        for a in actions:
            fast.step(a)

    def run_fast_py() -> None:
        for a in actions:
            fast_py.step(a)

    def run_raw() -> None:
        m, d = env.sim.model._model, env.sim.data._data
        step = mujoco.mj_step
        for _ in range(n * 25):
            step(m, d)

    variants: dict[str, Callable[[], None]] = {
        "stock": run_stock, "fast": run_fast, "fast-py": run_fast_py, "raw": run_raw,
    }
    rates: dict[str, list[float]] = defaultdict(list)
    spec = ResetSpec(task="", seed=0)
    slot.reset(spec)
    run_fast()  # warm up: kernel loaded, caches filled
    order = list(variants)
    for r in range(repeats):
        for key in order[r % len(order):] + order[: r % len(order)]:
            slot.reset(spec)
            start = time.perf_counter()
            variants[key]()
            rates[key].append(n / (time.perf_counter() - start))
    released = _gil_released_share(slot, env, fast, run_stock, run_fast, spec)
    slot.close()
    family.close()
    med = {k: _median(v) for k, v in rates.items()}
    label = f"{name} {config.get('task') or config.get('env_name')}"
    return {"env": label, "steps_per_round": n, "median_steps_per_s": med,
            "gil_released_share": released, "rounds": dict(rates)}


def _gil_released_share(slot: Any, env: Any, fast: Any, run_stock: Callable[[], None],
                        run_fast: Callable[[], None], spec: Any) -> dict[str, float]:
    """Share of a step's wall time spent in calls that release the GIL (MuJoCo, the kernel).

    It bounds what threads can gain: N slot threads can overlap at most this share of each step
    (Amdahl), whatever the load on the machine.
    """
    inside = [0.0]

    def timed(fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                inside[0] += time.perf_counter() - start
        return wrapper

    out = {}
    sim = env.sim
    for key, run, patch in (
        ("stock", run_stock,
         lambda: (setattr(sim, "forward", timed(sim.forward)), setattr(sim, "step", timed(sim.step)))),
        ("fast", run_fast, lambda: setattr(fast, "_kernel", timed(fast._kernel))),
    ):
        slot.reset(spec)
        kernel = fast._kernel
        patch()
        inside[0] = 0.0
        start = time.perf_counter()
        run()
        out[key] = inside[0] / (time.perf_counter() - start)
        sim.__dict__.pop("forward", None)
        sim.__dict__.pop("step", None)
        fast._kernel = kernel
    return out


def print_steps(res: dict[str, Any]) -> None:
    med = res["median_steps_per_s"]
    print(f"\n== steps: {res['env']} (state only), {res['steps_per_round']} actions per round, median steps/s")
    print(f"{'path':10} {'steps/s':>9} {'ms/step':>8} {'x stock':>8} {'of raw':>7}")
    for key in ("stock", "fast", "fast-py", "raw"):
        rate = med[key]
        print(f"{key:10} {rate:9.1f} {1000 / rate:8.2f} {rate / med['stock']:8.2f} {rate / med['raw']:7.2f}")
    share = res["gil_released_share"]
    print(f"GIL released for {100 * share['stock']:.0f}% of a stock step (mj_forward, mj_step) and "
          f"{100 * share['fast']:.0f}% of a fast step (the kernel): threads can overlap at most that share")


# ---------------------------------------------------------------------------------------------
# create


class _Ticker:
    """A thread that wakes every 1 ms; its longest gap is how long something held the GIL."""

    def __init__(self) -> None:
        self.gaps: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        last = time.perf_counter()
        while not self._stop.is_set():
            time.sleep(0.001)
            now = time.perf_counter()
            self.gaps.append(now - last)
            last = now

    def __enter__(self) -> _Ticker:
        self._thread.start()
        time.sleep(0.01)
        self.gaps.clear()
        return self

    def __exit__(self, *exc: object) -> None:
        time.sleep(0.005)
        self._stop.set()
        self._thread.join()

    @property
    def max_gap_ms(self) -> float:
        return 1000 * max(self.gaps, default=0.0)


def _timed(fn: Callable[[], Any]) -> tuple[float, Any]:
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def bench_create(repeats: int) -> dict[str, Any]:
    from services.env_worker.families import ResetSpec
    from services.env_worker.sharing import copy_model

    out: dict[str, Any] = {}
    samples: dict[str, list[float]] = defaultdict(list)
    stalls: dict[str, list[float]] = defaultdict(list)

    # A first build in a cold process: imports, scene assets decoded, compile, env.
    for name in ("libero", "robosuite"):
        out_cold = subprocess.run([sys.executable, __file__, "--child-cold-build", name], capture_output=True,
                                  text=True, timeout=600, check=True).stdout.strip().splitlines()[-1]
        cold = json.loads(out_cold)
        samples[f"{name}: first build in a cold process (imports, compile, env, reset)"].append(cold["total"])
    # A fresh environment build: a new group compiles the scene, then builds the env.
    for name, config in (("libero", LIBERO), ("robosuite", LIFT)):
        family = _family(name, config)
        t, slot = _timed(family.init)
        samples[f"{name}: fresh build (new group: compile + env)"].append(t)
        out[name] = (family, [slot])
    family, held = out["libero"]
    template = held[0]._env.sim.model._model

    for r in range(repeats):
        # The per-env model copy of the old CompiledModels, and the GIL-free one.
        for label, fn in (("copy.copy(model)", lambda: copy.copy(template)),
                          ("sharing.copy_model (GIL released)", lambda: copy_model(template))):
            with _Ticker() as ticker:
                t, twin = _timed(fn)
            del twin
            samples[f"libero: {label}"].append(t)
            stalls[f"libero: {label}"].append(ticker.max_gap_ms)
        # A new env on the shared template (the pool is empty: every slot is held).
        for name in ("libero", "robosuite"):
            fam, slots = out[name]
            with _Ticker() as ticker:
                t, slot = _timed(fam.init)
            slots.append(slot)
            samples[f"{name}: new slot, new env on the shared template"].append(t)
            stalls[f"{name}: new slot, new env on the shared template"].append(ticker.max_gap_ms)
            # A slot from the pool: close one, create again.
            slots.pop().close()
            t, slot = _timed(fam.init)
            slots.append(slot)
            samples[f"{name}: new slot from the group's pool"].append(t)

    # Resets (LIBERO includes its 10 settle steps).
    libero_slots = out["libero"][1]
    a, b = libero_slots[0], libero_slots[1]
    stock_family = _family("libero", {**LIBERO, "fast_step": False})
    stock_slot = stock_family.init()
    a.reset(ResetSpec(task="", seed=100))
    stock_slot.reset(ResetSpec(task="", seed=100))
    for r in range(repeats):
        t, _ = _timed(lambda: a.reset(ResetSpec(task="", seed=100, init_state_index=r)))
        samples["libero: reset, held seed, fast_step"].append(t)
        t, _ = _timed(lambda: stock_slot.reset(ResetSpec(task="", seed=100, init_state_index=r)))
        samples["libero: reset, held seed, stock env.step settle"].append(t)
        with _Ticker() as ticker:
            t, _ = _timed(lambda: a.reset(ResetSpec(task="", seed=200 + r)))
        samples["libero: reset, new seed (private model rewritten)"].append(t)
        stalls["libero: reset, new seed (private model rewritten)"].append(ticker.max_gap_ms)
        t, _ = _timed(lambda: b.reset(ResetSpec(task="", seed=200 + r)))
        samples["libero: reset, the key another slot just reset (model and settled state shared)"].append(t)
        # b shares a's model now; a new seed for b needs a model of its own (recycled or copied)
        with _Ticker() as ticker:
            t, _ = _timed(lambda: b.reset(ResetSpec(task="", seed=300 + r)))
        samples["libero: reset, new seed while sharing (recycle or copy)"].append(t)
        stalls["libero: reset, new seed while sharing (recycle or copy)"].append(ticker.max_gap_ms)
    lift_slot = out["robosuite"][1][0]
    for r in range(repeats):
        t, _ = _timed(lambda: lift_slot.reset(ResetSpec(task="", seed=r)))
        samples["robosuite: reset"].append(t)

    stats = {name: fam.sharing_stats() for name, (fam, _) in out.items()}
    for name, (fam, slots) in out.items():
        for s in slots:
            s.close()
        fam.close()
    stock_slot.close()
    stock_family.close()
    return {
        "median_ms": {k: 1000 * _median(v) for k, v in samples.items()},
        "max_gil_stall_ms": {k: _median(v) for k, v in stalls.items()},
        "sharing_stats": stats,
    }


def print_create(res: dict[str, Any]) -> None:
    print("\n== create: slot create and reset vs a fresh environment build (median ms; GIL stall = longest"
          " gap of a 1 ms ticker thread)")
    for key, ms in res["median_ms"].items():
        stall = res["max_gil_stall_ms"].get(key)
        extra = f"   GIL stall {stall:6.1f} ms" if stall is not None else ""
        print(f"  {key:60} {ms:9.1f}{extra}")
    fresh = res["median_ms"]["libero: fresh build (new group: compile + env)"]
    shared = res["median_ms"]["libero: new slot, new env on the shared template"]
    pool = res["median_ms"]["libero: new slot from the group's pool"]
    old = shared + res["median_ms"]["libero: copy.copy(model)"]
    print(f"  libero: new env, old way (shared-template build + copy.copy), computed: {old:.1f} ms")
    print(f"  libero ratios: fresh build / new env on template {fresh / shared:.1f}x, "
          f"/ slot from pool {fresh / max(pool, 1e-3):.0f}x")
    print(f"  sharing counters: {json.dumps(res['sharing_stats'])}")


# ---------------------------------------------------------------------------------------------
# parallel


def _step_loop(stepper: Any, actions: np.ndarray) -> None:
    for a in actions:
        stepper.step(a)


def _make_slots(count: int, fast: bool) -> tuple[Any, list[Any], list[Any]]:
    from services.env_worker.families import ResetSpec
    from services.env_worker.fast_step import make_stepper

    family = _family("libero", {**LIBERO, "fast_step": fast})
    slots = [family.init() for _ in range(count)]
    for i, s in enumerate(slots):
        s.reset(ResetSpec(task="", seed=0, init_state_index=i))
    steppers = [make_stepper(s._env, fast) for s in slots]
    _step_loop(steppers[0], _actions(2))  # warm up
    return family, slots, steppers


class _InProcess:
    """``count`` slots of one group in this process: stepped in turn by one thread, or one thread each."""

    def __init__(self, count: int, fast: bool) -> None:
        self.count = count
        self.family, self.slots, self.steppers = _make_slots(count, fast)

    def sequential(self, actions: np.ndarray) -> tuple[float, float]:
        cpu, start = time.process_time(), time.perf_counter()
        for a in actions:
            for s in self.steppers:
                s.step(a)
        steps = self.count * len(actions)
        return steps / (time.perf_counter() - start), 1000 * (time.process_time() - cpu) / steps

    def threads(self, actions: np.ndarray) -> tuple[float, float]:
        barrier = threading.Barrier(self.count + 1)

        def worker(stepper: Any) -> None:
            barrier.wait()
            _step_loop(stepper, actions)

        threads = [threading.Thread(target=worker, args=(s,)) for s in self.steppers]
        for t in threads:
            t.start()
        cpu = time.process_time()
        barrier.wait()
        start = time.perf_counter()
        for t in threads:
            t.join()
        steps = self.count * len(actions)
        return steps / (time.perf_counter() - start), 1000 * (time.process_time() - cpu) / steps

    def close(self) -> None:
        for s in self.slots:
            s.close()
        self.family.close()


class _Processes:
    """``count`` child processes with one slot each; every round they step at the same time."""

    def __init__(self, count: int, fast: bool, k: int) -> None:
        self.count, self.k = count, k
        cmd = [sys.executable, __file__, "--child-parallel", f"{int(fast)},{k}"]
        self.procs = [subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
                      for _ in range(count)]
        for p in self.procs:  # every child has built its env and warmed up (LIBERO prints to stdout too)
            while (line := p.stdout.readline()).strip() != "ready":
                if not line:
                    raise RuntimeError("a child process failed before it was ready")

    def round(self) -> tuple[float, float]:
        for p in self.procs:
            p.stdin.write("go\n")
            p.stdin.flush()
        spans = []
        for p in self.procs:
            while not (line := p.stdout.readline()).startswith("{"):
                if not line:
                    raise RuntimeError("a child process died")
            spans.append(json.loads(line))
        start = min(s["start"] for s in spans)
        end = max(s["end"] for s in spans)
        steps = self.count * self.k
        return steps / (end - start), 1000 * sum(s["cpu"] for s in spans) / steps

    def close(self) -> None:
        for p in self.procs:
            p.stdin.close()
            p.wait(timeout=120)


def child_cold_build(name: str) -> None:
    start = time.perf_counter()
    from services.env_worker.families import ResetSpec, select_gl_backend

    select_gl_backend()
    family = _family(name, LIBERO if name == "libero" else LIFT)
    slot = family.init()
    slot.reset(ResetSpec(task="", seed=0))
    print(json.dumps({"total": time.perf_counter() - start}), flush=True)


def child_parallel(arg: str) -> None:
    from services.env_worker.families import select_gl_backend

    select_gl_backend()
    fast, k = (int(x) for x in arg.split(","))
    family, slots, steppers = _make_slots(1, bool(fast))
    actions = _actions(k, seed=3)
    print("ready", flush=True)
    while sys.stdin.readline().strip() == "go":
        cpu = time.process_time()
        start = time.time()
        _step_loop(steppers[0], actions)
        end = time.time()
        print(json.dumps({"start": start, "end": end, "cpu": time.process_time() - cpu}), flush=True)
    slots[0].close()
    family.close()


def bench_parallel(counts: list[int], repeats: int, k_fast: int, k_stock: int) -> dict[str, Any]:
    """Per (path, N): the three ways, built once, then run in rotating order ``repeats`` times."""
    rows = {}
    for fast, k in ((True, k_fast), (False, k_stock)):
        for count in counts:
            local = _InProcess(count, fast)
            children = _Processes(count, fast, k)
            actions = _actions(k, seed=3)
            modes: dict[str, Callable[[], tuple[float, float]]] = {
                "sequential": lambda: local.sequential(actions),
                "threads": lambda: local.threads(actions),
                "processes": children.round,
            }
            runs: dict[str, list[tuple[float, float]]] = defaultdict(list)
            order = list(modes)
            try:
                for r in range(repeats):
                    for mode in order[r % 3:] + order[: r % 3]:
                        runs[mode].append(modes[mode]())
            finally:
                children.close()
                local.close()
            row = {mode: _median([x[0] for x in v]) for mode, v in runs.items()}
            row.update({f"{mode}_cpu_ms": _median([x[1] for x in v]) for mode, v in runs.items()})
            rows[f"{'fast' if fast else 'stock'} x{count}"] = row
    return rows


def print_parallel(rows: dict[str, Any]) -> None:
    print(f"\n== parallel: N LIBERO-Goal slots stepping at once on {os.cpu_count()} cores, aggregate steps/s (median;"
          f" load average {os.getloadavg()[0]:.1f} at the end)")
    print(f"{'path, N':12} {'1 thread':>9} {'N threads':>10} {'N procs':>9} "
          f"{'thr/seq':>8} {'proc/seq':>9} {'thr/proc':>9}")
    for key, r in rows.items():
        print(f"{key:12} {r['sequential']:9.1f} {r['threads']:10.1f} {r['processes']:9.1f} "
              f"{r['threads'] / r['sequential']:8.2f} {r['processes'] / r['sequential']:9.2f} "
              f"{r['threads'] / r['processes']:9.2f}")
    print("CPU ms per step (all threads / all processes), the cost that does not depend on the load:")
    for key, r in rows.items():
        print(f"{key:12} {r['sequential_cpu_ms']:9.2f} {r['threads_cpu_ms']:10.2f} {r['processes_cpu_ms']:9.2f}")


# ---------------------------------------------------------------------------------------------


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer rounds and steps (about 2 minutes)")
    p.add_argument("--repeats", type=int, default=0, help="rounds per measurement (default 5, quick 3)")
    p.add_argument("--only", default="steps,create,parallel", help="comma-separated sections to run")
    p.add_argument("--json", default="", help="also write the results to this file")
    p.add_argument("--child-parallel", default="", help=argparse.SUPPRESS)
    p.add_argument("--child-cold-build", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child_parallel:
        child_parallel(args.child_parallel)
        return
    if args.child_cold_build:
        child_cold_build(args.child_cold_build)
        return
    from services.env_worker.families import select_gl_backend

    select_gl_backend()
    from services.env_worker import fast_step

    repeats = args.repeats or (3 if args.quick else 5)
    sections = set(args.only.split(","))
    print(f"bench_sim: {platform.node()}, {os.cpu_count()} cores, python {platform.python_version()}, "
          f"repeats {repeats}, load average {os.getloadavg()[0]:.1f} at start; "
          f"fast step kernel ready in {fast_step.warm_up():.1f} s")
    results: dict[str, Any] = {}
    if "steps" in sections:
        n = 20 if args.quick else 40
        results["steps"] = [bench_steps("libero", LIBERO, repeats, n), bench_steps("robosuite", LIFT, repeats, n)]
        for res in results["steps"]:
            print_steps(res)
    if "create" in sections:
        results["create"] = bench_create(repeats)
        print_create(results["create"])
    if "resetphases" in sections:
        results["resetphases"] = bench_reset_phases(repeats)
        print_reset_phases(results["resetphases"])
    if "parallel" in sections:
        counts = [2] if args.quick else [2, 4]
        results["parallel"] = bench_parallel(counts, 3 if args.quick else 6, 40 if args.quick else 60, 15)
        print_parallel(results["parallel"])
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2, default=float))


if __name__ == "__main__":
    main()
