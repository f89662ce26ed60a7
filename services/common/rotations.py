"""Rotation conversions that the scripted oracle and the harness's motion tools both need.

Quaternions are xyzw, the order the observation tensors use (robosuite's convention).
"""

from __future__ import annotations

import numpy as np


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """xyzw quaternion to rotation matrix (the quaternion need not be normalized)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / max(float(np.linalg.norm(q)), 1e-9)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rotvec(m: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix, stable near 0 and near pi."""
    cos = np.clip((np.trace(m) - 1) / 2, -1.0, 1.0)
    angle = float(np.arccos(cos))
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    norm = float(np.linalg.norm(axis))
    if norm < 1e-6:  # angle near pi: the axis is the dominant column of (m + I)
        col = m + np.eye(3)
        axis = col[:, int(np.argmax(np.linalg.norm(col, axis=0)))]
        norm = float(np.linalg.norm(axis))
    return axis / norm * angle


def hand_down(finger_axis_xy: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation of the hand pointing down with the fingers closing along ``finger_axis_xy``, taking
    the sign nearest the current hand (rotation ``current``) so it never turns by more than 90 degrees.

    The hand is narrow across its finger axis (about 7 cm) and wide along it (about 21 cm), so a
    push with the side of the fingers needs little room behind the object."""
    y = np.array([finger_axis_xy[0], finger_axis_xy[1], 0.0])
    y /= max(float(np.linalg.norm(y)), 1e-9)
    if float(y @ current[:, 1]) < 0:
        y = -y
    z = np.array([0.0, 0.0, -1.0])
    return np.column_stack([np.cross(y, z), y, z])
