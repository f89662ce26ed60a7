"""Milestones mu_t and m*: derivation from goal predicates and evaluation on a scripted scene.

Derivation is tested on the goal shapes that occur in LIBERO-Goal, LIBERO-10 and their PRO
variants (on/in onto objects, fixture sites and table regions, drawers that must be opened first,
"put it in and close it", knobs); evaluation with a fake probe whose state the test sets step by
step, so every milestone kind and the stage selection are checked without a simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from services.common.milestone_kinds import MAX_MILESTONES, STAGE_KINDS, TEMPLATE_NAMES
from services.env_worker.milestones import (
    MilestoneTracker,
    SceneFacts,
    derive_plan,
    first_missing,
    milestone_specs,
)

KITCHEN = SceneFacts(
    articulated=frozenset({"cabinet_1_top_region", "cabinet_1_bottom_region", "stove_1", "microwave_1"}),
    containers={"cabinet_1_top_region": "cabinet_1", "cabinet_1_bottom_region": "cabinet_1",
                "stove_1_cook_region": "stove_1", "microwave_1_heating_region": "microwave_1"},
    table_regions=frozenset({"table_stove_front_region"}),
)


def test_pick_place_template() -> None:
    plan = derive_plan([["on", "bowl_1", "plate_1"]], KITCHEN)
    assert plan.names == [
        "reached(bowl_1)", "grasped(bowl_1)", "lifted(bowl_1)", "above(bowl_1,plate_1)", "on(bowl_1,plate_1)",
        "released(bowl_1)",
    ]
    assert [s.template for s in plan.stages] == ["pick_place"]


def test_table_region_is_a_slide_and_fixture_site_a_pick_place() -> None:
    slide = derive_plan([["on", "plate_1", "table_stove_front_region"]], KITCHEN)
    assert slide.names == [
        "reached(plate_1)", "contact(plate_1)", "toward(plate_1,table_stove_front_region)",
        "on(plate_1,table_stove_front_region)", "released(plate_1)",
    ]
    onto_fixture = derive_plan([["on", "bowl_1", "stove_1_cook_region"]], KITCHEN)
    assert onto_fixture.stages[0].template == "pick_place"


def test_in_drawer_implies_opening_it_first() -> None:
    plan = derive_plan([["in", "bowl_1", "cabinet_1_top_region"]], KITCHEN)
    assert [(s.predicate, s.implied) for s in plan.stages] == [
        (("open", "cabinet_1_top_region"), True), (("in", "bowl_1", "cabinet_1_top_region"), False),
    ]
    assert plan.stages[1].requires == (0,)
    assert plan.names[:3] == [
        "reached(cabinet_1_top_region.handle)", "contact(cabinet_1_top_region.handle)", "open(cabinet_1_top_region)",
    ]
    assert plan.names[-2:] == ["in(bowl_1,cabinet_1_top_region)", "released(bowl_1)"]


def test_close_goes_after_filling_the_container() -> None:
    """LIBERO-10 lists close() before in(); the drawer is opened, filled, then closed."""
    plan = derive_plan([["close", "cabinet_1_bottom_region"], ["in", "bowl_1", "cabinet_1_bottom_region"]], KITCHEN)
    assert [s.predicate[0] for s in plan.stages] == ["open", "in", "close"]
    assert "reached(cabinet_1_bottom_region.handle)#2" in plan.names, "repeated names are made unique"
    assert len(set(plan.names)) == len(plan.names)
    microwave = derive_plan([["in", "mug_1", "microwave_1_heating_region"], ["close", "microwave_1"]], KITCHEN)
    assert [s.predicate for s in microwave.stages] == [
        ("open", "microwave_1"), ("in", "mug_1", "microwave_1_heating_region"), ("close", "microwave_1"),
    ]


def test_knob_and_unknown_predicates() -> None:
    plan = derive_plan([["turnon", "stove_1"], ["on", "pot_1", "stove_1_cook_region"]], KITCHEN)
    assert plan.names[:3] == ["reached(stove_1.handle)", "contact(stove_1.handle)", "turnon(stove_1)"]
    assert derive_plan([["printjointstate", "x_1"]], KITCHEN).names == ["printjointstate(x_1)"]
    assert derive_plan([["up", "cube"]], SceneFacts()).names == [
        "reached(cube)", "grasped(cube)", "lifted(cube)", "up(cube)",
    ]


def test_too_many_milestones_is_refused() -> None:
    goal = [["on", f"obj_{i}", "plate_1"] for i in range(MAX_MILESTONES // 6 + 1)]
    with pytest.raises(ValueError, match="schema holds"):
        derive_plan(goal, KITCHEN)


def test_specs_are_privileged_and_fixed_size() -> None:
    specs = {s.name: s for s in milestone_specs()}
    assert specs["milestones"].shape == (MAX_MILESTONES,) and specs["milestones"].privileged
    assert specs["task_stage"].shape == (len(STAGE_KINDS),)
    assert specs["task_template"].shape == (len(TEMPLATE_NAMES),)


# ---- evaluation ---------------------------------------------------------------------------------


def box(center: tuple[float, float, float], half: float = 0.02) -> np.ndarray:
    c = np.asarray(center, dtype=np.float64)
    return np.concatenate([c - half, c + half])


@dataclass
class FakeProbe:
    """A scene the test drives by hand: boxes, eef, contacts and predicate values."""

    eef_pos: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.2]))
    boxes: dict[str, np.ndarray] = field(default_factory=dict)
    contacts: dict[str, tuple[bool, bool, bool]] = field(default_factory=dict)
    handles: dict[str, np.ndarray] = field(default_factory=dict)
    handle_touch: dict[str, bool] = field(default_factory=dict)
    predicates: dict[tuple[str, ...], bool] = field(default_factory=dict)

    def eef(self) -> np.ndarray:
        return self.eef_pos

    def bbox(self, name: str) -> np.ndarray:
        return self.boxes[name]

    def gripper_contact(self, name: str) -> tuple[bool, bool, bool]:
        return self.contacts.get(name, (False, False, False))

    def handle_bbox(self, name: str) -> np.ndarray:
        return self.handles[name]

    def handle_contact(self, name: str) -> bool:
        return self.handle_touch.get(name, False)

    def holds(self, predicate: tuple[str, ...]) -> bool:
        return self.predicates.get(tuple(predicate), False)


def _pick_place_scene() -> tuple[MilestoneTracker, FakeProbe]:
    plan = derive_plan([["on", "bowl_1", "plate_1"]], KITCHEN)
    probe = FakeProbe(boxes={"bowl_1": box((0.0, 0.0, 0.92)), "plate_1": box((0.2, 0.0, 0.91), 0.05)})
    tracker = MilestoneTracker(plan)
    tracker.start(probe)
    return tracker, probe


def test_pick_place_milestones_in_order_and_m_star() -> None:
    tracker, probe = _pick_place_scene()
    assert tracker.first_missing() == "reached(bowl_1)"
    probe.eef_pos = np.array([0.0, 0.0, 0.93])  # at the bowl
    tracker.update(probe)
    assert tracker.first_missing() == "grasped(bowl_1)"
    probe.contacts["bowl_1"] = (True, True, True)
    tracker.update(probe)
    assert tracker.first_missing() == "lifted(bowl_1)"
    probe.boxes["bowl_1"] = box((0.0, 0.0, 1.0))  # 8 cm up
    tracker.update(probe)
    assert tracker.first_missing() == "above(bowl_1,plate_1)"
    probe.boxes["bowl_1"] = box((0.2, 0.0, 1.0))  # over the plate
    tracker.update(probe)
    assert tracker.first_missing() == "on(bowl_1,plate_1)"
    probe.boxes["bowl_1"] = box((0.2, 0.0, 0.925))  # set down on the plate
    probe.predicates[("on", "bowl_1", "plate_1")] = True
    tracker.update(probe)
    assert tracker.first_missing() == "", "the goal holds: nothing is missing"
    assert tracker.reached_names() == tracker.plan.names[:5]
    probe.contacts["bowl_1"] = (False, False, False)
    current = tracker.update(probe)
    assert list(current) == [False, False, False, False, True, True], "mu_t is the state now"
    assert tracker.reached.all()
    tensors = tracker.tensors()
    assert tensors["milestones_reached"][:6].tolist() == [1.0] * 6 and not tensors["milestones_reached"][6:].any()
    assert tensors["task_stage"][STAGE_KINDS.index("on")] == 1.0
    assert tensors["task_template"][TEMPLATE_NAMES.index("pick_place")] == 1.0


def test_m_star_of_constructed_failures() -> None:
    """Gripper never closes -> grasped; lifted and stopped -> above (the paper's first missing milestone)."""
    tracker, probe = _pick_place_scene()
    probe.eef_pos = np.array([0.0, 0.0, 0.93])
    probe.contacts["bowl_1"] = (True, False, True)  # one finger only: contact but no grasp
    for _ in range(3):
        tracker.update(probe)
    assert tracker.first_missing() == "grasped(bowl_1)"

    tracker, probe = _pick_place_scene()
    probe.eef_pos = np.array([0.0, 0.0, 0.93])
    probe.contacts["bowl_1"] = (True, True, True)
    tracker.update(probe)
    probe.boxes["bowl_1"] = box((0.0, 0.0, 1.0))  # lifted, then the policy stops
    probe.eef_pos = np.array([0.0, 0.0, 1.01])
    for _ in range(3):
        tracker.update(probe)
    assert tracker.first_missing() == "above(bowl_1,plate_1)"
    assert first_missing(tracker.plan.names, tracker.reached_names()) == "above(bowl_1,plate_1)"


def test_released_needs_the_goal_and_no_contact() -> None:
    """Not touching the bowl at the start is not "released": it needs the goal predicate too."""
    tracker, _ = _pick_place_scene()
    assert not tracker.reached[5]


def test_stage_follows_implied_preconditions() -> None:
    plan = derive_plan([["in", "bowl_1", "cabinet_1_top_region"]], KITCHEN)
    probe = FakeProbe(
        boxes={"bowl_1": box((0.0, 0.0, 0.92)), "cabinet_1_top_region": box((0.1, -0.2, 1.0), 0.05)},
        handles={"cabinet_1_top_region": box((0.1, -0.13, 1.0), 0.01)},
    )
    tracker = MilestoneTracker(plan)
    tracker.start(probe)
    assert tracker.stage == 0 and tracker.tensors()["task_stage"][STAGE_KINDS.index("open")] == 1.0
    probe.eef_pos = np.array([0.1, -0.13, 1.0])
    probe.handle_touch["cabinet_1_top_region"] = True
    tracker.update(probe)
    assert tracker.first_missing() == "open(cabinet_1_top_region)"
    probe.predicates[("open", "cabinet_1_top_region")] = True
    tracker.update(probe)
    assert tracker.stage == 1 and tracker.first_missing() == "reached(bowl_1)"
    probe.predicates[("open", "cabinet_1_top_region")] = False  # the drawer slid shut again
    tracker.update(probe)
    assert tracker.stage == 0, "back to the precondition"
    assert tracker.reached[2], "reached milestones stay reached"


def test_slide_toward() -> None:
    plan = derive_plan([["on", "plate_1", "table_stove_front_region"]], KITCHEN)
    probe = FakeProbe(boxes={"plate_1": box((0.0, 0.0, 0.91)), "table_stove_front_region": box((0.0, 0.2, 0.9))})
    tracker = MilestoneTracker(plan)
    tracker.start(probe)
    probe.boxes["plate_1"] = box((0.0, 0.09, 0.91))
    tracker.update(probe)
    assert not tracker.reached[2]
    probe.boxes["plate_1"] = box((0.0, 0.11, 0.91))
    tracker.update(probe)
    assert tracker.reached[2]


def test_latch_only_updates_latch_like_full_ones() -> None:
    """A step nobody observes evaluates only the milestones not reached yet: the same latching,
    stage and m*, and the current flags it skipped are filled in on demand."""
    full, probe = _pick_place_scene()
    lazy = MilestoneTracker(full.plan)
    lazy.start(probe)
    probe.eef_pos = np.array([0.0, 0.0, 0.93])  # at the bowl, grasping it
    probe.contacts["bowl_1"] = (True, True, True)
    for tracker in (full, lazy):
        tracker.update(probe, latch_only=tracker is lazy)
    probe.boxes["bowl_1"] = box((0.0, 0.0, 1.0))  # lifted
    probe.eef_pos = np.array([0.5, 0.0, 1.2])  # reached(bowl_1) stops holding; it stays latched
    for tracker in (full, lazy):
        tracker.update(probe, latch_only=tracker is lazy)
    assert lazy.reached.tolist() == full.reached.tolist() and lazy.stage == full.stage
    assert lazy.first_missing() == full.first_missing() == "above(bowl_1,plate_1)"
    with pytest.raises(RuntimeError, match="refresh"):
        lazy.tensors()
    assert lazy.refresh(probe).tolist() == full.current.tolist()
    assert not lazy.current[0], "the skipped flag is the state now, not the latched one"
    for name, value in full.tensors().items():
        assert np.array_equal(lazy.tensors()[name], value), name
