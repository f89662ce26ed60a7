"""Episode videos through the gateway: a session asks, the env worker writes the MP4.

The stack is private: its env worker runs with ZETTA_VIDEO_DIR and a 10 s heartbeat timeout.
Making a GL context uploads the scene's textures inside MuJoCo with the GIL held (about 1 s on a
2-core CPU renderer, more under load), and this test is about videos, not heartbeats. The files are on this machine, so the test opens them with OpenCV as a user of
the stack would. The worker side (frame counts, chunk-end rendering, errors) is covered without
a stack in tests/unit/test_rendering.py.
"""

from __future__ import annotations

from pathlib import Path

import cv2

from tests.conftest import LIFT
from zetta import Gateway


def video_stats(path: str) -> tuple[int, int, int]:
    """Frames read back, width, height."""
    cap = cv2.VideoCapture(path)
    assert cap.isOpened(), path
    frames, width, height = 0, 0, 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames, height, width = frames + 1, frame.shape[0], frame.shape[1]
    cap.release()
    return frames, width, height


async def test_run_episode_records_video(stack_factory, tmp_path: Path) -> None:
    """RunEpisode and Reset with record_video: one frame per executed action plus the reset's."""
    videos = tmp_path / "videos"
    stack = stack_factory(env_workers=1, slots=2, heartbeat_timeout_ms=10000, families=["robosuite"],
                          extra_env={"ZETTA_LOG_LEVEL": "INFO", "ZETTA_VIDEO_DIR": str(videos)})
    async with Gateway(stack.gateway_address) as gw:
        group = await gw.create_sessions("robosuite", n=2, env_config={**LIFT, "cameras": ["agentview"], "camera_size": 64})
        recorded = (await group.subset(group.ids[:1]).run_episode(task="", seed=3, max_steps=6, record_video=True))[0]
        plain = (await group.subset(group.ids[1:]).run_episode(task="", seed=3, max_steps=6))[0]
        assert Path(recorded.video_path) == videos.resolve() / f"{recorded.episode_id}.mp4"
        assert video_stats(recorded.video_path) == (recorded.steps + 1, 64, 64)
        assert plain.video_path == ""
        # A reset says where the episode's video goes; a plain reset records nothing.
        reset = await group[0].reset(seed=4, record_video=True)
        assert Path(reset.video_path).name == f"{reset.episode_id}.mp4"
        assert (await group[1].reset(seed=4)).video_path == ""
        await group.close()
        assert video_stats(reset.video_path)[0] == 1  # closing the session completes the file
