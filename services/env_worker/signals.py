"""Physio-auxiliary signals phi_t: what the gripper and the task object are doing physically.

The paper's Loop 1 records, with every step, signals such as contact forces and collision
intensities next to the milestones; the runtime critics of the case studies read the same ones
(bilateral finger contact, the grasp predicate, object-gripper drift, realized vs commanded motion,
gripper aperture). They are published as privileged observation tensors (names ``phi_*``), declared
in the observation schema like any other tensor, so a critic, a rollout store or a client reads them
without any side channel.

Everything here is a pure function over MuJoCo arrays (``MjModel``/``MjData`` or plain numpy),
unit-tested on small constructed models; :class:`SignalTracker` is the only stateful piece: it keeps
what one signal needs from the previous step (the grasp reference of the drift, the previous
end-effector position) and is reset with the episode. Nothing here imports robosuite or LIBERO.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.common.specs import TensorSpec

#: The signals, in schema order: (name, shape, description). All are float32 and privileged.
SIGNALS: tuple[tuple[str, tuple[int, ...], str], ...] = (
    ("phi_finger_contact", (2,), "left, right finger (pad or body) touches the task object: 1.0 or 0.0"),
    ("phi_grasp", (1,), "grasp predicate: both fingers touch the task object (1.0 or 0.0)"),
    (
        "phi_object_gripper_drift",
        (1,),
        "how far (m) the task object moved in the end-effector frame since the grasp began; 0 when not grasped",
    ),
    ("phi_eef_object_dist", (1,), "distance (m) from the grip site to the task object's box; 0 inside it"),
    ("phi_object_vel", (6,), "task object linear (m/s) and angular (rad/s) velocity, world frame"),
    ("phi_contact_force", (3,), "net contact force (N, world frame) the gripper exerts on the task object"),
    (
        "phi_collision_intensity",
        (1,),
        "sum of normal contact forces (N) between the robot (arm and gripper) and anything but the task object",
    ),
    ("phi_gripper_aperture", (1,), "distance between the finger joints (m): about 0.08 open, 0 closed"),
    (
        "phi_eef_motion",
        (6,),
        "commanded end-effector translation of the last action (m, xyz), then the realized one over that step",
    ),
)


def signal_specs() -> list[TensorSpec]:
    """Schema entries of the signals."""
    return [TensorSpec(name, "float32", shape, privileged=True, description=d) for name, shape, d in SIGNALS]


def zero_signals() -> dict[str, np.ndarray]:
    """Every signal at zero, e.g. for a family step that has no task object."""
    return {name: np.zeros(shape, dtype=np.float32) for name, shape, _ in SIGNALS}


# ---------------------------------------------------------------------------------------------
# Contacts


@dataclass(frozen=True)
class Contacts:
    """The active contacts of one simulation state: geom pairs and the force on geom2 from geom1."""

    geom1: np.ndarray  # [n] int
    geom2: np.ndarray  # [n] int
    force: np.ndarray  # [n, 3] world frame, acting on geom2 (equal and opposite on geom1); [0, 3] if not read
    normal: np.ndarray  # [n] normal force magnitude (>= 0); [0] if not read

    @functools.cached_property
    def pairs(self) -> list[tuple[int, int]]:
        """The geom pairs as Python ints: several checks per step loop over them."""
        return list(zip(self.geom1.tolist(), self.geom2.tolist()))

    @classmethod
    def empty(cls) -> Contacts:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0))


def read_contacts(model: object, data: object, involving: frozenset[int] | None = None,
                  forces: bool = True) -> Contacts:
    """Contacts of a raw ``mujoco.MjModel``/``MjData`` with world-frame forces (``mj_contactForce``).

    ``involving``: keep only the contacts with at least one geom in this set (all when None), in
    MuJoCo's order. The signals only ask about the robot's contacts, while a tabletop scene holds
    many more between objects at rest, each of which would cost an ``mj_contactForce`` call.
    ``forces=False``: only which geoms touch (``force`` and ``normal`` are left empty), for a step
    that latches grasps and milestones but builds no observation.
    """
    import mujoco  # lazily: importing this module must not load a simulator

    n = int(data.ncon)  # type: ignore[attr-defined]
    if n == 0:
        return Contacts.empty()
    contact = data.contact  # type: ignore[attr-defined]
    geom1, geom2 = contact.geom1[:n], contact.geom2[:n]
    if involving is None:
        keep = np.arange(n)
    else:
        mask = _geom_mask(involving, int(model.ngeom))  # type: ignore[attr-defined]
        keep = np.flatnonzero(mask[geom1] | mask[geom2])
        if not len(keep):
            return Contacts.empty()
    pairs = (geom1[keep].astype(np.int64), geom2[keep].astype(np.int64))
    if not forces:
        return Contacts(*pairs, np.zeros((0, 3)), np.zeros(0))
    m = len(keep)
    frames = np.asarray(contact.frame[keep]).reshape(m, 3, 3)
    local = np.zeros((m, 6))
    buf = np.zeros(6)
    for row, i in enumerate(keep.tolist()):
        mujoco.mj_contactForce(model, data, i, buf)
        local[row] = buf
    force = np.einsum("nij,ni->nj", frames, local[:, :3])  # frame rows: normal, tangent1, tangent2
    return Contacts(*pairs, force, np.abs(local[:, 0]))


@functools.lru_cache(maxsize=64)
def _geom_mask(geoms: frozenset[int], ngeom: int) -> np.ndarray:
    """Which of a model's geoms are in ``geoms``: one lookup per contact in place of set tests. One
    entry more than the geoms, never set, so that a contact without a geom (-1: a flex) is in none."""
    mask = np.zeros(ngeom + 1, dtype=bool)
    mask[[g for g in geoms if 0 <= g < ngeom]] = True
    return mask


def _ids(geoms: object) -> frozenset[int]:
    if isinstance(geoms, frozenset):
        return geoms
    return frozenset(int(g) for g in np.asarray(geoms).reshape(-1))


def touches(contacts: Contacts, a: object, b: object) -> bool:
    """Whether any geom of ``a`` is in contact with any geom of ``b`` (arrays or sets of geom ids).

    A plain loop: a scene has tens of contacts, where numpy's set operations cost more than they save.
    """
    sa, sb = _ids(a), _ids(b)
    if not sa or not sb:
        return False
    for g1, g2 in contacts.pairs:
        if (g1 in sa and g2 in sb) or (g1 in sb and g2 in sa):
            return True
    return False


def force_on(contacts: Contacts, by: object, on: object) -> np.ndarray:
    """Net world-frame force (N) that geoms ``by`` exert on geoms ``on``."""
    sby, son = _ids(by), _ids(on)
    total = np.zeros(3)
    for i, (g1, g2) in enumerate(contacts.pairs):
        if g1 in sby and g2 in son:  # the force acts on geom2 from geom1
            total += contacts.force[i]
        elif g1 in son and g2 in sby:
            total -= contacts.force[i]
    return total


def collision_intensity(contacts: Contacts, robot: object, exclude: object) -> float:
    """Sum of normal forces (N) of contacts between ``robot`` geoms and geoms outside ``robot`` and ``exclude``."""
    srobot, sexclude = _ids(robot), _ids(exclude)
    total = 0.0
    for i, (g1, g2) in enumerate(contacts.pairs):
        in1, in2 = g1 in srobot, g2 in srobot
        if (in1 and not in2 and g2 not in sexclude) or (in2 and not in1 and g1 not in sexclude):
            total += float(contacts.normal[i])
    return total


# ---------------------------------------------------------------------------------------------
# Geometry and motion


def aabb_distance(point: np.ndarray, box: np.ndarray) -> float:
    """Euclidean distance from ``point`` to the box [min xyz, max xyz]; 0 inside it."""
    lo, hi = box[:3], box[3:]
    gap = np.maximum(np.maximum(lo - point, point - hi), 0.0)
    return float(np.linalg.norm(gap))


def in_frame(position: np.ndarray, frame_pos: np.ndarray, frame_mat: np.ndarray) -> np.ndarray:
    """``position`` expressed in the frame (origin ``frame_pos``, rotation matrix ``frame_mat``)."""
    return np.asarray(frame_mat).reshape(3, 3).T @ (np.asarray(position) - np.asarray(frame_pos))


def drift(relative_now: np.ndarray, relative_at_grasp: np.ndarray) -> float:
    """How far (m) an object moved relative to the hand since the grasp began."""
    return float(np.linalg.norm(np.asarray(relative_now) - np.asarray(relative_at_grasp)))


def commanded_translation(action: np.ndarray, input_max: np.ndarray, input_min: np.ndarray,
                          output_max: np.ndarray, output_min: np.ndarray) -> np.ndarray:
    """The end-effector translation (m) an OSC_POSE action asks for: robosuite's affine input scaling."""
    a = np.clip(np.asarray(action[:3], dtype=np.float64), input_min[:3], input_max[:3])
    in_mid, in_half = (input_max[:3] + input_min[:3]) / 2, (input_max[:3] - input_min[:3]) / 2
    out_mid, out_half = (output_max[:3] + output_min[:3]) / 2, (output_max[:3] - output_min[:3]) / 2
    return (a - in_mid) * out_half / in_half + out_mid


def body_velocity(model: object, data: object, body_id: int) -> np.ndarray:
    """Linear then angular velocity of a body's frame, world-aligned (``mj_objectVelocity``)."""
    import mujoco

    out = np.zeros(6)
    mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, int(body_id), out, 0)
    return np.concatenate([out[3:], out[:3]])  # MuJoCo returns [rot, lin]


# ---------------------------------------------------------------------------------------------
# Per-slot tracker


@dataclass(frozen=True)
class GripperGeoms:
    """Geom ids of the robot, resolved once per environment."""

    left: frozenset[int]
    right: frozenset[int]
    gripper: frozenset[int]  # hand and both fingers
    robot: frozenset[int]  # every geom of the arm and the gripper

    @functools.cached_property
    def all_geoms(self) -> frozenset[int]:
        """Every geom above: the contacts the signals read are those involving one of these."""
        return self.left | self.right | self.gripper | self.robot


@dataclass(frozen=True)
class SignalInputs:
    """What one step's signals are computed from (all world frame)."""

    contacts: Contacts
    object_geoms: frozenset[int] | np.ndarray
    object_bbox: np.ndarray  # [6]; zeros when there is no task object
    object_pos: np.ndarray
    object_vel: np.ndarray  # [6]
    eef_pos: np.ndarray
    eef_mat: np.ndarray  # [3, 3]
    finger_qpos: np.ndarray  # [2]
    commanded: np.ndarray  # [3] translation the last action asked for (zeros at reset)


class SignalTracker:
    """Computes the signals of each step and keeps the little state two of them need.

    The state must follow every step (a grasp's reference is taken on the step it begins, the
    realized motion is that of the last step), while the signals are read only where an
    observation is built: :meth:`track` runs on every step, :meth:`tensors` on the steps observed,
    and :meth:`compute` does both.
    """

    def __init__(self, geoms: GripperGeoms) -> None:
        self.geoms = geoms
        self._grasp_ref: np.ndarray | None = None
        self._grasp_object = 0
        self._last_eef: np.ndarray | None = None
        self._touch = (False, False)
        self._realized = np.zeros(3)

    def reset(self) -> None:
        """Forget the previous episode."""
        self._grasp_ref = None
        self._grasp_object = 0
        self._last_eef = None
        self._touch = (False, False)
        self._realized = np.zeros(3)

    def track(self, contacts: Contacts, object_geoms: frozenset[int] | np.ndarray, object_pos: np.ndarray,
              eef_pos: np.ndarray, eef_mat: np.ndarray) -> None:
        """Advance the state over one step (contacts need no forces here)."""
        g = self.geoms
        has_object = bool(len(object_geoms))
        left = has_object and touches(contacts, g.left, object_geoms)
        right = has_object and touches(contacts, g.right, object_geoms)
        self._touch = (left, right)
        if left and right:
            key = hash(_ids(object_geoms))
            if self._grasp_ref is None or key != self._grasp_object:
                self._grasp_ref, self._grasp_object = in_frame(object_pos, eef_pos, eef_mat), key
        else:
            self._grasp_ref = None
        self._realized = np.zeros(3) if self._last_eef is None else np.asarray(eef_pos) - self._last_eef
        self._last_eef = np.array(eef_pos, dtype=np.float64)

    @property
    def grasping(self) -> bool:
        """The grasp predicate of the last tracked step: both fingers touch the object."""
        return self._touch[0] and self._touch[1]

    def tensors(self, x: SignalInputs) -> dict[str, np.ndarray]:
        """The signals of the state the last :meth:`track` reached, which ``x`` describes."""
        g = self.geoms
        has_object = bool(len(x.object_geoms))
        left, right = self._touch
        relative = in_frame(x.object_pos, x.eef_pos, x.eef_mat)
        return {
            "phi_finger_contact": np.array([left, right], dtype=np.float32),
            "phi_grasp": np.array([left and right], dtype=np.float32),
            "phi_object_gripper_drift": np.array(
                [drift(relative, self._grasp_ref) if self._grasp_ref is not None else 0.0], dtype=np.float32
            ),
            "phi_eef_object_dist": np.array(
                [aabb_distance(np.asarray(x.eef_pos), x.object_bbox) if has_object else 0.0], dtype=np.float32
            ),
            "phi_object_vel": np.asarray(x.object_vel, dtype=np.float32),
            "phi_contact_force": force_on(x.contacts, g.gripper, x.object_geoms).astype(np.float32)
            if has_object else np.zeros(3, np.float32),
            "phi_collision_intensity": np.array(
                [collision_intensity(x.contacts, g.robot, x.object_geoms)], dtype=np.float32
            ),
            "phi_gripper_aperture": np.array([x.finger_qpos[0] - x.finger_qpos[1]], dtype=np.float32),
            "phi_eef_motion": np.concatenate([x.commanded, self._realized]).astype(np.float32),
        }

    def compute(self, x: SignalInputs) -> dict[str, np.ndarray]:
        """One step: :meth:`track` then :meth:`tensors`."""
        self.track(x.contacts, x.object_geoms, x.object_pos, x.eef_pos, x.eef_mat)
        return self.tensors(x)


def robot_geoms(model: object, gripper_left: Sequence[str], gripper_right: Sequence[str],
                gripper_all: Sequence[str], robot_prefixes: Sequence[str]) -> GripperGeoms:
    """Resolve the robot's geom ids from a raw ``mujoco.MjModel`` (names of fingers, prefixes of bodies)."""
    import mujoco

    def ids(names: Sequence[str]) -> frozenset[int]:
        return frozenset(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names)

    robot = []
    for geom in range(model.ngeom):  # type: ignore[attr-defined]
        body = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[geom])) or ""  # type: ignore[attr-defined]
        if body.startswith(tuple(robot_prefixes)):
            robot.append(geom)
    return GripperGeoms(ids(gripper_left), ids(gripper_right), ids(gripper_all), frozenset(robot))
