"""The episode bookkeeping every family's slot shares: step counting, truncation, the end-of-episode
guard, normalized observations, and frames and videos rendered only when needed."""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Mapping
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.env_worker import rendering
from services.env_worker.families.contract import (
    EpisodeError,
    ResetError,
    ResetSpec,
    Slot,
    SlotClosedError,
    StepOutcome,
)
from services.env_worker.families.schema import normalize_observation


class EpisodeSlot(Slot):
    """Episode bookkeeping shared by families: step counting, truncation, end-of-episode guard.

    Subclasses implement the simulator side in :meth:`_start` and :meth:`_advance` and return raw
    observations; this class normalizes them against the schema. A subclass whose observation
    costs much more than its bookkeeping may return none from ``_advance`` for a step that is not
    observed, and build it in :meth:`_raw_observation` when it is asked for.

    Camera images and videos come from ``renderer`` (rendering.SlotRenderer), here and not in the
    subclasses, so frames are rendered only when an observation or a video frame needs them:
    after a reset (not on its settle steps), after a step taken with ``render=True``, and on
    :meth:`observe` when the last step skipped them.
    """

    def __init__(self, schema: Mapping[str, TensorSpec], renderer: rendering.SlotRenderer | None = None) -> None:
        self._schema = schema
        #: The raw observation of the current state; None while none was built for it.
        self._raw: Mapping[str, Any] | None = None
        self._running = False  # an episode was started (reset) and the slot is open
        self._step = 0
        self._max_steps = 0
        self._over = False
        self._closed = False
        self._renderer = renderer
        self._image_names: tuple[str, ...] = renderer.image_names if renderer is not None else ()
        #: Images of the current simulator state once rendered; None until then.
        self._images: dict[str, np.ndarray] | None = None
        self._video: Any = None  # video.VideoRecorder while an episode is recorded
        self._video_path = ""

    @abstractmethod
    def _start(self, spec: ResetSpec) -> tuple[Mapping[str, Any], str, int]:
        """Reset the simulator: raw observation, the task's instruction and the step budget."""

    @abstractmethod
    def _advance(self, action: np.ndarray, observe: bool) -> tuple[Mapping[str, Any] | None, float, bool,
                                                                    dict[str, float]]:
        """Execute one action: raw observation, reward, success, numeric diagnostics.

        With ``observe`` False the raw observation may be None; :meth:`_raw_observation` then
        builds it for the current state if it is asked for after all.
        """

    def _raw_observation(self) -> Mapping[str, Any]:
        """The raw observation of the current state, after an ``_advance`` that returned none."""
        raise NotImplementedError(f"{type(self).__name__}._advance returned no observation but cannot build one")

    @abstractmethod
    def _release(self) -> None:
        """Hand the simulator back to the sharing group."""

    def reset(self, spec: ResetSpec) -> tuple[dict[str, np.ndarray], str]:
        self._check_open()
        self.finish_video()
        self._raw, self._images, self._video_path, self._running = None, None, "", False
        raw, instruction, max_steps = self._start(spec)
        raw = self._with_images(raw, render=True)
        self._raw, self._step, self._max_steps, self._over = raw, 0, max_steps, False
        self._running = True
        if spec.video_path:
            self._start_video(spec.video_path)
        return normalize_observation(raw, self._schema), spec.instruction or instruction

    def step(self, action: np.ndarray, render: bool = True, observe: bool = True) -> StepOutcome:
        self._check_open()
        if not self._running:
            raise EpisodeError("no episode is running: reset the slot first")
        if self._over:
            raise EpisodeError(f"the episode ended after {self._step} steps: reset the slot first")
        raw, reward, success, info = self._advance(action, observe)
        self._images = None
        if self._video is not None:
            self._record_frame()
        if raw is not None:
            raw = self._with_images(raw, render and observe)
        self._raw = raw
        self._step += 1
        truncated = self._step >= self._max_steps
        self._over = success or truncated
        video_path = self.finish_video() if self._over and self._video is not None else ""
        return StepOutcome(
            observation=normalize_observation(raw, self._schema, optional=self._image_names) if observe else None,
            reward=float(reward),
            terminated=success,
            truncated=truncated,
            success=success,
            info=info,
            video_path=video_path,
        )

    def observe(self) -> dict[str, np.ndarray]:
        self._check_open()
        if not self._running:
            raise EpisodeError("no episode is running: reset the slot first")
        if self._raw is None:
            self._raw = self._with_images(self._raw_observation(), render=False)
        if any(name not in self._raw for name in self._image_names):
            self._raw = self._with_images(self._raw, render=True)
        return normalize_observation(self._raw, self._schema)

    @property
    def renderer(self) -> rendering.SlotRenderer | None:
        """What renders this slot's cameras and video frames (None for a family without cameras)."""
        return self._renderer

    def finish_video(self) -> str:
        if self._video is not None:
            self._video.close()
            self._video = None
        return self._video_path

    def _with_images(self, raw: Mapping[str, Any], render: bool) -> Mapping[str, Any]:
        """``raw`` plus the camera images of the current state: rendered now if ``render``, else
        only those a video frame already rendered."""
        if not self._image_names:
            return raw
        if render and self._images is None:
            self._images = self._renderer.images() if self._renderer is not None else {}
        return {**raw, **self._images} if self._images else raw

    def _start_video(self, path: str) -> None:
        from services.env_worker.video import VideoRecorder

        if self._renderer is None:
            raise ResetError("this family renders no frames, so it cannot record a video")
        width, height = self._renderer.video_size()
        self._video = VideoRecorder(path, self._renderer.fps(), width, height)
        self._video_path = path
        self._record_frame()

    def _record_frame(self) -> None:
        """Append the current state to the video, sharing the observation's render if there is one."""
        assert self._renderer is not None and self._video is not None
        if self._image_names:
            self._with_images({}, render=True)  # fills self._images for this state
        self._video.add(self._renderer.video_frame(self._images))

    @property
    def episode_step(self) -> int:
        return self._step

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.finish_video()
            self._raw, self._images, self._running = None, None, False
            self._release()

    def _check_open(self) -> None:
        if self._closed:
            raise SlotClosedError("the slot is closed")
