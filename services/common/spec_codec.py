"""TensorSpec to and from its proto form."""

from __future__ import annotations

from services.common.specs import TensorSpec
from zetta_wire.codec import dtype_from_wire, dtype_to_wire
from zetta_wire.v1 import types_pb2


def spec_to_wire(spec: TensorSpec, out: types_pb2.TensorSpec | None = None) -> types_pb2.TensorSpec:
    """Proto form of a TensorSpec."""
    msg = out if out is not None else types_pb2.TensorSpec()
    msg.name = spec.name
    msg.dtype = dtype_to_wire(spec.dtype)
    msg.shape[:] = spec.shape
    msg.privileged = spec.privileged
    msg.description = spec.description
    if spec.low is not None:
        msg.low = spec.low
    if spec.high is not None:
        msg.high = spec.high
    return msg


def spec_from_wire(msg: types_pb2.TensorSpec) -> TensorSpec:
    """TensorSpec of its proto form."""
    return TensorSpec(
        name=msg.name,
        dtype=str(dtype_from_wire(msg.dtype).newbyteorder("=")),
        shape=tuple(int(d) for d in msg.shape),
        privileged=msg.privileged,
        description=msg.description,
        low=msg.low if msg.HasField("low") else None,
        high=msg.high if msg.HasField("high") else None,
    )
