"""The front-door demo: does a harness make the frozen policy more reliable, and is the harness the solver?

One LIBERO-PRO task (by default libero_goal_lan's "put the cream cheese in the bowl": the scene of
LIBERO-Goal, the instruction paraphrased), the same seeds (init states the shipped policy never
trained on), three conditions through the real stack:

- the shipped frozen policy alone (``bare``);
- the same policy under a shipped harness package (``harness``);
- that harness around a policy that outputs zero actions (``control``): a harness that solves the task
  by itself would succeed here, so a fair harness scores (close to) 0 % in this row.

It prints the three success rates with Wilson 95 % intervals, the interventions that fired, the
recoveries' share of the actions, and where the per-episode report and the video of one recovered
episode are. Episodes whose rollouts failed for infrastructure reasons are rerun on the same seed.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from services.common.policies import DEFAULT_POLICY, EXECUTE_STEPS, checkpoint_dir, policy_env_config
from services.common.provenance import page_header, provenance, weights_sha256
from services.harness.package import format as package_format
from zetta.client import EpisodeSummary, Gateway, SessionGroup, ZettaError
from zetta.credentials import ClientCredentials
from zetta_wire.stats import wilson

ROOT = Path(__file__).resolve().parents[2]
DEMO_SUITE = "libero_goal_lan"
DEMO_TASK = "put_the_cream_cheese_in_the_bowl"
DEMO_HARNESS = ROOT / "examples" / "harnesses" / "libero-goal-pick-place"
DO_NOTHING = "do-nothing"
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
    #: Init states 30-39: the shipped VLA's demonstrations used init states 0-29 (docs/results/vla.md).
    seeds: Sequence[int] = tuple(range(30, 40))
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


@dataclass
class MissionResult:
    """The three conditions, the video of one recovered episode and the report's path."""

    spec: MissionSpec
    conditions: dict[str, ConditionResult]
    wall_s: float
    video: str = ""
    video_seed: int | None = None
    #: Whether the recorded replay of that seed was itself a recovered success (the rollout is replayed,
    #: not the same bytes: without batch-invariant serving it can differ).
    video_recovered: bool | None = None
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


async def run_mission(address: str, spec: MissionSpec, log: Any = print,
                      credentials: ClientCredentials | None = None) -> MissionResult:
    """Run the three conditions on ``spec.seeds`` (one session per seed, the conditions one after the
    other on the same sessions), then replay one recovered episode with a video."""
    harness_dir = str(Path(spec.harness_dir).resolve())
    t0 = time.perf_counter()
    results: dict[str, ConditionResult] = {}
    video, video_seed, replay_recovered = "", None, None
    async with Gateway(address, **(credentials or ClientCredentials()).gateway_kwargs()) as gw:
        group = await gw.create_sessions(env_family="libero", n=len(spec.seeds),
                                         env_config={"suite": spec.suite, "task": spec.task,
                                                     **policy_env_config(spec.model)})
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
                video, video_seed, replay_recovered = replay[0].video_path, pick, recovered(replay[0])
        finally:
            await group.close()
    res = MissionResult(spec, results, time.perf_counter() - t0, video, video_seed, replay_recovered)
    res.report_path = write_report(res)
    return res


def _relative(path: str) -> str:
    """``path`` relative to the working directory when it lies below it (what a README can show)."""
    if not path:
        return ""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return path


def readme_block(doc: dict[str, Any]) -> str:
    """The README's copy of the demo's output, rebuilt from the published report (never typed)."""
    return "```\n" + summary(doc, "out/demo/report.json") + "\n```"


def report_doc(res: MissionResult) -> dict[str, Any]:
    """The run as one JSON document: the setup (commit, policy and checkpoint hash, harness and its
    content hash, task, seeds) and one row per episode (success, who acted, interventions)."""
    spec = res.spec
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
    harness_files = package_format.read_tree(Path(spec.harness_dir))
    default = MissionSpec()
    flags = [f"--episodes {len(spec.seeds)}" if len(spec.seeds) != len(default.seeds) else "",
             f"--suite {spec.suite}" if spec.suite != default.suite else "",
             f"--task {spec.task}" if spec.task != default.task else "",
             f"--harness {spec.harness_dir}" if Path(spec.harness_dir) != default.harness_dir else ""]
    return {**provenance(" ".join(["zetta up --demo", *filter(None, flags)]), ROOT), "suite": spec.suite, "task": spec.task, "seeds": list(spec.seeds),
            "model": spec.model, "checkpoint_sha256": weights_sha256(checkpoint_dir(spec.model)),
            "harness": Path(spec.harness_dir).name, "harness_content_hash": package_format.content_hash(harness_files),
            "execute_steps": spec.execute_steps, "wall_s": round(res.wall_s, 1), "video": _relative(res.video),
            "video_seed": res.video_seed, "video_recovered": res.video_recovered, "episodes": rows}


def write_report(res: MissionResult) -> Path:
    """``report.json`` in the spec's output directory."""
    out = Path(res.spec.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.json"
    path.write_text(json.dumps(report_doc(res), indent=1) + "\n")
    return path


def _rows(doc: dict[str, Any], condition: str, successful_only: bool = False) -> list[dict[str, Any]]:
    return [r for r in doc["episodes"] if r["condition"] == condition and (r["success"] or not successful_only)]


def recovery_share(rows: Sequence[dict[str, Any]]) -> float:
    """Recoveries' share of the actions executed over ``rows`` (0 when none ran)."""
    rec = sum(r["recovery_actions"] for r in rows)
    total = rec + sum(r["policy_actions"] for r in rows)
    return rec / total if total else 0.0


def summary(doc: dict[str, Any], report_path: Path | str = "") -> str:
    """The demo's printed summary from its report: one row per condition, then where to look next."""
    seeds = doc["seeds"]
    lines = [f"{doc['suite']} / {doc['task']}, seeds {seeds[0]}-{seeds[-1]} (init state = seed % 50), "
             f"policy {doc['model']} (model.pt sha256 {doc['checkpoint_sha256'][:12]}), "
             f"{doc['execute_steps']} actions per chunk",
             f"harness {doc['harness']} (content hash {doc['harness_content_hash'][:12]})",
             "",
             f"{'condition':<38} {'success':>8} {'rate':>5} {'Wilson 95%':>11} {'recovery share':>15}  interventions"]
    for name in CONDITIONS:
        rows = _rows(doc, name)
        if not rows:
            continue
        wins = sum(r["success"] for r in rows)
        lo, hi = wilson(wins, len(rows))
        kinds = Counter(i["kind"] for r in rows for i in r["interventions"])
        fired = ", ".join(f"{k}: {v}" for k, v in sorted(kinds.items())) or "-"
        share = f"{recovery_share(rows):.0%}" if name != "bare" else "-"
        lines.append(f"{LABELS[name]:<38} {wins:>4}/{len(rows):<3} {wins / len(rows):>5.0%} "
                     f"{f'{lo:.0%}-{hi:.0%}':>11} {share:>15}  {fired}")
    won = _rows(doc, "harness", successful_only=True)
    if won:
        lines.append(f"recoveries' share of the actions in successful harness episodes: {recovery_share(won):.0%}")
    lines.append("")
    if report_path:
        lines.append(f"report (every episode, its interventions): {report_path}")
    if doc.get("video"):
        again = {True: "", False: " (the replay differs from the run: it was not a recovered success)"}.get(
            doc.get("video_recovered"), "")
        lines.append(f"video of a recovered episode (seed {doc['video_seed']}): {doc['video']}{again}")
    else:
        lines.append("video: no episode was recovered by the harness on these seeds")
    lines.append(f"wall time {doc['wall_s']:.0f} s")
    return "\n".join(lines)


def page(doc: dict[str, Any]) -> str:
    """docs/results/demo.md: the printed summary and every episode of the published run."""
    lines = [page_header("demo", "make demo: a frozen policy, the same policy under a harness, the control", doc), "",
             "```", summary(doc, "out/demo/report.json"), "```", "",
             "| condition | seed | init state | success | steps | policy actions | recovery actions | interventions (kind: outcome) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in doc["episodes"]:
        fired = ", ".join(f"{i['kind']}: {i['outcome']}" for i in r["interventions"]) or "-"
        lines.append(f"| {r['condition']} | {r['seed']} | {r['init_state_index']} | {'yes' if r['success'] else 'no'} | "
                     f"{r['steps']} | {r['policy_actions']} | {r['recovery_actions']} | {fired} |")
    return "\n".join(lines) + "\n"
