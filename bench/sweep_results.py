"""What one `zetta bench rollout` run measured: its rows and their derived figures, as JSON.

The sweep (bench_sweep.py) fills these and the report (bench_report.py) renders them; both import
this module and not each other.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np


@dataclass
class Episode:
    """One finished episode: what the client (or the limit process) saw."""

    index: int
    success: bool
    steps: int
    latency_s: float
    #: Naive loops only: seconds of the episode spent building its environment.
    build_s: float = 0.0


@dataclass
class Usage:
    """Resources a row used over its wall time."""

    #: Whole machine, every process (other users' included), 100 = all cores busy.
    machine_cpu_pct: float
    #: The row's own processes (stack services and client, or the naive/limit processes).
    own_cpu_pct: float
    #: Mean GPU utilization from nvidia-smi; None without a GPU.
    gpu_pct: float | None
    #: Resident memory of the row's own processes at its end (MiB).
    rss_mib: float
    #: CPU seconds of the row's own processes, in all and by process name.
    cpu_s: float = 0.0
    cpu_s_by_process: dict[str, float] = field(default_factory=dict)


@dataclass
class Busy:
    """A stack point's span while every lane had an episode running: from the start until the first
    lane found no episode left. The lanes finish at different times and the early ones idle while
    the last run, a ragged end a long rollout job does not have and the ``limit`` rows' windows (every
    process stepping throughout) do not have either; this span is the point's steady state."""

    wall_s: float
    #: Env steps executed in the span (from the env workers' metrics, see :func:`env_steps`).
    steps: int
    #: CPU seconds of the point's own processes in the span.
    cpu_s: float


@dataclass
class Row:
    """One line of the table."""

    mode: str
    concurrency: int
    episodes: list[Episode]
    wall_s: float
    usage: Usage | None = None
    #: Mean items per inference batch from the policy worker's histogram over the row.
    batch_mean: float | None = None
    #: 1-minute load average at the end of the row.
    load: float = 0.0
    note: str = ""
    #: Mean time (ms) an inference request waited in the policy worker's queue over the row.
    queue_wait_ms: float | None = None
    #: Stack points: the span with every lane busy (None for rows measured in steady windows).
    busy: Busy | None = None

    @property
    def successes(self) -> int:
        return sum(e.success for e in self.episodes)

    @property
    def steps(self) -> int:
        return sum(e.steps for e in self.episodes)

    @property
    def episodes_per_min(self) -> float:
        return 60.0 * len(self.episodes) / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.wall_s if self.wall_s > 0 else 0.0

    @property
    def cpu_ms_per_step(self) -> float | None:
        """CPU time of the row's own processes per env step: its cost whatever share of the machine it got."""
        return 1000.0 * self.usage.cpu_s / self.steps if self.usage and self.steps else None

    @property
    def busy_steps_per_s(self) -> float:
        """Steps/s while every lane was busy; the whole row's for rows without a :class:`Busy` span."""
        if self.busy is None or self.busy.wall_s <= 0 or not self.busy.steps:
            return self.steps_per_s
        return self.busy.steps / self.busy.wall_s

    @property
    def busy_cpu_ms_per_step(self) -> float | None:
        """CPU ms per step while every lane was busy; the whole row's without a :class:`Busy` span."""
        if self.busy is None or not self.busy.steps:
            return self.cpu_ms_per_step
        return 1000.0 * self.busy.cpu_s / self.busy.steps

    def latency(self, q: float) -> float:
        return float(np.percentile([e.latency_s for e in self.episodes], q)) if self.episodes else math.nan

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out.update(episodes_per_min=self.episodes_per_min, steps_per_s=self.steps_per_s, cpu_ms_per_step=self.cpu_ms_per_step,
                   p50_s=self.latency(50), p99_s=self.latency(99), successes=self.successes,
                   busy_steps_per_s=self.busy_steps_per_s, busy_cpu_ms_per_step=self.busy_cpu_ms_per_step)
        return out


@dataclass
class Results:
    """Everything one invocation measured (written as JSON and rendered by bench.bench_report)."""

    args: dict[str, Any]
    machine: str
    started: str
    load_start: float
    load_end: float = 0.0
    rows: list[Row] = field(default_factory=list)
    #: ms per inference batch of the in-process policy, by batch size.
    inference_ms: dict[int, float] = field(default_factory=dict)
    #: Tensor ops per inference call (model_ops) and actions per inference (the model's chunk).
    policy_ops: int = 0
    chunk: int = 1
    gateway: dict[str, float] = field(default_factory=dict)
    #: Points that failed (the rows before them stand), e.g. a stack without sharing out of memory.
    failures: list[str] = field(default_factory=list)
    elapsed_s: float = 0.0
    #: What the limit rows stepped (the policy's recorded actions, or random ones).
    limit_actions: str = ""
    #: Paired rounds at the stack's best concurrency: {"limit": Row, "stack": Row} each (see Pairing).
    paired: list[dict[str, Row]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["rows"] = [r.to_json() for r in self.rows]
        out["paired"] = [{k: r.to_json() for k, r in pair.items()} for pair in self.paired]
        return out

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "Results":
        """A run written by ``--json``, to render its report again."""
        def row(r: dict[str, Any]) -> Row:
            usage = Usage(**r["usage"]) if r.get("usage") else None
            busy = Busy(**r["busy"]) if r.get("busy") else None
            return Row(r["mode"], r["concurrency"], [Episode(**e) for e in r["episodes"]], r["wall_s"], usage,
                       r.get("batch_mean"), r.get("load", 0.0), r.get("note", ""), r.get("queue_wait_ms"), busy)

        fields = {k: data[k] for k in ("args", "machine", "started", "load_start", "load_end", "policy_ops", "chunk",
                                       "gateway", "failures", "elapsed_s", "limit_actions") if k in data}
        return cls(**fields, rows=[row(r) for r in data["rows"]],
                   inference_ms={int(k): v for k, v in data.get("inference_ms", {}).items()},
                   paired=[{k: row(r) for k, r in pair.items()} for pair in data.get("paired", [])])
