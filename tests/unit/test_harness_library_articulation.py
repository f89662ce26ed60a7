"""The library's articulation stages (open/close a drawer, turn a knob): the ``articulation_stalled``
predicate on a toy drawer seen through the perception tool (no simulator), the ``redirect`` playbook
that serves those stages, the repair search offering it for an articulation m*, and the harness
library sharing no code with the scripted oracle."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from services.common import handles
import ast
from pathlib import Path

from services.harness.runtime import signals
from services.harness.runtime.api import Frame, Window
from services.harness.runtime.library import PREDICATES, resolve
from services.harness.runtime.library.playbooks import ARTICULATION_STAGES, PLAYBOOKS, check_playbooks, serving
from services.harness.runtime.perception import NoiseModel, Perception
from services.harness.runtime.orchestrator import milestone_kind
from services.common.milestone_kinds import STAGE_KINDS, TEMPLATE_NAMES
from services.evolver.diagnose import Case, repair_spec
from services.evolver.draft import HarnessDraft
from services.evolver.eod import t_eod
from services.evolver.profile import SuccessIndex
from services.evolver.repair import ReplayCase, SearchParams, search, stage_of
from services.evolver.replay import first_fire
from services.evolver.trace import TraceRecorder

#: A detector without noise: the predicate's logic is under test here.
EXACT = Perception(0, NoiseModel(0.0, 0.0, 0.0, 0.0, 0.0))
ROOT = Path(__file__).resolve().parents[2]

# A drawer's bar 1 cm deep along y, 9 cm wide along x, at the height of a middle drawer; it opens
# along +y by 15 cm (LIBERO-Goal's cabinet faces the robot's -y side here, as in test_oracle).
BAR = np.array([-0.002, -0.14, 1.007, 0.087, -0.125, 1.024])
# A knob's lever: a 2 x 1 x 1.5 cm box, turned by pushing it 4 cm along +x.
LEVER = np.array([0.10, 0.20, 0.92, 0.12, 0.21, 0.935])
DRAWER = ["reached(cab_middle.handle)", "contact(cab_middle.handle)", "open(cab_middle)"]
KNOB = ["reached(stove_1.handle)", "contact(stove_1.handle)", "turnon(stove_1)"]


def _one_hot(names, name) -> np.ndarray:
    v = np.zeros(len(names))
    v[names.index(name)] = 1.0
    return v


def _quat(rot: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(rot).as_quat()  # xyzw, as robosuite's robot0_eef_quat


class Fixture:
    """A toy drawer (``kind="open"``: the bar follows the hand along the axis once gripped) or knob
    (``kind="turnon"``: the lever is pushed along the axis by a hand that passes the push site).
    The hand moves by the commanded translation (1.0 = 5 cm) and turns by the commanded rotation
    (1.0 = 0.5 rad), as OSC_POSE; ``stuck`` makes the hand ignore every command."""

    def __init__(self, kind: str, eef=(-0.1, 0.05, 1.15), stuck: bool = False) -> None:
        self.kind = kind
        self.handle = (BAR if kind == "open" else LEVER).copy()
        self.d = np.array([0.0, 1.0, 0.0]) if kind == "open" else np.array([1.0, 0.0, 0.0])
        self.goal = handles.handle_frame({"task_object_bbox": self.handle, "task_motion_dir": self.d})[2] + self.d * (
            0.15 if kind == "open" else 0.04)
        self.eef = np.asarray(eef, dtype=np.float64)
        self.rot = handles.DOWN.copy()
        self.gap = 0.08
        self.grasp = False
        self.stuck = stuck
        self.names = DRAWER if kind == "open" else KNOB
        self.reached: set[str] = set()
        self.skill = handles.HandleSkill(handles.HandleParams(), lambda *a: np.zeros(7), STAGE_KINDS)

    def remaining(self) -> float:
        return float(np.linalg.norm(self.goal - (self.handle[:3] + self.handle[3:]) / 2))

    def done(self) -> bool:
        return self.remaining() < 0.01

    def obs(self) -> dict[str, np.ndarray]:
        center = (self.handle[:3] + self.handle[3:]) / 2
        gap = np.maximum(np.maximum(self.handle[:3] - self.eef, self.eef - self.handle[3:]), 0.0)
        kind = "other" if self.done() else self.kind  # the env moves on once the goal holds
        return {
            "robot0_eef_pos": self.eef.copy(),
            "robot0_eef_quat": _quat(self.rot),
            "robot0_gripper_qpos": np.array([self.gap / 2, -self.gap / 2]),
            "task_object_pos": center,
            "task_object_bbox": self.handle.copy(),
            "task_target_pos": self.goal.copy(),
            "task_target_bbox": np.zeros(6),
            "task_motion_dir": self.d.copy(),
            "task_grasped": np.array([float(self.grasp)]),
            "task_stage": _one_hot(STAGE_KINDS, kind),
            "task_template": _one_hot(TEMPLATE_NAMES, "articulate"),
            "phi_grasp": np.array([float(self.grasp)]),
            "phi_gripper_aperture": np.array([self.gap]),
            "phi_eef_object_dist": np.array([float(np.linalg.norm(gap))]),
        }

    def milestones(self) -> frozenset[str]:
        gap = np.maximum(np.maximum(self.handle[:3] - self.eef, self.eef - self.handle[3:]), 0.0)
        if np.linalg.norm(gap) < 0.03:
            self.reached.add(self.names[0])
        if self.grasp or self.moved():
            self.reached.add(self.names[1])
        if self.done():
            self.reached.add(self.names[2])
        return frozenset(self.reached)

    def moved(self) -> bool:
        return self.remaining() < (0.15 if self.kind == "open" else 0.04) - 1e-3

    def apply(self, action: np.ndarray) -> None:
        if self.stuck:
            return
        push_site = self.skill.push_site(self.obs()) if self.kind == "turnon" else None
        move = np.clip(action[:3], -1, 1) * 0.05
        self.rot = Rotation.from_rotvec(np.clip(action[3:6], -1, 1) * 0.5).as_matrix() @ self.rot
        self.eef = self.eef + move
        self.gap = float(np.clip(self.gap - 0.01 * np.sign(action[6]) * (abs(action[6]) > 0.1), 0.0, 0.08))
        if self.kind == "open":
            center = (self.handle[:3] + self.handle[3:]) / 2
            near = np.all(np.abs(self.eef - center) <= (self.handle[3:] - self.handle[:3]) / 2 + 0.012)
            if action[6] > 0 and near and self.gap <= 0.03:
                self.grasp = True
            if action[6] < 0:
                self.grasp = False
            if self.grasp:
                self.handle = self.handle + np.tile(self.d * float(move @ self.d), 2)
        else:
            rel = self.eef - push_site
            along = float(rel @ self.d)
            lateral = rel - along * self.d
            if along > 0 and np.linalg.norm(lateral[:2]) < 0.012 and abs(lateral[2]) < 0.015:
                self.handle = self.handle + np.tile(self.d * along, 2)  # the finger pushes the lever


def test_handle_milestones_have_their_own_kinds() -> None:
    """A handle's reached/contact milestones are articulation kinds, not a pick-and-place object's."""
    assert [milestone_kind(n) for n in DRAWER] == ["reached_handle", "contact_handle", "open"]
    assert milestone_kind("contact(cab_middle.handle)#2") == "contact_handle"
    assert milestone_kind("reached(bowl_1)") == "reached" and milestone_kind("contact(plate_1)") == "contact"
    assert stage_of("reached(stove_1.handle)") == ("reached_handle",)


# ---- the predicate ----------------------------------------------------------------------------------


def _windows(fixture: Fixture, hand_path, handle_shift=0.0):
    frames = []
    for i, eef in enumerate(hand_path):
        fixture.eef = np.asarray(eef, dtype=np.float64)
        obs = fixture.obs()
        if handle_shift:
            obs["task_object_bbox"] = obs["task_object_bbox"] + np.tile(fixture.d * handle_shift * i / len(hand_path), 2)
        frames.append(Frame(i, signals.visible(obs), None, frozenset(), EXACT.sensor(obs)))
    return Window(tuple(frames), "", fixture.names)


def _holds(w: Window, **overrides) -> bool:
    spec = PREDICATES["articulation_stalled"]
    return spec.fn(w, resolve(spec.params, overrides, "articulation_stalled")) is not None


def test_articulation_stalled_fires_on_a_hand_that_hovers_or_wiggles_without_moving_the_handle() -> None:
    hover = [(-0.1 + 0.002 * np.sin(i), 0.05, 1.15) for i in range(45)]
    assert _holds(_windows(Fixture("open"), hover))
    assert not _holds(_windows(Fixture("open"), hover[:30])), "needs its horizon"
    approach = [(-0.1 + 0.003 * i, 0.05 - 0.004 * i, 1.15 - 0.003 * i) for i in range(45)]
    assert not _holds(_windows(Fixture("open"), approach)), "closing in on the handle is progress"
    assert not _holds(_windows(Fixture("open"), hover, handle_shift=0.05)), "a moving handle is progress"
    pick = _windows(Fixture("open"), hover)
    frames = [Frame(f.step, {**f.obs, "task_stage": _one_hot(STAGE_KINDS, "in")}, None, f.milestones, f.perceive)
              for f in pick.frames]
    assert not _holds(Window(tuple(frames), "", ())), "silent on a pick-and-place stage"


# ---- playbooks and the repair search ---------------------------------------------------------------


def test_redirection_serves_every_articulation_kind_and_the_harness_never_moves_a_handle() -> None:
    check_playbooks()
    assert set(ARTICULATION_STAGES) == {"reached_handle", "contact_handle", "open", "close", "turnon", "turnoff"}
    for kind in ARTICULATION_STAGES:
        for holding in (None, False, True):
            assert [p.name for p in serving(kind, holding)] == ["redirect"]
    assert PLAYBOOKS["redirect"].steps == ("redirect_instruction",)
    assert "operate" not in PLAYBOOKS


def test_the_harness_library_shares_no_code_with_the_scripted_oracle() -> None:
    """Nothing under services/harness imports the oracle's modules or the handle motions it uses
    (geometry helpers such as services.common.rotations are shared math, not the oracle's skills)."""
    banned = ("services.common.handles", "services.policy_worker")
    paths = sorted((ROOT / "services" / "harness").rglob("*.py"))
    assert ROOT / "services" / "harness" / "runtime" / "library" / "recoveries.py" in paths, "the scan sees the library"
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [f"{node.module}.{a.name}" for a in node.names] if isinstance(node, ast.ImportFrom) else [])
            assert not any(n.startswith(banned) for n in names), f"{path}: imports {names}"


def _stalled_drawer_trace(seed: int):
    """A policy that wanders near a closed drawer and never reaches its bar (m* = reached(.handle))."""
    rng = np.random.default_rng(seed)
    fixture = Fixture("open")
    rec = TraceRecorder(DRAWER)
    for k in range(80):
        fixture.eef = np.array([-0.15, 0.1, 1.15]) + rng.normal(0, 0.002, 3) + (0.03 * min(k, 10) / 10, 0, 0)
        obs = {k2: np.asarray(v, np.float32) for k2, v in fixture.obs().items()}
        obs.update({"robot0_joint_pos": np.zeros(7, np.float32), "milestones": np.zeros(24, np.float32),
                    "milestones_reached": np.zeros(24, np.float32), "phi_finger_contact": np.zeros(2, np.float32),
                    "phi_eef_motion": np.zeros(6, np.float32), "phi_collision_intensity": np.zeros(1, np.float32)})
        actions = None if k == 0 else np.tile(np.array([0, 0, 0, 0, 0, 0, -1.0], np.float32), (2, 1))
        rec.frame(2 * k, obs, actions)
    return rec.finish()


def test_repair_offers_redirection_for_a_policy_that_stalls_at_a_drawer() -> None:
    """A cluster whose m* is a handle milestone is offered instruction redirection first, granted at
    every articulation kind; no pick-and-place playbook is offered for it."""
    misses = [_stalled_drawer_trace(s) for s in range(4)]
    index = SuccessIndex.build([])
    eods = [t_eod(t, index) for t in misses]
    detect = {n: first_fire(misses[0], p.fn, {k: v.default for k, v in p.params.items()})
              for n, p in PREDICATES.items() if n not in ("grasp_retained", "supported_placement")}
    assert detect["articulation_stalled"] is not None
    spec = repair_spec("0/r1/K1", "key", Case(misses[0], eods[0], False, DRAWER[0], {}, detect, 40), [])
    medoid = ReplayCase(misses[0], eods[0].step, eods[0].referenced)
    members = [ReplayCase(t, e.step, e.referenced) for t, e in zip(misses[1:], eods[1:])]
    cands = search(spec, HarnessDraft("evolved-0", ("0",)), medoid, members, [], SearchParams(max_candidates=6))
    assert cands and cands[0].plan.playbook == "redirect" and cands[0].plan.recovery == "redirect_instruction"
    assert set(ARTICULATION_STAGES) <= set(cands[0].critic.missing)
    assert any(c.critic.template == "articulation_stalled" for c in cands)
    assert not any(c.plan.playbook in ("acquire", "place") for c in cands)
