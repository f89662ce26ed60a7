"""The sandbox channel's wire format: length-prefixed binary frames, arrays as raw bytes.

Every message is ``u32 length | u8 kind | payload``. Numbers are packed with :mod:`struct`,
strings as ``u32 length | UTF-8``, numpy arrays as ``dtype string | ndim | shape | raw bytes``.
A frame's observation is one block of raw bytes laid out as the last LAYOUT message said (names,
dtypes, shapes: sent again only when they change, so a step carries no per-array headers).
The parent never unpickles what a sandbox child sends (the child runs untrusted code): replies
are decoded here, field by field, and anything malformed raises :class:`WireError`. The
direction parent -> child carries only trusted data; its set-up messages (the package's files)
are pickled, the per-step messages are not.
"""

from __future__ import annotations

import pickle
import struct
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

# Parent -> child.
INIT = 1        # pickled set-up: package files or sources, params, window size, whether to check
START = 2       # pickled: instruction, milestone names, policy instructions (a new episode)
STEP = 3        # a frame, then the indices of the critics to run (evaluate)
PUSH = 4        # a frame only, with perception answers: the steps since the last call (or a respawned child's window)
REC_START = 5   # start a package recovery: its mode, "<stem>:<factory>" and pickled params
REC_ACT = 6     # the active package recovery's next action
PERCEPT = 7     # the answer to a perception query
CHECK = 8       # pickled files: load and build a runtime inside the sandbox (publish-time probe)
LAYOUT = 9      # pickled [(name, dtype string, shape)]: how the observation blocks that follow are laid out
POLICY = 10     # pickled: the instructions the policy was trained on (Window.policy_instructions), no reply
# Child -> parent.
READY = 20      # isolation report after start-up
LOADED = 21     # critic names and module-level callables, or an error
RESULTS = 22    # per critic run its result head (RESULT), then the proposals and errors, then the queries asked
PERCEIVE = 23   # a perception query: frame step, query
REC_STARTED = 24
REC_ACTION = 25
CHECKED = 26    # problems found by CHECK
ERROR = 27      # the request failed (text)

MAX_MESSAGE = 64 << 20
#: Most bytes a child's reply may take: larger is a protocol violation.
MAX_REPLY = 1 << 20

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_HEAD = struct.Struct("<IB")
_I64 = struct.Struct("<q")
_F64 = struct.Struct("<d")
#: One critic's result in RESULTS: its index, the result kind, its elapsed time. RESULTS carries
#: the count, every result's head, then the bodies of the proposals and errors in order.
RESULT = struct.Struct("<IId")
_RESULT_HEADS: dict[int, struct.Struct] = {}


def result_heads(n: int) -> struct.Struct:
    """The heads of ``n`` results, packed back to back (:data:`RESULT` each)."""
    heads = _RESULT_HEADS.get(n)
    if heads is None:
        heads = struct.Struct("<" + "IId" * n)
        if len(_RESULT_HEADS) < 1024:
            _RESULT_HEADS[n] = heads
    return heads
#: A frame's milestones are the previous frame's (sent in place of a count of strings).
SAME_MILESTONES = 0xFFFFFFFF
#: One detection on the wire: position (3) and box (6), float64.
_DETECTION = 9
_STEP_HEAD = struct.Struct("<qI")
_SAME = _U32.pack(SAME_MILESTONES)
_NINE = struct.Struct("<9d")


class WireError(ValueError):
    """A message that does not decode (a child that broke the protocol)."""


def frame(kind: int, payload: bytes | bytearray | memoryview = b"") -> bytes:
    """One message: length, kind, payload."""
    return _HEAD.pack(len(payload) + 1, kind) + bytes(payload)


class Writer:
    """Builds a payload from parts."""

    __slots__ = ("parts",)

    def __init__(self) -> None:
        #: bytes-like parts (numpy arrays are written as their raw bytes, C-contiguous only).
        self.parts: list[Any] = []

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
        """Named arrays: per array a header (name, dtype, shape; cached, the same every step) and
        the raw bytes."""
        self.u32(len(named))
        parts = self.parts
        for k, v in named.items():
            a = v if isinstance(v, np.ndarray) and v.flags.c_contiguous else _contiguous(np.asarray(v))
            key = (k, a.dtype, a.shape)
            head = _HEADERS.get(key)
            if head is None:
                head = _header(k, a)
                if len(_HEADERS) < 4096:
                    _HEADERS[key] = head
            parts.append(head)
            if a.nbytes:
                parts.append(a.data.cast("B"))

    def message(self, kind: int) -> bytes:
        body = b"".join(self.parts)
        return _HEAD.pack(len(body) + 1, kind) + body


_HEADERS: dict[tuple[str, np.dtype[Any], tuple[int, ...]], bytes] = {}
_ARRAY_HEADS: dict[bytes, tuple[np.dtype[Any], tuple[int, ...], int]] = {}


def _parse_array_head(head: bytes) -> tuple[np.dtype[Any], tuple[int, ...], int]:
    """``u8 n | dtype string (n) | u8 ndim | u32 shape (ndim)`` -> dtype, shape, byte count."""
    n = head[0]
    try:
        dt = np.dtype(head[1 : 1 + n].decode("ascii"))
    except (TypeError, ValueError, UnicodeDecodeError) as exc:
        raise WireError(f"bad array dtype: {exc}") from None
    if dt.hasobject:
        raise WireError("object arrays are not allowed")
    ndim = head[1 + n]
    shape = struct.unpack_from(f"<{ndim}I", head, 2 + n)
    count = 1
    for d in shape:
        count *= d
    return dt, tuple(shape), count * dt.itemsize
_PARSED: dict[bytes, tuple[str, np.dtype[Any], tuple[int, ...], int]] = {}


def _contiguous(a: np.ndarray) -> np.ndarray:
    return a if a.flags.c_contiguous else np.ascontiguousarray(a).reshape(a.shape)


def _header(name: str, a: np.ndarray) -> bytes:
    """``u16 length | name | dtype | ndim | shape``, then the payload's byte count."""
    n, dt = name.encode(), a.dtype.str.encode()
    body = struct.pack(f"<H{len(n)}sB{len(dt)}sB{a.ndim}I", len(n), n, len(dt), dt, a.ndim, *a.shape)
    return struct.pack("<H", len(body)) + body + _U32.pack(a.nbytes)


def _parse_header(body: bytes) -> tuple[str, np.dtype[Any], tuple[int, ...], int]:
    try:
        (n,) = struct.unpack_from("<H", body, 0)
        name = body[2 : 2 + n].decode()
        pos = 2 + n
        dl = body[pos]
        dt = np.dtype(body[pos + 1 : pos + 1 + dl].decode("ascii"))
        pos += 1 + dl
        ndim = body[pos]
        shape = struct.unpack_from(f"<{ndim}I", body, pos + 1)
        if pos + 1 + 4 * ndim != len(body):
            raise WireError("array header has trailing bytes")
    except (struct.error, IndexError, UnicodeDecodeError, TypeError, ValueError) as exc:
        raise WireError(f"bad array header: {exc}") from None
    if dt.hasobject:
        raise WireError("object arrays are not allowed")
    count = 1
    for d in shape:
        count *= d
    return name, dt, tuple(shape), count * dt.itemsize


class Reader:
    """Reads a payload back; every read is bounds-checked."""

    __slots__ = ("buf", "pos", "end")

    def __init__(self, buf: bytes | memoryview) -> None:
        self.buf = memoryview(buf)
        self.pos = 0
        self.end = len(self.buf)

    def _take(self, n: int) -> memoryview:
        pos = self.pos
        if n < 0 or pos + n > self.end:
            raise WireError(f"message truncated at byte {pos} (wanted {n} more of {self.end})")
        self.pos = pos + n
        return self.buf[pos : pos + n]

    def _at(self, size: int) -> int:
        pos = self.pos
        if pos + size > self.end:
            raise WireError(f"message truncated at byte {pos} (wanted {size} more of {self.end})")
        self.pos = pos + size
        return pos

    def u32(self) -> int:
        return int(_U32.unpack_from(self.buf, self._at(4))[0])

    def take(self, n: int) -> memoryview:
        """The next ``n`` bytes."""
        return self._take(n)

    def take_at(self, n: int) -> int:
        """Skip the next ``n`` bytes (bounds-checked); returns where they begin in :attr:`buf`."""
        return self._at(n)

    def result(self) -> tuple[int, int, float]:
        """One critic result's head (:data:`RESULT`)."""
        index, kind, elapsed = RESULT.unpack_from(self.buf, self._at(RESULT.size))
        return index, kind, elapsed

    def u32s(self, n: int) -> tuple[int, ...]:
        """``n`` u32 values at once."""
        if n < 0 or n > 1 << 20:
            raise WireError(f"{n} values")
        return struct.unpack_from(f"<{n}I", self.buf, self._at(4 * n))

    def i64(self) -> int:
        return int(_I64.unpack_from(self.buf, self._at(8))[0])

    def f64(self) -> float:
        return float(_F64.unpack_from(self.buf, self._at(8))[0])

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
        buf, pos = self.buf, self.pos
        try:  # the header (dtype, ndim, shape) parsed once per distinct header
            n = buf[pos]
            size = 2 + n + 4 * buf[pos + 1 + n]
        except IndexError:
            raise WireError(f"message truncated at byte {pos}") from None
        if pos + size > self.end:
            raise WireError(f"message truncated at byte {pos} (wanted {size} more of {self.end})")
        head = bytes(buf[pos : pos + size])
        parsed = _ARRAY_HEADS.get(head)
        if parsed is None:
            parsed = _parse_array_head(head)
            if len(_ARRAY_HEADS) < 256:
                _ARRAY_HEADS[head] = parsed
        dt, shape, nbytes = parsed
        self._at(len(head))
        a = np.frombuffer(self._take(nbytes), dtype=dt).reshape(shape)
        return a.copy() if copy else a

    def arrays(self) -> dict[str, np.ndarray]:
        n = self.u32()
        out = {}
        for _ in range(n):
            (hl,) = _U16.unpack_from(self.buf, self._at(2))
            head = bytes(self._take(hl))
            parsed = _PARSED.get(head)
            if parsed is None:
                parsed = _parse_header(head)
                if len(_PARSED) < 4096:
                    _PARSED[head] = parsed
            name, dt, shape, nbytes = parsed
            if self.u32() != nbytes:
                raise WireError(f"array {name}: byte count does not match its shape")
            out[name] = np.frombuffer(self._take(nbytes), dtype=dt).reshape(shape)
        return out

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise WireError(f"{len(self.buf) - self.pos} bytes left over")


class FrameEncoder:
    """Encodes frames for one child (host side): the observation as one block of raw bytes, its
    layout in a LAYOUT message only when it changed, the milestones only when they changed."""

    __slots__ = ("_key", "_milestones", "_names", "_signature")

    def __init__(self) -> None:
        self._key: Any = None
        self._milestones: frozenset[str] | None = None
        #: The names and (dtype, shape) of the last frame's arrays, when all were plain arrays.
        self._names: tuple[str, ...] | None = None
        self._signature: list[tuple[np.dtype[Any], tuple[int, ...]]] | None = None

    def encode(self, w: Writer, step: int, obs: Mapping[str, np.ndarray], action: np.ndarray | None,
               milestones: frozenset[str]) -> bytes:
        """Writes the frame into ``w``; returns the LAYOUT message to send before it (b"" when the
        child knows the layout already)."""
        values = list(obs.values())
        block = None
        try:  # the common case: the layout of the last frame, every array C-contiguous
            if [(v.dtype, v.shape) for v in values] == self._signature and tuple(obs) == self._names:
                block = b"".join(values)  # (refuses a non-contiguous array)
        except (AttributeError, TypeError, ValueError, BufferError):
            block = None
        layout = b""
        if block is None:
            arrays = [v if type(v) is np.ndarray and v.flags.c_contiguous else _contiguous(np.asarray(v))
                      for v in values]
            key = (tuple(obs), [(a.dtype, a.shape) for a in arrays])
            if key != self._key:
                if any(a.dtype.hasobject for a in arrays):
                    raise ValueError("object arrays cannot go to the sandbox")
                self._key = key
                layout = frame(LAYOUT, pickle.dumps([(n, a.dtype.str, a.shape) for n, a in zip(key[0], arrays)]))
            # Arrays that are their own layout (not numpy scalars or other sequences) take the fast
            # path from the next frame on.
            exact = all(type(v) is np.ndarray for v in values)
            self._names, self._signature = (key[0], key[1]) if exact else (None, None)
            block = b"".join(arrays)
        parts = w.parts
        parts.append(_STEP_HEAD.pack(step, len(block)))
        parts.append(block)
        if action is None:
            parts.append(_U32.pack(0))
        else:
            parts.append(_U32.pack(1))
            w.array(np.asarray(action))
        if milestones == self._milestones:
            parts.append(_SAME)
        else:
            self._milestones = milestones
            w.texts(sorted(milestones))
        return layout


class FrameDecoder:
    """The inverse of :class:`FrameEncoder` (child side). The layout comes from the host (trusted);
    every read is still bounds-checked."""

    __slots__ = ("_layout", "_nbytes", "_milestones", "_dtype", "_slices")

    def __init__(self) -> None:
        self._layout: list[tuple[str, np.dtype[Any], int, int, tuple[int, ...]]] = []
        self._nbytes = 0
        self._milestones: frozenset[str] = frozenset()
        #: When every array of the layout has one dtype: that dtype, and per array its name,
        #: element range and shape (None: 1-d), to cut from one array over the whole block.
        self._dtype: np.dtype[Any] | None = None
        self._slices: list[tuple[str, int, int, tuple[int, ...] | None]] = []

    def set_layout(self, body: bytes | memoryview) -> None:
        layout, offset = [], 0
        for name, dt, shape in pickle.loads(body):
            dtype = np.dtype(dt)
            count = 1
            for d in shape:
                count *= d
            layout.append((name, dtype, offset, count, tuple(shape)))
            offset += count * dtype.itemsize
        self._layout, self._nbytes = layout, offset
        dtypes = {dt for _, dt, _, _, _ in layout}
        self._dtype = None
        if len(dtypes) == 1:
            (dtype,) = dtypes
            self._dtype = dtype
            self._slices = [(name, off // dtype.itemsize, off // dtype.itemsize + count, None if len(shape) == 1 else shape)
                            for name, _, off, count, shape in layout]

    def decode(self, r: Reader) -> tuple[int, dict[str, np.ndarray], np.ndarray | None, frozenset[str]]:
        step = r.i64()
        n = r.u32()
        if n != self._nbytes:
            raise WireError(f"observation of {n} bytes, its layout says {self._nbytes}")
        block = r.take(n)
        if self._dtype is not None:  # one array over the block, a view per observation (cheaper)
            flat = np.frombuffer(block, self._dtype)
            obs = {name: flat[a:b] if shape is None else flat[a:b].reshape(shape) for name, a, b, shape in self._slices}
        else:
            frombuffer = np.frombuffer
            obs = {name: frombuffer(block, dt, count, off).reshape(shape) for name, dt, off, count, shape in self._layout}
        action = r.array() if r.u32() else None
        n = r.u32()
        if n != SAME_MILESTONES:
            r.pos -= 4
            self._milestones = frozenset(r.texts())
        return step, obs, action, self._milestones


# Per-critic result kinds in RESULTS.
R_NONE, R_PROPOSAL, R_ERROR = 0, 1, 2


def encode_proposal(w: Writer, evidence: str, mode: str, details: Mapping[str, Any]) -> None:
    """``u32 length | head (evidence, mode, detail names) | one f64 per detail``: a critic
    proposes the same kinds with the same detail names step after step, so the head is built once
    per distinct kind (child side) and parsed once per distinct head (host side)."""
    key = (evidence, mode, tuple(details))
    head = _PROPOSAL_HEADS.get(key)
    if head is None:
        h = Writer()
        h.text(evidence)
        h.text(mode)
        h.texts([str(k) for k in key[2]])
        head = b"".join(h.parts)
        head = _U32.pack(len(head)) + head
        if len(_PROPOSAL_HEADS) < 1024:
            _PROPOSAL_HEADS[key] = head
    w.parts.append(head)
    values = [float(v) for v in details.values()]
    w.parts.append(_doubles(len(values)).pack(*values))


def decode_proposal(r: Reader) -> tuple[str, str, dict[str, float]]:
    n = r.u32()
    if n > 1 << 16:
        raise WireError(f"proposal head of {n} bytes")
    head = bytes(r.take(n))
    parsed = _PARSED_PROPOSALS.get(head)
    if parsed is None:
        h = Reader(head)
        evidence, mode, keys = h.text(), h.text(), tuple(h.texts(1024))
        h.done()
        parsed = (evidence, mode, keys)
        # (Bounded: the heads come from untrusted children. A child that fills it costs every
        # child of this host a parse per proposal, nothing else.)
        if len(head) <= 512 and len(_PARSED_PROPOSALS) < 256:
            _PARSED_PROPOSALS[head] = parsed
    evidence, mode, keys = parsed
    values = _doubles(len(keys)).unpack_from(r.buf, r.take_at(8 * len(keys))) if keys else ()
    return evidence, mode, dict(zip(keys, values))


_PROPOSAL_HEADS: dict[tuple[str, str, tuple[Any, ...]], bytes] = {}
_PARSED_PROPOSALS: dict[bytes, tuple[str, str, tuple[str, ...]]] = {}
_DOUBLES: dict[int, struct.Struct] = {}


def _doubles(n: int) -> struct.Struct:
    packer = _DOUBLES.get(n)
    if packer is None:
        packer = struct.Struct(f"<{n}d")
        if len(_DOUBLES) < 1024:
            _DOUBLES[n] = packer
    return packer


def pack_detections(found: Any) -> bytes:
    """A perception answer as a message of its own."""
    w = Writer()
    encode_detections(w, found)
    return w.message(PERCEPT)


def encode_detections(w: Writer, found: Any) -> None:
    """A perception answer: -1 for None, -2 then one detection for a single Detection, else the
    count; each detection as 9 float64 (position, box)."""
    if found is None:
        w.i64(-1)
    elif isinstance(found, list):
        w.i64(len(found))
        w.parts.extend(_detection(d) for d in found)
    else:
        w.i64(-2)
        w.parts.append(_detection(found))


def _detection(d: Any) -> bytes:
    pos, box = d.pos, d.box
    values = ((pos.tolist() if type(pos) is np.ndarray and pos.ndim == 1 else np.ravel(pos).tolist())
              + (box.tolist() if type(box) is np.ndarray and box.ndim == 1 else np.ravel(box).tolist()))
    if len(values) != _DETECTION:
        raise ValueError(f"a detection is a position (3) and a box (6), got {len(values)} numbers")
    try:
        return _NINE.pack(*values)
    except struct.error:  # not numbers: as float64 (what the array version did), or its error
        return np.array(values, dtype=np.float64).tobytes()


def decode_detections(r: Reader, detection: Any) -> Any:
    """The inverse of :func:`encode_detections`; ``detection`` builds one (api.Detection). The
    arrays are writable copies, as in-process."""
    n = r.i64()
    if n == -1:
        return None
    if n == -2:
        a = np.frombuffer(r.take(8 * _DETECTION), np.float64).copy()
        return detection(a[:3], a[3:])
    if n < 0 or n > 4096:
        raise WireError(f"{n} detections")
    rows = np.frombuffer(r.take(8 * _DETECTION * n), np.float64).reshape(n, _DETECTION).copy()
    return [detection(row[:3], row[3:]) for row in rows]
