"""The strip stage: a 30 mm plate cannot follow a tape that curls within its length, so the
plate chain's last plate is a chord and its tip lands mm off. From the plate fit, a
continuous strip (a fine chain whose twist and bend rates vary linearly between knots at
the model's nodes, in-plane bending held near zero as a tape's is) is fitted on the same
residuals; the tip frame is the strip's end, and the output plate chain is the one closest
to the strip in 3-D at the model's nodes, tip first, its last plate pulled towards the
strip's tip frame."""
from __future__ import annotations

import functools

import numpy as np

from . import _kernels_lm
from .chain import Chain
from .config import DEFAULT, FitConfig
from .residuals import residuals
from .solver import corner_fit, levenberg_marquardt_one, with_rows
from .tape import TapeSpec, forward_kinematics
from .views import Field


class Strip:
    """A continuous strip as a fine chain (cfg.strip_plates plates per model plate) whose
    joint angles (twist, out-of-plane and in-plane bend per length) vary linearly along
    the arc length between knots at the model's nodes, after a free first joint: 3 + 3(n+1)
    parameters. The plate chain cannot follow a tape that bends within one plate's length
    (a curl at the tip), so its last plate is a chord: the strip follows it."""

    def __init__(self, spec: TapeSpec, cfg: FitConfig = DEFAULT):
        self.cfg = cfg
        k = cfg.strip_plates
        self.fine = TapeSpec(np.repeat(spec.segment_lengths / k, k), spec.width, spec.base_position,
                             spec.base_rotation)
        self.chain = Chain(self.fine, cfg.strip_edge_t, cfg.strip_centre_t, cfg, cfg.strip_crease_t)
        self.T, self.prior = _strip_layout(spec.n, k, float(cfg.strip_in_plane_px))

    def angles(self, x: np.ndarray) -> np.ndarray:
        return (self.T @ x).reshape(-1, 3)

    def corners(self, x: np.ndarray):
        """The fine chain's corners (3 m_fine, 3) and their Jacobian (3 m_fine, 3, P)."""
        c, J = self.chain.corners(self.angles(x))
        return c, J @ self.T

    def residuals(self, fields: list[Field], x: np.ndarray):
        r, J, cost = residuals(self.chain, fields, (self.T @ x)[None], True, self.cfg)
        p = self.prior @ x
        return np.concatenate([r[0], p]), np.vstack([J[0] @ self.T, self.prior]), cost[0] + 0.5 * p @ p


@functools.lru_cache(maxsize=8)
def _strip_layout(n: int, k: int, in_plane_px: float):
    """:class:`Strip`'s parameter map T (3 n k, 3(n+2)) from knot rates to the fine
    chain's angles, and its in-plane prior (3(n+2), 3(n+2)); built once per n, shared: not
    to be written."""
    nf = n * k
    basis = np.zeros((nf, n + 2))
    basis[0, 0] = 1.0
    s = np.arange(1, nf) / k                      # fine joints' arc length [model plates]
    knot = np.minimum(s.astype(int), n - 1)
    t = s - knot
    basis[np.arange(1, nf), 1 + knot] = (1 - t) / k
    basis[np.arange(1, nf), 2 + knot] = t / k
    T = np.kron(basis, np.eye(3))                 # (3 nf, P): parameters -> fine angles
    prior = np.zeros(3 * (n + 2))
    prior[5::3] = in_plane_px                     # in-plane rates of every knot
    prior = np.diag(prior)
    return T, prior


_strips: dict = {}


def _strip_for(spec: TapeSpec, cfg: FitConfig) -> Strip:
    """The strip of ``spec`` (cached: its chain's fixed arrays cost more than a fit step)."""
    key = (spec.segment_lengths.tobytes(), float(spec.width), np.asarray(spec.base_position, float).tobytes(),
           np.asarray(spec.base_rotation, float).tobytes(), cfg)
    strip = _strips.get(key)
    if strip is None:
        if len(_strips) > 16:
            _strips.clear()
        strip = _strips[key] = Strip(spec, cfg)
    return strip


def strip_stage(chain: Chain, fields: list[Field], angles: np.ndarray, cfg: FitConfig = DEFAULT, extra=None):
    """The strip fitted to the views from the plate chain ``angles`` (n, 3). Returns
    output(frame_weight) -> the plate chain's angles (n, 3) fitted in 3-D to the strip: its
    corners at the model's nodes (the tip's weighted) and, by ``frame_weight``, its tip
    frame to the strip's (see :func:`_tip_frame_rows`). ``extra(corners, J)`` -> (residuals,
    Jacobian): more rows on the strip's fine corners in its fit to the views (the touched
    points of :mod:`estimator.touch`)."""
    spec = chain.spec
    strip = _strip_for(spec, cfg)
    k, n = cfg.strip_plates, spec.n
    # Start: the strip closest in 3-D to the plate chain (its corners linearly
    # interpolated along the plates at the fine nodes).
    shape = forward_kinematics(spec, angles)
    t = np.arange(n * k + 1) / k
    i = np.minimum(t.astype(int), n - 1)
    f = (t - i)[:, None]
    target = np.concatenate([a[i] * (1 - f) + a[i + 1] * f for a in (shape.nodes, shape.left, shape.right)])
    x0 = np.zeros(strip.T.shape[1])
    x0[:3] = angles[0]
    compiled = cfg.compiled and _kernels_lm.usable(fields)
    if compiled:
        x = _kernels_lm.corner_fit(strip.chain, strip.T, target, 1.0, x0, 20, 1e-4)
    else:
        x = levenberg_marquardt_one(corner_fit(strip.corners, target), x0, 20, 1e-4)
    if extra is None and compiled:
        x = _kernels_lm.strip_fit(strip, fields, x, cfg.strip_iterations, cfg.strip_rtol, cfg)
    else:
        fit = functools.partial(strip.residuals, fields)
        if extra is not None:
            fit = with_rows(fit, strip.corners, extra)
        x = levenberg_marquardt_one(fit, x, cfg.strip_iterations, cfg.strip_rtol)
    fine = forward_kinematics(strip.fine, strip.angles(x))
    # The output chain: the plate chain closest to the strip at the model's nodes.
    goal = np.concatenate([fine.nodes[::k], fine.left[::k], fine.right[::k]])
    w = np.ones(3 * (n + 1))
    w[[n, 2 * n + 1, 3 * n + 2]] = cfg.strip_tip_weight

    def output(frame_weight: float) -> np.ndarray:
        if compiled:
            return _kernels_lm.corner_fit(chain, _identity(3 * n), goal, w, angles.ravel(), 10, 1e-4, fine.frames[-1],
                                          frame_weight).reshape(n, 3)
        frame_rows = _tip_frame_rows(chain, fine.frames[-1], frame_weight) if frame_weight > 0 else None
        fun = corner_fit(chain.corners, goal, w, frame_rows)
        return levenberg_marquardt_one(fun, angles.ravel().copy(), 10, 1e-4).reshape(n, 3)

    output.tip = (fine.nodes[-1].copy(), fine.frames[-1].copy())   # the strip's end frame
    output.fine = fine   # the strip itself (the fine chain's shape)
    return output


@functools.lru_cache(maxsize=8)
def _identity(size: int) -> np.ndarray:
    """The (size, size) identity, shared (read-only would be another type for numba): not to
    be written."""
    return np.eye(size)


def _tip_frame_rows(chain: Chain, tip_frame: np.ndarray, weight: float):
    """``extra`` rows for :func:`corner_fit` on ``chain``'s corners pulling its tip frame
    F_n (the last plate's direction and width axis) onto ``tip_frame`` (3, 3), ``weight``
    times as strongly as a corner (a unit-vector difference counts as moving a corner by
    the last plate's length times it)."""
    n, m = chain.n, chain.n + 1
    length, width = float(chain.spec.segment_lengths[-1]), float(chain.spec.width)
    s = weight * length

    def rows(c, J):
        ex, Jx = (c[n] - c[n - 1]) / length, (J[n] - J[n - 1]) / length
        ey, Jy = (c[m + n] - c[2 * m + n]) / width, (J[m + n] - J[2 * m + n]) / width
        return s * np.concatenate([ex - tip_frame[:, 0], ey - tip_frame[:, 1]]), s * np.vstack([Jx, Jy])

    return rows
