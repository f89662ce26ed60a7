"""Rendering cost: per frame with and without reflections, per camera count and size, per backend.

Everything runs in one invocation and is printed side by side as medians over ``--repeats``
rounds; within a round the configurations are interleaved, so load that drifts during the run
(the machine is shared) weighs on all of them alike.

frames     The LIBERO-Goal scene "put_the_cream_cheese_in_the_bowl" (and robosuite Lift at 128),
           rendered through the slot's renderer (services/env_worker/rendering.py) from one reset
           state: ms per observation (all its cameras) and per frame, for 1 camera (agentview)
           and 2 (agentview + eye-in-hand), at each size, with reflections on (the model's own
           ``mat_reflectance``) and off (zeroed). Reflections are toggled on the same model, so
           the only difference is the reflective pass.
steps      ms per executed action on LIBERO-Goal with two 128x128 cameras, for the ways of
           producing images: none (state only); every step (what robosuite's camera observables
           did); only after the last action of an 8-action chunk (what the worker does now) --
           each with reflections on and off. Same episode key and actions for all; at most 3
           rounds (the every-step rows are slow).
antialias  LIBERO-Goal's agentview, reflections off (as the shipped image VLA reads it), at 64 and
           128 px, rendered with MuJoCo's 4x multisampled offscreen buffer and single-sampled
           (``antialias: false``): ms per frame, and how far the two frames of one state differ
           (mean and largest absolute difference per channel, 0-255).
backends   The 2-camera 128x128 observation in a fresh process per installed backend (MUJOCO_GL
           egl and osmesa; they cannot share a process), reflections on and off.

    python bench/bench_render.py            # about 5 minutes on a busy 2-core machine
    python bench/bench_render.py --quick    # about 2 minutes
"""

from __future__ import annotations

import argparse
import ctypes.util
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

TASK = "put_the_cream_cheese_in_the_bowl"
TWO = ("agentview", "robot0_eye_in_hand")
CHUNK = 8


def libero_config(size: int, cameras: Sequence[str] = TWO) -> dict[str, Any]:
    return {"suite": "libero_goal", "task": TASK, "cameras": list(cameras), "camera_size": size}


def open_slot(family_name: str, config: dict[str, Any]) -> tuple[Any, Any]:
    from services.env_worker.families import ResetSpec, get_family

    family = get_family(family_name)(config)
    slot = family.init()
    slot.reset(ResetSpec("", seed=0))
    return family, slot


class Reflections:
    """Toggle reflections on one model, restoring its compiled values."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.saved = model.mat_reflectance.copy()

    def set(self, on: bool) -> None:
        self.model.mat_reflectance[:] = self.saved if on else 0


def time_ms(fn: Callable[[], Any], n: int) -> float:
    """Median wall ms of ``n`` calls (after one warm-up call)."""
    fn()
    samples = []
    for _ in range(n):
        start = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - start) * 1000)
    return statistics.median(samples)


# ---------------------------------------------------------------------------------------------
# Frames


def bench_frames(sizes: Sequence[int], repeats: int, n: int) -> dict[tuple, list[float]]:
    """ms per observation by (scene, size, cameras, reflections)."""
    slots = {}
    for size in sizes:
        slots[("libero-goal", size)] = open_slot("libero", libero_config(size))
    slots[("lift", 128)] = open_slot("robosuite", {"env_name": "Lift", "cameras": list(TWO), "camera_size": 128})
    results: dict[tuple, list[float]] = defaultdict(list)
    for _ in range(repeats):
        for (scene, size), (_, slot) in slots.items():
            renderer = slot.renderer
            refl = Reflections(renderer.scene().model)
            for on in (True, False):
                refl.set(on)
                for cams in (TWO[:1], TWO):
                    results[(scene, size, len(cams), on)].append(time_ms(lambda c=cams: renderer.render(c), n))
            refl.set(True)
    for family, slot in slots.values():
        slot.close()
        family.close()
    return results


# ---------------------------------------------------------------------------------------------
# Antialiasing


def bench_antialias(sizes: Sequence[int], repeats: int, n: int) -> dict[tuple, Any]:
    """ms per frame by (size, antialias), and (size, "diff") -> (mean, max) pixel difference."""
    slots = {(size, on): open_slot("libero", {**libero_config(size, TWO[:1]), "reflections": False, "antialias": on})
             for size in sizes for on in (True, False)}
    results: dict[tuple, Any] = defaultdict(list)
    for size in sizes:
        with_aa, without = (slots[(size, on)][1].renderer.render(TWO[:1])[0].astype(int) for on in (True, False))
        gap = np.abs(with_aa - without)
        results[(size, "diff")] = (float(gap.mean()), int(gap.max()))
    for _ in range(repeats):
        for (size, on), (_, slot) in slots.items():
            results[(size, on)].append(time_ms(lambda r=slot.renderer: r.render(TWO[:1]), n))
    for family, slot in slots.values():
        slot.close()
        family.close()
    return results


# ---------------------------------------------------------------------------------------------
# Steps


def bench_steps(repeats: int, steps: int) -> dict[str, list[float]]:
    """ms per executed action by how images are produced."""
    from services.env_worker.families import ResetSpec

    family, slot = open_slot("libero", libero_config(128))
    refl = Reflections(slot.renderer.scene().model)
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, size=(steps, 7)).astype(np.float32)
    actions[:, 6] = -1

    def run(images: str) -> float:
        slot.reset(ResetSpec("", seed=0))
        start = time.perf_counter()
        for i, a in enumerate(actions):
            render = images == "every step" or (images == f"chunk end ({CHUNK})" and i % CHUNK == CHUNK - 1)
            slot.step(a, render=render)
        return (time.perf_counter() - start) * 1000 / steps

    modes = ["none (state only)", "every step", f"chunk end ({CHUNK})"]
    results: dict[str, list[float]] = defaultdict(list)
    for _ in range(repeats):
        for on in (True, False):
            refl.set(on)
            for mode in modes:
                if mode.startswith("none") and not on:
                    continue
                results[f"{mode}{'' if mode.startswith('none') else ', reflections ' + ('on' if on else 'off')}"].append(
                    run(mode)
                )
        refl.set(True)
        start = time.perf_counter()
        slot.reset(ResetSpec("", seed=1))
        results["reset (1 render, 10 settle steps)"].append((time.perf_counter() - start) * 1000)
    slot.close()
    family.close()
    return results


# ---------------------------------------------------------------------------------------------
# Backends (one child process each)


def child_backend(repeats: int, n: int, size: int = 128, cameras: Sequence[str] = TWO) -> None:
    """Runs in a child: one observation of ``cameras`` at ``size``, reflections on/off; prints JSON
    (ms per observation; bench/gpu_check.py runs it with one camera, so per frame)."""
    from services.env_worker.rendering import gl_backend_choice, gl_renderer_string

    _, slot = open_slot("libero", libero_config(size, cameras))
    renderer = slot.renderer
    refl = Reflections(renderer.scene().model)
    out: dict[str, Any] = {"backend": gl_backend_choice().backend, "renderer": gl_renderer_string(),
                           "size": size, "cameras": list(cameras), "on": [], "off": []}
    for _ in range(repeats):
        for on in (True, False):
            refl.set(on)
            out["on" if on else "off"].append(time_ms(lambda: renderer.render(cameras), n))
    print("RESULT " + json.dumps(out))


def bench_backends(rounds: int, repeats: int, n: int) -> dict[str, dict[str, Any]]:
    """Children alternate (egl, osmesa, egl, ...) so drifting load hits both backends alike."""
    results: dict[str, dict[str, Any]] = {}
    available = []
    for backend, library in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(library):
            available.append(backend)
        else:
            results[backend] = {"error": f"lib{library} not installed"}
    for _ in range(rounds):
        for backend in available:
            if "error" in results.get(backend, {}):
                continue
            env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
            proc = subprocess.run(
                [sys.executable, __file__, "--child-backend", "--repeats", str(repeats), "--n", str(n)],
                env=env, capture_output=True, text=True, timeout=900,
            )
            lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
            if proc.returncode != 0 or not lines:
                results[backend] = {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1][:120]}
                continue
            got = json.loads(lines[-1][len("RESULT "):])
            mine = results.setdefault(backend, {"renderer": got["renderer"], "on": [], "off": []})
            mine["on"] += got["on"]
            mine["off"] += got["off"]
    return results


# ---------------------------------------------------------------------------------------------


def med(xs: Sequence[float]) -> float:
    return statistics.median(xs)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="fewer repeats and sizes (about 2 minutes)")
    p.add_argument("--repeats", type=int, default=0, help="rounds per measurement (default 5, quick 3)")
    p.add_argument("--n", type=int, default=0, help="timed renders per point and round (default 5, quick 3)")
    p.add_argument("--child-backend", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--size", type=int, default=128, help=argparse.SUPPRESS)
    p.add_argument("--cameras", default=",".join(TWO), help=argparse.SUPPRESS)
    args = p.parse_args()
    repeats = args.repeats or (3 if args.quick else 5)
    n = args.n or (3 if args.quick else 5)
    if args.child_backend:
        child_backend(repeats, n, args.size, args.cameras.split(","))
        return

    from services.env_worker.rendering import gl_backend_choice, gl_renderer_string

    sizes = (128,) if args.quick else (84, 128, 256)
    wall = time.perf_counter()
    print(f"# bench_render: {platform.node()}, {os.cpu_count()} CPUs, python {platform.python_version()}")
    print(f"# this process: {gl_backend_choice().describe()}; OpenGL renderer: {gl_renderer_string()}")
    print(f"# medians of {repeats} rounds x {n} timed renders per point; ratio = reflections on / off")
    print(f"# load average at start: {' '.join(f'{x:.1f}' for x in os.getloadavg())} (the machine may be shared)\n")

    frames = bench_frames(sizes, repeats, n)
    print("## Render cost (ms)")
    print(f"{'scene':<12}{'size':>6}{'cams':>6} | {'obs on':>8}{'obs off':>9} | {'frame on':>9}{'frame off':>10} | {'on/off':>7}")
    for scene, size, cams in sorted({k[:3] for k in frames}, key=lambda k: (k[0] != "libero-goal", k[1], k[2])):
        on, off = med(frames[(scene, size, cams, True)]), med(frames[(scene, size, cams, False)])
        print(f"{scene:<12}{size:>6}{cams:>6} | {on:>8.1f}{off:>9.1f} | {on / cams:>9.1f}{off / cams:>10.1f} | {on / off:>6.2f}x")
    base = med(frames[("libero-goal", 128, 1, True)])
    print("\nper-frame cost relative to LIBERO-Goal 1 camera 128x128 reflections on:")
    for size in sizes:
        row = []
        for on in (True, False):
            per_frame = med(frames[("libero-goal", size, 2, on)]) / 2
            row.append(f"{size}px 2 cams refl {'on ' if on else 'off'} {per_frame / base:5.2f}x")
        print("  " + "   ".join(row))

    aa = bench_antialias((64, 128), repeats, n)
    print("\n## Antialiasing, LIBERO-Goal agentview, reflections off (ms per frame)")
    print(f"{'size':>5} | {'4x MSAA':>8}{'single':>8} | {'MSAA/single':>11} | pixel difference mean, max (0-255)")
    for size in (64, 128):
        on, off = med(aa[(size, True)]), med(aa[(size, False)])
        mean, peak = aa[(size, "diff")]
        print(f"{size:>5} | {on:>8.1f}{off:>8.1f} | {on / off:>10.2f}x | {mean:.1f}, {peak}")

    steps = bench_steps(min(repeats, 3), 16 if args.quick else 32)
    print("\n## Step cost, LIBERO-Goal, 2 cameras 128x128 (ms per executed action)")
    state = med(steps["none (state only)"])
    every_on = med(steps["every step, reflections on"])
    print(f"{'images':<36}{'ms/action':>10}{'actions/s':>11}{'vs every step refl on':>23}")
    for name, xs in steps.items():
        if name.startswith("reset"):
            continue
        m = med(xs)
        print(f"{name:<36}{m:>10.1f}{1000 / m:>11.1f}{every_on / m:>22.2f}x")
    print(f"state-only step: {state:.1f} ms; reset with cameras: {med(steps['reset (1 render, 10 settle steps)']):.0f} ms "
          "(robosuite's observables rendered 12 times per reset: 1 + 1 forced + 10 settle steps)")

    backends = bench_backends(1 if args.quick else 2, 2, n)
    print("\n## Backends, fresh process each: LIBERO-Goal, 2 cameras 128x128 (ms per observation)")
    print(f"{'MUJOCO_GL':<10}{'refl on':>9}{'refl off':>10}{'on/off':>8}  renderer")
    for backend, r in backends.items():
        if "error" in r:
            print(f"{backend:<10}  does not work here: {r['error']}")
            continue
        on, off = med(r["on"]), med(r["off"])
        print(f"{backend:<10}{on:>9.1f}{off:>10.1f}{on / off:>7.2f}x  {r['renderer']}")
    print(f"\n# total wall time {time.perf_counter() - wall:.0f} s; "
          f"load average at end: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
