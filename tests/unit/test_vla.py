"""The Zetta VLA: model contract, checkpoint, quantization plug-in, split serving, adapter.

Fast: the shipped checkpoint's cached instruction embeddings keep the sentence model out of
these tests; the closed-loop success checks are in tests/slow (``-m slow``).
"""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.policy_worker.models.base import FACTORIES  # noqa: E402
from services.policy_worker.scheduler import DeadlineExceededError, InferItem, SchedulerConfig  # noqa: E402
from services.policy_worker.vla.features import STATE_INPUTS  # noqa: E402
from services.policy_worker.vla.policy import STATE_CHECKPOINT, ZettaVLAPolicy, load_checkpoint  # noqa: E402

pytestmark = pytest.mark.skipif(not (STATE_CHECKPOINT / "model.pt").exists(), reason="no shipped checkpoint")


def state_policy(**kw) -> ZettaVLAPolicy:
    """The two-stage mechanics are the same for both variants; the state checkpoint needs no frames."""
    return ZettaVLAPolicy(STATE_CHECKPOINT, name="privileged-state-baseline", **kw)


def _batch(b: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {n: (rng.standard_normal((b, w)) * 0.1).astype(np.float32) for n, w in STATE_INPUTS}


@pytest.fixture(scope="module")
def policy() -> ZettaVLAPolicy:
    return state_policy()  # the default Gaussian start, seeded per request: rows compare exactly


@pytest.fixture(scope="module")
def instruction(policy) -> str:
    return sorted(policy.text.cache)[0]


def test_registered_and_checkpoint_is_small() -> None:
    assert "privileged-state-baseline" in FACTORIES
    size = sum(f.stat().st_size for f in STATE_CHECKPOINT.iterdir())
    assert size <= 25e6
    _, doc, cache = load_checkpoint(STATE_CHECKPOINT)
    assert doc["data"]["recipes"] and doc["training"]["steps_done"] > 0
    assert all(v.shape == (384,) for v in cache.values())


def test_inputs_are_not_goal_derived(policy) -> None:
    names = {s.name for s in policy.input_specs()}
    assert names == {n for n, _ in STATE_INPUTS}
    assert not any(n.startswith("task_") for n in names)


def test_infer_shapes_and_range(policy, instruction) -> None:
    for b in (1, 5):
        a = policy.infer(_batch(b), [instruction] * b)
        assert a.shape == (b, policy.chunk_size, 7) and a.dtype == np.float32
        assert np.all(np.abs(a) <= 1.0) and set(np.unique(a[..., 6])) <= {-1.0, 0.0, 1.0}


def test_batching_does_not_change_rows(policy, instruction) -> None:
    batch = _batch(4)
    together = policy.infer(batch, [instruction] * 4)
    alone = np.concatenate([policy.infer({k: v[i:i + 1] for k, v in batch.items()}, [instruction]) for i in range(4)])
    assert np.allclose(together[..., :6], alone[..., :6], atol=1e-4)


def test_instruction_changes_the_action(policy) -> None:
    instrs = sorted(policy.text.cache)
    batch = _batch(1)
    outs = [policy.infer(batch, [s]) for s in instrs[:3]]
    assert any(not np.allclose(outs[0], o, atol=1e-3) for o in outs[1:])


def test_w8a8_plugin_quantizes_only_prefix_mlp(instruction) -> None:
    from torch.ao.nn.quantized.dynamic import Linear as DynLinear

    q = state_policy(quantize="w8a8", noise="zero")
    assert q.quantized == ["encoder.prefix_mlp"]
    assert sum(isinstance(m, DynLinear) for m in q.model.encoder.prefix_mlp.modules()) == 3
    assert not any(type(m) is torch.nn.Linear for m in q.model.encoder.prefix_mlp.modules())
    assert not any(isinstance(m, DynLinear) for m in q.model.expert.modules())
    assert not any(isinstance(m, DynLinear) for m in q.model.encoder.obs.modules())
    f = state_policy(noise="zero")
    batch = _batch(8)
    diff = np.abs(q.infer(batch, [instruction] * 8)[..., :6] - f.infer(batch, [instruction] * 8)[..., :6])
    assert diff.mean() < 0.1


def test_split_matches_monolithic_and_honours_deadlines(instruction, monkeypatch) -> None:
    from services.policy_worker.vla.split import MonolithicVLA, SplitVLA

    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)  # the spawned stage-2 process reads it too

    batch = _batch(6, seed=3)
    items = [{k: v[i] for k, v in batch.items()} for i in range(6)]

    async def go():
        cfg = SchedulerConfig(max_batch=4, max_queue_delay=0.002)
        mono, split = MonolithicVLA(str(STATE_CHECKPOINT), config=cfg), SplitVLA(str(STATE_CHECKPOINT), vlm=cfg, ae=cfg, slots=64)
        try:
            def mk(i, d=5.0):
                return InferItem(f"t{i}", "m", items[i % 6], instruction, deadline=time.monotonic() + d)

            a = await asyncio.gather(*(mono.submit(mk(i)) for i in range(6)))
            b = await asyncio.gather(*(split.submit(mk(i)) for i in range(6)))
            with pytest.raises(DeadlineExceededError):
                await split.submit(mk(99, d=-1.0))
            return a, b
        finally:
            await mono.drain()
            await split.drain()

    a, b = asyncio.run(go())
    for x, y in zip(a, b, strict=True):
        assert x.shape == (8, 7)
        assert np.allclose(x[:, :6], y[:, :6], atol=1e-4)


def test_state_vector_is_built_once_per_batch(policy, instruction, monkeypatch) -> None:
    """The prefix and the noise seeds read one state vector: it is concatenated once per batch."""
    import services.policy_worker.vla.policy as policy_module

    calls = []
    real = policy_module.state_vector
    monkeypatch.setattr(policy_module, "state_vector", lambda *a, **k: calls.append(1) or real(*a, **k))
    policy.infer(_batch(4), [instruction] * 4)
    assert len(calls) == 1


def test_split_worker_holds_one_copy_of_each_stage(instruction, monkeypatch) -> None:
    """With ZETTA_VLA_SPLIT the worker's loaded VLA becomes the split's stage 1 (its action expert
    freed), instead of a second copy loaded beside it; the AE process holds stage 2 alone."""
    from services.policy_worker.scheduler import BatchScheduler
    from services.policy_worker.vla.split import SplitRouter, wrap_for_split

    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)
    model = state_policy()
    expected = model.infer(_batch(1), [instruction])[0]
    cfg = SchedulerConfig(max_batch=4, max_queue_delay=0.002)
    models = {"privileged-state-baseline": model}

    async def go():
        router = wrap_for_split(BatchScheduler(lambda m, x, i: models[m].infer(x, i), cfg), models, cfg)
        assert isinstance(router, SplitRouter)
        try:
            assert router._split["privileged-state-baseline"].policy is model
            assert hasattr(model.model, "encoder") and not hasattr(model.model, "expert")
            item = InferItem("t", "privileged-state-baseline", {k: v[0] for k, v in _batch(1).items()}, instruction,
                             deadline=time.monotonic() + 10)
            return await router.submit(item)
        finally:
            await router.drain()

    assert np.allclose(asyncio.run(go()), expected, atol=1e-4)


def test_adapter_contract_with_our_model(policy, instruction, monkeypatch) -> None:
    from services.policy_worker.vla.adapter import (
        AdapterContractError, ExternalPolicyAdapter, ZettaVLAAdapter, check_actions)
    from services.policy_worker.models.base import register_adapter

    monkeypatch.delenv("ZETTA_VLA_NOISE", raising=False)  # the fixture's default start, row for row
    adapter = ZettaVLAAdapter()
    batch = _batch(3)
    assert np.allclose(adapter.infer(batch, [instruction] * 3), policy.infer(batch, [instruction] * 3))
    register_adapter("test-adapter", lambda: adapter)
    try:
        from services.policy_worker.models.base import load_model

        assert load_model("test-adapter").name == "test-adapter"
    finally:
        FACTORIES.pop("test-adapter")
    with pytest.raises(AdapterContractError):
        check_actions(np.zeros((3, 8, 6), np.float32), 3, 8)
    with pytest.raises(AdapterContractError):
        check_actions(np.full((3, 8, 7), np.nan, np.float32), 3, 8)

    class Bad(ExternalPolicyAdapter):
        chunk_size = 2

        def input_specs(self):
            return []

        def to_policy_inputs(self, batch, instructions):
            return None

        def forward(self, inputs):
            return None

        def to_actions(self, outputs, batch_size):
            return np.zeros((batch_size, 2, 7))  # float64: violates the contract

    with pytest.raises(AdapterContractError):
        Bad().infer({}, ["x"])


def test_training_smoke(tmp_path, policy) -> None:
    from services.policy_worker.vla.model import VLAConfig
    from services.policy_worker.vla.train import TrainConfig, chunk_targets, train

    lengths = np.array([5, 3])
    acts = np.arange(8 * 7, dtype=np.float32).reshape(8, 7)
    t = chunk_targets(acts, lengths, 4)
    assert np.array_equal(t[3], acts[[3, 4, 4, 4]]) and np.array_equal(t[5], acts[[5, 6, 7, 7]])
    instr = sorted(policy.text.cache)[:2]
    rng = np.random.default_rng(0)
    path = str(tmp_path / "demos.npz")
    np.savez(path, states=rng.standard_normal((8, 156)).astype(np.float32), actions=acts / 100,
             episode_lengths=lengths, instructions=np.array(instr))
    meta = train([path], str(tmp_path / "ck"), VLAConfig(prefix_hidden=64, width=32, expert_hidden=32),
                 TrainConfig(steps=3, batch_size=4, warmup=1), log=lambda *_: None, text_cache=policy.text.cache)
    assert meta["training"]["steps_done"] == 3
    p2 = ZettaVLAPolicy(tmp_path / "ck")
    assert p2.infer(_batch(2), [instr[0]] * 2).shape == (2, 8, 7)


def test_pipeline_reuses_only_teacher_sets_with_the_same_recipe(tmp_path) -> None:
    import json
    from dataclasses import asdict

    from services.policy_worker.vla.data import DataRecipe
    from services.policy_worker.vla.train import reuse_demos

    path = str(tmp_path / "clean.npz")
    recipe = DataRecipe(teacher="oracle", seeds_per_task=4, max_episodes=40)
    assert not reuse_demos(recipe, path), "nothing there yet"
    np.savez(path, states=np.zeros((1, 156), np.float32))
    (tmp_path / "clean.npz.json").write_text(json.dumps({"recipe": asdict(recipe)}))
    assert reuse_demos(DataRecipe(teacher="oracle", seeds_per_task=4, max_episodes=40), path)
    assert not reuse_demos(DataRecipe(teacher="oracle", seeds_per_task=4, max_episodes=41), path)
    assert not reuse_demos(DataRecipe(teacher="oracle", seeds_per_task=4, max_episodes=40, action_noise=0.1), path)
    dagger = DataRecipe(teacher="oracle", seeds_per_task=4, max_episodes=40, dagger_checkpoint="ck")
    (tmp_path / "clean.npz.json").write_text(json.dumps({"recipe": asdict(dagger)}))
    assert not reuse_demos(dagger, path), "a DAgger set depends on the checkpoint's weights, never reused"


def test_pipeline_rounds_take_their_episodes_and_fresh_rounds_drop_the_older_sets() -> None:
    """Per-round episode counts (the last repeats); a fresh round keeps the clean set and its own rounds'."""
    from services.policy_worker.vla.train import PipelineConfig, _int_list

    pipe = PipelineConfig(dagger_rounds=3, dagger_episodes=[150, 300, 0], dagger_sampled_episodes=[0, 300],
                          fresh_from_round=2)
    assert [pipe.round_episodes(r) for r in range(3)] == [(150, 0), (300, 300), (0, 300)]
    assert PipelineConfig(dagger_episodes=150).round_episodes(2) == (150, 0), "a stored int still reads"  # type: ignore[arg-type]
    base = ["clean", "noisy"]
    dagger = [(0, "d1")]
    assert pipe.round_data(0, base, dagger) == ["clean", "noisy", "d1"], "round 1 aggregates"
    dagger += [(1, "d2"), (1, "d2s")]
    assert pipe.round_data(1, base, dagger) == ["clean", "d2", "d2s"], "the clean set anchors a fresh round"
    assert pipe.round_data(2, base, dagger + [(2, "d3s")]) == ["clean", "d2", "d2s", "d3s"]
    assert PipelineConfig().round_data(1, base, dagger) == ["clean", "noisy", "d1", "d2", "d2s"]
    assert _int_list("150") == [150] and _int_list("[150, 300]") == _int_list("150,300") == [150, 300]


def test_gaussian_start_is_seeded_per_request(instruction) -> None:
    """The same request draws the same x0 whatever else shares its batch and whichever policy
    instance serves it; another observation or another policy seed draws another one."""
    batch = _batch(3)
    a, b = state_policy(seed=5), state_policy(seed=5)
    assert a.noise == "gaussian"
    first = a.infer(batch, [instruction] * 3)
    assert np.array_equal(first, b.infer(batch, [instruction] * 3))
    assert np.array_equal(first, a.infer(batch, [instruction] * 3)), "a repeated request replays"
    seeds = a.request_seeds(a.state_inputs(batch), [instruction] * 3)
    assert len(set(seeds.tolist())) == 3, "each observation its own draw"
    other = state_policy(seed=6).request_seeds(a.state_inputs(batch), [instruction] * 3)
    assert not set(seeds.tolist()) & set(other.tolist())
    zero = state_policy(noise="zero").infer(batch, [instruction] * 3)
    assert not np.array_equal(first[..., :6], zero[..., :6])
    with pytest.raises(ValueError):
        state_policy(noise="uniform")


def test_batch_invariant_mode_makes_rows_independent_of_their_batch(instruction, monkeypatch) -> None:
    """Batched matmuls differ in the last bits with the batch size; in batch-invariant mode a
    request's actions are bit for bit the same alone, in a batch of 3 or of 8."""
    monkeypatch.setenv("ZETTA_VLA_BATCH_INVARIANT", "1")
    p = state_policy()
    batch = _batch(8)
    together = p.infer(batch, [instruction] * 8)
    alone = np.concatenate([p.infer({k: v[i:i + 1] for k, v in batch.items()}, [instruction]) for i in range(8)])
    three = p.infer({k: v[2:5] for k, v in batch.items()}, [instruction] * 3)
    assert np.array_equal(together, alone) and np.array_equal(three, together[2:5])


@pytest.mark.parametrize("noise", ["gaussian", "zero"])
def test_traced_action_expert_serves_the_eager_numbers_at_every_batch_size(instruction, noise) -> None:
    """The served stage 2 is a TorchScript trace made at batch 1; it gives the eager module's
    actions bit for bit at other batch sizes too (the flow time is built from the rows)."""
    traced, eager = state_policy(noise=noise), state_policy(noise=noise, trace=False)
    assert isinstance(traced._expert, torch.jit.ScriptModule) and eager._expert is eager.model.expert
    for b in (1, 3, 8):
        batch = _batch(b, seed=b)
        assert np.array_equal(traced.infer(batch, [instruction] * b), eager.infer(batch, [instruction] * b))


def test_traced_action_expert_with_a_quantized_expert(instruction) -> None:
    q = state_policy(quantize="expert.blocks")
    assert q.quantized == ["expert.blocks"]
    ref = state_policy(quantize="expert.blocks", trace=False)
    batch = _batch(4)
    assert np.array_equal(q.infer(batch, [instruction] * 4), ref.infer(batch, [instruction] * 4))


def test_gripper_snaps_to_the_three_commands_the_gripper_knows() -> None:
    from services.policy_worker.vla.model import VLAConfig, ZettaVLA

    class Fixed(torch.nn.Module):
        def forward(self, prefix, noise=None):
            g = torch.tensor([-0.9, -0.3, -0.1, 0.2, 0.6])
            return torch.cat([torch.full((5, 6), 3.0), g[:, None]], dim=1)[:, None, :]

    m = ZettaVLA(VLAConfig(width=8, prefix_hidden=8, expert_hidden=8, chunk=1))
    m.expert = Fixed()
    a = m.act(torch.zeros(5, 4, 8))
    assert a[:, 0, 6].tolist() == [-1.0, -1.0, 0.0, 0.0, 1.0]  # |g| < 0.25 holds the opening
    assert torch.all(a[..., :6] == 1.0)  # arm actions clamp to the action range


def test_image_variant_trains_and_runs_on_cpu(tmp_path, policy) -> None:
    from services.policy_worker.vla.features import IMAGE_INPUTS, PROPRIO_DIM
    from services.policy_worker.vla.model import VLAConfig
    from services.policy_worker.vla.train import TrainConfig, train

    rng = np.random.default_rng(1)
    instr = sorted(policy.text.cache)[:2]
    path = str(tmp_path / "demos.npz")
    np.savez(path, states=rng.standard_normal((6, 156)).astype(np.float32),
             actions=rng.uniform(-1, 1, (6, 7)).astype(np.float32), episode_lengths=np.array([4, 2]),
             instructions=np.array(instr), images=rng.integers(0, 255, (6, 32, 32, 3), dtype=np.uint8))
    meta = train([path], str(tmp_path / "ck"), VLAConfig(image_size=32, prefix_hidden=32, width=16, expert_hidden=16),
                 TrainConfig(steps=2, batch_size=4, warmup=1), log=lambda *_: None, text_cache=policy.text.cache)
    assert meta["training"]["steps_done"] == 2
    p = ZettaVLAPolicy(tmp_path / "ck", name="zetta-vla-image")
    names = {s.name for s in p.input_specs()}
    assert IMAGE_INPUTS[0] in names and "object_state" not in names
    batch = {n: (rng.standard_normal((3, w)) * 0.1).astype(np.float32) for n, w in STATE_INPUTS[:4]}
    batch[IMAGE_INPUTS[0]] = rng.integers(0, 255, (3, 32, 32, 3), dtype=np.uint8)
    assert sum(w for _, w in STATE_INPUTS[:4]) == PROPRIO_DIM
    assert p.infer(batch, [instr[0]] * 3).shape == (3, 8, 7)


@pytest.mark.gpu
def test_split_over_cuda_ipc_and_image_variant(tmp_path) -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from services.policy_worker.vla.model import VLAConfig, ZettaVLA

    m = ZettaVLA(VLAConfig(image_size=64)).cuda()
    loss = m.loss(torch.randn(4, 16, device="cuda"), torch.randn(4, 384, device="cuda"),
                  torch.randn(4, 8, 7, device="cuda"), torch.randint(0, 255, (4, 64, 64, 3), dtype=torch.uint8,
                                                                      device="cuda"))
    loss.backward()
    from services.policy_worker.vla.split import SplitVLA

    split = SplitVLA(str(STATE_CHECKPOINT), device="cuda", slots=64)
    try:
        assert split.prefixes.is_cuda
        b = _batch(1)
        instr = sorted(split.policy.text.cache)[0]
        out = asyncio.run(split.submit(InferItem("g", "m", {k: v[0] for k, v in b.items()}, instr,
                                                 deadline=time.monotonic() + 10)))
        assert out.shape == (8, 7)
    finally:
        split.close()


def test_a_wrist_camera_is_declared_and_read_by_an_encoder_of_its_own(tmp_path, policy) -> None:
    from services.common.policies import PROPRIO_INPUTS
    from services.policy_worker.vla.model import VLAConfig
    from services.policy_worker.vla.train import TrainConfig, train

    rng = np.random.default_rng(2)
    instr = sorted(policy.text.cache)[:1]
    path = str(tmp_path / "demos.npz")
    np.savez(path, states=rng.standard_normal((6, 156)).astype(np.float32),
             actions=rng.uniform(-1, 1, (6, 7)).astype(np.float32), episode_lengths=np.array([6]),
             instructions=np.array(instr), images=rng.integers(0, 255, (3, 2, 16, 16, 3), dtype=np.uint8),
             image_steps=np.array([0, 2, 4]))
    cams = ("agentview_image", "eye_in_hand_image")
    train([path], str(tmp_path / "ck"), VLAConfig(image_size=16, cameras=cams, prefix_hidden=16, width=8,
                                                  expert_hidden=8),
          TrainConfig(steps=2, batch_size=4, warmup=1), log=lambda *_: None, text_cache=policy.text.cache)
    p = ZettaVLAPolicy(tmp_path / "ck", name="zetta-vla-image", noise="zero")
    assert [s.name for s in p.input_specs()][-2:] == list(cams)
    assert p.model.cfg.cameras == cams and len(p.model.encoder.more_images) == 1
    batch = {n: (rng.standard_normal((2, w)) * 0.1).astype(np.float32) for n, w in PROPRIO_INPUTS}
    batch.update({c: rng.integers(0, 255, (2, 16, 16, 3), dtype=np.uint8) for c in cams})
    base = p.infer(batch, instr * 2)
    other = dict(batch, eye_in_hand_image=255 - batch["eye_in_hand_image"])
    assert not np.allclose(base, p.infer(other, instr * 2)), "the wrist frame reaches the actions"
    swapped = dict(batch, agentview_image=batch["eye_in_hand_image"], eye_in_hand_image=batch["agentview_image"])
    assert not np.allclose(base, p.infer(swapped, instr * 2)), "each camera has its own encoder"


@pytest.mark.parametrize("module", ["train", "data"])
@pytest.mark.parametrize("cameras", ["agentview_image,bogus", "eye_in_hand_image,eye_in_hand_image", ","])
def test_a_bad_cameras_option_is_a_usage_error_naming_the_choices(module: str, cameras: str, tmp_path, capsys) -> None:
    """zetta train and the data CLI refuse an unknown, repeated or empty camera list before any work,
    with exit status 2 and the cameras they accept."""
    import importlib

    main = importlib.import_module(f"services.policy_worker.vla.{module}").main
    with pytest.raises(SystemExit) as exc:
        main(["--cameras", cameras, "--out", str(tmp_path / "out")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --cameras" in err and "['agentview_image', 'eye_in_hand_image'], each once" in err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("suite", ["libero_goal_swap", "libero_goal_task", "libero_goal_lan", "libero_goal_object"])
def test_demos_are_never_collected_on_a_libero_pro_variant(suite: str, tmp_path, capsys) -> None:
    """The variants are what the policy is evaluated on: the recipe and the data CLI refuse them."""
    from services.policy_worker.vla.data import DataRecipe, main

    with pytest.raises(ValueError, match="LIBERO-PRO variant"):
        DataRecipe(suite=suite).episodes()
    with pytest.raises(SystemExit) as exc:
        main(["--suite", suite, "--tasks", "0", "--out", str(tmp_path / "d.npz")])
    assert exc.value.code == 2 and "LIBERO-PRO variant" in capsys.readouterr().err
    assert not (tmp_path / "d.npz.parts").exists()


def test_demos_on_another_libero_suite_name_their_tasks(tmp_path, capsys) -> None:
    """libero_goal's default task list means nothing on libero_90: the CLI asks for --tasks; the
    recipe lists that suite's episodes."""
    from services.policy_worker.vla.data import DataRecipe, main

    with pytest.raises(SystemExit) as exc:
        main(["--suite", "libero_90", "--out", str(tmp_path / "d.npz")])
    assert exc.value.code == 2 and "--tasks is required on libero_90" in capsys.readouterr().err
    recipe = DataRecipe(suite="libero_90", tasks=[9, 27], seeds_per_task=2, seed_offset=1000)
    assert recipe.episodes() == [(9, 1000, 0), (27, 1000, 0), (9, 1001, 1), (27, 1001, 1)]


def test_a_demo_process_that_dies_stops_the_collection_and_keeps_its_parts(tmp_path) -> None:
    """A worker that dies (here: a teacher that does not exist; in practice the OOM killer) fails the
    run with the command to continue, instead of assembling a set without its tasks."""
    from services.policy_worker.vla.data import DataRecipe, collect

    recipe = DataRecipe(tasks=[0], teacher="no-such-teacher", seeds_per_task=1, processes=1)
    out = tmp_path / "d.npz"
    with pytest.raises(RuntimeError, match="a demo process died .* rerun the same command to continue"):
        collect(recipe, str(out), log=lambda *_: None)
    assert not out.exists() and (tmp_path / "d.npz.parts" / "recipe.json").exists()
