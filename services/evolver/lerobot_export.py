"""Export stored rollouts as a LeRobot dataset, format v3.0 (what ``LeRobotDataset(root=...)`` loads).

Layout (LeRobot v3.0): ``meta/info.json``, ``meta/stats.json``, ``meta/tasks.parquet`` (the
instruction text is the task), ``meta/episodes/chunk-000/file-000.parquet`` (one row per episode:
length, tasks, where its rows and video lie, per-episode stats), ``data/chunk-000/file-000.parquet``
(one row per executed action) and, when the rollouts recorded videos, one H.264 file per episode
under ``videos/observation.images.agentview/chunk-CCC/file-FFF.mp4``.

Columns match what the image VLA reads (services/common/policies.py, PROPRIO_INPUTS), so a LeRobot
policy can be trained on Zetta rollouts: ``observation.images.agentview`` (the recorded camera
frame before the action), ``observation.state`` (eef pos 3, eef quat 4, gripper qpos 2, joint pos 7)
and ``action`` (7). The trace is recorded at the policy's call rate, so the actions of one chunk
share the state of the chunk's first frame; the camera frame is per action. Zetta's own columns:
``env_step``, ``next.done``, ``next.success``; the episode rows add ``seed``, ``harness``,
``success`` and the store key.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from services.evolver.lerobot_video import read_frames, write_frames
from services.evolver.store import Rollout, RolloutStore
from services.common.policies import ACTION_DIM, PROPRIO_INPUTS
from services.common.progress import progress

CODEBASE_VERSION = "v3.0"
FPS = 20
CHUNKS_SIZE = 1000
CAMERA = "observation.images.agentview"
STATE_NAMES = [f"{name}.{i}" for name, width in PROPRIO_INPUTS for i in range(width)]
ACTION_NAMES = ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)

_SCALARS = {"timestamp": "float32", "env_step": "int64", "frame_index": "int64", "episode_index": "int64",
            "index": "int64", "task_index": "int64", "next.done": "bool", "next.success": "bool"}


def export_lerobot(store: RolloutStore, rollouts: Sequence[Rollout], out: Path,
                   instructions: Mapping[tuple[str, str], str] | None = None, robot_type: str = "panda") -> dict[str, Any]:
    """Write the dataset under ``out`` (must not exist); returns meta/info.json's content.

    ``instructions`` maps a rollout's (suite, task) to its instruction text; a task without one is named
    ``suite/task`` so the export still loads, but a policy trained on it sees no instruction."""
    if out.exists():
        raise FileExistsError(f"{out} exists; export writes a new dataset")
    if not rollouts:
        raise ValueError("no rollouts to export: check --task/--harness against `zetta evolve` store contents")
    with_video = all(r.video_path for r in rollouts)
    tasks: dict[str, int] = {}
    tables, episodes, ep_stats = [], [], []
    video_info: dict[str, Any] = {}
    total = 0
    for ep, r in enumerate(progress(rollouts, desc="export")):
        text = (instructions or {}).get((r.suite, r.task), f"{r.suite}/{r.task}")
        columns = _episode_columns(store, r, ep, total, tasks.setdefault(text, len(tasks)))
        n = len(columns["action"])
        episode: dict[str, Any] = {"episode_index": ep, "tasks": [text], "length": n, "data/chunk_index": 0,
                                   "data/file_index": 0, "dataset_from_index": total, "dataset_to_index": total + n}
        stats = {k: _stats(v) for k, v in columns.items()}
        if with_video:
            chunk, file = divmod(ep, CHUNKS_SIZE)
            frames = read_frames(store.root / r.video_path, n)
            if len(frames) < n:
                raise ValueError(f"{r.key}: its video has {len(frames)} frames for {n} actions")
            video_info = write_frames(out / VIDEO_PATH.format(video_key=CAMERA, chunk_index=chunk, file_index=file),
                                      frames, FPS)
            stats[CAMERA] = _image_stats(frames)
            episode.update({f"videos/{CAMERA}/chunk_index": chunk, f"videos/{CAMERA}/file_index": file,
                            f"videos/{CAMERA}/from_timestamp": 0.0, f"videos/{CAMERA}/to_timestamp": n / FPS})
        episode.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0, "success": r.success,
                        "seed": r.seed, "harness": r.harness or "bare", "source_key": r.key})
        episode.update({f"stats/{k}/{s}": v.tolist() for k, st in stats.items() for s, v in st.items()})
        tables.append(_table(columns))
        episodes.append(episode)
        ep_stats.append(stats)
        total += n
    features = _features(tables[0].schema.field("observation.state").type.list_size, video_info)
    info = {"codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": len(episodes),
            "total_frames": total, "total_tasks": len(tasks), "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": 100, "video_files_size_in_mb": 200, "fps": FPS,
            "splits": {"train": f"0:{len(episodes)}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if video_info else None, "features": features}
    (out / "data" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.concat_tables(tables), out / DATA_PATH.format(chunk_index=0, file_index=0))
    (out / EPISODES_PATH).parent.mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(episodes), out / EPISODES_PATH)
    pd.DataFrame({"task_index": list(tasks.values())}, index=pd.Index(list(tasks), name="task")).to_parquet(
        out / "meta" / "tasks.parquet")
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=4) + "\n")
    (out / "meta" / "stats.json").write_text(json.dumps(_serial(_aggregate(ep_stats)), indent=4) + "\n")
    return info


def _episode_columns(store: RolloutStore, r: Rollout, ep: int, start: int, task: int) -> dict[str, np.ndarray]:
    """One row per executed action of rollout ``r``."""
    tr = store.trace(r)
    missing = [name for name, _ in PROPRIO_INPUTS if name not in tr.obs]
    if missing:
        raise ValueError(f"{r.key}: its trace lacks {missing}; observation.state needs {[n for n, _ in PROPRIO_INPUTS]}")
    last = max(tr.frames - 1, 0)
    before = np.clip(tr.action_frame - 1, 0, last)
    state = np.concatenate([np.asarray(tr.obs[name], np.float32).reshape(tr.frames, w) for name, w in PROPRIO_INPUTS],
                           axis=1)[before]
    n = len(tr.actions)
    done = np.zeros(n, dtype=bool)
    success = np.zeros(n, dtype=bool)
    if n:
        done[-1] = True
        success[-1] = r.success
    return {"action": np.asarray(tr.actions, np.float32).reshape(n, ACTION_DIM), "observation.state": state,
            "timestamp": np.arange(n, dtype=np.float32) / FPS,
            "env_step": np.asarray(tr.frame_step, np.int64)[np.clip(tr.action_frame, 0, last)],
            "frame_index": np.arange(n, dtype=np.int64), "episode_index": np.full(n, ep, np.int64),
            "index": np.arange(start, start + n, dtype=np.int64), "task_index": np.full(n, task, np.int64),
            "next.done": done, "next.success": success}


def _table(columns: Mapping[str, np.ndarray]) -> pa.Table:
    arrays = {}
    for name, values in columns.items():
        if values.ndim == 2:
            flat = pa.array(values.reshape(-1), type=pa.float32())
            arrays[name] = pa.FixedSizeListArray.from_arrays(flat, values.shape[1])
        else:
            arrays[name] = pa.array(values)
    return pa.table(arrays)


def _features(state_dim: int, video_info: Mapping[str, Any]) -> dict[str, Any]:
    features: dict[str, Any] = {
        "action": {"dtype": "float32", "shape": [ACTION_DIM], "names": ACTION_NAMES},
        "observation.state": {"dtype": "float32", "shape": [state_dim], "names": STATE_NAMES},
    }
    features.update({k: {"dtype": t, "shape": [1], "names": None} for k, t in _SCALARS.items()})
    if video_info:
        features[CAMERA] = {"dtype": "video", "shape": [video_info["video.height"], video_info["video.width"], 3],
                            "names": ["height", "width", "channels"], "info": dict(video_info)}
    return features


def _stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's per-feature statistics over rows: min, max, mean, std, count and quantiles."""
    x = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    if not len(x):
        x = np.zeros((1, x.shape[1]))
    out = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0), "count": np.array([len(values)])}
    out.update({f"q{int(q * 100):02d}": np.quantile(x, q, axis=0) for q in QUANTILES})
    return out


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics of frames scaled to [0, 1], shaped (3, 1, 1) as LeRobot keeps them."""
    pixels = frames.reshape(-1, 3).astype(np.float64) / 255.0
    st = _stats(pixels)
    st["count"] = np.array([len(frames)])
    return {k: (v if k == "count" else v.reshape(3, 1, 1)) for k, v in st.items()}


def _aggregate(per_episode: Sequence[Mapping[str, Mapping[str, np.ndarray]]]) -> dict[str, dict[str, np.ndarray]]:
    """Dataset statistics from per-episode ones: exact min/max/mean/std, count-weighted quantiles."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for key in per_episode[0]:
        eps = [e[key] for e in per_episode]
        counts = np.array([float(e["count"][0]) for e in eps])
        w = (counts / counts.sum()).reshape(-1, *([1] * eps[0]["mean"].ndim))
        means = np.stack([e["mean"] for e in eps])
        mean = (w * means).sum(0)
        var = (w * (np.stack([e["std"] for e in eps]) ** 2 + (means - mean) ** 2)).sum(0)
        agg = {"min": np.min([e["min"] for e in eps], axis=0), "max": np.max([e["max"] for e in eps], axis=0),
               "mean": mean, "std": np.sqrt(var), "count": np.array([int(counts.sum())])}
        agg.update({f"q{int(q * 100):02d}": (w * np.stack([e[f"q{int(q * 100):02d}"] for e in eps])).sum(0)
                    for q in QUANTILES})
        out[key] = agg
    return out


def _serial(stats: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {k: {s: v.tolist() for s, v in st.items()} for k, st in stats.items()}

