"""The LeRobot v3.0 export loads with LeRobot's own ``LeRobotDataset`` (PyPI ``lerobot-dataset``), offline.

The store holds constructed rollouts whose videos the env worker's ``VideoRecorder`` wrote, one
flat grey level per frame, so every decoded camera frame names the recorded frame it came from.

``lerobot-dataset`` imports torchvision at module level; torchvision's PyPI wheels are CUDA builds
that do not load next to the CPU torch this project pins. Its loading path for a video dataset
uses neither (rows come from parquet, frames from torchcodec), so when torchvision cannot be
imported the test stands in an empty module whose every use raises, which proves it unused.
"""

from __future__ import annotations

import importlib
import sys
import types
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from services.env_worker.video import VideoRecorder
from services.evolver.lerobot_export import CAMERA, export_lerobot
from services.evolver.lerobot_video import read_frames
from services.evolver.store import EpisodeKey, Outcome, RolloutStore
from tests.unit.test_evolver_fixtures import K, make_trace

INSTRUCTION = "put the cream cheese in the bowl"
SIZE = 32


def _level(frame: int) -> int:
    return 40 + 3 * frame


def _recorded_video(path: Path, frames: int) -> str:
    rec = VideoRecorder(str(path), 20, SIZE, SIZE)
    for i in range(frames):
        rec.add(np.full((SIZE, SIZE, 3), _level(i), np.uint8))
    return rec.close()


def _store(tmp_path: Path, videos: bool) -> RolloutStore:
    s = RolloutStore(tmp_path / "store")
    s.assign_splits("libero_goal", "6", dev=2, heldout=1)
    for seed, kind in ((2, "success"), (3, "drop")):
        tr = make_trace(kind, seed)
        video = _recorded_video(tmp_path / f"{seed}.mp4", len(tr.actions) + 1) if videos else ""
        s.add(EpisodeKey("libero_goal", "6", seed, "", "profile"),
              Outcome(kind == "success", int(tr.frame_step[-1]), "", [], tr, video, 1.0))
    return s


def _unusable_torchvision() -> types.ModuleType:
    def refuse(name: str):
        def call(*_a, **_k):
            raise AssertionError(f"torchvision.{name} was used while loading the export")
        return call

    tv = types.ModuleType("torchvision")
    tv.transforms = types.SimpleNamespace(ToTensor=refuse("transforms.ToTensor"))
    tv.io = types.SimpleNamespace(VideoReader=refuse("io.VideoReader"))
    tv.set_video_backend = refuse("set_video_backend")
    return tv


@pytest.fixture()
def lerobot(monkeypatch: pytest.MonkeyPatch) -> types.ModuleType:
    """``ledataset.datasets.lerobot_dataset``, offline, decoding with torchcodec."""
    pytest.importorskip("ledataset", reason="PyPI lerobot-dataset is not installed")
    pytest.importorskip("torchcodec", reason="torchcodec (LeRobot's video decoder) is not installed")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    try:
        importlib.import_module("torchvision")
    except (ImportError, RuntimeError):
        importlib.import_module("datasets")  # it probes for torchvision once; let it find none
        monkeypatch.setitem(sys.modules, "torchvision", _unusable_torchvision())
        for name in [m for m in sys.modules if m.startswith("ledataset")]:
            monkeypatch.delitem(sys.modules, name)
    return importlib.import_module("ledataset.datasets.lerobot_dataset")


def test_export_loads_with_lerobot_dataset(tmp_path: Path, lerobot: types.ModuleType) -> None:
    """Every row's action, state, task and camera frame come back as the store has them."""
    s = _store(tmp_path, videos=True)
    rollouts = s.query()
    info = export_lerobot(s, rollouts, tmp_path / "ds", {("libero_goal", "6"): INSTRUCTION})
    assert info["codebase_version"] == "v3.0" and info["features"][CAMERA]["shape"] == [SIZE, SIZE, 3]
    ds = lerobot.LeRobotDataset("zetta/export-test", root=tmp_path / "ds", video_backend="torchcodec")
    rows = 2 * (K - 1)
    assert len(ds) == 2 * rows and ds.meta.total_episodes == 2 and ds.fps == 20
    assert list(ds.meta.tasks.index) == [INSTRUCTION]
    assert set(ds.meta.stats) >= {"action", "observation.state", CAMERA}
    for ep, r in enumerate(rollouts):
        tr = s.trace(r)
        before = np.clip(tr.action_frame - 1, 0, tr.frames - 1)
        source = read_frames(s.root / r.video_path, rows + 1).reshape(rows + 1, -1).mean(1)
        for i in range(0, rows, 7):
            item = ds[ep * rows + i]
            assert item["episode_index"].item() == ep and item["frame_index"].item() == i
            np.testing.assert_allclose(item["action"].numpy(), tr.actions[i])
            np.testing.assert_allclose(item["observation.state"].numpy()[:3], tr.obs["robot0_eef_pos"][before[i]])
            assert item["task"] == INSTRUCTION
            frame = item[CAMERA].numpy()
            assert frame.shape == (3, SIZE, SIZE)
            nearest = int(np.argmin(np.abs(source - frame.mean() * 255)))
            assert nearest == i and abs(source[i] - frame.mean() * 255) < 2, (ep, i, frame.mean() * 255, source[i])
        assert ds[ep * rows + rows - 1]["next.done"].item()
    stats = ds.meta.stats
    np.testing.assert_allclose(stats["action"]["max"][6], 1.0)
    assert stats[CAMERA]["mean"].shape == (3, 1, 1)


def test_export_without_videos_and_refusals(tmp_path: Path, lerobot: types.ModuleType) -> None:
    """Rollouts without videos export rows only; an existing directory and an empty selection are refused."""
    s = _store(tmp_path, videos=False)
    info = export_lerobot(s, s.query(), tmp_path / "ds")
    assert CAMERA not in info["features"] and info["video_path"] is None
    ds = lerobot.LeRobotDataset("zetta/export-test", root=tmp_path / "ds")
    assert ds[0]["task"] == "libero_goal/6"
    episodes = pq.read_table(tmp_path / "ds" / "meta" / "episodes" / "chunk-000" / "file-000.parquet").to_pylist()
    assert [e["success"] for e in episodes] == [True, False] and episodes[1]["dataset_from_index"] == 2 * (K - 1)
    with pytest.raises(FileExistsError):
        export_lerobot(s, s.query(), tmp_path / "ds")
    with pytest.raises(ValueError, match="no rollouts"):
        export_lerobot(s, [], tmp_path / "empty")


def test_instructions_come_from_libero() -> None:
    """The task text is what the env worker gives the policy, LIBERO-PRO's redirected one included."""
    pytest.importorskip("libero")
    from services.evolver.instructions import libero_instructions

    got = libero_instructions([("libero_goal", "6"), ("libero_goal_task", "6"), ("robosuite", "Lift")])
    assert got == {("libero_goal", "6"): "put the cream cheese in the bowl",
                   ("libero_goal_task", "6"): "put the wine bottle in the bowl"}
