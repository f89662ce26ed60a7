"""The perception tool: what the harness knows of objects, as a real detector would report it.

Runtime critics and recoveries never see the simulator's object poses (services/harness/runtime/
signals.py keeps them out of every frame). They ask this tool instead: ``frame.perceive("object")``
for the object the current step of the task is about (the handle, on a drawer or knob stage),
``"target"`` for where it must go, ``"others"`` for the rest of the scene. Behind the API the tool
reads the simulator's state, and it answers only through the noise and failure model below,
which is on by default:

* position noise: every estimate is off by a per-episode bias (``bias_m``, a detector's calibration
  error) plus fresh per-frame jitter (``noise_m``), Gaussian, per axis;
* box size: the box's half extents are off by ``size_noise`` (relative, per episode);
* dropout: with probability ``dropout`` a query returns nothing on a frame (occlusion, a missed
  detection);
* confusion: with probability ``confusion`` the object query returns another object's position
  with the queried object's size (the detector grounded the phrase on the wrong object).

Estimates are drawn once per frame and query, so every read within a step agrees, from a generator
seeded by the episode (the same episode sees the same noise: validation replays stay comparable).
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from services.common.primitives import QUERIES

#: Floats per object in LIBERO's ``object_state``: pos, quat, pos and quat relative to the eef.
OBJECT_STATE_STRIDE = 14


@dataclass(frozen=True)
class NoiseModel:
    """The detector's error model (defaults: a good RGB-D detector at table range)."""

    noise_m: float = 0.004
    bias_m: float = 0.004
    size_noise: float = 0.05
    dropout: float = 0.03
    confusion: float = 0.02

    def __post_init__(self) -> None:
        if min(self.noise_m, self.bias_m, self.size_noise) < 0 or not (0 <= self.dropout < 1 and 0 <= self.confusion < 1):
            raise ValueError(f"perception noise model out of range: {self}")


#: What every harness gets unless its SKILL.md ``[perception]`` table says otherwise.
DEFAULT_NOISE = NoiseModel()
#: The least noise a package may ask for: a harness tuned on an exact sensor would not transfer.
MIN_NOISE = NoiseModel(noise_m=0.002, bias_m=0.002, size_noise=0.02, dropout=0.01, confusion=0.01)


def noise_from_table(table: Mapping[str, object]) -> NoiseModel:
    """SKILL.md ``[perception]`` -> a noise model; refuses unknown keys and noise under :data:`MIN_NOISE`."""
    fields = set(NoiseModel.__dataclass_fields__)
    unknown = sorted(set(table) - fields)
    if unknown:
        raise ValueError(f"[perception]: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(fields))}")
    model = NoiseModel(**{**DEFAULT_NOISE.__dict__, **{k: float(v) for k, v in table.items()}})  # type: ignore[arg-type]
    low = [k for k in fields if getattr(model, k) < getattr(MIN_NOISE, k)]
    if low:
        raise ValueError(f"[perception]: {', '.join(sorted(low))} below the least noise a harness may assume "
                         f"({', '.join(f'{k}={getattr(MIN_NOISE, k)}' for k in sorted(low))})")
    return model


@dataclass(frozen=True)
class Detection:
    """One estimate: the object's centre and axis-aligned box [min xyz, max xyz] (world, m)."""

    pos: np.ndarray
    box: np.ndarray


#: frame.perceive(query) -> a Detection, None (nothing detected), or for "others" a list of them.
Sensor = Callable[[str], "Detection | list[Detection] | None"]


def no_sensor(query: str) -> None:
    """The sensor of a frame built without one (a unit test's window): it never detects anything."""
    return None


def episode_seed(obs: Mapping[str, np.ndarray], instruction: str) -> int:
    """A seed from the episode's reset state and instruction: the same episode, the same noise."""
    h = hashlib.sha256(instruction.encode())
    for name in ("robot0_joint_pos", "robot0_eef_pos"):
        value = obs.get(name)
        if value is not None:
            h.update(np.asarray(value, dtype=np.float32).round(4).tobytes())
    return int.from_bytes(h.digest()[:8], "big")


class Perception:
    """The per-episode detector: its bias and size error, and a generator for per-frame draws."""

    def __init__(self, seed: int, model: NoiseModel = DEFAULT_NOISE) -> None:
        self.model = model
        self._rng = np.random.default_rng(seed)
        self._bias = self._rng.normal(0.0, model.bias_m, 3)
        self._scale = 1.0 + self._rng.normal(0.0, model.size_noise, 3)
        #: What every frame's sensor reads: the bias and scale as Python floats, the draws.
        self._bx, self._by, self._bz = self._bias.tolist()
        self._sx, self._sy, self._sz = self._scale.tolist()

    def sensor(self, exact: Mapping[str, np.ndarray]) -> Sensor:
        """The tool for one frame, reading ``exact`` (the simulator's tensors) behind a closure.

        (Runs at every env step: one small object per frame, and the arithmetic on Python floats,
        in the order of the array expressions it stands for, so the estimates are the same to the
        bit; the draws from the episode's generator are the same and in the same order.)"""
        return _FrameSensor(self, exact)


class _FrameSensor:
    """``frame.perceive``: one frame's answers, drawn when first asked, the same on every read."""

    __slots__ = ("_p", "_exact", "_cache")

    def __init__(self, perception: Perception, exact: Mapping[str, np.ndarray]) -> None:
        self._p = perception
        self._exact = exact
        self._cache: dict[str, Detection | list[Detection] | None] = {}

    def _estimate(self, box: list[float], centre: list[float] | None = None) -> Detection:
        p = self._p
        x0, y0, z0, x1, y1, z1 = box
        if centre is None:
            cx, cy, cz = (x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2
        else:
            cx, cy, cz = centre
        hx, hy, hz = (x1 - x0) / 2 * p._sx, (y1 - y0) / 2 * p._sy, (z1 - z0) / 2 * p._sz
        nx, ny, nz = p._rng.normal(0.0, p.model.noise_m, 3).tolist()
        px, py, pz = cx + p._bx + nx, cy + p._by + ny, cz + p._bz + nz
        return Detection(np.array((px, py, pz)), np.array((px - hx, py - hy, pz - hz, px + hx, py + hy, pz + hz)))

    def _others(self) -> list[list[float]]:
        exact = self._exact
        state = exact.get("object_state")
        if state is None:
            return []
        n = len(state) // OBJECT_STATE_STRIDE
        blocks = np.asarray(state[: n * OBJECT_STATE_STRIDE], dtype=np.float64).reshape(n, OBJECT_STATE_STRIDE)
        pos = blocks[np.any(blocks != 0.0, axis=1)][:, :3]
        obj = exact.get("task_object_pos")
        if obj is not None and np.any(obj):
            pos = pos[np.linalg.norm(pos - np.asarray(obj, dtype=np.float64), axis=1) > 0.02]
        return pos.tolist()

    def __call__(self, query: str) -> Detection | list[Detection] | None:
        cache = self._cache
        if query in cache:
            return cache[query]
        if query not in QUERIES:
            raise ValueError(f"perceive({query!r}): queries are {', '.join(QUERIES)}")
        p = self._p
        model, rng = p.model, p._rng
        found: Detection | list[Detection] | None
        if query == "others":
            found = [self._estimate(q + q, q) for q in self._others() if rng.random() >= model.dropout]
        else:
            raw = self._exact.get(f"task_{query}_bbox")
            box = None if raw is None else np.asarray(raw, dtype=np.float64).tolist()
            if box is None or not any(box) or rng.random() < model.dropout:
                found = None
            elif query == "object" and rng.random() < model.confusion and (pool := self._others()):
                found = self._estimate(box, pool[int(rng.integers(len(pool)))])
            else:
                found = self._estimate(box)
        cache[query] = found
        return found
