"""The wire format of tensors: raw little-endian bytes, dtype and shape, nothing else.

Every hop (SDK, gateway, env worker, policy worker, other languages) relies on this exact layout,
so round trips, the byte-count check and the byte order are pinned down here.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.common.spec_codec import spec_from_wire, spec_to_wire
from services.common.specs import WIRE_DTYPES, SpecError, TensorSpec
from zetta_wire.codec import (
    TensorDecodeError,
    decode,
    decode_observation,
    dtype_from_wire,
    dtype_to_wire,
    encode,
    encode_observation,
)
from zetta_wire.v1 import types_pb2

_WIRE = {
    "float32": types_pb2.DTYPE_FLOAT32, "float64": types_pb2.DTYPE_FLOAT64, "float16": types_pb2.DTYPE_FLOAT16,
    "uint8": types_pb2.DTYPE_UINT8, "int8": types_pb2.DTYPE_INT8, "int32": types_pb2.DTYPE_INT32,
    "int64": types_pb2.DTYPE_INT64, "bool": types_pb2.DTYPE_BOOL,
}


def _sample(dtype: str, shape: tuple[int, ...]) -> np.ndarray:
    rng = np.random.default_rng(7)
    if dtype == "bool":
        return rng.integers(0, 2, size=shape).astype(bool)
    if dtype.startswith("float"):
        return (rng.standard_normal(shape) * 100).astype(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)


@pytest.mark.parametrize("dtype", WIRE_DTYPES)
@pytest.mark.parametrize("shape", [(), (0,), (5,), (2, 3, 4)])
def test_round_trip_every_dtype(dtype: str, shape: tuple[int, ...]) -> None:
    """decode(encode(x)) gives x back bit for bit, with the documented dtype enum and byte count."""
    array = _sample(dtype, shape)
    tensor = encode(array)
    assert tensor.dtype == _WIRE[dtype]
    assert tuple(tensor.shape) == shape
    assert len(tensor.data) == array.size * np.dtype(dtype).itemsize
    # Survives serialisation too: the message is what crosses the network.
    back = decode(types_pb2.Tensor.FromString(tensor.SerializeToString()))
    assert back.dtype == np.dtype(dtype)
    assert back.shape == shape
    np.testing.assert_array_equal(back, array)


def test_wire_enum_covers_every_spec_dtype() -> None:
    """The dtypes a TensorSpec may declare are exactly the ones the codec can carry."""
    assert sorted(WIRE_DTYPES) == sorted(_WIRE)
    for name, code in _WIRE.items():
        assert dtype_to_wire(name) == code
        assert dtype_from_wire(code) == np.dtype(name)


def test_decode_is_a_read_only_view() -> None:
    """No copy on the way in: the array shares the message's bytes and cannot be written through."""
    back = decode(encode(np.arange(6, dtype=np.float32).reshape(2, 3)))
    assert not back.flags.writeable
    with pytest.raises(ValueError):
        back[0, 0] = 1.0


def test_non_contiguous_input_is_sent_in_c_order() -> None:
    """A transposed (Fortran-ordered) view travels in row-major order of its logical shape."""
    base = np.arange(12, dtype=np.int32).reshape(3, 4)
    view = base.T
    back = decode(encode(view))
    np.testing.assert_array_equal(back, view)
    assert encode(view).data == np.ascontiguousarray(view).tobytes()


@pytest.mark.parametrize("delta", [-1, 1, 4])
def test_wrong_byte_count_raises(delta: int) -> None:
    """Bytes that do not match dtype x shape are refused with a message giving both counts."""
    tensor = encode(np.zeros((2, 3), dtype=np.float32))
    tensor.data = tensor.data[:delta] if delta < 0 else tensor.data + b"\0" * delta
    with pytest.raises(TensorDecodeError) as info:
        decode(tensor)
    assert "needs 24 bytes" in str(info.value)
    assert f"got {24 + delta}" in str(info.value)


def test_unknown_dtype_and_negative_shape_raise() -> None:
    """DTYPE_UNSPECIFIED (0), unknown enum values and negative dimensions are malformed."""
    with pytest.raises(TensorDecodeError, match="not supported"):
        decode(types_pb2.Tensor(dtype=types_pb2.DTYPE_UNSPECIFIED, shape=[1], data=b"\0"))
    with pytest.raises(TensorDecodeError):
        decode(types_pb2.Tensor(dtype=99, shape=[1], data=b"\0"))
    with pytest.raises(TensorDecodeError, match="negative dimension"):
        decode(types_pb2.Tensor(dtype=types_pb2.DTYPE_UINT8, shape=[-1], data=b""))


def test_decode_error_is_a_value_error() -> None:
    """Callers that catch ValueError also catch malformed tensors."""
    assert issubclass(TensorDecodeError, ValueError)


def test_untravelable_dtype_raises() -> None:
    """complex and object arrays cannot travel; the message lists what can."""
    with pytest.raises(ValueError, match="cannot travel"):
        encode(np.zeros(2, dtype=np.complex64))
    with pytest.raises(ValueError, match="cannot travel"):
        dtype_to_wire("uint16")


@pytest.mark.parametrize("dtype", ["float32", "float64", "int32", "int64", "float16"])
def test_big_endian_input_is_sent_little_endian(dtype: str) -> None:
    """A big-endian array is converted: the wire bytes are little-endian and decode to the same values."""
    values = np.array([1, -2, 300, 4096], dtype=dtype)
    big = values.astype(np.dtype(dtype).newbyteorder(">"))
    assert big.tobytes() != values.astype(np.dtype(dtype).newbyteorder("<")).tobytes()
    tensor = encode(big)
    assert tensor.data == values.astype(np.dtype(dtype).newbyteorder("<")).tobytes()
    back = decode(tensor)
    assert back.dtype.byteorder in ("<", "=", "|") or back.dtype.isnative
    np.testing.assert_array_equal(back, values)


def test_decode_reads_little_endian_bytes_by_contract() -> None:
    """Bytes written by a little-endian producer in another language decode to the intended values."""
    raw = (1).to_bytes(4, "little") + (258).to_bytes(4, "little", signed=True)
    tensor = types_pb2.Tensor(dtype=types_pb2.DTYPE_INT32, shape=[2], data=raw)
    np.testing.assert_array_equal(decode(tensor), [1, 258])


def test_encode_into_existing_message() -> None:
    """``out`` is filled in place (how observations are written without extra copies)."""
    msg = types_pb2.StepResult()
    encode(np.ones((1, 7), dtype=np.float32), msg.executed_actions)
    assert tuple(msg.executed_actions.shape) == (1, 7)
    np.testing.assert_array_equal(decode(msg.executed_actions), np.ones((1, 7), dtype=np.float32))


def test_observation_round_trip() -> None:
    """Named tensors of mixed dtypes survive an Observation message."""
    arrays = {
        "robot0_eef_pos": np.array([0.1, 0.2, 0.3], dtype=np.float32),
        "agentview_image": np.arange(2 * 2 * 3, dtype=np.uint8).reshape(2, 2, 3),
        "task_grasped": np.array([1.0], dtype=np.float32),
        "flags": np.array([True, False]),
    }
    msg = types_pb2.Observation.FromString(encode_observation(arrays).SerializeToString())
    back = decode_observation(msg)
    assert set(back) == set(arrays)
    for name, array in arrays.items():
        assert back[name].dtype == array.dtype
        np.testing.assert_array_equal(back[name], array)


@pytest.mark.parametrize("dtype", WIRE_DTYPES)
def test_spec_round_trip(dtype: str) -> None:
    """A TensorSpec comes back equal from its proto form, free dimensions included."""
    spec = TensorSpec(name="action", dtype=dtype, shape=(-1, 7), privileged=True, description="chunk of actions")
    msg = types_pb2.TensorSpec.FromString(spec_to_wire(spec).SerializeToString())
    assert msg.dtype == _WIRE[dtype]
    assert list(msg.shape) == [-1, 7]
    back = spec_from_wire(msg)
    assert back == spec
    assert back.dtype == dtype  # native-order name, not '<f4'
    assert (back.privileged, back.description) == (True, "chunk of actions")


def test_spec_bounds_round_trip_and_stay_unset_when_unbounded() -> None:
    """Bounds travel with the spec (a gymnasium action space is built from them); an unbounded
    spec leaves them unset rather than sending 0."""
    bounded = TensorSpec(name="action", dtype="float32", shape=(7,), low=-1.0, high=1.0)
    back = spec_from_wire(types_pb2.TensorSpec.FromString(spec_to_wire(bounded).SerializeToString()))
    assert (back.low, back.high) == (-1.0, 1.0)
    msg = spec_to_wire(TensorSpec(name="x", dtype="float32", shape=(3,)))
    assert not msg.HasField("low") and not msg.HasField("high")
    assert spec_from_wire(msg).low is None and spec_from_wire(msg).high is None


def test_spec_from_wire_rejects_unknown_dtype() -> None:
    """A spec with an unset dtype is malformed, not silently float32."""
    with pytest.raises(TensorDecodeError):
        spec_from_wire(types_pb2.TensorSpec(name="x", shape=[1]))


def test_spec_check_against_decoded_arrays() -> None:
    """Decoded arrays pass the spec they were declared against; a wrong shape or dtype is named."""
    spec = TensorSpec(name="action", dtype="float32", shape=(-1, 7))
    spec.check(decode(encode(np.zeros((3, 7), dtype=np.float32))))
    with pytest.raises(SpecError, match="expected shape"):
        spec.check(decode(encode(np.zeros((3, 6), dtype=np.float32))))
    with pytest.raises(SpecError, match="expected dtype float32"):
        spec.check(decode(encode(np.zeros((3, 7), dtype=np.float64))))
