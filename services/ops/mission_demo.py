"""The front-door demo: does a harness make the frozen policy more reliable, and is the harness the solver?

One LIBERO-PRO task, the same seeds, three conditions through the real stack:

- the shipped frozen policy alone (``bare``);
- the same policy under a shipped harness package (``harness``);
- that harness around a policy that outputs zero actions (``control``): a harness that solves the task
  by itself would succeed here, so a fair harness scores (close to) 0 % in this row.

It prints the three success rates with Wilson 95 % intervals, the interventions that fired, the
recoveries' share of the actions, and where the per-episode report and the video of one recovered
episode are. Episodes whose rollouts failed for infrastructure reasons are rerun on the same seed.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.common.policies import DEFAULT_POLICY, checkpoint_dir, policy_env_config
from services.harness.package import format as package_format
from zetta.client import EpisodeSummary, Gateway, SessionGroup, ZettaError
from zetta_wire.stats import wilson

ROOT = Path(__file__).resolve().parents[2]
DEMO_SUITE = "libero_goal_swap"
DEMO_TASK = "put_the_cream_cheese_in_the_bowl"
DEMO_HARNESS = ROOT / "examples" / "harnesses" / "libero-goal-pick-place"
DO_NOTHING = "do-nothing"
#: Actions of each chunk executed before the policy is asked again (the VLA's evaluation setting).
EXECUTE_STEPS = 4
CONDITIONS = ("bare", "harness", "control")
LABELS = {"bare": "frozen policy alone", "harness": "frozen policy + harness",
          "control": "do-nothing policy + harness (control)"}
#: Rollouts that failed for infrastructure reasons (not the policy's or the harness's): rerun.
_RERUN = {"DEADLINE_EXCEEDED", "UNAVAILABLE"}


@dataclass
class MissionSpec:
    """What the demo runs: one task, its seeds, the policy and the harness package."""

    suite: str = DEMO_SUITE
    task: str = DEMO_TASK
    seeds: Sequence[int] = tuple(range(10))
    model: str = DEFAULT_POLICY
    harness_dir: Path = DEMO_HARNESS
    execute_steps: int = EXECUTE_STEPS
    #: Step budget per episode; 0: the suite's own (LIBERO's 300 for libero_goal variants).
    max_steps: int = 0
    out_dir: Path = Path("out/demo")


@dataclass
class ConditionResult:
    """One condition's episodes, in seed order."""

    name: str
    episodes: list[EpisodeSummary] = field(default_factory=list)

    @property
    def successes(self) -> int:
        """Successful episodes."""
        return sum(e.success for e in self.episodes)

    def interventions(self) -> Counter[str]:
        """Interventions that fired, by kind, over all episodes."""
        out: Counter[str] = Counter()
        for e in self.episodes:
            if e.harness_report is not None:
                out.update(e.harness_report.interventions_by_kind)
        return out

    def recovery_share(self, successful_only: bool = False) -> float:
        """Recoveries' share of the executed actions (0 without a harness)."""
        rec = pol = 0
        for e in self.episodes:
            if e.harness_report is None or (successful_only and not e.success):
                continue
            rec += e.harness_report.recovery_actions
            pol += e.harness_report.policy_actions
        return rec / (rec + pol) if rec + pol else 0.0


@dataclass
class MissionResult:
    """The three conditions, the video of one recovered episode and the report's path."""

    spec: MissionSpec
    conditions: dict[str, ConditionResult]
    wall_s: float
    video: str = ""
    video_seed: int | None = None
    report_path: Path | None = None


def recovered(e: EpisodeSummary) -> bool:
    """A success in which at least one recovery ran."""
    return bool(e.success and e.harness_report is not None and e.harness_report.recovery_actions > 0)


async def _episodes(group: SessionGroup, spec: MissionSpec, seeds: Sequence[int], model: str, harness_dir: str,
                    record_video: bool = False, tries: int = 3) -> list[EpisodeSummary]:
    for attempt in range(tries):
        try:
            return await group.run_episode(spec.task, list(seeds), [s % 50 for s in seeds], model,
                                           max_steps=spec.max_steps, execute_steps=spec.execute_steps,
                                           harness_dir=harness_dir,
                                           record_video=record_video)
        except ZettaError as exc:
            if exc.code.name not in _RERUN or attempt == tries - 1:
                raise
            print(f"  rollouts failed ({exc.code.name}: {exc}); rerunning the same seeds", flush=True)
    raise AssertionError("unreachable")


async def run_mission(address: str, spec: MissionSpec, log: Any = print) -> MissionResult:
    """Run the three conditions on ``spec.seeds`` (one session per seed, the conditions one after the
    other on the same sessions), then replay one recovered episode with a video."""
    harness_dir = str(Path(spec.harness_dir).resolve())
    t0 = time.perf_counter()
    results: dict[str, ConditionResult] = {}
    video, video_seed = "", None
    async with Gateway(address) as gw:
        group = await gw.create_sessions(env_family="libero", n=len(spec.seeds),
                                         env_config={"suite": spec.suite, **policy_env_config(spec.model)})
        try:
            plan = {"bare": (spec.model, ""), "harness": (spec.model, harness_dir), "control": (DO_NOTHING, harness_dir)}
            for name, (model, hdir) in plan.items():
                t = time.perf_counter()
                eps = await _episodes(group, spec, spec.seeds, model, hdir)
                results[name] = ConditionResult(name, eps)
                log(f"  {LABELS[name]:<38} {results[name].successes}/{len(eps)} "
                    f"({time.perf_counter() - t:.0f} s)")
            pick = next((s for s, e in zip(spec.seeds, results["harness"].episodes) if recovered(e)), None)
            if pick is not None:
                replay = await _episodes(group.subset(group.ids[:1]), spec, [pick], spec.model, harness_dir,
                                         record_video=True)
                video, video_seed = replay[0].video_path, pick
        finally:
            await group.close()
    res = MissionResult(spec, results, time.perf_counter() - t0, video, video_seed)
    res.report_path = write_report(res)
    return res


def _checkpoint_sha(model: str) -> str:
    ckpt = checkpoint_dir(model)
    path = ckpt / "model.pt" if ckpt is not None else None
    return hashlib.sha256(path.read_bytes()).hexdigest() if path is not None and path.exists() else ""


def write_report(res: MissionResult) -> Path:
    """One JSON document: the setup (policy, checkpoint hash, harness hash, seeds) and one row per episode."""
    spec = res.spec
    out = Path(spec.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, cond in res.conditions.items():
        for seed, e in zip(spec.seeds, cond.episodes):
            r = e.harness_report
            rows.append({"condition": name, "seed": seed, "init_state_index": seed % 50, "success": e.success,
                         "steps": e.steps, "first_missing_milestone": e.first_missing_milestone,
                         "policy_actions": r.policy_actions if r else e.steps,
                         "recovery_actions": r.recovery_actions if r else 0,
                         "interventions": [{"kind": i.get("kind"), "outcome": i.get("outcome"),
                                            "start_step": i.get("start_step"), "actions": i.get("actions")}
                                           for i in (r.interventions if r else [])]})
    doc = {"suite": spec.suite, "task": spec.task, "seeds": list(spec.seeds), "model": spec.model,
           "checkpoint_sha256": _checkpoint_sha(spec.model),
           "harness": str(spec.harness_dir), "harness_content_hash": package_format.content_hash(package_format.read_tree(Path(spec.harness_dir))),
           "execute_steps": spec.execute_steps, "wall_s": round(res.wall_s, 1), "video": res.video,
           "video_seed": res.video_seed, "episodes": rows}
    path = out / "report.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def summary(res: MissionResult) -> str:
    """The demo's printed summary: one row per condition, then where to look next."""
    spec = res.spec
    n = len(spec.seeds)
    lines = [f"{spec.suite} / {spec.task}, seeds {spec.seeds[0]}-{spec.seeds[-1]} (init state = seed % 50), "
             f"policy {spec.model}, {spec.execute_steps} actions per chunk",
             f"harness {Path(spec.harness_dir).name}",
             "",
             f"{'condition':<38} {'success':>8} {'rate':>5} {'Wilson 95%':>11} {'recovery share':>15}  interventions"]
    for name, cond in res.conditions.items():
        lo, hi = wilson(cond.successes, n)
        kinds = ", ".join(f"{k}: {v}" for k, v in sorted(cond.interventions().items())) or "-"
        share = f"{cond.recovery_share():.0%}" if name != "bare" else "-"
        lines.append(f"{LABELS[name]:<38} {cond.successes:>4}/{n:<3} {cond.successes / n:>5.0%} "
                     f"{f'{lo:.0%}-{hi:.0%}':>11} {share:>15}  {kinds}")
    harness = res.conditions.get("harness")
    if harness is not None and harness.successes:
        lines.append(f"recoveries' share of the actions in successful harness episodes: "
                     f"{harness.recovery_share(successful_only=True):.0%}")
    lines.append("")
    lines.append(f"report (every episode, its interventions): {res.report_path}")
    if res.video:
        lines.append(f"video of a recovered episode (seed {res.video_seed}): {res.video}")
    else:
        lines.append("video: no episode was recovered by the harness on these seeds")
    lines.append(f"wall time {res.wall_s:.0f} s")
    return "\n".join(lines)
