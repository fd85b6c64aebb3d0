"""Camera rotations corrected from the views themselves, with three cameras or more.

A camera turned by a fraction of a degree shifts its silhouette by a few pixels. With two
cameras the tape's shape absorbs that (the two views are explained by a shifted shape, and
nothing in them tells the error apart); with three, the views disagree, and the fit that
explains all three at once is poor: ``poor_fit``, where the tape itself was seen well.
Here the chain's joint angles and each camera's rotation about its optical centre are
fitted together (Levenberg-Marquardt on the local stage's residuals, the rotations held
near the calibration by a prior; their Jacobian columns from the residual kernel, the robust
weights held as for the angles: :func:`_rotation_columns`), and the capture is estimated
again with the corrected cameras (:func:`estimator.fit.estimate` decides when, and which
answer stands).

The tape's fixed base anchors the world frame: a rotation of all cameras together moves
the base's image and is paid for there. What the views cannot tell apart is left to the
prior (``PRIOR_PX`` per ``SIGMA_DEG``), so the corrected rotations are not the cameras'
true errors; what improves is the shape that explains all the views at once (measured on
simulated captures with every camera turned 0.3 and 0.5 deg: README, The verdict)."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from .capture import Capture, View
from .chain import Chain
from .config import DEFAULT, FitConfig
from .geometry import Camera
from . import _kernels
from ._kernels_boxes import hidden_points
from .residuals import residuals
from .solver import levenberg_marquardt_one
from .views import prepare

MIN_VIEWS = 3
"""Cameras needed: with two, a shifted shape explains both views (nothing to correct from)."""
SIGMA_DEG = 0.5
"""The calibration's rotation error the prior expects of a camera [deg] (issue 13's bound)."""
PRIOR_PX = 3.0
"""The prior's residual [px] for a rotation of ``SIGMA_DEG`` about each axis: a correction
costs like a boundary this far off per ``SIGMA_DEG``."""
MAX_DEG = 1.0
"""A correction larger than this [deg] for any camera is not a calibration error the
cameras could have: the corrected answer is not taken."""
ITERATIONS = 20
RTOL = 1e-4


def turned(camera: Camera, rotation: np.ndarray) -> Camera:
    """``camera`` turned about its optical centre by the rotation vector ``rotation`` (3,)
    [rad] in its own frame: R -> dR R, t -> dR t."""
    dR = cv2.Rodrigues(np.asarray(rotation, float).reshape(3, 1))[0]
    return camera.with_pose(dR @ camera.R, dR @ camera.t)


def camera_corrections(capture: Capture, angles: np.ndarray, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """(K, 3) rotation vectors [rad], one per camera, that with joint angles fitted from
    ``angles`` (n, 3) explain the views best, each held near zero by the prior."""
    chain = Chain(capture.tape, cfg=cfg)
    fields = [prepare(v, capture.scene, cfg) for v in capture.views]
    K, na = len(fields), angles.size
    prior = PRIOR_PX / np.radians(SIGMA_DEG)
    ns = chain.samples
    arrays = _kernels._chain_arrays(chain)

    def at(w: np.ndarray) -> list:
        return [dataclasses.replace(f, camera=turned(f.camera, w[3 * k:3 * k + 3])) for k, f in enumerate(fields)]

    def fun(x: np.ndarray):
        a, w = x[None, :na], x[na:]
        cams = at(w)
        r, J, cost = residuals(chain, cams, a, True, cfg)
        Jw = np.zeros((r.shape[1], 3 * K))
        pts, _ = _kernels.points(chain, a.reshape(1, chain.n, 3), False)
        row = 0
        for k, f in enumerate(cams):
            rows = len(f.outline) + ns
            Jw[row:row + rows, 3 * k:3 * k + 3] = _rotation_columns(f, pts, ns, arrays, cfg)
            row += rows
        rp = prior * w
        Jp = np.zeros((3 * K, na + 3 * K))
        Jp[:, na:] = prior * np.eye(3 * K)
        return (np.concatenate([r[0], rp]), np.vstack([np.hstack([J[0], Jw]), Jp]),
                float(cost[0]) + 0.5 * float(rp @ rp))

    x = levenberg_marquardt_one(fun, np.concatenate([np.asarray(angles, float).ravel(), np.zeros(3 * K)]),
                                ITERATIONS, RTOL)
    return x[na:].reshape(K, 3)


def corrected(capture: Capture, rotations: np.ndarray) -> Capture:
    """``capture`` with each camera turned by its row of ``rotations`` (K, 3) [rad]."""
    views = [View(turned(v.camera, w), v.mask, v.ignore, v.image) for v, w in zip(capture.views, rotations)]
    return dataclasses.replace(capture, views=views)


def _rotation_columns(field, pts: np.ndarray, ns: int, arrays: tuple, cfg: FitConfig) -> np.ndarray:
    """(P + ns, 3): the Jacobian of ``field``'s rows of the residuals (its outline's coverage,
    then the chain's ns sample points) by its camera's rotation vector, the robust weights held
    as the local stage holds them. Turning the camera by w moves a point's camera-frame
    position p to p + w x p: as the world point moving by -R^T [p]x w, which the residual
    kernel takes as a point Jacobian of three columns. ``pts``: (1, ns + corners, 3)."""
    cam = field.camera
    p_cam = pts[0] @ cam.R.T + cam.t
    skew = np.zeros((len(p_cam), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p_cam[:, 2], p_cam[:, 1], -p_cam[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p_cam[:, 2], -p_cam[:, 1], p_cam[:, 0]
    point_jacobian = np.ascontiguousarray(-(cam.R.T @ skew)[None])
    _, _, edge, weight, segments, fold_of = arrays[:6]
    rows = len(field.outline) + ns
    res, jac = np.empty((1, rows)), np.empty((1, rows, 3))
    _kernels.view_residuals(pts, point_jacobian, True, _kernels.camera_params(cam), field.field, field.x0, field.y0,
                            field.has_ignore, field.outline, ns, edge, weight, segments, fold_of, cfg.delta_out_px,
                            cfg.delta_in_px, hidden_points(field, pts[:, :ns]), res, jac, 0)
    return jac[0] * np.sqrt(field.weight)
