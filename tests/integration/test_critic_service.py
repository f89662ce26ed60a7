"""The critic service over real gRPC on loopback, against a real redis-server and its own process.

Registry: publish (idempotent, immutable, lineage), get, list, diff, pin, the error codes, and a
restart (of the service, and of Redis's memory) that keeps every version. Evaluate: one episode
of a package through H3b's harness runtime, decision by decision. CLI: `zetta harness ...`.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import numpy as np
import pytest
import redis

from tests.unit.test_harness_package import example_files, write_tree
from zetta import ZettaError
from services.ops import harness as zh
from services.ops.local_stack import LocalStack
from zetta_wire.v1 import critic_pb2, critic_pb2_grpc


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    """Redis, a gateway and the critic service; no env or policy workers are needed here."""
    st = LocalStack(env_workers=0, policy_workers=0, workdir=tmp_path_factory.mktemp("critic-stack"))
    st.start()
    try:
        yield st
    finally:
        st.stop()


@pytest.fixture
def reg(stack: LocalStack) -> Iterator[zh.HarnessRegistry]:
    with zh.HarnessRegistry(stack.critic_address, timeout=60) as client:
        yield client


def code_of(call) -> tuple[grpc.StatusCode, str]:  # type: ignore[no-untyped-def]
    with pytest.raises(ZettaError) as info:
        call()
    return info.value.code, info.value.details


# ---- registry -------------------------------------------------------------------------------------


def test_publish_is_idempotent_immutable_and_tracks_lineage(reg: zh.HarnessRegistry) -> None:
    v1, created = reg.publish(example_files(name="lineage"), evidence={"clusters": ["k1"]}, validation={"heldout": 0.9})
    assert (v1.ref, created, v1.parent, v1.lineage) == ("lineage@1", True, "", [])
    assert v1.evidence == {"clusters": ["k1"]} and v1.validation == {"heldout": 0.9}
    again, created = reg.publish(example_files(name="lineage"), parent="lineage@1", evidence={"other": 1})
    assert (again, created) == (v1, False)  # same content: same version, first manifest kept
    v2, created = reg.publish(example_files(name="lineage", radius=0.6), parent="lineage@1")
    assert (v2.ref, created, v2.parent, v2.lineage) == ("lineage@2", True, "lineage@1", ["lineage@1"])
    v3, _ = reg.publish(example_files(name="lineage", radius=0.7), parent="lineage@latest")
    assert (v3.ref, v3.parent, v3.lineage) == ("lineage@3", "lineage@2", ["lineage@1", "lineage@2"])
    manifest, files = reg.get("lineage@1")
    assert manifest == v1
    assert files.pop("manifest.json")
    assert files == example_files(name="lineage")


def test_get_by_every_reference_form(reg: zh.HarnessRegistry, tmp_path: Path) -> None:
    write_tree(tmp_path / "pkg", example_files(name="refs"))
    v1, _ = reg.publish(tmp_path / "pkg")
    v2, _ = reg.publish(example_files(name="refs", radius=0.9))
    assert reg.get("refs@1", manifest_only=True) == (v1, {})
    assert reg.get("refs@latest", manifest_only=True)[0] == v2
    assert reg.get("refs", manifest_only=True)[0] == v2
    reg.pin("test/refs", "refs@1")
    assert reg.get("refs@pinned", task="test/refs", manifest_only=True)[0] == v1
    assert reg.get("", task="test/refs", manifest_only=True)[0] == v1
    out = tmp_path / "out"
    assert reg.download("refs@2", out) == v2
    assert json.loads((out / "manifest.json").read_text())["content_hash"] == v2.content_hash
    assert (out / "params" / "reach.toml").read_bytes() == example_files(radius=0.9)["params/reach.toml"]


def test_list_diff_and_pins(reg: zh.HarnessRegistry) -> None:
    reg.publish(example_files(name="listed"))
    reg.publish(example_files(name="listed", radius=0.8, extra_tool="\nEXTRA = 2\n"))
    previous = reg.pin("test/listed", "listed@1")
    assert previous == ("listed@1", "")
    assert reg.pin("test/listed", "listed@latest") == ("listed@2", "listed@1")
    assert reg.get_pin("test/listed") == "listed@2"
    versions, pins = reg.list("listed")
    assert [m.ref for m in versions] == ["listed@1", "listed@2"]
    assert pins == {"test/listed": "listed@2"}
    all_versions, _ = reg.list()
    assert {"listed@1", "listed@2"} <= {m.ref for m in all_versions}
    d = reg.diff("listed@1", "listed@2")
    assert (d.base.version, d.head.version) == (1, 2)
    assert [(f.path, f.change) for f in d.files] == [
        ("params/reach.toml", critic_pb2.FILE_CHANGE_MODIFIED),
        ("tools/reach.py", critic_pb2.FILE_CHANGE_MODIFIED),
    ]
    assert "+EXTRA = 2" in d.files[1].unified_diff
    assert [(p.file, p.key, p.base_json, p.head_json) for p in d.params] == [("reach", "radius", "0.5", "0.8")]


def test_concurrent_publishes_get_distinct_versions(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    def publish(i: int) -> str:
        with zh.HarnessRegistry(stack.critic_address, timeout=120) as client:
            return client.publish(example_files(name="racy", radius=1.0 + i))[0].ref

    with ThreadPoolExecutor(4) as pool:
        refs = list(pool.map(publish, range(4)))
    assert sorted(refs) == [f"racy@{v}" for v in (1, 2, 3, 4)]
    assert sorted(m.ref for m in reg.list("racy")[0]) == sorted(refs)


def test_error_codes(reg: zh.HarnessRegistry) -> None:
    bad = example_files(name="errors")
    bad["tools/evil.py"] = b"import math\nimport subprocess\n"
    code, details = code_of(lambda: reg.publish(bad))
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert "tools/evil.py:2: import of 'subprocess' is not allowed" in details
    spin = example_files(name="errors")
    spin["tools/spin.py"] = b"X = 1\nY = [][3]\n"
    code, details = code_of(lambda: reg.publish(spin))
    assert (code, "tools/spin.py:2: import failed: IndexError" in details) == (grpc.StatusCode.INVALID_ARGUMENT, True)
    code, details = code_of(lambda: reg.publish(example_files(name="errors"), parent="errors@7"))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "parent 'errors@7'" in details
    code, _ = code_of(lambda: reg._call("Publish", critic_pb2.PublishRequest(files=example_files(), evidence_json="{oops")))
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    reg.publish(example_files(name="errors"))
    code, details = code_of(lambda: reg.get("errors@9"))
    assert (code, details) == (grpc.StatusCode.NOT_FOUND, "harness errors has no version 9 (latest is errors@1)")
    assert code_of(lambda: reg.get("nobody@1"))[0] == grpc.StatusCode.NOT_FOUND
    assert code_of(lambda: reg.get("bad ref@@"))[0] == grpc.StatusCode.INVALID_ARGUMENT
    assert code_of(lambda: reg.get("errors@pinned"))[0] == grpc.StatusCode.INVALID_ARGUMENT
    assert code_of(lambda: reg.get_pin("test/unpinned"))[0] == grpc.StatusCode.NOT_FOUND
    assert code_of(lambda: reg.pin("", "errors@1"))[0] == grpc.StatusCode.INVALID_ARGUMENT
    assert code_of(lambda: reg.pin("test/errors", "errors@pinned"))[0] == grpc.StatusCode.INVALID_ARGUMENT
    reg.publish(example_files(name="other"))
    reg.pin("test/errors", "other@1")
    code, details = code_of(lambda: reg.get("errors@pinned", task="test/errors"))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "pinned to other@1" in details
    assert code_of(lambda: reg.diff("errors@1", "errors@5"))[0] == grpc.StatusCode.NOT_FOUND


def test_metrics_count_calls_and_rejections(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    reg.publish(example_files(name="metered"))
    with urllib.request.urlopen(stack.services["critic"].metrics_url, timeout=5) as resp:
        text = resp.read().decode()
    assert 'zetta_critic_requests_total{code="OK",method="Publish"}' in text
    assert 'zetta_critic_requests_total{code="INVALID_ARGUMENT",method="Publish"}' in text
    assert "zetta_critic_packages_rejected_total" in text
    assert 'zetta_hop_latency_seconds_count{method="Publish",service="critic"}' in text


# ---- Evaluate -------------------------------------------------------------------------------------


def far(radius: float) -> dict[str, np.ndarray]:
    return {"robot0_eef_pos": np.array([radius, 0.0, 0.0], dtype=np.float32), "phi_grasp": np.zeros(1, np.float32)}


async def test_evaluate_runs_one_episode_decision_by_decision(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    v1, _ = reg.publish(example_files(name="evaluated"))
    action = np.zeros(7, dtype=np.float64)
    async with zh.evaluate("evaluated@1", "reach the goal", ["reached(goal)"], address=stack.critic_address) as ev:
        assert ev.manifest == v1
        decisions = [await ev.step(far(0.1), None)]
        for radius in (0.1, 0.1, 0.1, 0.9, 0.9, 0.9, 0.1, 0.1, 0.1):
            decisions.append(await ev.step(far(radius), action, milestones=["reached(goal)"]))
        report = await ev.finish(success=True)
    assert [d.step for d in decisions] == list(range(10))
    # The code critic is evaluated every 4th step, its proposal coming with the next step; through
    # the intervention it is evaluated at every step, and re-entry follows the first clear one.
    assert [d.mode for d in decisions] == ["policy"] * 5 + ["hold"] * 2 + ["policy"] * 3
    assert [len(d.proposals) for d in decisions] == [0, 0, 0, 0, 0, 1, 1, 0, 0, 0]
    first = decisions[5].proposals[0]
    assert (first.critic, first.evidence, first.suggested_mode) == ("reach.too_far", "too_far", "hold")
    assert first.details["radius"] == pytest.approx(0.9, abs=1e-6)
    assert {d.intervention_id for d in decisions[5:7]} == {"iv1"}
    assert all(d.action is not None and d.action.shape == (7,) for d in decisions[5:7])
    assert decisions[7].action is None and decisions[7].intervention_id == ""
    # the episode's report: who acted, and the one intervention from proposal to re-entry
    assert (report.harness, report.version, report.content_hash) == ("evaluated", "1", v1.content_hash)
    assert (report.policy_actions, report.recovery_actions) == (7, 2)
    assert dict(report.actions_by_mode) == {"policy": 7, "hold": 2}
    assert dict(report.interventions_by_kind) == {"hold": 1}
    (iv,) = report.interventions
    assert (iv.id, iv.kind, iv.proposer, iv.evidence) == ("iv1", "hold", "reach.too_far", "too_far")
    assert (iv.start_step, iv.end_step, iv.outcome, iv.actions) == (5, 7, "reentered", 2)
    assert report.proposals == 2 and not report.disabled_critics


async def test_evaluate_redirects_the_policy_under_an_instruction_it_was_trained_on(
        reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    """A redirection on the Evaluate stream names one of the client's ``policy_instructions`` that
    serves the sub-goal; without them, the sub-goal's own words."""
    files = example_files(name="evaluated-redirect")
    files["plans/recoveries.toml"] = b'[hold]\nrecovery = "redirect_instruction"\nparams = { steps = 5 }\nmax_steps = 20\n'
    reg.publish(files)
    names = ["reached(cream_cheese_1)", "grasped(cream_cheese_1)", "lifted(cream_cheese_1)", "in(cream_cheese_1,bowl_1)"]
    action = np.zeros(7, dtype=np.float64)
    for trained, expected in ((["put the cream cheese in the bowl", "turn on the stove"], "put the cream cheese in the bowl"),
                              ([], "pick up the cream cheese")):
        async with zh.evaluate("evaluated-redirect@1", "put the cream cheese on the plate", names,
                               address=stack.critic_address, policy_instructions=trained) as ev:
            decisions = [await ev.step(far(0.1), None)]
            for _ in range(5):
                decisions.append(await ev.step(far(0.9), action))
            report = await ev.finish(success=False)
        assert decisions[5].mode == "hold" and decisions[5].action is None
        assert decisions[5].instruction == expected
        assert report.interventions[0].instruction == expected


async def test_evaluate_uses_the_task_pin(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    reg.publish(example_files(name="pinned-eval"))
    v2, _ = reg.publish(example_files(name="pinned-eval", radius=2.0))
    reg.pin("test/pinned-eval", "pinned-eval@2")
    async with zh.evaluate("", "reach", task="test/pinned-eval", address=stack.critic_address) as ev:
        assert ev.manifest == v2
        decision = await ev.step(far(0.9), None)  # inside the larger radius of version 2
    assert (decision.mode, decision.proposals) == ("policy", [])


async def test_evaluate_errors(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    with pytest.raises(ZettaError) as info:
        async with zh.evaluate("missing@1", "x", address=stack.critic_address):
            pass
    assert info.value.code == grpc.StatusCode.NOT_FOUND
    reg.publish(example_files(name="eval-errors"))
    async with grpc.aio.insecure_channel(stack.critic_address) as channel:
        call = critic_pb2_grpc.CriticServiceStub(channel).Evaluate()
        await call.write(critic_pb2.EvaluateRequest(step=critic_pb2.EvaluateStep()))
        with pytest.raises(grpc.aio.AioRpcError) as rpc:
            await call.read()
        assert rpc.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "first Evaluate message must be a start" in rpc.value.details()
        call = critic_pb2_grpc.CriticServiceStub(channel).Evaluate()
        await call.write(critic_pb2.EvaluateRequest(start=critic_pb2.EvaluateStart(harness="eval-errors@1")))
        assert (await call.read()).started.manifest.version == 1
        step = critic_pb2.EvaluateStep()
        step.observation.tensors["robot0_eef_pos"].dtype = 1
        step.observation.tensors["robot0_eef_pos"].shape[:] = [3]
        step.observation.tensors["robot0_eef_pos"].data = b"\0" * 5
        await call.write(critic_pb2.EvaluateRequest(step=step))
        with pytest.raises(grpc.aio.AioRpcError) as rpc:
            await call.read()
        assert rpc.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "needs 12 bytes, got 5" in rpc.value.details()
        # More policy instructions than a model has, or one that is no sentence: refused at the start.
        from services.critic.servicer import MAX_INSTRUCTION_CHARS, MAX_POLICY_INSTRUCTIONS

        for bad, says in ((["put the bowl on the plate"] * (MAX_POLICY_INSTRUCTIONS + 1), "entries; at most"),
                          (["ok", "x" * (MAX_INSTRUCTION_CHARS + 1)], "policy_instructions[1] is")):
            call = critic_pb2_grpc.CriticServiceStub(channel).Evaluate()
            await call.write(critic_pb2.EvaluateRequest(start=critic_pb2.EvaluateStart(
                harness="eval-errors@1", policy_instructions=bad)))
            with pytest.raises(grpc.aio.AioRpcError) as rpc:
                await call.read()
            assert rpc.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert says in rpc.value.details()


# ---- command line ---------------------------------------------------------------------------------


def test_cli_publish_list_get_diff_pin(stack: LocalStack, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["--critic", stack.critic_address]
    write_tree(tmp_path / "a", example_files(name="cli"))
    write_tree(tmp_path / "b", example_files(name="cli", radius=0.25))
    (tmp_path / "ev.json").write_text('{"seeds": [1, 2]}')
    assert zh.main([*base, "publish", str(tmp_path / "a"), "--evidence", str(tmp_path / "ev.json")]) == 0
    assert zh.main([*base, "publish", str(tmp_path / "b"), "--parent", "cli@1"]) == 0
    assert zh.main([*base, "publish", str(tmp_path / "a")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("published cli@1  sha256 ")
    assert out[1].startswith("published cli@2") and out[1].endswith("parent cli@1")
    assert out[2].startswith("already published as cli@1")
    assert zh.main([*base, "pin", "test/cli", "cli@2"]) == 0
    assert zh.main([*base, "pin", "test/cli"]) == 0
    assert capsys.readouterr().out.splitlines() == ["test/cli -> cli@2", "cli@2"]
    assert zh.main([*base, "list", "cli"]) == 0
    listing = capsys.readouterr().out
    assert "cli@1" in listing and "cli@2" in listing and "test/cli" in listing
    assert zh.main([*base, "diff", "cli@1", "cli@2"]) == 0
    diff = capsys.readouterr().out
    assert "params/reach.toml radius: 0.5 -> 0.25" in diff and "+radius = 0.25" in diff
    assert zh.main([*base, "get", "cli@pinned", "--task", "test/cli", "--out", str(tmp_path / "got")]) == 0
    assert (tmp_path / "got" / "params" / "reach.toml").read_text().startswith("radius = 0.25")
    assert zh.main([*base, "get", "cli@9"]) == 1
    assert "NOT_FOUND" in capsys.readouterr().err


def test_corrupted_store_is_data_loss_not_wrong_bytes(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    """Files edited behind the registry's back are never served as the version."""
    manifest, _ = reg.publish(example_files(name="tampered"))
    assert stack.workdir is not None
    stored = stack.workdir / "critic-store" / "packages" / manifest.content_hash / "params" / "reach.toml"
    stored.write_text("radius = 1000.0\n")
    code, details = code_of(lambda: reg.get("tampered@1"))
    assert code == grpc.StatusCode.DATA_LOSS and "hash to" in details
    assert reg.get("tampered@1", manifest_only=True)[0] == manifest


def test_service_refuses_to_start_on_an_unusable_store(stack: LocalStack, tmp_path: Path) -> None:
    """A store path that cannot be a directory stops the process at once with the variable named."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    env = {**stack.services["critic"].env, "ZETTA_CRITIC_STORE": str(blocker / "store"), "ZETTA_CRITIC_PORT": "0",
           "ZETTA_METRICS_PORT": "-1"}
    done = subprocess.run([sys.executable, "-m", "services.critic.main"], env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode != 0
    assert f"ZETTA_CRITIC_STORE={blocker / 'store'} is not a writable directory" in done.stderr


# ---- durability (last: restarts the service) ------------------------------------------------------


def test_restart_and_lost_redis_keep_every_version(reg: zh.HarnessRegistry, stack: LocalStack) -> None:
    v1, _ = reg.publish(example_files(name="durable"))
    v2, _ = reg.publish(example_files(name="durable", radius=0.3), parent="durable@1")
    reg.pin("test/durable", "durable@2")
    stack.kill("critic", signal.SIGTERM)
    stack.start_critic()
    assert reg.get("durable@1")[0] == v1  # reachable again on the same address
    assert reg.get("durable@2", manifest_only=True)[0] == v2
    assert reg.get_pin("test/durable") == "durable@2"
    # Redis loses the registry's keys (restart without persistence): the store restores versions.
    client = redis.Redis.from_url(stack.redis_url or "")
    keys = list(client.scan_iter("zetta:critic:*"))
    assert keys
    client.delete(*keys)
    stack.kill("critic", signal.SIGKILL)
    stack.start_critic()
    assert reg.get("durable@1", manifest_only=True)[0] == v1
    assert reg.get("durable@latest", manifest_only=True)[0] == v2
    v3, created = reg.publish(example_files(name="durable", radius=0.4))
    assert (v3.ref, created) == ("durable@3", True)  # numbering continues after the restored versions
    assert reg.publish(example_files(name="durable"))[0] == v1
    assert "restored registry pointers from the package store" in stack.services["critic"].log.read_text()
