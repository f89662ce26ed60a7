"""Numpy arrays to and from the wire format (shared by the SDK and every service): dtype, shape and raw bytes, nothing else.

No pickling, no per-element encoding: ``tobytes`` on the way out and ``frombuffer`` (a view, no
copy) on the way in, which is what keeps 128x128 images cheap on the step path.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from zetta_wire.v1 import types_pb2

_TO_WIRE: dict[np.dtype, types_pb2.Dtype] = {
    np.dtype("float32"): types_pb2.DTYPE_FLOAT32,
    np.dtype("float64"): types_pb2.DTYPE_FLOAT64,
    np.dtype("float16"): types_pb2.DTYPE_FLOAT16,
    np.dtype("uint8"): types_pb2.DTYPE_UINT8,
    np.dtype("int8"): types_pb2.DTYPE_INT8,
    np.dtype("int32"): types_pb2.DTYPE_INT32,
    np.dtype("int64"): types_pb2.DTYPE_INT64,
    np.dtype("bool"): types_pb2.DTYPE_BOOL,
}
_FROM_WIRE: dict[int, np.dtype] = {v: k.newbyteorder("<") for k, v in _TO_WIRE.items()}


class TensorDecodeError(ValueError):
    """A tensor on the wire is malformed (unknown dtype, byte count not matching its shape)."""


def dtype_to_wire(dtype: np.dtype | str) -> types_pb2.Dtype:
    """Wire enum of a numpy dtype; raises ValueError for dtypes that cannot travel."""
    try:
        return _TO_WIRE[np.dtype(dtype)]
    except KeyError:
        raise ValueError(f"dtype {np.dtype(dtype)} cannot travel; use one of {sorted(str(d) for d in _TO_WIRE)}") from None


def dtype_from_wire(code: int) -> np.dtype:
    """Numpy dtype of a wire enum value."""
    try:
        return _FROM_WIRE[code]
    except KeyError:
        known = ", ".join(types_pb2.Dtype.Name(c) for c in _FROM_WIRE)
        raise TensorDecodeError(f"dtype {code} is not supported; use one of {known}") from None


def encode(array: np.ndarray, out: types_pb2.Tensor | None = None) -> types_pb2.Tensor:
    """Write ``array`` into ``out`` (or a new Tensor) as little-endian C-order bytes."""
    tensor = out if out is not None else types_pb2.Tensor()
    arr = np.asarray(array)
    if arr.dtype.byteorder == ">":
        arr = arr.astype(arr.dtype.newbyteorder("<"))
    tensor.dtype = dtype_to_wire(arr.dtype)
    tensor.shape[:] = arr.shape
    tensor.data = np.ascontiguousarray(arr).tobytes()
    return tensor


def decode(tensor: types_pb2.Tensor) -> np.ndarray:
    """A read-only numpy view over the tensor's bytes."""
    dtype = dtype_from_wire(tensor.dtype)
    shape = tuple(int(d) for d in tensor.shape)
    if any(d < 0 for d in shape):
        raise TensorDecodeError(f"negative dimension in shape {list(shape)}")
    expected = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if len(tensor.data) != expected:
        raise TensorDecodeError(
            f"tensor of dtype {dtype} and shape {list(shape)} needs {expected} bytes, got {len(tensor.data)}"
        )
    return np.frombuffer(tensor.data, dtype=dtype).reshape(shape)


def encode_observation(arrays: Mapping[str, np.ndarray], out: types_pb2.Observation | None = None) -> types_pb2.Observation:
    """Fill an Observation message with named tensors."""
    obs = out if out is not None else types_pb2.Observation()
    for name, array in arrays.items():
        encode(array, obs.tensors[name])
    return obs


def decode_observation(obs: types_pb2.Observation) -> dict[str, np.ndarray]:
    """Named numpy views over an Observation message."""
    return {name: decode(t) for name, t in obs.tensors.items()}
