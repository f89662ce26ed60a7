"""Post-settle snapshots of LIBERO environments, per episode key: a repeated reset restores them.

A LIBERO reset is robosuite's ``env.reset()``, the benchmark's init state, then ``settle_steps``
no-op actions so the objects come to rest (docs/simulation.md: the settle steps are 83% of a
reset). Those steps are a pure function of the state they start from, so the second reset of a
key in a sharing group (on any of its environments) does not need to replay them: it keeps ``env.reset()`` and the init
state (they choose the fixture model and rebuild the controller), checks that the simulation
stands exactly where it stood when the snapshot was taken, and copies the settled state back:

* the whole ``MjData`` (``mj_copyData``: positions, velocities, warm start, controls, contacts,
  every derived quantity, exactly as the last settle step left them);
* the Python state the fast step path changes: the env's step counters and observation cache,
  the OSC controller's state, the gripper's command, every observable's sampling timer and last
  value, and LIBERO's tracked object states;
* the settle steps' last observation.

Only environments stepped by the fast path's :class:`~services.env_worker.fast_step.FastStepper`
are snapshotted: robosuite's own ``env.step`` also fills per-robot history buffers. The snapshots
of a group live in one :class:`Store` that its environments share (the group's family attaches it),
so a key settled on one slot restores on another. A snapshot is used only when the environment
holds the same ``MjModel`` object, or one of the same template (services/env_worker/sharing.py:
they differ at most in fixture poses), with the same fixture poses, and the freshly set init state
equals the one it was taken from, bit for bit; anything else replays the settle steps.
``tests/unit/test_families.py`` checks that a restored reset steps the same trajectory as a
replayed one, on the same environment and on another.
"""

from __future__ import annotations

import copy
import threading
from collections import OrderedDict
from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.env_worker.sharing import interchangeable

#: Snapshots kept per store (one holds about 1.5 MB resident on a LIBERO-Goal scene: MuJoCo copies
#: only the used part of MjData); the least recently used goes first.
CAPACITY = 32
_ATTR = "_zetta_settled"
#: Env attributes a step changes, and the observable fields a sample changes.
_ENV_FIELDS = ("timestep", "cur_time", "done", "_obs_cache")
_OBSERVABLE_FIELDS = ("_time_since_last_sample", "_current_delay", "_current_observed_value", "_sampled")


def _state_fields(obj: Any) -> dict[str, Any]:
    """Copies of an object's plain-data attributes (arrays, numbers, flags, strings, None)."""
    out = {}
    for name, value in vars(obj).items():
        if isinstance(value, np.ndarray):
            out[name] = value.copy()
        elif value is None or isinstance(value, (bool, int, float, str, np.generic)):
            out[name] = value
    return out


def _put(obj: Any, fields: Mapping[str, Any]) -> None:
    for name, value in fields.items():
        setattr(obj, name, value.copy() if isinstance(value, np.ndarray) else copy.deepcopy(value))


@dataclass
class Snapshot:
    """The settled state of one key on one environment."""

    model: Any
    body_pos: np.ndarray
    body_quat: np.ndarray
    start: np.ndarray
    data: Any
    env_fields: dict[str, Any]
    controller: dict[str, Any]
    gripper: dict[str, Any]
    observables: dict[str, dict[str, Any]]
    tracked: list[dict[str, Any]]
    observation: dict[str, Any]

    def matches(self, env: Any, start: np.ndarray) -> bool:
        """The environment stands where it stood when this snapshot's settle steps began."""
        model = env.sim.model._model
        return (
            (model is self.model or interchangeable(model, self.model))
            and np.array_equal(model.body_pos, self.body_pos)
            and np.array_equal(model.body_quat, self.body_quat)
            and np.array_equal(start, self.start)
        )

    def restore(self, env: Any) -> dict[str, Any]:
        """Put the settled state back; returns the settle steps' last observation."""
        import mujoco

        mujoco.mj_copyData(env.sim.data._data, env.sim.model._model, self.data)
        _put(env, self.env_fields)
        robot = env.robots[0]
        _put(robot.controller, self.controller)
        _put(robot.gripper, self.gripper)
        for name, fields in self.observables.items():
            _put(env._observables[name], fields)
        for state, fields in zip(env.tracking_object_states_change, self.tracked, strict=True):
            _put(state, fields)
        return copy.deepcopy(self.observation)


def start_state(env: Any) -> np.ndarray:
    """The simulation state the settle steps start from (what the snapshot must match)."""
    return np.asarray(env.sim.get_state().flatten(), dtype=np.float64)


def capture(env: Any, start: np.ndarray, observation: Mapping[str, Any]) -> Snapshot:
    """The settled state of ``env`` now, after settle steps that began at ``start``."""
    import mujoco

    model = env.sim.model._model
    data = mujoco.MjData(model)
    mujoco.mj_copyData(data, model, env.sim.data._data)
    robot = env.robots[0]
    return Snapshot(
        model=model,
        body_pos=model.body_pos.copy(),
        body_quat=model.body_quat.copy(),
        start=start.copy(),
        data=data,
        env_fields={name: copy.deepcopy(getattr(env, name)) for name in _ENV_FIELDS},
        controller=_state_fields(robot.controller),
        gripper={"current_action": np.array(robot.gripper.current_action)},
        observables={
            name: {f: copy.deepcopy(getattr(o, f)) for f in _OBSERVABLE_FIELDS} for name, o in env._observables.items()
        },
        tracked=[_state_fields(state) for state in env.tracking_object_states_change],
        observation=copy.deepcopy(dict(observation)),
    )


class Store:
    """The settled snapshots of a sharing group's environments, by key, least recently used first out."""

    def __init__(self, capacity: int = CAPACITY) -> None:
        self.capacity = capacity
        self._snaps: OrderedDict[Hashable, Snapshot] = OrderedDict()
        self._lock = threading.Lock()  # slots reset on their own threads

    def get(self, key: Hashable) -> Snapshot | None:
        with self._lock:
            snap = self._snaps.get(key)
            if snap is not None:
                self._snaps.move_to_end(key)
            return snap

    def put(self, key: Hashable, snap: Snapshot) -> None:
        with self._lock:
            self._snaps[key] = snap
            self._snaps.move_to_end(key)
            while len(self._snaps) > self.capacity:
                self._snaps.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._snaps.clear()

    def __len__(self) -> int:
        return len(self._snaps)


def attach(env: Any, store: Store) -> None:
    """Make ``env`` keep and restore its snapshots in ``store`` (its group's)."""
    setattr(env, _ATTR, store)


def forget(env: Any) -> None:
    """Drop every snapshot ``env`` could restore (its group's store): its next reset of any key
    replays the settle steps (what a benchmark that repeats keys does to measure first resets)."""
    found: Store | None = getattr(env, _ATTR, None)
    if found is not None:
        found.clear()


def lookup(env: Any, key: Hashable, start: np.ndarray) -> Snapshot | None:
    """The snapshot of ``key`` in ``env``'s store if it applies to the state ``env`` stands in now."""
    found: Store | None = getattr(env, _ATTR, None)
    snap = found.get(key) if found is not None else None
    return snap if snap is not None and snap.matches(env, start) else None


def store(env: Any, key: Hashable, snap: Snapshot) -> None:
    """Keep ``snap`` for ``key`` in ``env``'s store (a store of its own if no group attached one)."""
    found: Store | None = getattr(env, _ATTR, None)
    if found is None:
        found = Store()
        attach(env, found)
    found.put(key, snap)
