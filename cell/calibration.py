"""Camera calibration from robot-held cross-plate points (the paper's sec. 2.2).

The robot carries the cross plate through a 3-D grid of poses; each pose gives one 3-D
point (the flange pose the arm reports composed with the plate's offset, i.e. robot
coordinates) and, per camera, the detected cross centre. Per camera the points are
non-planar, so the solve is: a DLT initial guess (normalised, Hartley), decomposed into
K, R, t; then ``cv2.calibrateCamera`` with ``CALIB_USE_INTRINSIC_GUESS`` on all points as
one view, the distortion terms chosen by the cell file fixed or free; gross outliers
removed and the solve repeated. The result is in the robot's base frame directly.

This module is the numerical part and the pose planner; :mod:`cell.calibrate_run` is
not needed: :func:`run_calibration` drives any :class:`cell.arm.Arm` and camera source.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, Sequence

import cv2
import numpy as np
import scipy.linalg

from estimator.errors import TapecellError
from estimator.geometry import Camera, rot_x, rot_y, rot_z

from .cross import REASONS, CrossDetection, CrossParams, detect_cross


class CalibrationError(TapecellError):
    """Calibration cannot give trustworthy cameras (too few poses, large residuals,
    an unreachable grid); nothing is written."""


DISTORTION_MODELS = {
    # model name -> (number of free terms in k1, k2, p1, p2, k3 order, calibrateCamera flags)
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
}


# ------------------------------------------------------------------------------ DLT
def dlt_projection(points_world: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3, 4) projection matrix P with pixels ~ P [X; 1], by the normalised DLT.

    points_world: (N, 3) non-coplanar points [m], N >= 6; pixels: (N, 2).
    """
    X = np.asarray(points_world, float)
    x = np.asarray(pixels, float)
    if len(X) < 6:
        raise CalibrationError(f"the DLT needs at least 6 points, got {len(X)}")
    # Hartley normalisation: centroid at 0, mean distance sqrt(2) (2-D) / sqrt(3) (3-D).
    def norm_T(p: np.ndarray) -> np.ndarray:
        c = p.mean(axis=0)
        s = np.sqrt(p.shape[1]) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-12)
        T = np.eye(p.shape[1] + 1)
        T[:-1, :-1] *= s
        T[:-1, -1] = -s * c
        return T
    Tx, TX = norm_T(x), norm_T(X)
    xn = (np.c_[x, np.ones(len(x))] @ Tx.T)[:, :2]
    Xn = np.c_[X, np.ones(len(X))] @ TX.T
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -xn[:, :1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -xn[:, 1:] * Xn
    _, sv, vt = np.linalg.svd(A)
    if sv[-2] < 1e-9 * sv[0]:
        raise CalibrationError("the calibration points are degenerate (coplanar or collinear)")
    Pn = vt[-1].reshape(3, 4)
    return np.linalg.inv(Tx) @ Pn @ TX


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P -> (K (3,3) with positive diagonal and K[2,2]=1, R camera_from_world, t [m])."""
    M = P[:, :3]
    K, R = scipy.linalg.rq(M)
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:           # P is defined up to sign
        R, t = -R, -t
    scale = K[2, 2]
    return K / scale, R, t


# ----------------------------------------------------------------------------- solve
@dataclass(frozen=True, eq=False)
class CameraFit:
    """One camera's calibration.

    camera: the calibrated camera, ``rms_px`` set (inliers only).
    initial: the DLT camera the refinement started from (no distortion).
    residuals_px: (N,) reprojection error of every input point [px], outliers included.
    inliers: (N,) bool, the points the final solve used.
    """

    camera: Camera
    initial: Camera
    residuals_px: np.ndarray
    inliers: np.ndarray

    @property
    def n_outliers(self) -> int:
        return int(np.count_nonzero(~self.inliers))


def _refine(name: str, size: tuple[int, int], X: np.ndarray, x: np.ndarray, K0: np.ndarray,
            flags: int) -> tuple[Camera, float]:
    w, h = size
    obj = [X.astype(np.float32).reshape(-1, 1, 3)]
    img = [x.astype(np.float32).reshape(-1, 1, 2)]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj, img, (w, h), K0.copy(), np.zeros(5), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
            criteria=crit)
    except cv2.error as e:
        raise CalibrationError(f"camera {name}: OpenCV calibration failed ({str(e).strip().splitlines()[-1]})") from None
    R, _ = cv2.Rodrigues(rvecs[0])
    return Camera(name, w, h, np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:5],
                  R, np.asarray(tvecs[0], float).reshape(3), float(rms)), float(rms)


def _residuals(camera: Camera, X: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(camera.project(X) - x, axis=1)


def calibrate_camera(name: str, size: tuple[int, int], points_world: np.ndarray, pixels: np.ndarray,
                     distortion_model: str = "k1k2", outlier_px: float = 0.5,
                     max_rounds: int = 5) -> CameraFit:
    """Calibrate one camera from (N, 3) world points [m] and their (N, 2) pixels.

    ``size`` is (width, height). Points whose residual exceeds both ``outlier_px`` and
    five times the median residual are dropped and the solve repeated (at most
    ``max_rounds`` times), which removes mis-detections without trimming honest noise.
    """
    if distortion_model not in DISTORTION_MODELS:
        raise CalibrationError(f"unknown distortion model '{distortion_model}' "
                               f"(known: {', '.join(DISTORTION_MODELS)})")
    X = np.asarray(points_world, float).reshape(-1, 3)
    x = np.asarray(pixels, float).reshape(-1, 2)
    flags = DISTORTION_MODELS[distortion_model]
    inliers = np.ones(len(X), bool)
    P = dlt_projection(X, x)
    K0, R0, t0 = decompose_projection(P)
    K0[0, 1] = 0.0                      # OpenCV's model has no skew
    initial = Camera(name, size[0], size[1], K0, np.zeros(5), R0, t0)
    camera = initial
    for _ in range(max_rounds):
        camera, _ = _refine(name, size, X[inliers], x[inliers], camera.K, flags)
        r = _residuals(camera, X, x)
        limit = max(outlier_px, 5.0 * float(np.median(r[inliers])))
        new = r <= limit
        if np.array_equal(new, inliers) or np.count_nonzero(new) < 6:
            break
        inliers = new
    r = _residuals(camera, X, x)
    rms = float(np.sqrt(np.mean(r[inliers] ** 2)))
    camera = Camera(camera.name, camera.width, camera.height, camera.K, camera.dist, camera.R, camera.t, rms)
    return CameraFit(camera, initial, r, inliers)


def camera_errors(calibrated: Camera, true: Camera) -> dict[str, float]:
    """How far ``calibrated`` is from ``true``: focal [%], principal point [px], centre
    [m], rotation [deg]."""
    f_err = max(abs(calibrated.K[0, 0] / true.K[0, 0] - 1), abs(calibrated.K[1, 1] / true.K[1, 1] - 1))
    pp = float(np.linalg.norm(calibrated.K[:2, 2] - true.K[:2, 2]))
    centre = float(np.linalg.norm(calibrated.center - true.center))
    dR = calibrated.R @ true.R.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    return {"focal_pct": 100.0 * f_err, "principal_px": pp, "centre_m": centre, "rotation_deg": angle}
