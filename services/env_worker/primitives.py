"""The harness's tools for any client: perception estimates and bounded closed-loop motions.

These are the paper's API categories "Perception & Planning" (noisy object and target boxes, grasp
proposals) and "Low-Level Control" (servo the grip site to a position or a pose, with a gripper
command),
built from the same code the harness runtime's critics and recoveries use
(services/harness/runtime/perception.py, runtime/library/tools.py), so an external agent reads and
acts exactly as a harness does. Both run on the slot's thread like every other slot operation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from services.common import grpc_errors as ge
from services.common.primitives import DEFAULT_ANGLE_TOLERANCE_RAD, DEFAULT_TOLERANCE_M
from services.common.rotations import quat_to_mat, rotvec
from services.env_worker.chunks import ChunkRun, run_chunk, step_result
from services.env_worker.slots import BoundSlot
from services.harness.runtime.library import tools
from services.harness.runtime.perception import DEFAULT_NOISE, Detection, NoiseModel, Perception, episode_seed
from zetta_wire.v1 import types_pb2



def episode_perception(obs: dict[str, np.ndarray] | object, instruction: str,
                       noise: NoiseModel | None = None) -> Perception:
    """The episode's detector, seeded from its reset state and instruction as the harness's is,
    with the noise model of the session's harness package when it has one (its ``[perception]``):
    the same episode perceives with the same bias and noise for a client as for its harness."""
    return Perception(episode_seed(obs, instruction), noise or DEFAULT_NOISE)  # type: ignore[arg-type]


def _detection(query: str, d: Detection, grasps: bool) -> types_pb2.Detection:
    out = types_pb2.Detection(query=query, position=[float(v) for v in d.pos], box=[float(v) for v in d.box])
    if grasps and query == "object":
        for g in tools.sample_grasps(d.box):
            out.grasps.add(grip_point=[float(v) for v in g.point(d.box)], finger_axis=g.finger_axis)
    return out


def perceive(slot: BoundSlot, queries: Sequence[str], grasps: bool) -> types_pb2.PerceiveResult:
    """Estimates for ``queries`` on the slot's current state (on the slot's thread)."""
    episode = slot.require_episode()
    assert slot.last_obs is not None
    sensor = episode.perception.sensor(slot.last_obs)
    result = types_pb2.PerceiveResult(session_id=slot.session_id, episode_id=episode.episode_id,
                                      episode_step=slot.env.episode_step)
    for query in queries:
        found = sensor(query)
        for d in found if isinstance(found, list) else [found] if found is not None else []:
            result.detections.append(_detection(query, d, grasps))
    return result


def require_no_harness(slot: BoundSlot) -> None:
    """A harness owns its session's control: motions there would bypass its critics."""
    if slot.harness is not None:
        raise ge.failed_precondition(
            f"session {slot.session_id} runs a harness, which owns its control; Move needs an episode reset "
            "without one", [slot.session_id])


def _arrived(m: types_pb2.Motion, goal: np.ndarray, eef: np.ndarray, desired: np.ndarray | None,
             quat: np.ndarray | None, tolerance: float, angle_tolerance: float) -> bool:
    """Whether every goal the motion names (position, orientation) is within its tolerance."""
    if not len(m.position) and desired is None:
        return False
    if len(m.position) and np.linalg.norm(goal - eef) > tolerance:
        return False
    return desired is None or (quat is not None
                               and float(np.linalg.norm(rotvec(desired @ quat_to_mat(quat).T))) <= angle_tolerance)


def move(slot: BoundSlot, m: types_pb2.Motion) -> types_pb2.StepResult:
    """Servo the grip site toward ``m.position`` and the hand toward ``m.orientation`` one control
    step at a time (on the slot's thread), at most ``m.max_steps`` steps, fewer once every goal the
    motion names is within tolerance; naming neither, hold where the hand is for all ``max_steps``
    (a gripper closing). Cameras render only for the final observation."""
    slot.require_episode()
    obs = slot.last_obs
    assert obs is not None
    start = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
    goal = np.asarray(m.position, dtype=np.float64) if len(m.position) else start
    tolerance = m.tolerance_m or DEFAULT_TOLERANCE_M
    angle_tolerance = m.angle_tolerance_rad or DEFAULT_ANGLE_TOLERANCE_RAD
    desired = quat_to_mat(np.asarray(m.orientation, dtype=np.float64)) if len(m.orientation) else None
    dim = slot.family.action_spec().shape[-1]
    dtype = np.dtype(slot.family.action_spec().dtype)
    executed: list[np.ndarray] = []
    steps: list[Mapping[str, np.ndarray]] = []
    reward = 0.0
    run: ChunkRun | None = None
    for _ in range(m.max_steps):
        eef = np.asarray(obs["robot0_eef_pos"], dtype=np.float64)
        quat = np.asarray(obs["robot0_eef_quat"], dtype=np.float64) if "robot0_eef_quat" in obs else None
        if executed and _arrived(m, goal, eef, desired, quat, tolerance, angle_tolerance):
            break
        action = tools.move_action(eef, goal, m.gripper, max_action=m.max_action or 1.0)
        if quat is not None and (desired is not None or m.hand_down):
            action[3:6] = tools.orient_action(quat, tools.DOWN if desired is None else desired)
        chunk = np.clip(action[:dim], -1.0, 1.0).astype(dtype)[None]
        run = run_chunk(slot, chunk, render=False)
        executed.append(run.actions[0])
        steps += run.steps
        reward += run.reward
        obs = run.outcome.observation
        if slot.episode is None or slot.episode.ended:
            break
    assert run is not None
    run.outcome.observation = slot.env.observe()  # with the camera images the steps skipped
    slot.last_obs = run.outcome.observation
    return step_result(slot, ChunkRun(run.outcome, np.stack(executed), reward, run.truncated, 0, steps))
