"""`zetta bench rollout` in small: every measuring piece once, then the report built from them.

The default-suite smoke test drives the real pieces with tiny numbers (two sessions of the shared
stack, 8-step episodes, one naive episode, a fraction of a second of the limit loop in this
process) and renders the docs page into a temporary directory; the slow test runs the whole
command line end to end with tiny settings. The full sweep is never part of a test run.
"""

from __future__ import annotations

import json
import os
import queue
import threading
from pathlib import Path

import pytest

from bench import bench_report
from bench import bench_sweep as bs
from services.ops.cli import main as zetta_main
from services.ops.local_stack import LocalStack

SCRIPTED = "scripted-pick-place"  # the shared stack's policy worker serves it


def test_cli_forwards_bench(capsys: pytest.CaptureFixture[str]) -> None:
    assert zetta_main(["bench"]) == 2
    assert "zetta bench rollout" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        zetta_main(["bench", "rollout", "--help"])
    assert info.value.code == 0
    assert "--max-steps" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        bs.parse_args(["--concurrency", "0"])


async def test_sweep_pieces_and_report(shared_stack: LocalStack, tmp_path: Path) -> None:
    logs: list[str] = []
    probe: dict[str, float] = {}
    failures: list[str] = []
    spec = bs.StackSpec("stack", env_workers=2, slots=4, model=SCRIPTED)
    url = shared_stack.services["policy-0"].metrics_url
    limit_calls: list[float] = []

    def limit_now(seconds: float) -> bs.Row:  # stands in for run_limit's processes, which the slow test runs
        limit_calls.append(seconds)
        return bs.Row("limit", 1, [bs.Episode(0, False, 8, 0.05)], 0.05)

    pairing = bs.Pairing(2, limit_now)
    stack_rows = await bs._stack_points(shared_stack, spec, [1, 2], episodes=2, task=bs.DEFAULT_TASK, max_steps=8,
                                        policy_url=url, log=logs.append, gateway_probe=probe, failures=failures,
                                        pairing=pairing)
    assert failures == []
    assert [(r.mode, r.concurrency, len(r.episodes)) for r in stack_rows] == [("stack", 1, 4), ("stack", 2, 8)]
    best = max(stack_rows, key=lambda r: r.steps_per_s).concurrency
    assert len(pairing.results) == 2 == len(limit_calls)
    # Each limit window is as long as the stack's window before it: the best sweep point's, then the
    # round's own (round 2 measures the stack first).
    best_row = max(stack_rows, key=lambda r: r.steps_per_s)
    assert limit_calls == [best_row.wall_s, pairing.results[1]["stack"].wall_s]
    for p in pairing.results:  # a sweep point's episodes, at the best concurrency
        assert (p["stack"].mode, p["stack"].concurrency, len(p["stack"].episodes)) == (
            "stack-paired", best, bs.MIN_EPISODES_PER_LANE * best)
    for row in stack_rows:
        assert all(e.steps == 8 for e in row.episodes)  # the fixed budget, whatever the policy does
        # The span with every lane busy: the env workers' own step count, within the point's.
        assert row.busy is not None and 0 < row.busy.wall_s <= row.wall_s and row.busy.cpu_s > 0
        assert 0 < row.busy.steps <= row.steps and row.busy_cpu_ms_per_step is not None
        assert row.batch_mean is not None and row.batch_mean >= 1.0
        assert row.usage is not None and row.usage.own_cpu_pct > 0 and row.usage.rss_mib > 100
    one = stack_rows[0]  # one lane is busy until its last episode ends: the span is the whole point
    assert one.busy is not None and one.busy.steps == one.steps
    assert probe["observe_p50_ms"] > 0

    from services.policy_worker.models.base import load_model

    rows: dict[str, bs.Row] = {}
    policy = load_model(SCRIPTED)
    bs.run_naive(rows, policy, [0], bs.DEFAULT_TASK, 8, False, logs.append)
    assert rows["naive"].steps == 8 and rows["naive"].wall_s > 0
    assert 0 < rows["naive"].episodes[0].build_s < rows["naive"].episodes[0].latency_s
    keys = bs.limit_keys(2)  # spread: the second key is a seed and 7 init states on
    assert keys == [bs.episode_key(0), bs.episode_key(bs.LIMIT_KEY_STRIDE)] == [(0, 0), (1, 7)]
    assert len({init for _, init in bs.limit_keys(50)}) == 50  # up to 50 keys, 50 init states
    replays = bs.record_replays(policy, keys, bs.DEFAULT_TASK, 8)
    assert [key for key, _ in replays] == keys and all(a.shape == (8, 7) for _, a in replays)

    out: queue.Queue[dict] = queue.Queue()
    bs.limit_child("obs", bs.DEFAULT_TASK, 8, 0.2, 1, threading.Barrier(1), out, replays)
    result = out.get_nowait()
    assert result["episodes"] and all(steps == 8 for steps, _ in result["episodes"])
    bs.limit_child("fast", bs.DEFAULT_TASK, 8, 0.1, 1, threading.Barrier(1), out)  # no recording: random actions
    assert all(steps == 8 for steps, _ in out.get_nowait()["episodes"])
    limit = bs.Row("limit-obs", 1, [bs.Episode(i, False, s, t) for i, (s, t) in enumerate(result["episodes"])],
                   result["end"] - result["start"])

    res = bs.Results({"task": bs.DEFAULT_TASK, "max_steps": 8, "model": SCRIPTED}, bs.machine(), "now", 0.0,
                     rows=[rows["naive"], limit, *stack_rows], inference_ms={1: 2.0, 8: 3.0}, policy_ops=100, chunk=1,
                     gateway=probe, paired=pairing.results)
    table = bench_report.text_table(res)
    assert table.count("\n") == 1 + len(res.rows)
    written = bench_report.write_docs(res, tmp_path, "zetta bench rollout --test", {"commit": "abc", "dirty": False})
    text = (tmp_path / "throughput.md").read_text()
    assert text.startswith("# Rollout throughput") and "measured by: `zetta bench rollout --test`" in text
    assert "| stack | 2 | 8 |" in text and "Scale-out model" in text and "Paired rounds" in text
    assert {p.name for p in written} == {"throughput.json", "throughput.md", "throughput-episodes.png",
                                         "throughput-steps.png", "throughput-latency.png", "throughput-cpu.png"}
    assert all(p.stat().st_size > 1000 for p in written)
    assert bench_report.page(json.loads((tmp_path / "throughput.json").read_text())) == text  # what gen_results renders
    again = bs.Results.from_json(json.loads(json.dumps(res.to_json(), default=float)))  # what --json writes
    assert bench_report.targets(again) == bench_report.targets(res)


def test_limit_pool_measures_the_same_processes_again_and_stops_early() -> None:
    """The paired rounds' limit: processes built once, a window per measure(); close() releases
    processes still waiting for rounds that will not come."""
    logs: list[str] = []
    pool = bs.LimitPool("fast", bs.DEFAULT_TASK, 8, 0.3, 1, rounds=3)
    try:
        first, second = pool.measure(logs.append), pool.measure(logs.append, seconds=1.2)
    finally:
        pool.close()
    for row in (first, second):
        assert row.mode == "limit" and row.steps >= 8 and all(e.steps == 8 for e in row.episodes)
        assert row.cpu_ms_per_step is not None and row.cpu_ms_per_step > 0
    assert second.episodes and len(logs) == 2
    assert first.wall_s < 1.0 <= 1.2 <= second.wall_s  # the window the parent asked for, each time
    assert all(not c.is_alive() for c in pool._children), "the third round's wait was released"


def test_targets_judge_the_issue_thresholds() -> None:
    def row(mode: str, c: int, n: int, wall: float, latency: float) -> bs.Row:
        return bs.Row(mode, c, [bs.Episode(i, False, 100, latency) for i in range(n)], wall)

    res = bs.Results({}, "m", "now", 0.0, rows=[
        row("naive", 1, 2, 60.0, 30.0),                   # 2 episodes/min, 3.3 steps/s
        row("limit", 2, 100, 10.0, 0.2),                  # 1000 steps/s
        row("stack", 8, 100, 50.0, 4.0),                  # 120 episodes/min
        row("stack", 16, 100, 40.0, 6.0),                 # 150 episodes/min = 75x naive, 250 steps/s
        row("stack", 32, 100, 12.0, 7.9),                 # 833 steps/s = 83% of the limit
    ])
    met = {name: ok for name, _, ok in bench_report.targets(res)}
    assert list(met.values()) == [True, True, True]
    res.rows[-1].episodes = [bs.Episode(i, False, 100, 8.1) for i in range(100)]  # growth 2.03x
    res.rows[-1].wall_s = 13.0  # 769 steps/s = 77%
    assert [ok for _, _, ok in bench_report.targets(res)] == [True, False, False]
    res.rows[-1].wall_s = 10.0  # 1000 steps/s, as fast as the limit...
    res.rows[1].usage = bs.Usage(100.0, 50.0, None, 1.0, cpu_s=50.0)  # ...but the limit needs 5 CPU ms a step
    res.rows[-1].usage = bs.Usage(100.0, 90.0, None, 1.0, cpu_s=70.0)  # and the stack 7: 71%, not met
    (_, measured, ok) = bench_report.targets(res)[1]
    assert ok is False and "CPU cost per step 71%" in measured


def test_paired_rounds_judge_the_limit_target_on_their_medians() -> None:
    """Measured seconds apart, the rounds decide; the sweep's rows (minutes apart) are only quoted."""
    def row(mode: str, c: int, wall: float, cpu_s: float) -> bs.Row:
        return bs.Row(mode, c, [bs.Episode(i, False, 100, 1.0) for i in range(10)], wall,
                      bs.Usage(100.0, 90.0, None, 1.0, cpu_s=cpu_s))  # 1000 steps

    res = bs.Results({}, "m", "now", 0.0, rows=[row("limit", 2, 1.0, 4.0), row("stack", 8, 1.6, 6.0)])
    (_, measured, ok) = bench_report.targets(res)[1]
    assert ok is False and "steps/s 62% at concurrency 8" in measured  # the sweep alone: not met
    # Three rounds: 85/80/90% of the limit's steps/s, CPU shares 82/79/88%: medians 85% and 82%.
    res.paired = [{"limit": row("limit", 2, 1.0, 4.0), "stack": row("stack-paired", 8, 1 / 0.85, 4.0 / 0.82)},
                  {"limit": row("limit", 2, 1.0, 4.0), "stack": row("stack-paired", 8, 1 / 0.80, 4.0 / 0.79)},
                  {"limit": row("limit", 2, 1.0, 4.0), "stack": row("stack-paired", 8, 1 / 0.90, 4.0 / 0.88)}]
    (_, measured, ok) = bench_report.targets(res)[1]
    assert ok is True and measured.startswith("paired rounds at concurrency 8, median of 3: steps/s 85%, CPU cost "
                                              "per step 82%") and "minutes apart" in measured
    res.paired[0]["stack"].usage.cpu_s = 4.0 / 0.75  # the CPU median falls to 79%: not met
    assert bench_report.targets(res)[1][2] is False
    assert bench_report.paired_table(res).count("\n") == 1 + len(res.paired)
    # A round is judged on the span with every lane busy: 700 of its 1000 steps in 0.7 s at 4.0/0.82
    # CPU s per 1000 steps, while its whole window (a ragged end) shows 75% and 75%.
    res.paired[0]["stack"] = bs.Row("stack-paired", 8, [bs.Episode(i, False, 100, 1.0) for i in range(10)], 1 / 0.75,
                                    bs.Usage(100.0, 90.0, None, 1.0, cpu_s=4.0 / 0.75),
                                    busy=bs.Busy(0.7 / 0.85, 700, 0.7 * 4.0 / 0.82))
    (_, measured, ok) = bench_report.targets(res)[1]
    assert ok is True and "steps/s 85%, CPU cost per step 82%" in measured
    assert "| 1 | 1000 | 850 | 85% |" in bench_report.paired_table(res)


def test_latency_growth_floor_from_littles_law() -> None:
    """At concurrency 8 the stack kept 60% of the cores busy at 3 CPU ms a step; at 32 a step costs
    the same: growth can be no less than 4 x 0.6 = 2.4x, and the target names the floor."""
    def row(c: int, latency: float, own_pct: float) -> bs.Row:
        usage = bs.Usage(100.0, own_pct, None, 1.0, cpu_s=0.3)  # 100 steps x 3 ms
        return bs.Row("stack", c, [bs.Episode(i, False, 100 // 4, latency) for i in range(4)], 10.0, usage)

    res = bs.Results({}, "m", "now", 0.0, rows=[row(8, 4.0, 60.0), row(32, 10.0, 100.0)])
    assert abs(bench_report.latency_growth_floor(res) - 2.4) < 1e-9
    (_, measured, ok) = bench_report.targets(res)[2]
    assert ok is False and measured.startswith("2.50x") and "less than 2.40x" in measured
    res.rows[0].usage.own_cpu_pct = 40.0  # a machine with room to spare at 8: the floor is 1.6x
    assert abs(bench_report.latency_growth_floor(res) - 1.6) < 1e-9


@pytest.mark.slow
def test_command_line_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "run.json"
    code = zetta_main(["bench", "rollout", "--concurrency", "1,2", "--baseline-concurrency", "2", "--episodes", "2",
                       "--max-steps", "8", "--naive-episodes", "1", "--naive-fast-episodes", "1",
                       "--limit-seconds", "0.5", "--paired-rounds", "2", "--paired-seconds", "0.5", "--json", str(out),
                       "--write-docs", "--docs-dir", str(tmp_path)])
    assert code == 0
    data = json.loads(out.read_text())
    modes = [(r["mode"], r["concurrency"]) for r in data["rows"]]
    cores = os.cpu_count()
    assert modes == [("naive", 1), ("naive-fast", 1), ("limit", cores), ("limit-obs", cores), ("stack", 1),
                     ("stack", 2), ("stack-off", 2)]
    assert (tmp_path / "throughput-latency.png").exists()
    assert [(p["limit"]["mode"], p["stack"]["mode"]) for p in data["paired"]] == [("limit", "stack-paired")] * 2


@pytest.mark.parametrize("sharing", [True, False])
async def test_resource_sharing_switch(sharing: bool) -> None:
    """ZETTA_RESOURCE_SHARING=false (the stack-off baseline) gives every session a group of its own,
    which is closed with the session; on, sessions of one config share one group."""
    from google.protobuf import struct_pb2

    from services.env_worker.config import EnvWorkerConfig
    from services.env_worker.policy_client import PolicyClient
    from services.env_worker.servicer import EnvWorkerServicer
    from services.env_worker.slots import SlotTable
    from zetta_wire.v1 import env_worker_pb2

    cfg = EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1", "ZETTA_RESOURCE_SHARING": str(sharing).lower()})
    assert cfg.resource_sharing is sharing
    table = SlotTable(2, ("robosuite",))
    servicer = EnvWorkerServicer(table, PolicyClient([], 1000), resource_sharing=cfg.resource_sharing)
    config = struct_pb2.Struct()
    config.update({"env_name": "Lift"})
    try:
        await servicer.OpenSlots(env_worker_pb2.OpenSlotsRequest(session_ids=["a", "b"], env_family="robosuite",
                                                                 env_config=config), None)
        a, b = table.get(["a", "b"])
        assert (a.family is b.family) is sharing
        stats = [a.family.sharing_stats(), b.family.sharing_stats()]
        if sharing:
            assert stats[0]["models_compiled"] == 1
        else:
            assert [s["models_compiled"] for s in stats] == [1, 1]
        await servicer.CloseSlots(env_worker_pb2.CloseSlotsRequest(session_ids=["a", "b"]), None)
        for s in (a, b):
            s.executor.submit(lambda: None).result(timeout=60)  # the close ran on the slot's thread
        assert (a.family.sharing_stats()["envs_idle"] == 2) is sharing  # off: its group was closed with it
    finally:
        table.shutdown()


def test_resource_sharing_setting_fails_fast() -> None:
    from services.common.config import ConfigError
    from services.env_worker.config import EnvWorkerConfig

    assert EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1"}).resource_sharing is True
    with pytest.raises(ConfigError, match="ZETTA_RESOURCE_SHARING"):
        EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1", "ZETTA_RESOURCE_SHARING": "maybe"})
