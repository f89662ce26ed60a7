"""Executing a chunk of actions on a slot and its wire result: shared by client steps, policy steps,
whole episodes and motion primitives, so every path ends episodes and counts steps the same way."""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from services.env_worker import metrics
from services.env_worker.families import StepOutcome
from services.env_worker.slots import BoundSlot
from zetta_wire.codec import encode, encode_observation
from zetta_wire.v1 import types_pb2

#: Observation tensors that are camera images (never in step_observations).
CAMERA_SUFFIX = "_image"


def recorded(obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A step's observation as ``step_observations`` carries it: no camera images, and copied (an
    env may reuse its buffers on the next step)."""
    return {k: np.array(v) for k, v in obs.items() if not k.endswith(CAMERA_SUFFIX)}


@dataclass
class ChunkRun:
    """What executing one chunk did: the last step's outcome (its observation is the chunk's
    last), the actions executed, their summed reward, and how many a recovery chose; with
    ``Episode.record_steps``, the observation after each executed action."""

    outcome: StepOutcome
    actions: np.ndarray
    reward: float
    truncated: bool
    by_recovery: int
    steps: list[Mapping[str, np.ndarray]] = field(default_factory=list)


def run_chunk(slot: BoundSlot, chunk: np.ndarray, render: bool = True) -> ChunkRun:
    """Execute a chunk on the slot's thread, stopping at the end of the episode. RunEpisodes reads
    only the reward and the end of the episode from it, so nothing is encoded here. ``render=False``
    leaves the camera images out of the chunk's last observation (a caller that steps on)."""
    episode = slot.episode
    assert episode is not None
    env = slot.env
    family = slot.family_name
    step_hist = metrics.STEP_SECONDS.labels(family)
    reward = 0.0
    executed = 0
    outcome = None
    last = len(chunk) - 1
    by_recovery = 0
    steps: list[Mapping[str, np.ndarray]] | None = [] if episode.record_steps else None
    if slot.harness is not None:  # critics at every step; a recovery's actions replace the policy's
        outcome, chunk, reward, by_recovery = slot.harness.run_chunk(
            env, chunk, episode.max_steps, step_hist, None if steps is None else lambda o: steps.append(recorded(o)))
        executed = len(chunk)
    else:
        for i, action in enumerate(chunk):
            start = time.perf_counter()
            # Only the observation this call returns is built: the one after the chunk's last action
            # (the steps before it keep reward, success, milestones and signal state up to date),
            # unless the episode records every step (then without images but on the last).
            outcome = env.step(action, render=render and i == last, observe=i == last or steps is not None)
            step_hist.observe(time.perf_counter() - start)
            reward += outcome.reward
            executed += 1
            if steps is not None:
                steps.append(recorded(outcome.observation))
            if outcome.terminated or outcome.truncated or env.episode_step >= episode.max_steps:
                break
    assert outcome is not None
    if executed - 1 != last:  # the episode ended inside the chunk: build its final observation
        outcome.observation = env.observe()
    metrics.STEPS.labels(family).inc(executed)
    truncated = outcome.truncated or (env.episode_step >= episode.max_steps and not outcome.terminated)
    if outcome.terminated or truncated:
        episode.ended = True
        episode.success = outcome.success
        metrics.EPISODES.labels(family, "success" if outcome.success else "failure").inc()
        if slot.harness is not None:
            slot.harness.end_episode(outcome.success)
    slot.last_obs = outcome.observation
    return ChunkRun(outcome, chunk[:executed], reward, truncated, by_recovery, steps or [])


def step_result(slot: BoundSlot, run: ChunkRun) -> types_pb2.StepResult:
    """The wire form of a chunk's run (on the slot's thread: encoding the observation is copy work)."""
    env, outcome = slot.env, run.outcome
    result = types_pb2.StepResult(
        session_id=slot.session_id,
        reward=run.reward,
        terminated=outcome.terminated,
        truncated=run.truncated,
        success=outcome.success,
        episode_step=env.episode_step,
        info=outcome.info,
        video_path=outcome.video_path,
        first_missing_milestone=env.first_missing_milestone(),
        milestones_reached=env.milestones_reached(),
    )
    encode(run.actions, result.executed_actions)
    encode_observation(outcome.observation, result.observation)
    for obs in run.steps:
        encode_observation(obs, result.step_observations.add())
    if slot.harness is not None:
        slot.harness.annotate(result, run.by_recovery)
    return result
