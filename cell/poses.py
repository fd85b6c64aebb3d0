"""UR poses and 4x4 transforms.

A UR pose is ``[x, y, z, rx, ry, rz]``: a position in metres and a rotation vector in
radians, in the robot's base frame (= the world). Rotation vectors are ambiguous near a
half turn (``r`` and ``-r`` of length pi are the same rotation), so every conversion goes
through :class:`scipy.spatial.transform.Rotation` and never through hand-written
Rodrigues formulas.

Frames are named in variables: ``world_from_flange`` maps flange coordinates to world
coordinates. The :class:`cell.arm.Arm` interface takes and reports FLANGE poses (the
controller's TCP offset is zero); a tool's offset ``flange_from_tool`` comes from the cell
file and is composed here.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from tapecell.estimator.errors import TapecellError
from tapecell.estimator.geometry import is_rotation
from .config import matrix_to_pose, pose_to_matrix


class PoseError(TapecellError):
    """A pose or transform is malformed (wrong shape, not finite, not a rotation)."""


def as_pose6(pose: Any, what: str = "pose") -> np.ndarray:
    """``pose`` as a finite float array of shape (6,), or a :class:`PoseError` naming ``what``."""
    try:
        arr = np.asarray(pose, dtype=float)
    except (TypeError, ValueError):
        raise PoseError(f"{what} is not a numeric [x, y, z, rx, ry, rz]") from None
    if arr.shape != (6,):
        raise PoseError(f"{what} has shape {list(arr.shape)}, expected [x, y, z, rx, ry, rz]")
    if not np.all(np.isfinite(arr)):
        raise PoseError(f"{what} holds NaN or infinite numbers")
    return arr


def as_transform(T: Any, what: str = "transform", tol: float = 1e-6) -> np.ndarray:
    """``T`` as a 4x4 rigid transform (rotation block orthonormal, det +1), or a PoseError."""
    try:
        arr = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        raise PoseError(f"{what} is not a numeric 4x4 matrix") from None
    if arr.shape != (4, 4):
        raise PoseError(f"{what} has shape {list(arr.shape)}, expected 4x4")
    if not np.all(np.isfinite(arr)):
        raise PoseError(f"{what} holds NaN or infinite numbers")
    if not is_rotation(arr[:3, :3], tol):
        raise PoseError(f"{what} has a rotation block that is not a rotation matrix")
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0]):
        raise PoseError(f"{what} has a last row other than [0, 0, 0, 1]")
    return arr


def pose6_to_matrix(pose: Any) -> np.ndarray:
    """[x, y, z, rx, ry, rz] (m, rotation vector rad) -> 4x4 transform."""
    return pose_to_matrix(as_pose6(pose))


def matrix_to_pose6(T: Any) -> np.ndarray:
    """4x4 transform -> [x, y, z, rx, ry, rz]; the rotation vector has length <= pi."""
    return matrix_to_pose(as_transform(T))


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (``a_from_b`` -> ``b_from_a``)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_from(rotation: Any, translation: Any) -> np.ndarray:
    """4x4 transform from a (3, 3) rotation and a (3,) translation [m]."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(rotation, float)
    T[:3, 3] = np.asarray(translation, float)
    return as_transform(T)


def flange_target_for_tool(world_from_tool: Any, flange_from_tool: Any) -> np.ndarray:
    """The flange pose6 that puts the tool frame at ``world_from_tool``.

    world_from_flange = world_from_tool @ inv(flange_from_tool). Both arguments are 4x4
    transforms, or ``flange_from_tool`` may be a pose6 as written in the cell file.
    """
    return matrix_to_pose6(world_from_flange_for_tool(world_from_tool, flange_from_tool))


def world_from_flange_for_tool(world_from_tool: Any, flange_from_tool: Any) -> np.ndarray:
    """4x4 world_from_flange that puts the tool at ``world_from_tool`` (see above)."""
    W = as_transform(world_from_tool, "world_from_tool")
    F = _as_transform_or_pose(flange_from_tool, "flange_from_tool")
    return W @ invert(F)


def tool_from_flange_pose(flange_pose: Any, flange_from_tool: Any) -> np.ndarray:
    """4x4 world_from_tool for an arm whose flange is at ``flange_pose`` (pose6)."""
    return pose6_to_matrix(flange_pose) @ _as_transform_or_pose(flange_from_tool, "flange_from_tool")


def rotation_angle_between(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle [rad] of the rotation taking ``Ra`` to ``Rb``."""
    return float(np.linalg.norm(Rotation.from_matrix(Ra.T @ Rb).as_rotvec()))


def interpolate_pose6(start: Any, end: Any, n: int) -> np.ndarray:
    """(n, 6) poses along the straight line from ``start`` to ``end``: positions linear,
    orientations by slerp (what a UR ``moveL`` does), both end points included."""
    return _along(start, end, np.linspace(0.0, 1.0, max(int(n), 2)))


def interpolate_pose6_at(start: Any, end: Any, s: float) -> np.ndarray:
    """(6,) the pose a fraction ``s`` (0-1) along the straight line from ``start`` to ``end``,
    as :func:`interpolate_pose6` samples it."""
    return _along(start, end, np.array([float(s)]))[0]


def _along(start: Any, end: Any, s: np.ndarray) -> np.ndarray:
    """(len(s), 6) the poses at fractions ``s`` along the line from ``start`` to ``end``."""
    a, b = as_pose6(start, "start pose"), as_pose6(end, "end pose")
    positions = a[:3] + s[:, None] * (b[:3] - a[:3])
    from scipy.spatial.transform import Slerp

    slerp = Slerp([0.0, 1.0], Rotation.from_rotvec(np.stack([a[3:], b[3:]])))
    return np.concatenate([positions, slerp(s).as_rotvec()], axis=1)


def _as_transform_or_pose(value: Any, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape == (6,):
        return pose6_to_matrix(arr)
    return as_transform(arr, what)


def pose_distance(a: Any, b: Any) -> tuple[float, float]:
    """(position distance [m], rotation angle [rad]) between two pose6. Compare poses with
    this, never element-wise: near a half turn ``r`` and ``-r`` are the same rotation."""
    A, B = pose6_to_matrix(a), pose6_to_matrix(b)
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), rotation_angle_between(A[:3, :3], B[:3, :3])
