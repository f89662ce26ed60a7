"""Export rollouts as a LeRobot-style dataset (v2 layout: parquet per episode, mp4 per camera, meta/).

One row per executed action: ``action`` (7 floats), ``observation.state`` (proprioception: eef
pos, eef quat, gripper qpos, joint pos) of the last recorded frame before that action (the trace
is recorded at the policy's call rate, so actions of one chunk share the chunk's first state),
``timestamp`` (env step / fps), ``frame_index``, ``episode_index``, ``index``, ``task_index``,
``next.done`` and ``next.success`` on the last row. Videos are the env worker's recordings.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from services.evolver.store import Rollout, RolloutStore

FPS = 20
STATE_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos", "robot0_joint_pos")
CAMERA = "observation.images.agentview"


def export_lerobot(store: RolloutStore, rollouts: Sequence[Rollout], out: Path, instructions: dict[str, str] | None = None,
                   robot_type: str = "panda") -> dict[str, Any]:
    """Write the dataset under ``out`` (must not exist); returns meta/info.json's content."""
    if out.exists():
        raise FileExistsError(f"{out} exists; export writes a new dataset")
    (out / "meta").mkdir(parents=True)
    tasks: dict[str, int] = {}
    episodes = []
    total = 0
    videos = 0
    state_dim = 0
    for ep, r in enumerate(rollouts):
        tr = store.trace(r)
        text = (instructions or {}).get(r.task, f"{r.suite}/{r.task}")
        tidx = tasks.setdefault(text, len(tasks))
        prev = np.clip(tr.action_frame - 1, 0, max(tr.frames - 1, 0))
        state = np.concatenate([tr.obs[k] for k in STATE_KEYS if k in tr.obs], axis=1)[prev]
        state_dim = state.shape[1]
        n = len(tr.actions)
        done = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        if n:
            done[-1] = True
            success[-1] = r.success
        steps = np.asarray(tr.frame_step)[np.clip(tr.action_frame, 0, max(tr.frames - 1, 0))]
        table = pa.table({
            "action": pa.array(list(tr.actions.astype(np.float32)), type=pa.list_(pa.float32(), 7)),
            "observation.state": pa.array(list(state.astype(np.float32)), type=pa.list_(pa.float32(), state_dim)),
            "timestamp": pa.array(np.arange(n, dtype=np.float32) / FPS),
            "env_step": pa.array(steps.astype(np.int64)),
            "frame_index": pa.array(np.arange(n, dtype=np.int64)),
            "episode_index": pa.array(np.full(n, ep, dtype=np.int64)),
            "index": pa.array(np.arange(total, total + n, dtype=np.int64)),
            "task_index": pa.array(np.full(n, tidx, dtype=np.int64)),
            "next.done": pa.array(done),
            "next.success": pa.array(success),
        })
        path = out / "data" / "chunk-000" / f"episode_{ep:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        if r.video_path:
            dest = out / "videos" / "chunk-000" / CAMERA / f"episode_{ep:06d}.mp4"
            dest.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(store.root / r.video_path, dest)
            videos += 1
        episodes.append({"episode_index": ep, "tasks": [text], "length": n, "success": r.success, "seed": r.seed,
                         "harness": r.harness or "bare", "source_key": r.key})
        total += n
    features: dict[str, Any] = {
        "action": {"dtype": "float32", "shape": [7], "names": ["dx", "dy", "dz", "drx", "dry", "drz", "gripper"]},
        "observation.state": {"dtype": "float32", "shape": [state_dim], "names": None},
        "timestamp": {"dtype": "float32", "shape": [1]}, "env_step": {"dtype": "int64", "shape": [1]},
        "frame_index": {"dtype": "int64", "shape": [1]}, "episode_index": {"dtype": "int64", "shape": [1]},
        "index": {"dtype": "int64", "shape": [1]}, "task_index": {"dtype": "int64", "shape": [1]},
        "next.done": {"dtype": "bool", "shape": [1]}, "next.success": {"dtype": "bool", "shape": [1]},
    }
    if videos:
        features[CAMERA] = {"dtype": "video", "shape": [None, None, 3], "names": ["height", "width", "channel"],
                            "video_info": {"video.fps": FPS, "video.codec": "mp4v"}}
    info = {"codebase_version": "v2.0", "robot_type": robot_type, "fps": FPS, "total_episodes": len(episodes),
            "total_frames": total, "total_tasks": len(tasks), "total_videos": videos, "total_chunks": 1,
            "chunks_size": 1000, "splits": {"train": f"0:{len(episodes)}"},
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
            "features": features}
    (out / "meta" / "info.json").write_text(json.dumps(info, indent=2) + "\n")
    (out / "meta" / "episodes.jsonl").write_text("".join(json.dumps(e) + "\n" for e in episodes))
    (out / "meta" / "tasks.jsonl").write_text("".join(json.dumps({"task_index": i, "task": t}) + "\n"
                                                      for t, i in tasks.items()))
    return info
