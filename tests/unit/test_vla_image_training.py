"""The image VLA's data and training mechanics: frames at the policy-call stride, runs that
resume where they were cut off, the shift augmentation, the start-up input check."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from services.common.specs import TensorSpec, render_config  # noqa: E402
from services.policy_worker.vla.data import DataRecipe, _load_episode, _save_episode, episode_key  # noqa: E402
from services.policy_worker.vla.model import VLAConfig  # noqa: E402
from services.policy_worker.vla.train import Resume, TrainConfig, load_demos, random_shift, train  # noqa: E402

TEXT = {"put the bowl on the plate": np.linspace(-1, 1, 384).astype(np.float32),
        "open the top drawer": np.linspace(1, -1, 384).astype(np.float32)}


def test_render_config_follows_the_declared_cameras() -> None:
    specs = [TensorSpec("robot0_eef_pos", "float32", (3,)), TensorSpec("agentview_image", "uint8", (64, 64, 3))]
    assert render_config(specs) == {"cameras": ["agentview"], "camera_size": 64, "reflections": False, "antialias": True}
    assert render_config(specs[:1]) == {}


def test_sessions_render_as_the_checkpoint_was_trained() -> None:
    """Frames of a new recipe are single-sampled (cheaper); a checkpoint whose recipes predate the
    choice was trained on multisampled frames, and its sessions keep rendering that way."""
    from services.common.policies import trained_antialiased
    from services.policy_worker.vla.features import image_env_config

    assert image_env_config(64)["antialias"] is False
    assert DataRecipe(image_size=64).antialias is False
    assert episode_key(DataRecipe(image_size=64)) != episode_key(DataRecipe(image_size=64, antialias=True))
    old, new = {"recipe": {"image_size": 64}}, {"recipe": {"image_size": 64, "antialias": False}}
    assert trained_antialiased({"data": {"recipes": [old]}}) is True
    assert trained_antialiased({"data": {"recipes": [new, {"recipe": {"image_size": 0}}]}}) is False
    assert trained_antialiased({"data": {"recipes": [new, old]}}) is True


def test_episode_parts_round_trip_and_key_ignores_counts(tmp_path) -> None:
    rng = np.random.default_rng(0)
    states, actions = rng.standard_normal((9, 156)).astype(np.float32), rng.standard_normal((9, 7)).astype(np.float32)
    images, frames = rng.integers(0, 255, (3, 8, 8, 3), dtype=np.uint8), np.array([0, 4, 8])
    _save_episode(str(tmp_path), (3, 1007, 7, "open the top drawer", True, states, actions, images, frames))
    _save_episode(str(tmp_path), (4, 1007, 7, "RuntimeError('reset')", False, None, None, None, None))
    back = _load_episode(str(tmp_path / "3_1007.npz"))
    assert back[:5] == (3, 1007, 7, "open the top drawer", True)
    assert np.array_equal(back[5], states) and np.array_equal(back[7], images) and np.array_equal(back[8], frames)
    failed = _load_episode(str(tmp_path / "4_1007.npz"))
    assert failed[4] is False and failed[5] is None
    assert not list(tmp_path.glob(".*tmp*")), "parts are written atomically"
    a = DataRecipe(image_size=64, seeds_per_task=30, max_episodes=300, processes=2)
    assert episode_key(a) == episode_key(DataRecipe(image_size=64, seeds_per_task=20, max_episodes=200, processes=1))
    assert episode_key(a) != episode_key(DataRecipe(image_size=64, action_noise=0.1))
    assert episode_key(a) != episode_key(DataRecipe(image_size=96))


def test_frames_index_the_transitions_they_were_taken_at(tmp_path) -> None:
    """Two demo files with frames every 2 steps: samples map to the right global transition."""
    paths = []
    for k, n in enumerate((5, 4)):
        p = str(tmp_path / f"d{k}.npz")
        np.savez(p, states=np.full((n, 156), k, np.float32), actions=np.zeros((n, 7), np.float32),
                 episode_lengths=np.array([n]), instructions=np.array(["open the top drawer"]),
                 images=np.zeros((len(range(0, n, 2)), 8, 8, 3), np.uint8), image_steps=np.arange(0, n, 2))
        paths.append(p)
    demos = load_demos(paths)
    assert demos["image_steps"].tolist() == [0, 2, 4, 5, 7]
    assert demos["states"][demos["image_steps"]][:, 0].tolist() == [0, 0, 0, 1, 1]


def test_random_shift_moves_content_within_the_pad() -> None:
    img = torch.zeros(64, 16, 16, 3, dtype=torch.uint8)
    img[:, 8, 8] = 255
    out = random_shift(img, 2)
    assert out.shape == img.shape and out.dtype == torch.uint8
    ys, xs = torch.nonzero(out[..., 0] == 255, as_tuple=True)[1:]
    assert ys.min() >= 6 and ys.max() <= 10 and xs.min() >= 6 and xs.max() <= 10
    assert len({(int(y), int(x)) for y, x in zip(ys, xs)}) > 1, "different frames get different shifts"
    assert torch.equal(random_shift(img, 0), img)


def _image_demos(tmp_path) -> str:
    rng = np.random.default_rng(2)
    path = str(tmp_path / "demos.npz")
    np.savez(path, states=rng.standard_normal((12, 156)).astype(np.float32),
             actions=rng.uniform(-1, 1, (12, 7)).astype(np.float32), episode_lengths=np.array([8, 4]),
             instructions=np.array(sorted(TEXT)), images=rng.integers(0, 255, (6, 16, 16, 3), dtype=np.uint8),
             image_steps=np.array([0, 2, 4, 6, 8, 10]))
    return path


def test_resume_restores_the_exact_state(tmp_path) -> None:
    path = _image_demos(tmp_path)
    model = VLAConfig(image_size=16, prefix_hidden=16, width=8, expert_hidden=8)
    cfg = TrainConfig(steps=6, batch_size=4, warmup=1, checkpoint_every=3)
    straight = train([path], str(tmp_path / "a"), model, cfg, log=lambda *_: None, text_cache=dict(TEXT))

    class Cut(Exception):
        """The run is killed right after its step-3 training state reached the disk."""

    import services.policy_worker.vla.train as t

    saved = {}
    original = t.Resume.save

    def save_then_stop(self, step, *a, **kw):
        original(self, step, *a, **kw)
        saved["step"] = step
        raise Cut()

    t.Resume.save = save_then_stop
    try:
        with pytest.raises(Cut):
            train([path], str(tmp_path / "b"), model, cfg, log=lambda *_: None, text_cache=dict(TEXT))
    finally:
        t.Resume.save = original
    assert saved["step"] == 3
    logs: list[str] = []
    resumed = train([path], str(tmp_path / "b"), model, cfg, log=logs.append, text_cache=dict(TEXT))
    assert any("resuming training at step 3" in m for m in logs)
    a = torch.load(tmp_path / "a" / "model.pt")
    b = torch.load(tmp_path / "b" / "model.pt")
    assert all(torch.equal(a[k], b[k]) for k in a), "resumed weights equal the uninterrupted run's"
    assert resumed["training"]["steps_done"] == straight["training"]["steps_done"] == 6
    assert not Resume(str(tmp_path / "b"), cfg, model, "").path.exists(), "a finished run leaves no state behind"


def test_resume_state_of_another_configuration_is_not_used(tmp_path) -> None:
    model = VLAConfig(image_size=16, prefix_hidden=16, width=8, expert_hidden=8)
    cfg = TrainConfig(steps=6, batch_size=4, warmup=1)
    net = torch.nn.Linear(2, 2)
    opt = torch.optim.AdamW(net.parameters())
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 1.0)
    Resume(str(tmp_path / "ck"), cfg, model, "").save(3, net, opt, sched, [0.5], 1.0)
    logs: list[str] = []
    other = Resume(str(tmp_path / "ck"), TrainConfig(**{**cfg.__dict__, "lr": 1e-4}), model, "")
    assert other.restore(net, opt, sched, logs.append) == 0 and "another configuration" in logs[0]
    assert Resume(str(tmp_path / "ck"), cfg, model, "").restore(net, opt, sched, logs.append) == 3


def test_input_check_names_the_tensor_a_family_cannot_supply() -> None:
    from services.common.config import ConfigError
    from services.policy_worker.input_check import check_models

    class Declares:
        def __init__(self, *specs: TensorSpec) -> None:
            self.specs = list(specs)

        def input_specs(self) -> list[TensorSpec]:
            return self.specs

    ok = Declares(TensorSpec("robot0_eef_pos", "float32", (3,)), TensorSpec("agentview_image", "uint8", (64, 64, 3)))
    check_models({"ok": ok}, "libero")
    with pytest.raises(ConfigError, match=r"model 'cam': .*unknown cameras \['wrist'\]"):
        check_models({"cam": Declares(TensorSpec("wrist_image", "uint8", (64, 64, 3)))}, "libero")
    with pytest.raises(ConfigError, match=r"model 'typo' reads robot0_eef_pose \(not in the family"):
        check_models({"typo": Declares(TensorSpec("robot0_eef_pose", "float32", (3,)))}, "libero")
    with pytest.raises(ConfigError, match=r"robot0_joint_pos \(declared float32\[6\], the family supplies float32\[7\]"):
        check_models({"shape": Declares(TensorSpec("robot0_joint_pos", "float32", (6,)))}, "libero")


def test_recipes_record_the_cameras_the_model_reads() -> None:
    from services.policy_worker.vla.features import image_env_config

    both = ["agentview_image", "eye_in_hand_image"]
    assert DataRecipe(image_size=64).cameras == ["agentview_image"]
    assert episode_key(DataRecipe(image_size=64)) != episode_key(DataRecipe(image_size=64, cameras=both))
    assert image_env_config(64, cameras=tuple(both))["cameras"] == ["agentview", "robot0_eye_in_hand"]
    with pytest.raises(ValueError, match="eye_in_hand_image"):
        VLAConfig(image_size=64, cameras=("agentview_image", "frontview_image"))
    with pytest.raises(ValueError, match="each once"):
        VLAConfig(image_size=64, cameras=("agentview_image", "agentview_image"))


def test_random_shift_draws_each_cameras_shift_on_its_own() -> None:
    torch.manual_seed(0)
    frames = torch.zeros(64, 2, 12, 12, 3, dtype=torch.uint8)
    frames[:, :, 6, 6] = 255
    out = random_shift(frames, 2)
    assert out.shape == frames.shape
    spots = [tuple(torch.nonzero(out[b, v, :, :, 0] == 255)[0].tolist()) for b in range(64) for v in range(2)]
    assert all(4 <= r <= 8 and 4 <= c <= 8 for r, c in spots)
    assert sum(spots[2 * b] != spots[2 * b + 1] for b in range(64)) > 32


def test_training_refuses_frames_of_other_cameras_than_the_model_reads(tmp_path) -> None:
    rng = np.random.default_rng(0)
    path = str(tmp_path / "d.npz")
    np.savez(path, states=rng.standard_normal((4, 156)).astype(np.float32),
             actions=rng.uniform(-1, 1, (4, 7)).astype(np.float32), episode_lengths=np.array([4]),
             instructions=np.array(["open the top drawer"]),
             images=rng.integers(0, 255, (2, 1, 16, 16, 3), dtype=np.uint8), image_steps=np.array([0, 2]))
    cfg = VLAConfig(image_size=16, cameras=("agentview_image", "eye_in_hand_image"), width=8, prefix_hidden=8,
                    expert_hidden=8)
    with pytest.raises(ValueError, match="1 camera image"):
        train([path], str(tmp_path / "ck"), cfg, TrainConfig(steps=1, batch_size=2), log=lambda *_: None,
              text_cache=TEXT)


def test_a_fine_tune_keeps_the_cameras_of_the_checkpoint_it_starts_from(tmp_path) -> None:
    """With ``init``, the demos are checked against the starting checkpoint's cameras, not the
    caller's model configuration (the CLI's defaults), and the result reads what it read."""
    rng = np.random.default_rng(1)

    def demos(name: str, cameras: int) -> str:
        path = str(tmp_path / name)
        np.savez(path, states=rng.standard_normal((8, 156)).astype(np.float32),
                 actions=rng.uniform(-1, 1, (8, 7)).astype(np.float32), episode_lengths=np.array([8]),
                 instructions=np.array(["open the top drawer"]),
                 images=rng.integers(0, 255, (4, cameras, 16, 16, 3), dtype=np.uint8), image_steps=np.arange(0, 8, 2))
        return path

    both = ("agentview_image", "eye_in_hand_image")
    small = dict(image_size=16, width=8, prefix_hidden=8, expert_hidden=8)
    quiet = dict(log=lambda *_: None, text_cache=TEXT)
    train([demos("two.npz", 2)], str(tmp_path / "base"), VLAConfig(**small, cameras=both),
          TrainConfig(steps=1, batch_size=2), **quiet)
    agentview_only = VLAConfig(image_size=64)
    train([demos("two-more.npz", 2)], str(tmp_path / "tuned"), agentview_only, TrainConfig(steps=1, batch_size=2),
          init=str(tmp_path / "base"), **quiet)
    saved = json.loads((tmp_path / "tuned" / "config.json").read_text())["model"]
    assert tuple(saved["cameras"]) == both and saved["image_size"] == 16
    with pytest.raises(ValueError, match=f"the model of {re.escape(str(tmp_path / 'base'))} reads .*--cameras {','.join(both)}"):
        train([demos("one.npz", 1)], str(tmp_path / "bad"), agentview_only, TrainConfig(steps=1, batch_size=2),
              init=str(tmp_path / "base"), **quiet)
