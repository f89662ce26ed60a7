"""Action values and policy specs checked against what the session declared, before anything runs.

A NaN, an infinity or a value outside the action spec's [low, high] would be executed by the
simulator without complaint (and poison the episode's trace), so the gateway refuses it with the
session and the element's index; the whole batch fails and nothing in it steps.
"""

from __future__ import annotations

import numpy as np

from services.common import grpc_errors as ge
from services.gateway.registry import SessionRecord
from zetta_wire.v1 import types_pb2

#: Most actions one ActionStep may execute per session (a chunk), and most a PolicySpec may ask for.
MAX_CHUNK = 256
#: Longest instruction (PolicySpec, ResetSpec) and longest task or harness name (ResetSpec): these
#: strings go on to the policy's text encoder and the harness registry, so they are bounded here.
MAX_INSTRUCTION_CHARS = 2000
MAX_NAME_CHARS = 256


def _where(values: np.ndarray, mask: np.ndarray) -> tuple[str, float]:
    """The first offending element as ``[i]`` or ``[k, i]`` and its value."""
    index = tuple(int(i) for i in np.argwhere(mask)[0])
    return "[" + ", ".join(map(str, index)) + "]", float(values[index])


def check_action_values(rec: SessionRecord, values: np.ndarray) -> None:
    """INVALID_ARGUMENT naming the session and index of the first non-finite or out-of-range element."""
    if values.dtype.kind != "f" and rec.action_low is None and rec.action_high is None:
        return
    if values.dtype.kind == "f":
        bad = ~np.isfinite(values)
        if bad.any():
            at, value = _where(values, bad)
            raise ge.invalid(
                f"action of session {rec.session_id}: element {at} is {value}; actions must be finite",
                [rec.session_id],
            )
    low = -np.inf if rec.action_low is None else rec.action_low
    high = np.inf if rec.action_high is None else rec.action_high
    out = (values < low) | (values > high)
    if out.any():
        at, value = _where(values, out)
        raise ge.invalid(
            f"action of session {rec.session_id}: element {at} is {value:g}, outside the action spec's "
            f"range [{low:g}, {high:g}]",
            [rec.session_id],
        )


def check_policy_spec(policy: types_pb2.PolicySpec) -> None:
    """Refuse an execute_steps or timeout_ms that cannot mean anything (INVALID_ARGUMENT)."""
    if not 0 <= policy.execute_steps <= MAX_CHUNK:
        raise ge.invalid(
            f"policy.execute_steps must be between 0 (the whole chunk) and {MAX_CHUNK}, got {policy.execute_steps}"
        )
    if policy.timeout_ms < 0:
        raise ge.invalid(f"policy.timeout_ms must be >= 0 (0: the server default), got {policy.timeout_ms}")
    if len(policy.instruction) > MAX_INSTRUCTION_CHARS:
        raise ge.invalid(f"policy.instruction has {len(policy.instruction)} characters; at most {MAX_INSTRUCTION_CHARS}")
    if len(policy.model) > MAX_NAME_CHARS:
        raise ge.invalid(f"policy.model has {len(policy.model)} characters; at most {MAX_NAME_CHARS}")


def check_reset_spec(spec: types_pb2.ResetSpec, what: str = "spec") -> None:
    """Refuse a ResetSpec whose strings are longer than any real one (INVALID_ARGUMENT)."""
    if len(spec.instruction) > MAX_INSTRUCTION_CHARS:
        raise ge.invalid(f"{what}.instruction has {len(spec.instruction)} characters; at most {MAX_INSTRUCTION_CHARS}")
    for field in ("task", "harness", "harness_dir"):
        value = getattr(spec, field)
        if len(value) > MAX_NAME_CHARS:
            raise ge.invalid(f"{what}.{field} has {len(value)} characters; at most {MAX_NAME_CHARS}")
