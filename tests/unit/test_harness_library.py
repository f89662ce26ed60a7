"""The library's predicates, recoveries and tools on constructed states (no simulator).

Each state is a dict of the observation tensors the env families publish, built so that the
condition under test holds or not by a margin; the recoveries are stepped on a toy kinematic
model (the commanded translation moves the hand, a grasped object follows it).
"""

from __future__ import annotations

import numpy as np
import pytest

from services.harness.runtime import signals
from services.harness.runtime.api import Frame, Window
from services.harness.runtime.perception import NoiseModel, Perception
from services.harness.runtime.library import PREDICATES, RECOVERIES, EpisodeMemory, ParamError, resolve
from services.harness.runtime.library import tools as t
from services.harness.runtime.library.recoveries import DONE, FAILED, Chain

OBJ = np.array([0.0, 0.0, 0.90, 0.04, 0.03, 0.95])  # a 4 x 3 x 5 cm object on a table at z = 0.90
BOWL = np.array([0.20, -0.06, 0.90, 0.32, 0.06, 0.96])


def state(eef=(0.02, 0.015, 1.05), obj=OBJ, target=BOWL, grasp=0.0, aperture=0.08, drift=0.0,
          force=(0.0, 0.0, 0.0), motion=(0.0,) * 6, others=()) -> dict[str, np.ndarray]:
    eef = np.asarray(eef, dtype=np.float64)
    obj = np.asarray(obj, dtype=np.float64)
    gap = np.maximum(np.maximum(obj[:3] - eef, eef - obj[3:]), 0.0)
    blocks = [np.concatenate([t.box_center(obj), [0, 0, 0, 1], np.zeros(7)])]
    blocks += [np.concatenate([np.asarray(o, dtype=np.float64), [0, 0, 0, 1], np.zeros(7)]) for o in others]
    return {
        "robot0_eef_pos": eef,
        "robot0_eef_quat": np.array([1.0, 0.0, 0.0, 0.0]),  # x-axis half turn: pointing down (DOWN)
        "task_object_pos": t.box_center(obj),
        "task_object_bbox": obj,
        "task_target_bbox": np.asarray(target, dtype=np.float64),
        "phi_grasp": np.array([grasp]),
        "phi_gripper_aperture": np.array([aperture]),
        "phi_eef_object_dist": np.array([float(np.linalg.norm(gap))]),
        "phi_object_gripper_drift": np.array([drift]),
        "phi_contact_force": np.asarray(force, dtype=np.float64),
        "phi_eef_motion": np.asarray(motion, dtype=np.float64),
        "phi_collision_intensity": np.array([0.0]),
        "object_state": np.concatenate(blocks + [np.zeros(14)]),
    }


#: A detector without noise: these tests are about the predicates' and recoveries' logic.
EXACT = Perception(0, NoiseModel(0.0, 0.0, 0.0, 0.0, 0.0))


def frame(step: int, obs: dict[str, np.ndarray], action, milestones: frozenset[str]) -> Frame:
    """A frame as the runtime builds it: the readable signals and the perception tool over ``obs``."""
    return Frame(step, signals.visible(obs), action, milestones, EXACT.sensor(obs))


def window(states, actions=None, milestones=None) -> Window:
    frames = []
    for i, s in enumerate(states):
        a = None if actions is None else actions[i]
        frames.append(frame(i, s, a, frozenset(milestones[i]) if milestones else frozenset()))
    return Window(tuple(frames), "put the object in the bowl", ())


def holds(name: str, w: Window, **overrides) -> bool:
    spec = PREDICATES[name]
    return spec.fn(w, resolve(spec.params, overrides, name)) is not None


CLOSE_ACTION = np.array([0, 0, 0, 0, 0, 0, 1.0])


# ---- predicates -----------------------------------------------------------------------------------


def test_grasp_retained_needs_a_steady_grasp_without_slip() -> None:
    held = [state(grasp=1.0, aperture=0.03) for _ in range(6)]
    assert holds("grasp_retained", window(held), steps=5)
    assert not holds("grasp_retained", window(held[:-1] + [state(grasp=0.0)]), steps=5)
    assert not holds("grasp_retained", window(held[:-1] + [state(grasp=1.0, drift=0.05)]), steps=5)


def test_grasp_lost_only_while_the_gripper_stays_commanded_closed() -> None:
    states = [state(grasp=1.0)] * 6 + [state(grasp=0.0)] * 3
    closing = [CLOSE_ACTION] * len(states)
    assert holds("grasp_lost", window(states, closing))
    opening = closing[:-1] + [np.array([0, 0, 0, 0, 0, 0, -1.0])]
    assert not holds("grasp_lost", window(states, opening))  # a deliberate release
    assert not holds("grasp_lost", window(states[:-1] + [state(grasp=1.0)], closing))


def test_failed_acquisition_is_a_shut_gripper_near_the_object_without_grasp() -> None:
    assert holds("failed_acquisition", window([state(eef=(0.02, 0.015, 0.96), aperture=0.002)]))
    assert not holds("failed_acquisition", window([state(eef=(0.02, 0.015, 0.96), aperture=0.002, grasp=1.0)]))
    assert not holds("failed_acquisition", window([state(eef=(0.02, 0.015, 1.20), aperture=0.002)]))
    assert not holds("failed_acquisition", window([state(eef=(0.02, 0.015, 0.96), aperture=0.05)]))


def test_stalled_progress_needs_no_motion_and_no_new_milestone() -> None:
    still = [state() for _ in range(10)]
    assert holds("stalled_progress", window(still), horizon=10)
    moving = [state(eef=(0.02, 0.015, 1.05 + 0.01 * i)) for i in range(10)]
    assert not holds("stalled_progress", window(moving), horizon=10)
    ms = [set()] * 9 + [{"reached(obj)"}]
    assert not holds("stalled_progress", window(still, milestones=ms), horizon=10)


def test_non_approach_when_the_hand_hovers_short_of_the_object() -> None:
    hover = [state(eef=(0.02, 0.015, 0.99)) for _ in range(20)]  # 4 cm above the top, not closing in
    assert holds("non_approach", window(hover), horizon=20)
    closing = [state(eef=(0.02, 0.015, 1.2 - 0.01 * i)) for i in range(20)]
    assert not holds("non_approach", window(closing), horizon=20)
    assert not holds("non_approach", window([state(eef=(0.02, 0.015, 0.99), grasp=1.0)] * 20), horizon=20)


def test_hovering_unacquired_when_the_hand_bobs_over_the_object_without_closing() -> None:
    bob = [state(eef=(0.02, 0.015, 0.99 + 0.03 * (i % 2))) for i in range(45)]  # 4-7 cm over the top
    assert holds("hovering_unacquired", window(bob))
    assert not holds("hovering_unacquired", window(bob[:44]))  # not for horizon frames yet
    assert not holds("hovering_unacquired", window(bob[:-1] + [state(eef=(0.3, 0.015, 1.2))]))  # moved off
    assert not holds("hovering_unacquired", window(bob[:-1] + [state(eef=(0.02, 0.015, 0.96), grasp=1.0)]))
    ms = [set()] * 44 + [{"grasped(obj)"}]
    assert not holds("hovering_unacquired", window(bob, milestones=ms))
    assert not holds("hovering_unacquired", window(bob), near=0.03)


def test_approach_wrong_object_when_closing_in_on_another_object() -> None:
    other = (-0.3, 0.0, 0.93)
    toward_other = [state(eef=(-0.3 + 0.1 - 0.005 * i, 0.0, 1.0), others=[other]) for i in range(15)]
    assert holds("approach_wrong_object", window(toward_other))
    toward_task = [state(eef=(0.2 - 0.01 * i, 0.015, 1.0), others=[other]) for i in range(15)]
    assert not holds("approach_wrong_object", window(toward_task))


def test_drift_of_a_held_object() -> None:
    assert holds("drift", window([state(grasp=1.0, drift=0.05)]))
    assert not holds("drift", window([state(grasp=1.0, drift=0.01)]))
    assert not holds("drift", window([state(grasp=0.0, drift=0.05)]))


def test_held_near_target_and_stalled_transport() -> None:
    over = np.array([0.24, -0.015, 0.98, 0.28, 0.015, 1.03])  # held above the bowl's centre
    assert holds("held_near_target", window([state(obj=over, grasp=1.0)]))
    assert not holds("held_near_target", window([state(obj=over, grasp=0.0)]))
    assert not holds("held_near_target", window([state(obj=OBJ + [0, 0, 0.1, 0, 0, 0.1], grasp=1.0)]))
    lifted = OBJ + [0, 0, 0.1, 0, 0, 0.1]
    stuck = [state(obj=lifted, grasp=1.0) for _ in range(25)]
    assert holds("held_stalled_transport", window(stuck))
    carried = [state(obj=lifted + [0.01 * i, 0, 0, 0.01 * i, 0, 0], grasp=1.0) for i in range(25)]
    assert not holds("held_stalled_transport", window(carried))


def test_supported_placement_needs_the_object_at_rest_on_or_in_the_target() -> None:
    inside = np.array([0.24, -0.015, 0.91, 0.28, 0.015, 0.96])
    assert holds("supported_placement", window([state(obj=inside)]))
    sliding = [state(obj=inside + [0.015 * (i - 5), 0, 0, 0.015 * (i - 5), 0, 0]) for i in range(6)]  # 0.3 m/s
    assert not holds("supported_placement", window(sliding))
    assert not holds("supported_placement", window([state(obj=OBJ)]))  # beside the bowl
    assert not holds("supported_placement", window([state(obj=inside + [0, 0, 0.1, 0, 0, 0.1])]))  # in the air


def test_blocked_motion_compares_commanded_and_realized_translation() -> None:
    blocked = [state(motion=(0.01, 0, 0, 0.0005, 0, 0)) for _ in range(10)]
    assert holds("blocked_motion", window(blocked))
    free = [state(motion=(0.01, 0, 0, 0.009, 0, 0)) for _ in range(10)]
    assert not holds("blocked_motion", window(free))


def test_contact_stability_falls_with_speed_and_force_oscillation() -> None:
    from services.harness.runtime.library import STABILITY_PARAMS, contact_stability

    p = resolve(STABILITY_PARAMS, {}, "stability")
    rest = contact_stability(window([state(force=(0, 0, 5.0))] * 5), p)
    moving = contact_stability(window([state(obj=OBJ + [0.01 * i, 0, 0, 0.01 * i, 0, 0]) for i in range(11)]), p)
    hand = contact_stability(window([state(eef=(0.02 + 0.01 * i, 0.015, 1.05)) for i in range(11)]), p)
    shaking = contact_stability(window([state(force=(0, 0, 20.0 * (i % 2))) for i in range(5)]), p)
    assert rest == pytest.approx(1.0)
    assert moving < 0.2 and shaking < 0.2 and hand < 0.2


def test_parameters_are_checked_against_the_schema() -> None:
    with pytest.raises(ParamError, match="unknown"):
        resolve(PREDICATES["drift"].params, {"nope": 1}, "drift")
    with pytest.raises(ParamError, match="outside"):
        resolve(PREDICATES["drift"].params, {"max_drift": 5.0}, "drift")
    with pytest.raises(ParamError, match="integer"):
        resolve(PREDICATES["grasp_lost"].params, {"confirm": 2.5}, "grasp_lost")


# ---- tools --------------------------------------------------------------------------------------


def test_segment_box_test_and_clear_waypoint_rises_over_obstacles() -> None:
    box = np.array([0.0, -0.05, 0.9, 0.1, 0.05, 1.0])
    assert t.segment_hits_box(np.array([-0.1, 0, 0.95]), np.array([0.2, 0, 0.95]), box)
    assert not t.segment_hits_box(np.array([-0.1, 0, 1.1]), np.array([0.2, 0, 1.1]), box)
    start, goal = np.array([-0.1, 0, 0.95]), np.array([0.2, 0, 0.95])
    wp = t.clear_waypoint(start, goal, [box], margin=0.01, clearance=0.05)
    assert wp[:2] == pytest.approx(start[:2]) and wp[2] == pytest.approx(1.05)
    assert t.clear_waypoint(np.array([-0.1, 0, 1.2]), np.array([0.2, 0, 1.2]), [box], 0.01, 0.05) == pytest.approx(
        [0.2, 0, 1.2])


def test_grasp_proposals_are_object_relative_and_skip_failed_ones() -> None:
    proposals = t.sample_grasps(OBJ)
    assert proposals[0].finger_axis == 1  # across the narrow (3 cm) side
    moved = OBJ + [0.5, 0.2, 0, 0.5, 0.2, 0]
    assert proposals[0].point(moved) - proposals[0].point(OBJ) == pytest.approx([0.5, 0.2, 0])
    fresh = t.fresh_grasp(OBJ, [proposals[0]], tolerance=0.008)
    assert fresh is not None and not fresh.equivalent(proposals[0], 0.008)
    assert t.fresh_grasp(OBJ, proposals, tolerance=0.008) is None


def test_objects_wider_than_the_hand_are_gripped_by_the_rim() -> None:
    """A bowl (11 cm both ways) gets rim grasps: the grip point just inside one edge, fingers closing
    across that wall, below the rim's top; every side is proposed once per depth, none at the centre."""
    bowl = np.array([-0.14, -0.05, 0.90, -0.03, 0.06, 0.95])
    proposals = t.sample_grasps(bowl)
    assert len(proposals) == 8 and len({(p.offset, p.finger_axis) for p in proposals}) == 8
    for p in proposals:
        half = (bowl[3 + p.finger_axis] - bowl[p.finger_axis]) / 2
        assert abs(p.offset[p.finger_axis]) == pytest.approx(half - 0.012)
        assert p.offset[1 - p.finger_axis] == 0.0 and -0.03 < p.offset[2] < 0.0
        assert bowl[2] < p.point(bowl)[2] < bowl[5]


def test_orientation_action_is_zero_when_aligned() -> None:
    quat_down = np.array([1.0, 0.0, 0.0, 0.0])
    assert t.orient_action(quat_down, t.DOWN) == pytest.approx(np.zeros(3), abs=1e-9)
    assert np.linalg.norm(t.orient_action(np.array([0.0, 0.0, 0.0, 1.0]), t.DOWN)) > 0.1


# ---- recoveries on a toy kinematic model ---------------------------------------------------------


class Toy:
    """The hand moves by the commanded translation (1.0 = 5 cm, as OSC_POSE); the gripper closes
    over ``close_steps`` steps and grasps the object if the hand is in it then; a grasped object
    follows the hand; a released object falls onto whatever is under it."""

    def __init__(self, eef, obj=OBJ, target=BOWL, graspable=True, slip_after: int | None = None,
                 lowest: float = 0.0) -> None:
        self.eef = np.asarray(eef, dtype=np.float64)
        self.lowest = lowest  # the hand cannot go below this height (something in the way)
        self.obj = np.asarray(obj, dtype=np.float64).copy()
        self.target = target
        self.aperture = 0.08
        self.grasp = False
        self.graspable = graspable
        self.slip_after = slip_after
        self.held_steps = 0
        self.slipped = False

    def obs(self) -> dict[str, np.ndarray]:
        return state(eef=self.eef, obj=self.obj, target=self.target, grasp=float(self.grasp), aperture=self.aperture)

    def apply(self, action: np.ndarray) -> None:
        move = np.clip(action[:3], -1, 1) * 0.05
        move[2] = max(move[2], self.lowest - self.eef[2])
        self.eef = self.eef + move
        if self.grasp:
            self.obj = self.obj + np.concatenate([move, move])
            self.held_steps += move[2] > 0
            if self.slip_after is not None and self.held_steps > self.slip_after:
                self.grasp, self.slip_after = False, None  # slips once, while being lifted
                self.slipped = True  # and cannot be caught again before the gripper reopens
        if action[6] > 0:
            self.aperture = max(0.0, self.aperture - 0.01)
            inside = np.all(self.eef >= self.obj[:3] - 0.005) and np.all(self.eef <= self.obj[3:] + 0.005)
            if inside and self.graspable and not self.slipped and self.aperture <= 0.04:
                self.grasp = True
                self.aperture = max(self.aperture, 0.03)
        elif action[6] < 0:
            self.aperture = min(0.08, self.aperture + 0.02)
            self.slipped = False
            if self.grasp:
                self.grasp = False
        if not self.grasp:
            floor = self.target[5] if self._over(self.target) else 0.90
            if self._over(self.target) and self.target[5] - self.target[2] > 0.03:
                floor = self.target[2] + 0.005  # inside a bowl
            drop = self.obj[2] - floor
            self.obj = self.obj - [0, 0, drop, 0, 0, drop]

    def _over(self, box) -> bool:
        c = t.box_center(self.obj)
        return bool(box[0] <= c[0] <= box[3] and box[1] <= c[1] <= box[4])


def drive(name: str, toy: Toy, steps: int = 400, memory: EpisodeMemory | None = None, **overrides):
    spec = RECOVERIES[name]
    rec = spec.factory(resolve(spec.params, overrides, name))
    frames = [frame(0, toy.obs(), None, frozenset())]
    rec.start(Window(tuple(frames), "", ()), memory or EpisodeMemory())
    for i in range(steps):
        action = rec.act(Window(tuple(frames[-40:]), "", ()))
        if action is None:
            return rec, i
        toy.apply(action)
        frames.append(frame(i + 1, toy.obs(), action, frozenset()))
    return rec, steps


def test_freeze_holds_still_for_its_steps() -> None:
    toy = Toy(eef=(0.0, 0.0, 1.1))
    rec, n = drive("freeze", toy, steps=20)
    assert rec.status == DONE and n == 5
    assert toy.eef == pytest.approx([0.0, 0.0, 1.1])


def test_release_and_restage_opens_and_rises_over_the_object() -> None:
    toy = Toy(eef=(0.02, 0.015, 0.93))
    toy.aperture = 0.0
    rec, _ = drive("release_and_restage", toy)
    assert rec.status == DONE and toy.aperture >= 0.07 and toy.eef[2] >= OBJ[5] + 0.07


def test_pregrasp_reaches_hover_over_a_fresh_grasp_rising_over_obstacles() -> None:
    toy = Toy(eef=(0.40, 0.0, 0.93))  # beyond the bowl, low: the straight line crosses it
    heights = []
    spec = RECOVERIES["pregrasp"]
    rec = spec.factory(resolve(spec.params, {}, "pregrasp"))
    frames = [frame(0, toy.obs(), None, frozenset())]
    rec.start(Window(tuple(frames), "", ()), EpisodeMemory())
    while (a := rec.act(Window(tuple(frames), "", ()))) is not None:
        toy.apply(a)
        frames.append(frame(len(frames), toy.obs(), a, frozenset()))
        if BOWL[0] <= toy.eef[0] <= BOWL[3]:
            heights.append(toy.eef[2])
    assert rec.status == DONE
    goal = rec.proposal.point(OBJ) + [0, 0, 0.06]
    assert toy.eef == pytest.approx(goal, abs=0.011)
    assert min(heights) > BOWL[5]  # never swept through the bowl


def test_regrasp_acquires_and_lifts() -> None:
    toy = Toy(eef=(0.1, 0.1, 1.1))
    memory = EpisodeMemory()
    rec, _ = drive("regrasp", toy, memory=memory)
    assert rec.status == DONE and toy.grasp and toy.obj[2] > OBJ[2] + 0.03
    assert memory.last_grasp is not None and not memory.failed_grasps


def test_regrasp_never_repeats_a_failed_grasp_and_gives_up_within_budget() -> None:
    toy = Toy(eef=(0.1, 0.1, 1.1), graspable=False)
    memory = EpisodeMemory()
    rec, _ = drive("regrasp", toy, steps=2000, memory=memory, max_attempts=3)
    assert rec.status == FAILED and "3 grasp attempts" in rec.reason
    assert len(memory.failed_grasps) == 3
    for i, a in enumerate(memory.failed_grasps):
        for b in memory.failed_grasps[i + 1:]:
            assert not a.equivalent(b, 0.008)


def test_regrasp_charges_the_last_grasp_when_it_is_needed_again() -> None:
    memory = EpisodeMemory()
    drive("regrasp", Toy(eef=(0.1, 0.1, 1.1)), memory=memory)
    first = memory.last_grasp
    drive("regrasp", Toy(eef=(0.1, 0.1, 1.1)), memory=memory)
    assert memory.failed_grasps == [first] and not memory.last_grasp.equivalent(first, 0.008)


def test_regrasp_fails_an_attempt_whose_grasp_slips_in_the_lift_check() -> None:
    toy = Toy(eef=(0.1, 0.1, 1.1), slip_after=1)
    memory = EpisodeMemory()
    rec, _ = drive("regrasp", toy, memory=memory)
    assert rec.status == DONE and len(memory.failed_grasps) == 1  # the second attempt held


def test_place_chain_aligns_lowers_releases_and_retreats() -> None:
    lifted = OBJ + [0, 0, 0.12, 0, 0, 0.12]
    toy = Toy(eef=t.box_center(lifted), obj=lifted)
    toy.grasp, toy.aperture = True, 0.03
    specs = [RECOVERIES[n] for n in ("fine_alignment", "lower_until_supported_then_release", "retreat_until_separated")]
    chain = Chain([s.factory(resolve(s.params, {}, s.name)) for s in specs])
    frames = [frame(0, toy.obs(), None, frozenset())]
    chain.start(Window(tuple(frames), "", ()), EpisodeMemory())
    for _ in range(400):
        a = chain.act(Window(tuple(frames[-40:]), "", ()))
        if a is None:
            break
        toy.apply(a)
        frames.append(frame(len(frames), toy.obs(), a, frozenset()))
    assert chain.status == DONE
    c = t.box_center(toy.obj)
    assert BOWL[0] < c[0] < BOWL[3] and BOWL[1] < c[1] < BOWL[4] and toy.obj[2] < BOWL[5]  # in the bowl
    assert not toy.grasp and toy.eef[2] - toy.obj[5] > 0.02  # released and separated


def test_fine_alignment_fails_without_a_grasp() -> None:
    rec, _ = drive("fine_alignment", Toy(eef=(0.0, 0.0, 1.1)))
    assert rec.status == FAILED and "not held" in rec.reason


def test_registries_expose_typed_schemas() -> None:
    for registry in (PREDICATES, RECOVERIES):
        for name, spec in registry.items():
            assert spec.name == name and spec.doc
            for pname, param in spec.params.items():
                assert param.kind in ("float", "int") and param.low <= param.default <= param.high, (name, pname)


def test_regrasp_gives_up_on_a_blocked_descent_and_tries_another_proposal() -> None:
    toy = Toy(eef=(0.1, 0.1, 1.1), lowest=0.97)  # stuck 5 cm over the grip point
    memory = EpisodeMemory()
    rec, _ = drive("regrasp", toy, steps=2000, memory=memory, max_attempts=2)
    assert rec.status == FAILED and "blocked on the way down" in rec.reason
    assert len(memory.failed_grasps) == 2 and not memory.failed_grasps[0].equivalent(memory.failed_grasps[1], 0.008)


def test_regrasp_closes_where_the_descent_settles_just_short() -> None:
    toy = Toy(eef=(0.1, 0.1, 1.1), lowest=0.925)  # 5 mm over the grip point: within 2.5 x tolerance
    rec, _ = drive("regrasp", toy)
    assert rec.status == DONE and toy.grasp


class Wall(Toy):
    """The toy with a wall at x = ``wall``: the hand cannot pass it."""

    def __init__(self, *args, wall: float, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.wall = wall

    def apply(self, action: np.ndarray) -> None:
        action = action.copy()
        action[0] = min(action[0], max(0.0, (self.wall - self.eef[0]) / 0.05))
        super().apply(action)


def _held(toy: Toy) -> Toy:
    toy.grasp, toy.aperture = True, 0.03
    return toy


def test_fine_alignment_blocked_over_the_target_is_done_and_short_of_it_fails() -> None:
    lifted = OBJ + [0, 0, 0.12, 0, 0, 0.12]
    over = _held(Wall(eef=t.box_center(lifted), obj=lifted, wall=0.22))  # centre can reach x = 0.24 > BOWL[0] + inset
    rec, _ = drive("fine_alignment", over)
    assert rec.status == DONE and BOWL[0] < t.box_center(over.obj)[0] < BOWL[3]
    short = _held(Wall(eef=t.box_center(lifted), obj=lifted, wall=0.10))
    rec, _ = drive("fine_alignment", short)
    assert rec.status == FAILED and "blocked short" in rec.reason
