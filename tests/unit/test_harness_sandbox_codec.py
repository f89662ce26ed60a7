"""The sandbox channel's per-step encoding (services/harness/sandbox/codec.py): a frame's
observation as one block laid out by the last LAYOUT message, milestones only when they change,
detections as 9 float64 each; the child decodes what the host encoded, exactly."""

from __future__ import annotations

import numpy as np
import pytest

from services.harness.runtime.api import Detection
from services.harness.sandbox import codec


def _messages(data: bytes) -> list[tuple[int, memoryview]]:
    out, pos = [], 0
    while pos < len(data):
        length, kind = codec._HEAD.unpack_from(data, pos)
        out.append((kind, memoryview(data)[pos + 5: pos + 4 + length]))
        pos += 4 + length
    return out


def _roundtrip(enc: codec.FrameEncoder, dec: codec.FrameDecoder, step, obs, action, milestones):
    w = codec.Writer()
    layout = enc.encode(w, step, obs, action, milestones)
    msgs = _messages(layout + w.message(codec.PUSH))
    for kind, body in msgs[:-1]:
        assert kind == codec.LAYOUT
        dec.set_layout(body)
    r = codec.Reader(msgs[-1][1])
    out = dec.decode(r)
    r.done()
    return bool(layout), out


def test_frames_round_trip_and_the_layout_is_sent_only_when_it_changes() -> None:
    enc, dec = codec.FrameEncoder(), codec.FrameDecoder()
    obs = {"robot0_eef_pos": np.arange(3, dtype=np.float32), "phi_grasp": np.float64(0.5) * np.ones(1),
           "task_stage": np.zeros((2, 4), dtype=np.int8), "empty_depth": np.zeros((0, 3)),
           "strided_image": np.arange(24, dtype=np.uint8).reshape(4, 6)[:, ::2]}  # not contiguous
    sent, (step, got, action, ms) = _roundtrip(enc, dec, 0, obs, None, frozenset())
    assert sent and step == 0 and action is None and ms == frozenset()
    assert list(got) == list(obs)
    for k, v in obs.items():
        assert got[k].dtype == v.dtype and got[k].shape == v.shape and np.array_equal(got[k], v)
    obs2 = {k: v + 1 for k, v in obs.items()}
    sent, (step, got, action, ms) = _roundtrip(enc, dec, 1, obs2, np.array([0.1, -1.0]), frozenset({"a", "b"}))
    assert not sent and step == 1 and ms == {"a", "b"} and np.array_equal(action, [0.1, -1.0])
    assert all(np.array_equal(got[k], obs2[k]) for k in obs2)
    sent, (_, _, _, ms) = _roundtrip(enc, dec, 2, obs2, None, frozenset({"a", "b"}))
    assert not sent and ms == {"a", "b"}  # the same milestones: not sent again, still decoded
    # Same bytes, another shape: a new layout.
    obs3 = {**obs2, "task_stage": obs2["task_stage"].reshape(4, 2)}
    sent, (_, got, _, ms) = _roundtrip(enc, dec, 3, obs3, None, frozenset())
    assert sent and got["task_stage"].shape == (4, 2) and ms == frozenset()


def test_a_block_that_does_not_match_its_layout_is_refused() -> None:
    enc, dec = codec.FrameEncoder(), codec.FrameDecoder()
    _roundtrip(enc, dec, 0, {"phi_grasp": np.zeros(2)}, None, frozenset())
    w = codec.Writer()
    codec.FrameEncoder().encode(w, 1, {"phi_grasp": np.zeros(3)}, None, frozenset())
    with pytest.raises(codec.WireError, match="layout"):
        dec.decode(codec.Reader(memoryview(w.message(codec.PUSH))[5:]))
    with pytest.raises(ValueError, match="object arrays"):
        codec.FrameEncoder().encode(codec.Writer(), 0, {"x": np.array([object()])}, None, frozenset())


@pytest.mark.parametrize("found", [None, Detection(np.array([1.0, 2, 3]), np.arange(6.0)),
                                   [], [Detection(np.array([1.0, 2, 3]), np.arange(6.0)),
                                        Detection(np.zeros(3), np.ones(6))]])
def test_detections_round_trip_as_writable_copies(found) -> None:
    w = codec.Writer()
    codec.encode_detections(w, found)
    r = codec.Reader(memoryview(w.message(codec.PERCEPT))[5:])
    got = codec.decode_detections(r, Detection)
    r.done()
    if found is None:
        assert got is None
        return
    for a, b in zip(found if isinstance(found, list) else [found], got if isinstance(got, list) else [got]):
        assert np.array_equal(a.pos, b.pos) and np.array_equal(a.box, b.box)
        assert b.pos.flags.writeable and b.box.flags.writeable
    assert isinstance(got, list) == isinstance(found, list)
