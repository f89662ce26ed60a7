"""One rollout's trace tau = {(s_t, a_t, mu_t, phi_t)} plus its interventions, as one compressed npz.

Loop 1 of the paper keeps every valid rollout with its full trace; Loop 2 replays critics over
it and measures its divergence from the successful ones. The trace is recorded at the policy's
call rate: frame k is the observation after the k-th executed chunk (frame 0 after the reset),
``frame_step[k]`` its env step, and ``actions`` holds every executed action with
``action_frame[i]`` the frame it led to. Camera images are not stored here (the video has them).

A trace recorded with ``ResetSpec.record_steps`` also holds ``step_obs``: the observation at every
env step (entry t after t actions, entry 0 the reset), which is what the runtime's critics saw, so
a critic replay (services/evolver/replay.py) runs over those, step by step as at runtime. Divergence
and clustering stay at the call-rate frames.
"""

from __future__ import annotations

import io
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Observation tensors that are camera images: kept in the video, never in the trace.
IMAGE_SUFFIX = "_image"
#: Width of :func:`relative_state`.
STATE_DIM = 9
#: The outcome the harness runtime records for an intervention still in control when the episode
#: succeeded (services/harness/runtime/engine.py): it never handed back to the policy.
IN_CONTROL_AT_SUCCESS = "in_control_at_success"


def in_control_at_success(interventions: Sequence[Mapping[str, Any]]) -> bool:
    """Whether an intervention, not the policy under the episode's instruction, was in control at
    the success step. The re-entry contract says an intervention ends by handing back; one still
    in control at success finished the task itself, so no decision of the evolver credits the
    success (a redirection counts too: the policy then worked under another instruction)."""
    return any(str(iv.get("outcome", "")) == IN_CONTROL_AT_SUCCESS for iv in interventions)


@dataclass
class Trace:
    """The arrays of one rollout; ``obs`` maps a tensor name to [K, ...] over the K frames."""

    obs: dict[str, np.ndarray]
    frame_step: np.ndarray
    actions: np.ndarray
    action_frame: np.ndarray
    milestone_names: list[str]
    interventions: list[dict[str, Any]] = field(default_factory=list)
    #: Env steps whose action came from a recovery, not the policy (from the harness report).
    recovery_steps: int = 0
    #: The observation at every env step ([T + 1, ...] per tensor; entry t after ``actions[t - 1]``),
    #: empty when the rollout did not record steps.
    step_obs: dict[str, np.ndarray] = field(default_factory=dict)
    #: The episode's instruction (ResetResult.instruction); "" in traces recorded before it was kept.
    instruction: str = ""

    @property
    def steps(self) -> int:
        """Number of per-step observations (T + 1 for a trace recorded with every step, else 0)."""
        return int(len(next(iter(self.step_obs.values())))) if self.step_obs else 0

    @property
    def frames(self) -> int:
        """Number of recorded frames K."""
        return int(len(self.frame_step))

    @property
    def mu(self) -> np.ndarray:
        """mu_t: milestones that hold at each frame, [K, len(M)] booleans."""
        m = self.obs.get("milestones")
        if m is None:
            return np.zeros((self.frames, len(self.milestone_names)), dtype=bool)
        return m[:, : len(self.milestone_names)] > 0.5

    @property
    def mu_reached(self) -> np.ndarray:
        """Milestones observed at some frame up to each frame, [K, len(M)] booleans."""
        return np.maximum.accumulate(self.mu, axis=0) if self.frames else self.mu

    def to_bytes(self) -> bytes:
        """The compressed npz of this trace."""
        arrays = {f"obs/{k}": v for k, v in self.obs.items()}
        arrays.update({f"step/{k}": v for k, v in self.step_obs.items()})
        arrays.update(
            frame_step=self.frame_step, actions=self.actions, action_frame=self.action_frame,
            meta=np.frombuffer(json.dumps({"milestone_names": self.milestone_names, "interventions":
                                           self.interventions, "recovery_steps": self.recovery_steps,
                                           "instruction": self.instruction}).encode(),
                               dtype=np.uint8),
        )
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "Trace":
        """Inverse of :meth:`to_bytes`."""
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            meta = json.loads(z["meta"].tobytes().decode())
            obs = {k[4:]: z[k] for k in z.files if k.startswith("obs/")}
            steps = {k[5:]: z[k] for k in z.files if k.startswith("step/")}
            return cls(obs=obs, frame_step=z["frame_step"], actions=z["actions"], action_frame=z["action_frame"],
                       milestone_names=list(meta["milestone_names"]), interventions=list(meta["interventions"]),
                       recovery_steps=int(meta.get("recovery_steps", 0)), step_obs=steps,
                       instruction=str(meta.get("instruction", "")))


class TraceRecorder:
    """Accumulates frames while an episode runs; one per episode."""

    def __init__(self, milestone_names: Sequence[str], instruction: str = "") -> None:
        self.milestone_names = list(milestone_names)
        self.instruction = instruction
        self._obs: dict[str, list[np.ndarray]] = {}
        self._steps: list[int] = []
        self._actions: list[np.ndarray] = []
        self._action_frame: list[int] = []
        self.interventions: list[dict[str, Any]] = []
        self.recovery_steps = 0
        self._step_obs: dict[str, list[np.ndarray]] = {}
        self._recorded_steps = 0

    def frame(self, step: int, obs: Mapping[str, np.ndarray], executed: np.ndarray | None = None) -> None:
        """Record the observation at env step ``step`` and the actions that led to it."""
        k = len(self._steps)
        if executed is not None and len(executed):
            acts = np.asarray(executed, dtype=np.float32).reshape(len(executed), -1)
            self._actions.append(acts)
            self._action_frame.extend([k] * len(acts))
        for name, value in _state(obs).items():
            self._obs.setdefault(name, []).append(value)
        self._steps.append(int(step))

    def step(self, obs: Mapping[str, np.ndarray]) -> None:
        """Record the observation of the next env step (the reset's first, then one per action)."""
        for name, value in _state(obs).items():
            self._step_obs.setdefault(name, []).append(value)
        self._recorded_steps += 1

    def finish(self) -> Trace:
        """The trace recorded so far."""
        obs = {k: np.stack(v) for k, v in self._obs.items() if len(v) == len(self._steps)}
        actions = np.concatenate(self._actions) if self._actions else np.zeros((0, 7), np.float32)
        steps = {k: np.stack(v) for k, v in self._step_obs.items() if len(v) == self._recorded_steps}
        if steps and self._recorded_steps != len(actions) + 1:
            raise ValueError(f"{self._recorded_steps} step observations for {len(actions)} actions: a trace "
                             "that records steps has one per action and one for the reset")
        return Trace(obs=obs, frame_step=np.asarray(self._steps, dtype=np.int32), actions=actions,
                     action_frame=np.asarray(self._action_frame, dtype=np.int32),
                     milestone_names=self.milestone_names, interventions=list(self.interventions),
                     recovery_steps=self.recovery_steps, step_obs=steps, instruction=self.instruction)


def _state(obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The tensors a trace keeps: every one but the camera images."""
    return {name: np.asarray(v) for name, v in obs.items()
            if not name.endswith(IMAGE_SUFFIX) and np.asarray(v).dtype != np.uint8}


def relative_state(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """The object-relative state used by EOD and clustering, per frame ([K, STATE_DIM] for [K, ...] inputs):
    gripper-to-object offset, object-to-target offset, grasp flag, gripper aperture, eef height.

    Relative poses, not absolute ones, so that the same mechanism at a shifted layout (LIBERO-PRO
    swap) lands near its reference."""
    eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float32)
    zeros3 = np.zeros_like(eef)
    obj = np.asarray(obs.get("task_object_pos", zeros3), dtype=np.float32)
    tgt = np.asarray(obs.get("task_target_pos", zeros3), dtype=np.float32)
    one = eef[..., :1]
    grasp = np.asarray(obs.get("phi_grasp", np.zeros_like(one)), dtype=np.float32)
    aperture = np.asarray(obs.get("phi_gripper_aperture", np.zeros_like(one)), dtype=np.float32)
    return np.concatenate([obj - eef, tgt - obj, grasp, aperture, eef[..., 2:3]], axis=-1)
