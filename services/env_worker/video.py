"""Episode videos: MP4 files (OpenCV ``VideoWriter``, ``mp4v``) written by the env worker.

A session asks for a video per episode (``ResetSpec.record_video``). The worker writes
``$ZETTA_VIDEO_DIR/<episode_id>.mp4`` with one frame after the reset and one per executed action,
at the environment's control rate (20 fps for robosuite and LIBERO), showing the session's
cameras side by side (``agentview`` when the session renders none). The file is complete when
the episode ends, when the next reset starts, when the slot closes, or when a ``RunEpisodes``
call returns; the result that completes it carries its path (``video_path``).

``ZETTA_VIDEO_DIR`` is checked when the worker starts (:func:`check_video_dir`): a worker that
cannot write there refuses to start instead of failing the first episode that asks.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

#: FourCC of the codec: MPEG-4 Part 2, which every OpenCV build can write without extra libraries.
FOURCC = "mp4v"


class VideoError(RuntimeError):
    """A video cannot be written (no writable directory, codec unavailable, bad frame)."""


def check_video_dir(path: str) -> str:
    """Create ``path`` if needed and prove it writable; returns the absolute path, or raises VideoError."""
    if not path:
        raise VideoError("no video directory is configured (ZETTA_VIDEO_DIR)")
    target = Path(path).expanduser()
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise VideoError(f"{path}: cannot create the video directory: {exc.strerror or exc}") from None
    if not target.is_dir():
        raise VideoError(f"{path}: not a directory")
    try:
        with tempfile.NamedTemporaryFile(dir=target, prefix=".zetta-write-check-"):
            pass
    except OSError as exc:
        raise VideoError(f"{path}: not writable: {exc.strerror or exc}") from None
    return str(target.resolve())


class VideoRecorder:
    """Writes RGB frames of one episode to an MP4 file; frames must all have one size."""

    def __init__(self, path: str, fps: float, width: int, height: int) -> None:
        import cv2

        self.path = path
        self.size = (width, height)
        self.frames = 0
        self._cv2 = cv2
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self._writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*FOURCC), float(fps), (width, height))
        if not self._writer.isOpened():
            self._writer.release()
            raise VideoError(f"{path}: OpenCV cannot open an {FOURCC} writer at {width}x{height}")

    @property
    def closed(self) -> bool:
        """The file is complete and no more frames are taken."""
        return self._writer is None

    def add(self, rgb: np.ndarray) -> None:
        """Append one frame, uint8 of shape (height, width, 3), row 0 at the top."""
        if self._writer is None:
            raise VideoError(f"{self.path}: the recording is finished")
        if rgb.dtype != np.uint8 or rgb.shape != (self.size[1], self.size[0], 3):
            raise VideoError(f"{self.path}: frame {rgb.dtype}{list(rgb.shape)} does not fit {self.size[0]}x{self.size[1]} RGB")
        self._writer.write(self._cv2.cvtColor(rgb, self._cv2.COLOR_RGB2BGR))
        self.frames += 1

    def close(self) -> str:
        """Finish the file (idempotent); returns its path."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        return self.path

    def discard(self) -> None:
        """Finish and delete the file (the episode failed before its first frame)."""
        self.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass
