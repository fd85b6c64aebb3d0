"""Camera rotations corrected from the views themselves, with two cameras or more.

A camera turned by a fraction of a degree shifts its silhouette by a few pixels. With two
cameras the tape's shape absorbs most of that (the two views are explained by a shifted
shape) but not at the tape's base, which is fixed: the model misses the observed tape there
(``poor_fit`` by the base check, or an end no longer located, ``hidden``); with three, the
views disagree too, and the fit that explains all three at once is poor: ``poor_fit``, where
the tape itself was seen well.
Here the chain's joint angles and each camera's rotation about its optical centre are
fitted together (Levenberg-Marquardt on the local stage's residuals, the rotations held
near the calibration by a prior; their Jacobian columns from the residual kernel, the robust
weights held as for the angles: :func:`_kernels.rotation_terms`), and the capture is estimated
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
from .residuals import residuals
from .solver import levenberg_marquardt_one
from .views import prepare

MIN_VIEWS = 2
"""Cameras needed. With two, the shape alone can absorb most of a calibration error (a shifted
shape explains both views), but not at the base, which cannot move: there the corrected
rotations are anchored, and the shape follows. (3 until 2026-11-27, on the belief that two
views leave nothing to correct from; simulated two-camera captures with both cameras turned
0.5 deg, development seeds 916500-916529: "ok" 0 of 30 before, 27 after, 0.10-2.26 mm off.)"""
SIGMA_DEG = 0.5
"""The calibration's rotation error the prior expects of a camera [deg] (issue 13's bound)."""
PRIOR_PX = 3.0
"""The prior's residual [px] for a rotation of ``SIGMA_DEG`` about each axis: a correction
costs like a boundary this far off per ``SIGMA_DEG``."""
MAX_DEG = 1.0
"""A correction larger than this [deg] for any camera is not a calibration error the
cameras could have: the corrected answer is not taken."""
MIN_GAIN = 0.9
"""The corrected answer is taken only where its eq.-11 cost (on the corrected cameras) is at
most this fraction of the answer's on the cameras as given: corrections that fit a wrong shape
better do not explain the views better. The development capture noisy-902049 (3 cameras,
noisy masks, the calibration right) was ``poor_fit`` 9.0 mm off; corrections of 0.2-0.3 deg made it "ok" 12.7 mm
off at 0.985 of the cost. On 100 simulated 3-camera captures with every camera turned 0.25 or
0.5 deg (seeds 905000-, 906000- with noisy masks, 907000-) the 83 corrected answers that were
"ok" cost 0.07-0.81 of the first answer (median 0.27) and lay within 3.4 mm of the true tip."""
OK_BASE_PX = 2.0
"""An "ok" answer whose model meets the tape at its base (``verdict.BASE_OFFSET_PX``, 3 px) only
to more than this [px] in some view is estimated again on corrected cameras too: a camera
turned 0.3 deg can leave the base within 3 px and the tip 8-10 mm off (sweep episodes
1046012, 1046113 and 1046125: 2.6-3.0 px at the base, "ok" 7.7-9.6 mm off; corrected 0.2-0.9
mm). On
calibrated development captures of every kind (1043000-) "ok" answers met the base to at most
2.9 px, 1-2 % of them above 2 px."""
OK_MIN_GAIN = 0.6
"""... and the corrected answer replaces an "ok" one only where its eq.-11 cost is at most this
fraction of the first's (``MIN_GAIN`` for the others): corrections also fit a right answer a
little better, and one a little worse. On calibrated development captures corrected "ok"
answers cost 0.68-1.25 of the first (the 0.68 a part capture 1.0 mm off made 5.2 mm off);
on simulated ones with both cameras turned 0.3 deg, 0.39-0.65, 0.3-1.5 mm off instead of
2.8-4.4 mm."""
CORRECTED_OFFSET_PX = 1.8
"""A corrected answer stands only where it explains every view to within this mean boundary
distance [px] ... (cameras whose calibration error was found leave no view explained only
roughly: corrected answers on simulated captures with every camera turned 0.25 or 0.5 deg
(1093000-, 1094000-, chain and shell tape, 2 and 3 cameras, 88 corrected) showed at most 1.40
px, on synthetic calib_rot captures (1092000- to 1095000-, 8) at most 1.06 px; fresh
shell-c2-1095002, calibrated, poor_fit 10.4 mm off, was corrected by 0.08 and 0.14 deg to
"ok" 11.6 mm off at 2.17 px) ..."""
SUPPORT = 0.7
"""... and where the corrected cameras explain its shape clearly better than the cameras as
given: its eq.-11 cost on the corrected cameras at most this fraction of the same shape's on
the cameras as given. Else the gain over the first answer is the second search's, which
found another shape, not the correction's (shell-c2-1095002: 0.77; the corrected answers
above 0.05-0.62 on the turned simulated captures, the highest at 0.25 deg, and 0.24-0.48 on
the synthetic ones)."""
ITERATIONS = 20
RTOL = 1e-4


def turned(camera: Camera, rotation: np.ndarray) -> Camera:
    """``camera`` turned about its optical centre by the rotation vector ``rotation`` (3,)
    [rad] in its own frame: R -> dR R, t -> dR t."""
    dR = cv2.Rodrigues(np.asarray(rotation, float).reshape(3, 1))[0]
    return camera.with_pose(dR @ camera.R, dR @ camera.t)


def camera_corrections(capture: Capture, angles: np.ndarray, cfg: FitConfig = DEFAULT,
                       fields: list | None = None) -> np.ndarray:
    """(K, 3) rotation vectors [rad], one per camera, that with joint angles fitted from
    ``angles`` (n, 3) explain the views best, each held near zero by the prior. ``fields``:
    the views as :func:`views.prepare` made them for this capture and ``cfg``, when made."""
    chain = Chain(capture.tape, cfg=cfg)
    if fields is None:
        fields = [prepare(v, capture.scene, cfg) for v in capture.views]
    K, na = len(fields), angles.size
    prior = PRIOR_PX / np.radians(SIGMA_DEG)

    def at(w: np.ndarray) -> list:
        return [dataclasses.replace(f, camera=turned(f.camera, w[3 * k:3 * k + 3])) for k, f in enumerate(fields)]

    def fun(x: np.ndarray):
        a, w = x[None, :na], x[na:]
        cams = at(w)
        r, J, cost = residuals(chain, cams, a, True, cfg)
        Jw = np.zeros((r.shape[1], 3 * K))
        views = _kernels.rotation_terms(chain, cams, a.reshape(chain.n, 3), cfg.delta_out_px, cfg.delta_in_px)
        Jw[:len(views)] = views      # the rows after the views' (prior, boxes) do not depend on them
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
