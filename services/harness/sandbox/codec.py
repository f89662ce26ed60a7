"""The sandbox channel's wire format: length-prefixed binary frames, arrays as raw bytes.

Every message is ``u32 length | u8 kind | payload``. Numbers are packed with :mod:`struct`,
strings as ``u32 length | UTF-8``, numpy arrays as ``dtype string | ndim | shape | raw bytes``.
The parent never unpickles what a sandbox child sends (the child runs untrusted code): replies
are decoded here, field by field, and anything malformed raises :class:`WireError`. The
direction parent -> child carries only trusted data; its set-up messages (the package's files)
are pickled, the per-step messages are not.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

# Parent -> child.
INIT = 1        # pickled set-up: package files or sources, params, window size, whether to check
START = 2       # pickled: instruction, milestone names (a new episode)
STEP = 3        # a frame, then the indices of the critics to run (evaluate)
PUSH = 4        # a frame only (restoring the window of a respawned child)
REC_START = 5   # start a package recovery: its mode, "<stem>:<factory>" and pickled params
REC_ACT = 6     # the active package recovery's next action
PERCEPT = 7     # the answer to a perception query
CHECK = 8       # pickled files: load and build a runtime inside the sandbox (publish-time probe)
# Child -> parent.
READY = 20      # isolation report after start-up
LOADED = 21     # critic names and module-level callables, or an error
RESULTS = 22    # one result per critic run
PERCEIVE = 23   # a perception query: frame step, query
REC_STARTED = 24
REC_ACTION = 25
CHECKED = 26    # problems found by CHECK
ERROR = 27      # the request failed (text)

MAX_MESSAGE = 64 << 20
#: Most bytes a child's reply may take: larger is a protocol violation.
MAX_REPLY = 1 << 20

_U32 = struct.Struct("<I")
_HEAD = struct.Struct("<IB")
_I64 = struct.Struct("<q")
_F64 = struct.Struct("<d")


class WireError(ValueError):
    """A message that does not decode (a child that broke the protocol)."""


def frame(kind: int, payload: bytes | bytearray | memoryview = b"") -> bytes:
    """One message: length, kind, payload."""
    return _HEAD.pack(len(payload) + 1, kind) + bytes(payload)


class Writer:
    """Builds a payload from parts."""

    __slots__ = ("parts",)

    def __init__(self) -> None:
        self.parts: list[bytes | memoryview] = []

    def u32(self, v: int) -> None:
        self.parts.append(_U32.pack(v))

    def i64(self, v: int) -> None:
        self.parts.append(_I64.pack(v))

    def f64(self, v: float) -> None:
        self.parts.append(_F64.pack(v))

    def text(self, s: str) -> None:
        b = s.encode("utf-8", "replace")
        self.parts.append(_U32.pack(len(b)))
        self.parts.append(b)

    def texts(self, items: Sequence[str]) -> None:
        self.u32(len(items))
        for s in items:
            self.text(s)

    def array(self, a: np.ndarray) -> None:
        if not a.flags.c_contiguous:
            a = np.ascontiguousarray(a).reshape(a.shape)  # (ascontiguousarray makes a 0-d array 1-d)
        dt = a.dtype.str.encode()
        self.parts.append(struct.pack(f"<B{len(dt)}sB{a.ndim}I", len(dt), dt, a.ndim, *a.shape))
        self.parts.append(a.data.cast("B") if a.nbytes else b"")

    def arrays(self, named: Mapping[str, np.ndarray]) -> None:
        self.u32(len(named))
        for k, v in named.items():
            self.text(k)
            self.array(np.asarray(v))

    def message(self, kind: int) -> bytes:
        body = b"".join(self.parts)
        return _HEAD.pack(len(body) + 1, kind) + body


class Reader:
    """Reads a payload back; every read is bounds-checked."""

    __slots__ = ("buf", "pos")

    def __init__(self, buf: bytes | memoryview) -> None:
        self.buf = memoryview(buf)
        self.pos = 0

    def _take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.buf):
            raise WireError(f"message truncated at byte {self.pos} (wanted {n} more of {len(self.buf)})")
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out

    def u32(self) -> int:
        return int(_U32.unpack(self._take(4))[0])

    def i64(self) -> int:
        return int(_I64.unpack(self._take(8))[0])

    def f64(self) -> float:
        return float(_F64.unpack(self._take(8))[0])

    def text(self, limit: int = 1 << 16) -> str:
        n = self.u32()
        if n > limit:
            raise WireError(f"string of {n} bytes over the limit of {limit}")
        return bytes(self._take(n)).decode("utf-8", "replace")

    def texts(self, limit: int = 4096) -> list[str]:
        n = self.u32()
        if n > limit:
            raise WireError(f"{n} strings over the limit of {limit}")
        return [self.text() for _ in range(n)]

    def array(self, copy: bool = False) -> np.ndarray:
        (n,) = struct.unpack("<B", self._take(1))
        dt = np.dtype(bytes(self._take(n)).decode("ascii"))
        if dt.hasobject:
            raise WireError("object arrays are not allowed")
        (ndim,) = struct.unpack("<B", self._take(1))
        shape = struct.unpack(f"<{ndim}I", self._take(4 * ndim))
        count = 1
        for s in shape:
            count *= s
        data = self._take(count * dt.itemsize)
        a = np.frombuffer(data, dtype=dt).reshape(shape)
        return a.copy() if copy else a

    def arrays(self) -> dict[str, np.ndarray]:
        n = self.u32()
        return {self.text(): self.array() for _ in range(n)}

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise WireError(f"{len(self.buf) - self.pos} bytes left over")


def encode_frame(w: Writer, step: int, obs: Mapping[str, np.ndarray], action: np.ndarray | None,
                 milestones: Iterable[str]) -> None:
    """A trajectory frame (what critics read): step, observation, action, milestones."""
    w.i64(step)
    w.arrays(obs)
    if action is None:
        w.u32(0)
    else:
        w.u32(1)
        w.array(np.asarray(action))
    w.texts(sorted(milestones))


def decode_frame(r: Reader) -> tuple[int, dict[str, np.ndarray], np.ndarray | None, frozenset[str]]:
    step = r.i64()
    obs = r.arrays()
    action = r.array() if r.u32() else None
    return step, obs, action, frozenset(r.texts())


# Per-critic result kinds in RESULTS.
R_NONE, R_PROPOSAL, R_ERROR = 0, 1, 2


def encode_proposal(w: Writer, evidence: str, mode: str, details: Mapping[str, Any]) -> None:
    w.text(evidence)
    w.text(mode)
    w.u32(len(details))
    for k, v in details.items():
        w.text(str(k))
        w.f64(float(v))


def decode_proposal(r: Reader) -> tuple[str, str, dict[str, float]]:
    evidence, mode = r.text(), r.text()
    n = r.u32()
    if n > 1024:
        raise WireError(f"{n} details over the limit of 1024")
    return evidence, mode, {r.text(): r.f64() for _ in range(n)}


def pack_detections(found: Any) -> bytes:
    """A perception answer: -1 for None, -2 then one box for a single Detection, else a list."""
    w = Writer()
    if found is None:
        w.i64(-1)
    elif isinstance(found, list):
        w.i64(len(found))
        for d in found:
            w.array(np.asarray(d.pos, dtype=np.float64))
            w.array(np.asarray(d.box, dtype=np.float64))
    else:
        w.i64(-2)
        w.array(np.asarray(found.pos, dtype=np.float64))
        w.array(np.asarray(found.box, dtype=np.float64))
    return w.message(PERCEPT)
