"""Episode videos for a LeRobot dataset: decode the env worker's recording, re-encode it frame-exact.

LeRobot's loader decodes a camera frame by its timestamp (row ``i`` at ``i / fps``, tolerance
1e-4 s), so the file must hold exactly one frame per row at constant rate. The env worker's
recording has one more frame (the observation after the last action), in MPEG-4 Part 2, which
browsers and LeRobot's visualiser cannot play; the export writes H.264 (yuv420p) with PyAV.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

CODEC = "libx264"
PIX_FMT = "yuv420p"


def read_frames(path: Path, limit: int) -> np.ndarray:
    """The first ``limit`` RGB frames of ``path`` as [N, H, W, 3] uint8 (fewer if the file is shorter)."""
    import av

    frames = []
    with av.open(str(path)) as container:
        for frame in container.decode(video=0):
            if len(frames) == limit:
                break
            frames.append(frame.to_ndarray(format="rgb24"))
    if not frames:
        raise ValueError(f"{path}: the video has no frames")
    return np.stack(frames)


def write_frames(path: Path, frames: np.ndarray, fps: int) -> dict[str, object]:
    """Encode [N, H, W, 3] uint8 frames at ``fps``; returns LeRobot's ``video_info`` of the file."""
    import av

    n, height, width, _ = frames.shape
    if height % 2 or width % 2:
        frames = frames[:, : height - height % 2, : width - width % 2]
        n, height, width, _ = frames.shape
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as container:
        stream = container.add_stream(CODEC, rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, PIX_FMT
        stream.time_base = Fraction(1, fps)
        stream.options = {"g": "2", "crf": "18"}
        for i, rgb in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
            frame.pts = i
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return {"video.height": height, "video.width": width, "video.codec": "h264", "video.pix_fmt": PIX_FMT,
            "video.is_depth_map": False, "video.fps": fps, "video.channels": 3, "has_audio": False}
