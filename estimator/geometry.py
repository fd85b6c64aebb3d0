"""Rotations and pinhole cameras in OpenCV's convention.

A world point ``X`` maps to camera coordinates ``x_cam = R @ X + t`` (R, t are
camera_from_world), x right, y down, z forward; pixel centres sit at integer coordinates.
All lengths are metres.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .errors import CaptureError


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about x (the paper's eq. 2)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about y (eq. 3)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` radians about z (eq. 4)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def check_finite(value: Any, shape: tuple[int, ...] | None, what: str, source: str = "") -> np.ndarray:
    """``value`` as a float array of ``shape``; a :class:`CaptureError` naming ``what`` otherwise."""
    where = f"{source}: " if source else ""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise CaptureError(f"{where}{what} is not a numeric array") from None
    if shape is not None and arr.shape != shape:
        raise CaptureError(f"{where}{what} has shape {list(arr.shape)}, expected {list(shape)}")
    if not np.all(np.isfinite(arr)):
        raise CaptureError(f"{where}{what} holds NaN or infinite numbers")
    return arr


def is_rotation(R: np.ndarray, tol: float = 1e-5) -> bool:
    """True when the (3, 3) ``R`` is a proper rotation: R R^T = I within ``tol``, det > 0."""
    return bool(np.allclose(R @ R.T, np.eye(3), atol=tol) and np.linalg.det(R) >= 0)


def check_rotation(value: Any, what: str, source: str = "", tol: float = 1e-5) -> np.ndarray:
    """``value`` as a 3x3 proper rotation matrix, or a :class:`CaptureError`."""
    R = check_finite(value, (3, 3), what, source)
    where = f"{source}: " if source else ""
    if not is_rotation(R, tol):
        raise CaptureError(f"{where}{what} is not a rotation matrix (R R^T != I or det != 1)")
    return R


def look_at(position: Any, target: Any, up: Any) -> np.ndarray:
    """(3, 3) world_from_camera rotation in OpenCV's axes (x right, y down, z forward) of a
    camera at ``position`` [m] looking at ``target`` [m] with ``up`` up in the image.
    Degenerate input (target at the position, looking along ``up``) gives NaN: callers
    that read it from a file check first and say which file."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z = z / np.linalg.norm(z)
    down = -np.asarray(up, float)
    y = down - np.dot(down, z) * z
    y = y / np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation (m)."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


_DIST_LENGTHS = (0, 4, 5, 8, 12)
MAX_IMAGE_SIDE = 20000
"""Pixels a side: a larger image is not from a camera (and would not fit in memory)."""
MAX_CAMERA_DISTANCE_M = 20.0
"""No camera of a cell is farther from the robot's base: a larger |t| is in millimetres."""


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated pinhole camera with OpenCV lens distortion.

    name: identifier, e.g. "cam0".
    width, height: image size in pixels.
    K: (3, 3) intrinsic matrix [px].
    dist: OpenCV distortion vector (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4]]]).
    R, t: camera_from_world rotation (3, 3) and translation (3,) [m].
    rms_px: calibration residual [px] when the camera was calibrated, else None.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rms_px: float | None = None

    @property
    def camera_from_world(self) -> np.ndarray:
        return transform(self.R, self.t)

    @property
    def world_from_camera(self) -> np.ndarray:
        return transform(self.R.T, -self.R.T @ self.t)

    @functools.cached_property
    def center(self) -> np.ndarray:
        """Optical centre in the world frame [m] (computed once: a camera is not changed
        after it is made, :meth:`with_pose` makes a new one; read-only)."""
        c = -self.R.T @ self.t
        c.setflags(write=False)
        return c

    @functools.cached_property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 3) camera-frame points [m]."""
        return np.asarray(points_world, float) @ self.R.T + self.t

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) pixel coordinates, lens distortion applied.

        Agrees with ``cv2.projectPoints``; points behind the camera give non-finite
        or meaningless pixels, as there.
        """
        return self.project_camera(self.to_camera(points_world))

    def project_camera(self, points_camera: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points -> (N, 2) pixels."""
        pc = np.asarray(points_camera, float)
        z = pc[..., 2]
        x = pc[..., 0] / z
        y = pc[..., 1] / z
        if self.has_distortion:
            x, y = _distort(x, y, self.dist)
        K = self.K
        u = K[0, 0] * x + K[0, 1] * y + K[0, 2]
        v = K[1, 1] * y + K[1, 2]
        return np.stack([u, v], axis=-1)

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> "Camera":
        return Camera(self.name, self.width, self.height, self.K, self.dist, R, t, self.rms_px)

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "name": self.name,
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }
        if self.rms_px is not None:
            d["rms_px"] = float(self.rms_px)
        return d

    @classmethod
    def from_json(cls, d: Mapping[str, Any], source: str = "") -> "Camera":
        """Validate and build a camera from its JSON object (formats.md)."""
        where = f"{source}: " if source else ""
        if not isinstance(d, Mapping):
            raise CaptureError(f"{where}a camera entry is not an object")
        name = d.get("name")
        if not isinstance(name, str) or not name:
            raise CaptureError(f"{where}a camera has no name")
        what = f"camera {name}"
        for key in ("width", "height", "K", "R", "t"):
            if key not in d:
                raise CaptureError(f"{where}{what} has no '{key}'")
        width, height = d["width"], d["height"]
        if (not (isinstance(width, int) and isinstance(height, int)) or isinstance(width, bool)
                or isinstance(height, bool) or width <= 0 or height <= 0):
            raise CaptureError(f"{where}{what} has an invalid image size {width}x{height}")
        if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
            raise CaptureError(f"{where}{what} has an image size {width}x{height} px; more than "
                               f"{MAX_IMAGE_SIDE} px a side is not a camera image")
        K = check_finite(d["K"], (3, 3), f"{what} K", source)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise CaptureError(f"{where}{what} K is not an intrinsic matrix [[fx,s,cx],[0,fy,cy],[0,0,1]]")
        if not (-0.5 <= K[0, 2] <= width - 0.5 and -0.5 <= K[1, 2] <= height - 0.5):
            raise CaptureError(f"{where}{what} K puts the principal point at ({K[0, 2]:.1f}, {K[1, 2]:.1f}) px, "
                               f"outside its {width}x{height} image")
        dist = check_finite(d.get("dist", []), None, f"{what} dist", source).reshape(-1)
        if dist.size not in _DIST_LENGTHS:
            raise CaptureError(f"{where}{what} dist has {dist.size} terms; expected one of {_DIST_LENGTHS[1:]}")
        if dist.size == 0:
            dist = np.zeros(5)
        R = check_rotation(d["R"], f"{what} R", source)
        t = check_finite(d["t"], (3,), f"{what} t", source)
        if np.linalg.norm(t) > MAX_CAMERA_DISTANCE_M:
            raise CaptureError(f"{where}{what} is {np.linalg.norm(t):.4g} m from the world origin (|t|); the file "
                               f"looks like it is in millimetres (metres expected)")
        rms = d.get("rms_px")
        if rms is not None:
            rms = float(check_finite(rms, (), f"{what} rms_px", source))
        return cls(name, width, height, K, dist, R, t, rms)


def _distort(x: np.ndarray, y: np.ndarray, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's lens model applied to normalised coordinates."""
    d = np.zeros(12)
    d[: dist.size] = dist
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return xd, yd
