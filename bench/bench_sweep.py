"""`zetta bench rollout`: the concurrency sweep, its two baselines and the machine's limit, in one run.

Every figure of docs/results/throughput.md comes from one invocation, so that the rows compare under the
same load (the machine may be shared; the 1-minute load average is recorded with every row).
All rows run the same episodes: LIBERO-Goal ``--task`` rendering the camera the policy reads (the
image VLA: agentview at its size, once per policy call; nothing for a state policy), episode i from init state
i % 50 and seed i // 50 (see :func:`episode_key`), a fixed step budget ``--max-steps`` (episode
length depends on success, so steps/s is reported next to episodes/min), the same policy
(``--model``, default the shipped ``zetta-vla-image``), whose action chunks are executed whole.

rows
  naive        one process, episodes one after another, a LIBERO env built from scratch for every
               episode with LIBERO's own ``env.step`` (``fast_step: false``), the policy in-process
               on a batch of one, camera frames rendered at every step as robosuite does; half of its episodes run first, half last, so drifting load
               weighs on both ends of the run
  naive-fast   the same loop on our fast step path (a reference row: what the step path alone gives)
  stack        ``LocalStack`` (Redis, gateway, critic service, env workers each pinned to its own
               cores, one policy worker) on loopback;
               ``c`` lanes each run episodes back to back on one session with ``run_episode``
  stack-off    the same stack with batching (``ZETTA_MAX_BATCH=1``) and resource sharing
               (``ZETTA_RESOURCE_SHARING=false``: every session compiles its own scene) off
  limit        one process per core, no infrastructure, no policy: reset, then the actions the
               policy takes on ``--limit-keys`` keys spread over the stacks' init states and seeds
               (:func:`limit_keys`), through the fast step path (``FastStepper.step``), rendering the
               policy's camera after each chunk of actions, rendering the
               policy's camera after each chunk of actions
  limit-obs    the same with the slot's step as a chunked policy needs it: milestones, success
               and the signals' state every step, the canonical observation the policy reads
               after each action chunk

    zetta bench rollout                          # the full sweep (15-30 minutes on 2 shared cores)
    zetta bench rollout --concurrency 1,4 --baseline-concurrency 2 --episodes 4 --max-steps 16 \
        --naive-episodes 2 --naive-fast-episodes 2 --limit-seconds 2     # a quick look
    zetta bench rollout --write-docs             # also docs/results/throughput.{json,md} + PNG plots
    zetta bench rollout --from-json run.json --write-docs   # re-render a run saved with --json
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import functools
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.sweep_results import Busy, Episode, Results, Row, Usage
from services.common.policies import DEFAULT_POLICY, policy_env_config
from services.common.progress import add_progress_option, progress
from services.common.provenance import RESULTS_DIR, git_source, machine as cpu_machine

DEFAULT_TASK = "put_the_cream_cheese_in_the_bowl"
SUITE = "libero_goal"
DEFAULT_MODEL = DEFAULT_POLICY
#: The issue's sweep, plus 4: on 2 cores the stack saturates them between 2 and 8 lanes, so its
#: best point is often 4. Without sharing every session holds its own scene (about 0.6 GB for
#: LIBERO-Goal), so the no-sharing baseline stops at 8 on a shared 24 GB machine (16 was killed for
#: memory there, as the paper's baselines failed beyond 16).
DEFAULT_CONCURRENCY = (1, 4, 8, 16, 32, 64)
DEFAULT_BASELINE_CONCURRENCY = (1, 8)
#: Batch sizes the scale-out model measures inference at.
MODEL_BATCHES = (1, 8, 16, 32, 64)
#: Fewest episodes each lane of a measured stack point runs. The lanes of a point finish at
#: different times and the early ones idle while the last run; with 4 episodes a lane that ragged
#: end weighs about half what it does with 2 (a long rollout job has none).
MIN_EPISODES_PER_LANE = 4

Log = Callable[[str], None]


def episode_key(i: int) -> tuple[int, int]:
    """(seed, init state index) of episode i: the benchmark's 50 init states in turn, the seed moving
    on only after all 50. LIBERO's own evaluation keeps one seed and walks the init states; the
    seed also places the static fixtures, so slots on one seed share one model (sharing.py) while
    a seed per episode would give every slot a private copy of the scene (about 0.2 GB each)."""
    return i // 50, i % 50


#: The policy whose inputs every row's envs render (set by :func:`sweep` before any process starts,
#: so the limit processes it spawns see it too).
MODEL_VARIABLE = "ZETTA_BENCH_MODEL"


def env_config(task: str, max_steps: int, fast_step: bool = True) -> dict[str, Any]:
    """The LIBERO config every row uses: the cameras the benchmarked policy reads, at its size
    (:func:`services.common.policies.policy_env_config`; none for a state policy)."""
    render = policy_env_config(os.environ.get(MODEL_VARIABLE, DEFAULT_MODEL))
    return {"suite": SUITE, "task": task, "max_steps": max_steps, "fast_step": fast_step, **render}


def load_average() -> float:
    """1-minute load average (what `uptime` prints first)."""
    return os.getloadavg()[0]


# ---------------------------------------------------------------------------------------------
# resource accounting


class _GpuSampler:
    """Mean GPU utilization over a span from ``nvidia-smi -lms``; inert without nvidia-smi."""

    def __init__(self) -> None:
        self.samples: list[float] = []
        self._proc: subprocess.Popen[str] | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        exe = shutil.which("nvidia-smi")
        if exe is None:
            return
        self._proc = subprocess.Popen(
            [exe, "--query-gpu=utilization.gpu", "--format=csv,noheader,nounits", "-lms", "500"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self._proc is not None and self._proc.stdout is not None
        for line in self._proc.stdout:
            values = [float(v) for v in line.split(",") if v.strip().replace(".", "", 1).isdigit()]
            if values:
                self.samples.append(statistics.mean(values))

    def stop(self) -> float | None:
        if self._proc is None:
            return None
        self._proc.terminate()
        self._proc.wait(timeout=5)
        if self._thread is not None:
            self._thread.join(timeout=5)
        return statistics.mean(self.samples) if self.samples else None


def _proc_stat(pid: int) -> tuple[int, float] | None:
    """(parent pid, CPU seconds user + system) of a process from /proc; None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / _CLOCK_TICKS


def _machine_cpu() -> tuple[float, float]:
    """(busy, total) jiffies of all cores since boot, from the first line of /proc/stat."""
    values = [float(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0.0)
    return sum(values) - idle, sum(values)


_CLOCK_TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _is_profiler(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/comm").read_text().strip() == "py-spy"
    except OSError:
        return False


class ResourceMeter:
    """CPU of the machine and of named processes (with their descendants) over one span, from /proc."""

    def __init__(self, procs: Callable[[], dict[str, int]]) -> None:
        self._procs = procs
        self._cpu: dict[str, dict[int, float]] = {}
        self._machine = (0.0, 0.0)
        self._t0 = 0.0
        self._gpu = _GpuSampler()

    @staticmethod
    def _trees(roots: dict[str, int]) -> dict[str, dict[int, float]]:
        """CPU seconds of every process under each named root, by pid.

        A process counts once, for its nearest named ancestor (the client started the stack's
        services, which are roots of their own); profilers (py-spy) are not counted.
        """
        stats = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                stat = _proc_stat(int(entry.name))
                if stat is not None:
                    stats[int(entry.name)] = stat
        children: dict[int, list[int]] = {}
        for pid, (ppid, _) in stats.items():
            children.setdefault(ppid, []).append(pid)
        named = set(roots.values())
        out: dict[str, dict[int, float]] = {}
        for name, root in roots.items():
            todo, seen = [root], out.setdefault(name, {})
            while todo:
                pid = todo.pop()
                if pid not in stats or pid in seen or (pid != root and pid in named) or _is_profiler(pid):
                    continue
                seen[pid] = stats[pid][1]
                todo += children.get(pid, [])
        return out

    def start(self) -> None:
        self._machine = _machine_cpu()
        self._cpu = self._trees(self._procs())
        self._t0 = time.perf_counter()
        self._gpu.start()

    def _since_start(self, now: dict[str, dict[int, float]]) -> dict[str, float]:
        return {name: sum(t - self._cpu.get(name, {}).get(pid, 0.0) for pid, t in times.items())
                for name, times in now.items()}

    def mark(self) -> tuple[float, float]:
        """(seconds, CPU seconds of the named processes) since :meth:`start`, the span going on."""
        return time.perf_counter() - self._t0, sum(self._since_start(self._trees(self._procs())).values())

    def stop(self) -> Usage:
        wall = max(time.perf_counter() - self._t0, 1e-9)
        busy, total = _machine_cpu()
        machine = 100.0 * (busy - self._machine[0]) / max(total - self._machine[1], 1e-9)
        now = self._trees(self._procs())
        by_process = self._since_start(now)
        rss = 0
        page = os.sysconf("SC_PAGE_SIZE")
        for times in now.values():
            for pid in times:
                with contextlib.suppress(OSError, IndexError, ValueError):
                    rss += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * page
        used = sum(by_process.values())
        cores = os.cpu_count() or 1
        return Usage(machine, 100.0 * used / wall / cores, self._gpu.stop(), rss / 2**20, used, by_process)


# ---------------------------------------------------------------------------------------------
# in-process loops: naive baselines and the limit


@contextlib.contextmanager
def quiet_fds() -> Iterator[None]:
    """Silence stdout/stderr at the descriptor level (LIBERO's and robosuite's import chatter)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def naive_episode(policy: Any, index: int, task: str, max_steps: int, fast_step: bool,
                  key: tuple[int, int] | None = None) -> tuple[Episode, np.ndarray]:
    """A fresh LIBERO env (its scene compiled again), one episode with the in-process policy, batch 1.

    The episode is ``key`` (seed, init state index), by default :func:`episode_key` of ``index``;
    the step budget is the env's own (``max_steps`` in its config truncates the episode). Returns
    the episode (with the seconds the env build took) and the actions it executed, which the
    ``limit`` rows replay. bench/bench_rollout.py runs its naive baseline through this too. A
    policy that reads camera frames gets them rendered at every step, as robosuite's own
    ``env.step`` does, on the naive row; the fast row renders only the observation the policy reads.
    """
    from services.env_worker.families import ResetSpec, get_family

    start = time.perf_counter()
    config = env_config(task, max_steps, fast_step)
    family = get_family("libero")(config)  # a new group: nothing cached
    every_step = bool(config.get("cameras")) and not fast_step
    slot = family.init()
    build_s = time.perf_counter() - start
    executed: list[np.ndarray] = []
    try:
        seed, init = key if key is not None else episode_key(index)
        obs, instruction = slot.reset(ResetSpec(task=task, seed=seed, init_state_index=init))
        success = False
        while slot.episode_step < max_steps:
            chunk = policy.infer({k: v[None] for k, v in obs.items()}, [instruction])[0]
            outcome = None
            for i, action in enumerate(chunk):
                outcome = slot.step(action, render=every_step or i == len(chunk) - 1)
                executed.append(np.asarray(action))
                if outcome.terminated or outcome.truncated:
                    break
            assert outcome is not None
            obs, success = outcome.observation, outcome.success
            if outcome.terminated or outcome.truncated:
                break
        steps = slot.episode_step
    finally:
        slot.close()
        family.close()
    actions = np.stack(executed).astype(np.float32) if executed else np.zeros((0, 7), np.float32)
    return Episode(index, success, steps, time.perf_counter() - start, build_s), actions


#: A recorded episode the limit rows replay: its key (seed, init state index) and executed actions.
Replay = tuple[tuple[int, int], np.ndarray]


#: Episode indices a step apart in the limit rows' keys: 57 = 50 + 7 moves one seed and 7 init
#: states on, so up to 50 keys have 50 different init states and their seeds climb as the stacks' do.
LIMIT_KEY_STRIDE = 57


def limit_keys(count: int) -> list[tuple[int, int]]:
    """The episode keys whose policy actions the limit rows replay, spread over the init states and
    seeds the stacks' episodes run (the physics of one init state costs up to 15 % more per step
    than another's, so a few neighbouring keys would not stand for the stacks' mix)."""
    return [episode_key(k * LIMIT_KEY_STRIDE) for k in range(count)]


def record_replays(policy: Any, keys: Sequence[tuple[int, int]], task: str, max_steps: int) -> list[Replay]:
    """The actions the in-process policy executes on each of ``keys`` (fast path, batch 1)."""
    out: list[Replay] = []
    with quiet_fds():
        for key in keys:
            _, actions = naive_episode(policy, 0, task, max_steps, True, key=key)
            if len(actions):
                out.append((key, actions))
    return out


def random_replays(seed: int, max_steps: int, count: int = 50) -> list[Replay]:
    """Episodes of fixed random actions (gripper closing and opening every 20 steps) on fresh keys:
    what the limit rows replay with ``--limit-keys 0`` instead of the policy's own actions."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-0.5, 0.5, size=(max_steps, 7)).astype(np.float32)
    actions[:, 6] = np.where(np.arange(max_steps) % 40 < 20, -1.0, 1.0)
    return [(episode_key(seed * 1000 + k), actions) for k in range(count)]


def limit_child(kind: str, task: str, max_steps: int, seconds: Any, seed: int, barrier: Any, out: Any,
                replays: Sequence[Replay] = (), chunk: int = 8, rounds: int = 1, ready: Any = None) -> None:
    """One core's worth of stepping with no infrastructure: reset, an episode's actions, repeat.

    ``kind`` "fast": ``FastStepper.step`` on the slot's env (the fastest env path); "obs": the
    slot's own step (fast path plus milestones and signal state every step, and the canonical
    observation after every ``chunk`` actions, where a policy executing chunks reads it). ``replays``
    are the episodes to step, in turn from the ``seed``-th (the policy's recorded actions in the
    sweep: the same contact-rich physics the stacks step); none: :func:`random_replays`. Every
    reset replays the settle steps (no settled snapshot is reused), as the first reset of a key
    does in the stacks, whose episodes never repeat a key on one env.

    ``rounds`` windows of ``seconds`` each (a number, or a shared ``multiprocessing.Value`` read as
    each window starts, so the parent can size every window), every one started by ``barrier`` and
    reported on ``out``, so one set of processes (built once) can be measured again and again; an
    aborted barrier ends it. ``ready`` (a queue) hears when the set-up is done.
    """
    import threading

    with quiet_fds():
        from services.env_worker.families import settled
        from services.env_worker.families import ResetSpec, get_family, select_gl_backend
        from services.env_worker.fast_step import make_stepper, warm_up

        select_gl_backend()
        warm_up()
        config = env_config(task, max_steps)
        family = get_family("libero")(config)
        slot = family.init()
        cameras = list(config.get("cameras", ()))
        replays = list(replays) or random_replays(seed, max_steps)
        slot.reset(ResetSpec(task=task, seed=seed))
        stepper = make_stepper(slot._env, True)
        for a in replays[0][1][:5]:
            stepper.step(a.astype(np.float64))
    if ready is not None:
        ready.put(seed)
    k = seed
    try:
        for _ in range(rounds):
            barrier.wait()
            window = float(seconds.value) if hasattr(seconds, "value") else float(seconds)
            cpu0, start = time.process_time(), time.time()
            episodes = []
            while time.time() - start < window:
                t = time.perf_counter()
                (key_seed, init), actions = replays[k % len(replays)]
                settled.forget(slot._env)
                slot.reset(ResetSpec(task=task, seed=key_seed, init_state_index=init))
                if kind == "fast":
                    for i, a in enumerate(actions):
                        stepper.step(a.astype(np.float64))
                        if cameras and (i % chunk == chunk - 1 or i == len(actions) - 1):
                            slot._renderer.render(cameras)  # the frames a policy call reads
                else:
                    for i, a in enumerate(actions):
                        slot.step(a, observe=i % chunk == chunk - 1 or i == len(actions) - 1)
                episodes.append((len(actions), time.perf_counter() - t))
                k += 1
            out.put({"start": start, "end": time.time(), "cpu": time.process_time() - cpu0, "episodes": episodes})
    except threading.BrokenBarrierError:  # the parent stopped measuring early
        pass
    finally:
        slot.close()
        family.close()


class LimitPool:
    """``procs`` limit processes built once, measured in ``rounds`` windows on demand; the
    constructor returns once they are built, so their set-up loads nothing measured after it."""

    def __init__(self, kind: str, task: str, max_steps: int, seconds: float, procs: int,
                 replays: Sequence[Replay] = (), chunk: int = 8, rounds: int = 1) -> None:
        import multiprocessing

        ctx = multiprocessing.get_context("spawn")
        self.kind, self.procs = kind, procs
        self._seconds = ctx.Value("d", seconds)  # every window's length, which measure() may change
        self._barrier = ctx.Barrier(procs + 1)
        self._out = ctx.Queue()
        ready = ctx.Queue()
        self._children = [ctx.Process(target=limit_child, args=(kind, task, max_steps, self._seconds, i + 1,
                                                                self._barrier, self._out, replays, chunk, rounds,
                                                                ready))
                          for i in range(procs)]
        for c in self._children:
            c.start()
        for _ in self._children:
            ready.get(timeout=600)

    def measure(self, log: Log, seconds: float = 0.0) -> Row:
        """One window (of ``seconds``, or the constructor's), all processes stepping at once;
        aggregated over the span from the first start to the last end."""
        children = self._children
        if seconds > 0:
            self._seconds.value = seconds
        meter = ResourceMeter(lambda: {f"{self.kind}-{i}": c.pid for i, c in enumerate(children) if c.pid is not None})
        self._barrier.wait(timeout=600)
        meter.start()
        results = [self._out.get(timeout=self._seconds.value + 600) for _ in children]
        usage = meter.stop()
        start = min(r["start"] for r in results)
        end = max(r["end"] for r in results)
        episodes = [Episode(i, False, s, lat) for i, (s, lat) in enumerate(e for r in results for e in r["episodes"])]
        usage.cpu_s = sum(r["cpu"] for r in results)  # the stepping loops alone, not start-up or hand-over
        row = Row(f"limit{'' if self.kind == 'fast' else '-obs'}", self.procs, episodes, end - start, usage,
                  load=load_average())
        log(f"{row.mode}: {self.procs} processes, {row.steps} steps in {row.wall_s:.1f} s = {row.steps_per_s:.0f} "
            f"steps/s, {row.episodes_per_min:.1f} episodes/min, {row.cpu_ms_per_step:.2f} CPU ms per step (resets "
            f"included); load {row.load:.2f}")
        return row

    def close(self) -> None:
        """Release the processes, also those still waiting for a round."""
        self._barrier.abort()
        for c in self._children:
            c.join(timeout=60)


def run_limit(kind: str, task: str, max_steps: int, seconds: float, procs: int, log: Log,
              replays: Sequence[Replay] = (), chunk: int = 8) -> Row:
    """``procs`` processes stepping at once for one window of ``seconds``."""
    pool = LimitPool(kind, task, max_steps, seconds, procs, replays, chunk)
    try:
        return pool.measure(log)
    finally:
        pool.close()


def run_naive(rows: dict[str, Row], policy: Any, indices: Sequence[int], task: str, max_steps: int,
              fast_step: bool, log: Log) -> None:
    """Run naive episodes ``indices``, adding them (and their wall time) to the naive row."""
    if not indices:
        return
    mode = "naive-fast" if fast_step else "naive"
    row = rows.setdefault(mode, Row(mode, 1, [], 0.0))
    meter = ResourceMeter(lambda: {"naive": os.getpid()})
    meter.start()
    t0 = time.perf_counter()
    done = []
    with progress(total=len(indices), desc=mode, leave=False) as bar:
        for i in indices:
            with quiet_fds():  # per episode, so that the bar between them reaches the terminal
                episode, _ = naive_episode(policy, i, task, max_steps, fast_step)
            done.append(episode)
            bar.update()
    wall = time.perf_counter() - t0
    usage = meter.stop()
    row.episodes += done
    row.wall_s += wall
    row.usage = usage if row.usage is None else Usage(
        (row.usage.machine_cpu_pct + usage.machine_cpu_pct) / 2, (row.usage.own_cpu_pct + usage.own_cpu_pct) / 2,
        None, max(row.usage.rss_mib, usage.rss_mib), row.usage.cpu_s + usage.cpu_s,
        {"naive": row.usage.cpu_s + usage.cpu_s})
    row.load = load_average()
    log(f"{mode}: {len(done)} episodes in {wall:.1f} s ({60 * len(done) / wall:.1f}/min, "
        f"{sum(e.steps for e in done) / wall:.0f} steps/s); load {row.load:.2f}")


def sample_observation(task: str, max_steps: int) -> tuple[dict[str, np.ndarray], str]:
    """One canonical first observation of ``task`` and its instruction, to time the policy on."""
    from services.env_worker.families import ResetSpec, get_family

    with quiet_fds():
        family = get_family("libero")(env_config(task, max_steps))
        slot = family.init()
        obs, instruction = slot.reset(ResetSpec(task=task))
        slot.close()
        family.close()
    return obs, instruction


def inference_costs(policy: Any, obs: dict[str, np.ndarray], instruction: str, repeats: int = 5) -> dict[int, float]:
    """CPU milliseconds per inference batch of the in-process policy, per batch size (scale-out model).

    Thread CPU time rather than wall time: the policy runs on this thread (one torch thread, as the
    policy worker runs it), and on a shared machine wall time mostly measures the other jobs.
    """
    out = {}
    for b in MODEL_BATCHES:
        batch = {k: np.repeat(v[None], b, axis=0) for k, v in obs.items()}
        policy.infer(batch, [instruction] * b)
        samples = []
        for _ in range(repeats):
            t = time.thread_time()
            policy.infer(batch, [instruction] * b)
            samples.append(time.thread_time() - t)
        out[b] = 1000 * statistics.median(samples)
    return out


def model_ops(policy: Any, obs: dict[str, np.ndarray], instruction: str) -> int:
    """Tensor operations one inference call dispatches: on a GPU each is about one kernel launch,
    which bounds a small policy's GPU time from below (the scale-out model's prediction)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        policy.infer({k: v[None] for k, v in obs.items()}, [instruction])
    return sum(1 for e in prof.events()
               if e.name.startswith("aten::") and not (e.cpu_parent is not None and e.cpu_parent.name.startswith("aten::")))


# ---------------------------------------------------------------------------------------------
# the stack


#: Policy worker histograms a stack point reads the mean of over its span.
POLICY_HISTOGRAMS = ("zetta_policy_batch_size", "zetta_policy_queue_wait_seconds")


def histogram_totals(url: str, model: str) -> dict[str, tuple[float, float]]:
    """(sum, count) of each of :data:`POLICY_HISTOGRAMS` of the policy worker for ``model``."""
    from prometheus_client.parser import text_string_to_metric_families

    from services.ops.hops import scrape

    out = {name: (0.0, 0.0) for name in POLICY_HISTOGRAMS}
    for family in text_string_to_metric_families(scrape(url)):
        if family.name not in out:
            continue
        total, count = out[family.name]
        for s in family.samples:
            if s.labels.get("model") == model:
                if s.name.endswith("_sum"):
                    total += s.value
                elif s.name.endswith("_count"):
                    count += s.value
        out[family.name] = (total, count)
    return out


def env_steps(urls: Sequence[str]) -> int:
    """Env steps the env workers at ``urls`` executed so far, all families: the count of their step
    duration histogram, observed after every step (``zetta_env_steps_total`` grows a chunk at a time)."""
    from prometheus_client.parser import text_string_to_metric_families

    from services.ops.hops import scrape

    total = 0.0
    for url in urls:
        for family in text_string_to_metric_families(scrape(url)):
            if family.name == "zetta_env_step_duration_seconds":
                total += sum(s.value for s in family.samples if s.name.endswith("_count"))
    return int(total)


def histogram_mean(before: dict[str, tuple[float, float]], after: dict[str, tuple[float, float]],
                   name: str) -> float | None:
    """Mean of one histogram's observations between two :func:`histogram_totals`; None without any."""
    count = after[name][1] - before[name][1]
    return (after[name][0] - before[name][0]) / count if count else None


def balanced(infos: Sequence[Any], n: int) -> list[str]:
    """``n`` session ids spread round-robin over the workers that hold them."""
    by_worker: dict[str, list[str]] = {}
    for info in infos:
        by_worker.setdefault(info.worker_id, []).append(info.session_id)
    queues = [list(v) for _, v in sorted(by_worker.items())]
    out: list[str] = []
    while len(out) < n and any(queues):
        for q in queues:
            if q and len(out) < n:
                out.append(q.pop(0))
    return out


async def run_lanes(gateway: Any, ids: Sequence[str], episodes: int, task: str, max_steps: int,
                    first_index: int, on_first_idle: Callable[[], None] | None = None,
                    label: str = "stack") -> tuple[list[Episode], float]:
    """``len(ids)`` lanes, each running ``run_episode`` back to back on its own session, drawing
    episodes from one queue; ``on_first_idle`` is called once, when a lane first finds it empty (from
    then on lanes go idle one by one). ``label`` names the progress bar."""
    from zetta.client import Session

    counter = iter(range(first_index, first_index + episodes))
    done: list[Episode] = []
    idle_seen = False

    async def lane(sid: str) -> None:
        nonlocal idle_seen
        session = Session(gateway, sid)
        for i in counter:
            t = time.perf_counter()
            seed, init = episode_key(i)
            s = await session.run_episode(task=task, seed=seed, init_state_index=init, max_steps=max_steps)
            done.append(Episode(i, s.success, s.steps, time.perf_counter() - t))
            bar.update()
        if not idle_seen:
            idle_seen = True
            if on_first_idle is not None:
                on_first_idle()

    t0 = time.perf_counter()
    with progress(total=episodes, desc=f"{label} c={len(ids)}", leave=False) as bar:
        await asyncio.gather(*(lane(sid) for sid in ids))
    return sorted(done, key=lambda e: e.index), time.perf_counter() - t0


async def create_sessions(gw: Any, n: int, config: dict[str, Any], batch: int, log: Log) -> Any:
    """``n`` sessions, created ``batch`` at a time (a burst of env builds in one worker can starve
    its heartbeats on a loaded 2-core machine), then warmed with one short episode each."""
    from zetta.client import SessionGroup

    t = time.perf_counter()
    infos: list[Any] = []
    warm = 0.0
    for k in range(0, n, batch):
        group = await gw.create_sessions(env_family="libero", n=min(batch, n - k), env_config=config, keepalive=False)
        infos += group.infos
        w = time.perf_counter()  # warmed a batch at a time too: 64 first resets at once can starve heartbeats
        await group.run_episode(task=config["task"], seed=0, init_state_index=0, max_steps=min(config["max_steps"], 8))
        warm += time.perf_counter() - w
    sessions = SessionGroup(gw, infos)
    sessions.start_keepalive()
    log(f"  {n} sessions created in {time.perf_counter() - t - warm:.1f} s and warmed up in {warm:.1f} s "
        "(one 8-step episode each; not counted)")
    return sessions


def stack_pids(stack: Any) -> dict[str, int]:
    """The stack's processes and this client process, by name."""
    pids = {name: s.proc.pid for name, s in stack.services.items()}
    if stack.redis_proc is not None:
        pids["redis"] = stack.redis_proc.pid
    pids["client"] = os.getpid()
    return pids


@dataclass
class StackSpec:
    """How one stack of the run is set up."""

    mode: str
    env_workers: int
    slots: int
    model: str
    extra_env: dict[str, str] = field(default_factory=dict)
    #: Record every service with py-spy during the point at ``profile_concurrency`` into this directory.
    profile_dir: str = ""
    profile_concurrency: int = 0


class Profiler:
    """py-spy on every service of a stack for one point: raw collapsed stacks per service, plus a summary.

    py-spy attaches to the running processes (root, or ptrace allowed), samples at 100 Hz and costs
    the stack little; SIGINT makes it write what it has.
    """

    def __init__(self, stack: Any, directory: Path) -> None:
        self._stack = stack
        self._dir = directory
        self._spies: list[tuple[str, subprocess.Popen[bytes]]] = []

    def start(self) -> None:
        exe = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
        self._dir.mkdir(parents=True, exist_ok=True)
        for name, svc in self._stack.services.items():
            cmd = [exe, "record", "-p", str(svc.proc.pid), "-r", "100", "-f", "raw", "-o", str(self._dir / f"{name}.txt")]
            self._spies.append((name, subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)))

    def stop(self) -> Path:
        import signal

        from bench import bench_report

        for _, spy in self._spies:
            spy.send_signal(signal.SIGINT)
        for _, spy in self._spies:
            spy.wait(timeout=60)
        summary = self._dir / "summary.txt"
        summary.write_text("\n\n".join(bench_report.profile_summary(self._dir / f"{name}.txt")
                                        for name, _ in self._spies if (self._dir / f"{name}.txt").exists()))
        return summary


def run_stack(spec: StackSpec, concurrency: Sequence[int], episodes: int, task: str, max_steps: int,
              log: Log, failures: list[str], gateway_probe: dict[str, float] | None = None,
              pairing: Pairing | None = None) -> list[Row]:
    """Start a stack, run every concurrency point on it, stop it; a point that fails ends the stack's
    sweep, is added to ``failures`` and the points before it are kept."""
    from services.ops.local_stack import LocalStack

    workdir = Path(tempfile.mkdtemp(prefix="zetta-bench-"))
    env = {"ZETTA_LOG_LEVEL": "WARNING", **spec.extra_env}
    stack = LocalStack(env_workers=spec.env_workers, slots=spec.slots, policy_workers=1, families=("libero",),
                       models=(spec.model,), workdir=workdir, extra_env=env, heartbeat_timeout_ms=30_000)
    t = time.perf_counter()
    with stack:
        log(f"{spec.mode}: {spec.env_workers} env workers x {spec.slots} slots + 1 policy worker ({spec.model}) "
            f"up in {time.perf_counter() - t:.1f} s; {' '.join(f'{k}={v}' for k, v in spec.extra_env.items())}")
        policy_url = stack.services["policy-0"].metrics_url
        rows = asyncio.run(_stack_points(stack, spec, concurrency, episodes, task, max_steps, policy_url, log,
                                         gateway_probe, failures, pairing))
    shutil.rmtree(workdir, ignore_errors=True)
    return rows


async def _stack_points(stack: Any, spec: StackSpec, concurrency: Sequence[int], episodes: int, task: str,
                        max_steps: int, policy_url: str, log: Log, gateway_probe: dict[str, float] | None,
                        failures: list[str], pairing: Pairing | None = None) -> list[Row]:
    from zetta.client import Gateway, ZettaError

    rows: list[Row] = []
    async with Gateway(stack.gateway_address) as gw:
        sessions = await create_sessions(gw, max(concurrency), env_config(task, max_steps), 2 * spec.env_workers, log)
        env_urls = [svc.metrics_url for name, svc in stack.services.items() if name.startswith("env-")]
        first = 0

        async def point(c: int, n: int, mode: str, profile: bool = False) -> Row:
            nonlocal first
            ids = balanced(sessions.infos, c)
            meter = ResourceMeter(lambda: stack_pids(stack))
            profiler = Profiler(stack, Path(spec.profile_dir)) if profile else None
            before = histogram_totals(policy_url, spec.model)
            if profiler is not None:
                profiler.start()
            steps0 = env_steps(env_urls)
            meter.start()
            busy: list[Busy] = []

            def first_idle() -> None:
                wall_s, cpu_s = meter.mark()
                busy.append(Busy(wall_s, env_steps(env_urls) - steps0, cpu_s))

            try:
                done, wall = await run_lanes(gw, ids, n, task, max_steps, first, first_idle, mode)
            finally:
                if profiler is not None:
                    log(f"  profile of {mode} c={c}: {profiler.stop()}")
            usage = meter.stop()
            after = histogram_totals(policy_url, spec.model)
            first += n
            wait = histogram_mean(before, after, "zetta_policy_queue_wait_seconds")
            row = Row(mode, c, done, wall, usage, histogram_mean(before, after, "zetta_policy_batch_size"),
                      load_average(), queue_wait_ms=None if wait is None else 1000.0 * wait,
                      busy=busy[0] if busy else None)
            log(f"  {mode} c={c}: {n} episodes in {wall:.1f} s = {row.episodes_per_min:.1f}/min, "
                f"{row.steps_per_s:.0f} steps/s ({row.busy_steps_per_s:.0f} while every lane was busy, "
                f"{row.busy.wall_s if row.busy else wall:.1f} s), p50 {row.latency(50):.2f} s, p99 {row.latency(99):.2f} s, "
                f"batch {row.batch_mean or 0:.1f}, queue wait {row.queue_wait_ms or 0:.1f} ms, CPU own "
                f"{usage.own_cpu_pct:.0f}% machine {usage.machine_cpu_pct:.0f}%, load {row.load:.2f}")
            return row

        try:
            for c in concurrency:
                profile = bool(spec.profile_dir) and c == spec.profile_concurrency
                try:
                    rows.append(await point(c, max(episodes, MIN_EPISODES_PER_LANE * c), spec.mode, profile))
                except ZettaError as err:  # e.g. an env worker killed for memory: the rows so far stand
                    failures.append(f"{spec.mode} at concurrency {c}: {err}")
                    log(f"  {spec.mode} c={c} FAILED: {err}")
                    break
            if pairing is not None and rows and not failures:
                best_row = max(rows, key=lambda r: r.steps_per_s)
                best, last_wall = best_row.concurrency, best_row.wall_s
                log(f"  paired rounds at the best concurrency ({best}): limit and stack in turn")
                for r in range(pairing.rounds):
                    stack_first = r % 2 == 1  # alternate the order, so drifting load weighs on both
                    pair: dict[str, Row] = {}
                    for part in (("stack", "limit") if stack_first else ("limit", "stack")):
                        if part == "limit":  # in a thread: the loop keeps the sessions' leases alive
                            pair["limit"] = await asyncio.to_thread(pairing.limit, pairing.seconds or last_wall)
                        else:
                            pair["stack"] = await point(best, max(episodes, MIN_EPISODES_PER_LANE * best),
                                                        f"{spec.mode}-paired")
                            last_wall = pair["stack"].wall_s
                    pairing.results.append(pair)
            if gateway_probe is not None and not failures:
                gateway_probe.update(await _gateway_hop(sessions))
        finally:
            with contextlib.suppress(ZettaError):
                await sessions.close()
    return rows


@dataclass
class Pairing:
    """Rounds that measure the ``limit`` row and the stack's best point one right after the other.

    The sweep's rows run minutes apart, and on a shared machine the same measurement a few
    minutes later can differ by a quarter; a round compares two measurements made seconds apart,
    and the medians over rounds (the order alternating) are what the limit target is judged on.
    """

    rounds: int
    #: Measures the limit for a window of the given seconds.
    limit: Callable[[float], Row]
    #: Seconds of each limit window; 0: as long as the stack's last window (the sweep's point at
    #: first), so that both sides of a round average the machine's drift over the same time.
    seconds: float = 0.0
    results: list[dict[str, Row]] = field(default_factory=list)


async def _gateway_hop(sessions: Any, calls: int = 200) -> dict[str, float]:
    """Round trip of ``Observe`` on one session: client -> gateway -> env worker and back (idle stack)."""
    one = sessions.subset([sessions.ids[0]])
    samples = []
    for _ in range(calls):
        t = time.perf_counter()
        await one.observe()
        samples.append(time.perf_counter() - t)
    return {"observe_p50_ms": 1000 * statistics.median(samples),
            "observe_p99_ms": 1000 * float(np.percentile(samples, 99))}


# ---------------------------------------------------------------------------------------------
# the run


def machine() -> str:
    """One line about the machine."""
    return f"{cpu_machine()}, Python {platform.python_version()}, {platform.system()}"


def sweep(args: argparse.Namespace, log: Log) -> Results:
    """The whole run, in an order that spreads drifting load over the rows (see the module doc)."""
    from services.policy_worker.models.base import load_model

    res = Results(vars(args).copy(), machine(), time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), load_average())
    os.environ.setdefault("ZETTA_TORCH_THREADS", "1")
    os.environ[MODEL_VARIABLE] = args.model
    with quiet_fds():
        policy = load_model(args.model)
    obs, instruction = sample_observation(args.task, args.max_steps)
    res.inference_ms = inference_costs(policy, obs, instruction)
    res.policy_ops = model_ops(policy, obs, instruction)
    res.chunk = int(policy.chunk_size)
    log("inference ms per batch: " + ", ".join(f"B={b}: {ms:.1f}" for b, ms in res.inference_ms.items()))
    rows: dict[str, Row] = {}
    half = (args.naive_episodes + 1) // 2
    fast_half = (args.naive_fast_episodes + 1) // 2
    run_naive(rows, policy, range(half), args.task, args.max_steps, False, log)
    run_naive(rows, policy, range(fast_half), args.task, args.max_steps, True, log)
    t = time.perf_counter()
    replays = record_replays(policy, limit_keys(args.limit_keys), args.task, args.max_steps)
    res.limit_actions = (
        f"the policy's own actions on {len(replays)} episode key(s) ({', '.join(f'{s}/{i}' for (s, i), _ in replays)} "
        "as seed/init state: spread over the init states and seeds the stacks run), recorded in-process and "
        "replayed in turn" if replays else "fixed random actions (--limit-keys 0)")
    log(f"limit rows step {res.limit_actions} (recorded in {time.perf_counter() - t:.1f} s)")
    cores = args.limit_processes or os.cpu_count() or 1
    limits = [run_limit(kind, args.task, args.max_steps, args.limit_seconds, cores, log, replays, res.chunk)
              for kind in ("fast", "obs")]
    slots = -(-max(args.concurrency) // args.env_workers)
    profile_c = args.profile_concurrency or (16 if 16 in args.concurrency else max(args.concurrency))
    pool = LimitPool("fast", args.task, args.max_steps, args.paired_seconds or args.limit_seconds, cores, replays,
                     res.chunk, args.paired_rounds) if args.paired_rounds else None
    try:
        pairing = (Pairing(args.paired_rounds, functools.partial(pool.measure, log), args.paired_seconds)
                   if pool is not None else None)
        stack = run_stack(StackSpec("stack", args.env_workers, slots, args.model, profile_dir=args.profile,
                                    profile_concurrency=profile_c),
                          args.concurrency, args.episodes, args.task, args.max_steps, log, res.failures, res.gateway,
                          pairing)
    finally:
        if pool is not None:
            pool.close()
    res.paired = pairing.results if pairing is not None else []
    off: list[Row] = []
    if args.baseline_concurrency:
        off_slots = -(-max(args.baseline_concurrency) // args.env_workers)
        off = run_stack(StackSpec("stack-off", args.env_workers, off_slots, args.model,
                                  {"ZETTA_MAX_BATCH": "1", "ZETTA_INFER_HOLD_MS": "0",
                                   "ZETTA_RESOURCE_SHARING": "false"}),
                        args.baseline_concurrency, args.episodes, args.task, args.max_steps, log, res.failures)
    limits_after = [run_limit(kind, args.task, args.max_steps, args.limit_seconds, cores, log, replays, res.chunk)
                    for kind in ("fast", "obs")]
    run_naive(rows, policy, range(fast_half, args.naive_fast_episodes), args.task, args.max_steps, True, log)
    run_naive(rows, policy, range(half, args.naive_episodes), args.task, args.max_steps, False, log)
    for before, after in zip(limits, limits_after):  # one row each, over both measurements
        before.note = (f"{before.steps_per_s:.0f} steps/s before the stacks, {after.steps_per_s:.0f} after "
                       f"(load {before.load:.1f} and {after.load:.1f}); the row is both together")
        before.episodes += after.episodes
        before.wall_s += after.wall_s
        before.load = max(before.load, after.load)
        if before.usage is not None and after.usage is not None:
            before.usage.cpu_s += after.usage.cpu_s
    res.rows = [r for r in (rows.get("naive"), rows.get("naive-fast")) if r is not None] + limits + stack + off
    res.load_end = load_average()
    return res


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    def ints(text: str) -> list[int]:
        values = [int(x) for x in text.split(",") if x.strip()]
        if any(v < 1 for v in values):
            raise argparse.ArgumentTypeError("concurrency levels must be >= 1")
        return values

    p = argparse.ArgumentParser(prog="zetta bench rollout", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    p.add_argument("--concurrency", type=ints, default=list(DEFAULT_CONCURRENCY),
                   help="comma-separated concurrency levels of the stack (default 1,4,8,16,32,64)")
    p.add_argument("--baseline-concurrency", type=lambda s: ints(s) if s else [],
                   default=list(DEFAULT_BASELINE_CONCURRENCY),
                   help="levels of the no-batching, no-sharing stack (default 1,8; empty: skip it)")
    p.add_argument("--episodes", type=int, default=16,
                   help="episodes per stack point, at least 4 x its concurrency (default 16)")
    p.add_argument("--max-steps", type=int, default=120, help="fixed step budget of every episode (default 120)")
    p.add_argument("--naive-episodes", type=int, default=8, help="episodes of the naive loop (default 8)")
    p.add_argument("--naive-fast-episodes", type=int, default=4, help="episodes of the naive-fast loop (default 4)")
    p.add_argument("--limit-seconds", type=float, default=12.0, help="seconds of each limit measurement (default 12)")
    p.add_argument("--limit-processes", type=int, default=0, help="processes of the limit rows (default: one per core)")
    p.add_argument("--limit-keys", type=int, default=10,
                   help="episode keys whose policy actions the limit rows replay (default 10; 0: random actions)")
    p.add_argument("--paired-rounds", type=int, default=6,
                   help="rounds of the limit and the stack's best point measured one after the other, the limit "
                        "target judged on their medians (default 6; 0: judge on the sweep's rows)")
    p.add_argument("--paired-seconds", type=float, default=0.0,
                   help="seconds of each paired round's limit window (default 0: as long as the stack's last window)")
    p.add_argument("--env-workers", type=int, default=2, help="env worker processes of the stack (default 2)")
    p.add_argument("--model", default=DEFAULT_MODEL, help=f"served policy (default {DEFAULT_MODEL})")
    p.add_argument("--task", default=DEFAULT_TASK, help=f"LIBERO-Goal task (default {DEFAULT_TASK})")
    p.add_argument("--profile", default="", metavar="DIR",
                   help="py-spy every stack service during one point: raw stacks and summary.txt into DIR")
    p.add_argument("--profile-concurrency", type=int, default=0,
                   help="the point --profile records (default 16 if swept, else the largest)")
    p.add_argument("--json", default="", help="also write every measurement to this JSON file")
    p.add_argument("--from-json", default="", metavar="FILE",
                   help="measure nothing: print (and with --write-docs write) the report of a run saved with --json")
    p.add_argument("--write-docs", action="store_true", help="write docs/results/throughput.json, its page throughput.md and throughput-*.png")
    add_progress_option(p)
    p.add_argument("--docs-dir", default="", help="where --write-docs writes (default: the repository's docs/results/)")
    args = p.parse_args(argv)
    if args.limit_keys < 0:
        p.error("--limit-keys must be >= 0")
    if args.episodes < 1 or args.max_steps < 1 or args.naive_episodes < 0 or args.naive_fast_episodes < 0:
        p.error("--episodes and --max-steps must be >= 1, naive episode counts >= 0")
    if args.env_workers < 1 or args.limit_seconds <= 0 or args.paired_rounds < 0 or args.paired_seconds < 0:
        p.error("--env-workers must be >= 1, --limit-seconds > 0, --paired-seconds and --paired-rounds >= 0")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """`zetta bench rollout ...`: run the sweep, print the table, optionally write the docs."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] != "rollout":
        print("usage: zetta bench rollout [options]   (zetta bench rollout --help)", file=sys.stderr)
        return 2
    args = parse_args(argv[1:])
    from bench import bench_report

    t0 = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", flush=True)

    if args.from_json:
        data = json.loads(Path(args.from_json).read_text())
        res = Results.from_json(data)
        command = data.get("command", "zetta bench rollout")
        source = data.get("source") or {"commit": "unknown", "note": f"{args.from_json} did not record its commit"}
    else:
        log(f"{machine()}; load average {load_average():.2f}; task {SUITE}/{args.task}, {args.max_steps} steps per "
            f"episode, model {args.model}, concurrency {args.concurrency}, baseline {args.baseline_concurrency}")
        source = git_source(Path(__file__).resolve().parents[1])
        res = sweep(args, log)
        res.elapsed_s = time.perf_counter() - t0
        command = ("zetta bench rollout " + " ".join(a for a in argv[1:])).strip()
    print()
    print(bench_report.text_table(res))
    print()
    if res.paired:
        print(f"paired rounds (limit and the stack at concurrency {res.paired[0]['stack'].concurrency}, one after the "
              "other):")
        print(bench_report.aligned([bench_report.PAIRED_HEADER, *bench_report.paired_rows(res)]))
        print()
    print(bench_report.targets_text(res))
    for failure in res.failures:
        print(f"FAILED   {failure}")
    if args.json:
        Path(args.json).write_text(json.dumps({**res.to_json(), "command": command, "source": source}, indent=1,
                                              default=float))
    if args.write_docs:
        docs = Path(args.docs_dir) if args.docs_dir else RESULTS_DIR
        for path in bench_report.write_docs(res, docs, command, source):
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
