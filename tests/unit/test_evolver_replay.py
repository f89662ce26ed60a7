"""A critic replay over a trace that recorded every step sees the frames the runtime's critics saw:
one per env step, so a horizon of n frames spans n steps as at runtime (not n policy calls)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from services.evolver.replay import first_fire, frames, resume_frame
from services.evolver.trace import Trace, TraceRecorder
from services.harness.runtime.library import PREDICATES

EVERY = 4
STOP = 40
STEPS = 160


def _obs(t: int) -> dict[str, np.ndarray]:
    """The hand moves 1 cm per step until step STOP, then holds still."""
    x = 0.01 * min(t, STOP)
    return {"robot0_eef_pos": np.array([x, 0.0, 0.2], np.float32),
            "robot0_eef_quat": np.array([1, 0, 0, 0], np.float32),
            "robot0_gripper_qpos": np.array([0.04, -0.04], np.float32),
            "milestones": np.zeros(2, np.float32),
            "agentview_image": np.zeros((4, 4, 3), np.uint8)}


def record(every_step: bool, obs: Callable[[int], dict[str, np.ndarray]] = _obs, instruction: str = "") -> Trace:
    rec = TraceRecorder(["reached(a)", "grasped(a)"], instruction)
    rec.frame(0, obs(0))
    if every_step:
        rec.step(obs(0))
    for t in range(EVERY, STEPS + 1, EVERY):
        if every_step:
            for s in range(t - EVERY + 1, t + 1):
                rec.step(obs(s))
        rec.frame(t, obs(t), np.zeros((EVERY, 7), np.float32))
    return rec.finish()


def test_a_trace_that_recorded_every_step_keeps_them_without_images() -> None:
    tr = record(every_step=True)
    assert tr.steps == STEPS + 1 and tr.frames == STEPS // EVERY + 1
    assert "agentview_image" not in tr.step_obs
    back = Trace.from_bytes(tr.to_bytes())
    np.testing.assert_array_equal(back.step_obs["robot0_eef_pos"], tr.step_obs["robot0_eef_pos"])
    fs = frames(back)
    assert [f.step for f in fs] == list(range(STEPS + 1)) and fs[0].action is None and fs[5].action is not None
    assert not record(every_step=False).step_obs


def test_a_horizon_counts_env_steps_on_a_trace_of_every_step() -> None:
    """stalled_progress with horizon 20 fires 20 steps after the hand stopped, as the runtime's
    critic does; over the call-rate frames alone it would take 20 policy calls (80 steps)."""
    fn = PREDICATES["stalled_progress"].fn
    params = {"horizon": 20.0, "min_motion": 0.02}
    fired = first_fire(record(every_step=True), fn, params)
    assert fired is not None and STOP + 18 <= fired <= STOP + 21
    coarse = first_fire(record(every_step=False), fn, params)
    assert coarse is not None and coarse >= STOP + 18 * EVERY


def test_a_horizon_past_the_default_window_still_fires() -> None:
    """The replay widens its window past an integer parameter, as the runtime's window is."""
    fired = first_fire(record(every_step=True), PREDICATES["stalled_progress"].fn, {"horizon": 100.0, "min_motion": 0.02})
    assert fired is not None and fired >= STOP + 98


def test_replay_from_a_resume_frame_starts_at_its_env_step() -> None:
    tr = record(every_step=True)
    tr.interventions = [{"end_step": 70}]
    start = resume_frame(tr, 150)
    assert tr.frame_step[start] == 72
    fired = first_fire(tr, PREDICATES["stalled_progress"].fn, {"horizon": 20.0, "min_motion": 0.02}, start=start)
    assert fired is not None and fired >= 72


def test_steps_that_do_not_match_the_actions_are_refused() -> None:
    rec = TraceRecorder([])
    rec.frame(0, _obs(0))
    rec.step(_obs(0))
    rec.frame(4, _obs(4), np.zeros((4, 7), np.float32))
    with pytest.raises(ValueError, match="one per action"):
        rec.finish()


LATE = '''
from services.harness.runtime.api import Proposal


def critic_late(window, params):
    if window.now.step >= int(params["at"]) and len(window.frames) > int(params["at"]) // 2:
        return Proposal("c_late.late", "late", "hold", {"frames": float(len(window.frames))})
    return None
'''


def test_a_code_critic_replays_at_the_runtimes_cadence_in_its_sandbox() -> None:
    """A package's code critic runs every ZETTA_CODE_CRITIC_EVERY (4) steps at runtime, over a window
    of every step; so it does in the replay: first due at step 44 for a critic that holds from 41."""
    from services.evolver.replay import SandboxedCritic

    with SandboxedCritic("c_late", LATE, {"at": 41}) as critic:
        assert critic.every == 4
        assert first_fire(record(every_step=True), critic, {}) == 44
        # Over call-rate frames alone its window holds 21 frames only at step 80.
        assert first_fire(record(every_step=False), critic, {}) == 80


def test_a_trace_keeps_its_episode_instruction() -> None:
    rec = TraceRecorder(["reached(a)"], "put the a on the b")
    rec.frame(0, _obs(0))
    back = Trace.from_bytes(rec.finish().to_bytes())
    assert back.instruction == "put the a on the b"
    assert Trace.from_bytes(record(every_step=False).to_bytes()).instruction == ""


def test_a_redirection_the_runtime_would_not_start_is_no_false_positive() -> None:
    """A critic that fires while nothing is reached, paired with instruction redirection: on a
    success whose own instruction is the trained sentence the redirection would ask, the runtime
    does not start it (nothing changes for the policy), so the search does not count it; on a
    success under an unseen sentence, or with the policy's sentences unknown, it counts."""
    import dataclasses

    from services.evolver.repair import REDIRECT, ReplayCase, plan_of, plan_redirect, score_critic
    from tests.unit.test_evolver_fixtures import make_trace

    def nothing_reached(w: object, params: object) -> bool:
        return not w.now.milestones  # type: ignore[attr-defined]

    trained = ("put the a on the b", "put the c in the d")
    miss = make_trace("miss", 4)
    medoid = ReplayCase(miss, 40, referenced=False)
    own = [dataclasses.replace(make_trace("success", s), instruction="put the a on the b") for s in range(3)]
    unseen = dataclasses.replace(make_trace("success", 9), instruction="move the a onto the b")
    redirect = plan_redirect(plan_of("redirect"), trained)
    assert plan_of("redirect").recovery == REDIRECT and redirect == trained
    assert plan_redirect(plan_of("acquire"), trained) is None
    assert score_critic(nothing_reached, {}, medoid, [], own, 40, redirect=redirect) == (0, 1.0, 0.0)
    assert score_critic(nothing_reached, {}, medoid, [], own + [unseen], 40, redirect=redirect)[2] == 0.25
    assert score_critic(nothing_reached, {}, medoid, [], own, 40, redirect=None)[2] == 1.0
    assert score_critic(nothing_reached, {}, medoid, [], own, 40, redirect=())[2] == 1.0, \
        "with no trained sentence known the redirection asks the sub-goal's words, never the episode's"
    # The medoid's own redirection is vetoed the same way: on a failure under the trained sentence
    # the runtime would not start it either, so it catches nothing.
    same = ReplayCase(dataclasses.replace(miss, instruction="put the a on the b"), 40, referenced=False)
    assert score_critic(nothing_reached, {}, same, [], own, 40, redirect=redirect) is None


def test_replayed_frames_perceive_what_the_runtime_perceived() -> None:
    """The perception tool's noise is seeded per episode from the reset state and the instruction:
    a replay that drew it with another seed judged critics on detections the runtime never saw (the
    repair search's coverage and false positives then did not hold in closed loop)."""
    from pathlib import Path

    from services.harness.package.loader import load_package
    from services.harness.runtime.engine import HarnessRuntime
    from services.harness.runtime.library import tools as t

    def obs(s: int) -> dict[str, np.ndarray]:
        o = _obs(s)
        o["task_object_bbox"] = np.array([0.3, -0.02, 0.1, 0.34, 0.02, 0.14], np.float32)
        o["milestones_reached"] = np.zeros(2, np.float32)
        return o

    trace = record(every_step=True, obs=obs, instruction="put the a on the b")
    root = Path(__file__).resolve().parents[2]
    runtime = HarnessRuntime(load_package(root / "examples" / "harnesses" / "libero-goal-pick-place"), sandboxed=False)
    runtime.start(trace.instruction, trace.milestone_names)
    replayed = frames(trace)
    for k in range(trace.steps):
        runtime.step({n: v[k] for n, v in trace.step_obs.items()}, None if k == 0 else np.zeros(7, np.float32),
                     frozenset())
        assert t.eef_object_dist(runtime._frames[-1]) == t.eef_object_dist(replayed[k]), k
    runtime.close()
