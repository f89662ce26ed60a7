"""The contract of the gateway's harness tools (Perceive, Move), checked where requests enter.

One definition for the gateway, which refuses bad requests before they reach a worker, and the
env worker and harness runtime, which implement them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from services.common import grpc_errors as ge
from zetta_wire.v1 import types_pb2

#: What the perception tool estimates: the object the current stage is about, where it goes, the rest.
QUERIES = ("object", "target", "others")
DEFAULT_QUERIES = ("object", "target")
#: Longest motion one Move call may run: well below an episode, like a recovery's step budget.
MAX_MOTION_STEPS = 100
DEFAULT_TOLERANCE_M = 0.005
DEFAULT_ANGLE_TOLERANCE_RAD = 0.05


def check_queries(queries: Sequence[str]) -> list[str]:
    """The queries to answer (the default when none), or INVALID_ARGUMENT saying which are known."""
    if not queries:
        return list(DEFAULT_QUERIES)
    unknown = [q for q in queries if q not in QUERIES]
    if unknown:
        raise ge.invalid(f"perception queries {unknown!r} are unknown; known: {', '.join(QUERIES)}")
    if len(set(queries)) != len(queries):
        raise ge.invalid(f"perception queries {list(queries)!r} repeat a query; ask each at most once")
    return list(queries)


def check_motion(session_id: str, m: types_pb2.Motion) -> None:
    """INVALID_ARGUMENT naming the session for a motion no controller should run."""
    def bad(what: str) -> ge.ServiceError:
        return ge.invalid(f"motion of session {session_id}: {what}", [session_id])

    if len(m.position) not in (0, 3) or not np.all(np.isfinite(m.position)):
        raise bad(f"position must be 3 finite numbers (x, y, z in metres) or empty, got {list(m.position)[:8]}")
    if not (np.isfinite(m.gripper) and -1.0 <= m.gripper <= 1.0):
        raise bad(f"gripper must be in [-1, 1] (-1 opens, +1 closes), got {m.gripper}")
    if not 1 <= m.max_steps <= MAX_MOTION_STEPS:
        raise bad(f"max_steps must be 1 to {MAX_MOTION_STEPS}, got {m.max_steps}")
    if not (np.isfinite(m.tolerance_m) and 0.0 <= m.tolerance_m <= 0.5):
        raise bad(f"tolerance_m must be in [0, 0.5] metres (0: {DEFAULT_TOLERANCE_M}), got {m.tolerance_m}")
    if not (np.isfinite(m.max_action) and 0.0 <= m.max_action <= 1.0):
        raise bad(f"max_action must be in (0, 1] (0: 1), got {m.max_action}")
    if len(m.orientation) not in (0, 4) or not np.all(np.isfinite(m.orientation)) or (
            len(m.orientation) and abs(float(np.linalg.norm(m.orientation)) - 1.0) > 0.01):
        raise bad(f"orientation must be a unit quaternion [x, y, z, w] (norm within 0.01 of 1) or empty, "
                  f"got {list(m.orientation)[:8]}")
    if len(m.orientation) and m.hand_down:
        raise bad("orientation and hand_down both set the hand's orientation; send one")
    if not (np.isfinite(m.angle_tolerance_rad) and 0.0 <= m.angle_tolerance_rad <= np.pi):
        raise bad(f"angle_tolerance_rad must be in [0, pi] (0: {DEFAULT_ANGLE_TOLERANCE_RAD}), "
                  f"got {m.angle_tolerance_rad}")
