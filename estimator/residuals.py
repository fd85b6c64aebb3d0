"""Residuals of the local stage: per view, the plate chain's edge (and, where the tape folds
in the image, joint-line) and centre-line sample points against the observed silhouette's signed distance field (robust: Huber outside,
Cauchy for edge points inside, which may be hidden edges) and the observed outline's
coverage by the model's outline; a weak prior on the joint angles; the penetration of
scene boxes. With their exact Jacobian through the chain and the camera projection."""
from __future__ import annotations

import numpy as np

from . import _kernels, _kernels_boxes, reference
from .chain import Chain
from .config import DEFAULT, FitConfig
from .views import Field


def residuals(chain: Chain, fields: list[Field], params: np.ndarray, jacobian: bool, cfg: FitConfig = DEFAULT):
    """Weighted residuals (B, R), Jacobian (B, R, P) or None, and robust cost (B,) of a
    batch of parameter vectors (B, P = 3n joint angles)."""
    B, N = params.shape
    angles = params.reshape(B, chain.n, 3)
    ns = chain.samples
    boxes = fields[0].boxes if fields else ()
    # After the views' rows: the prior's (N), then with scene boxes the corners' penetration.
    extra = N + (3 * (chain.n + 1) if boxes else 0)
    # Compiled per-view terms (estimator/_kernels.py), written in place, or their NumPy
    # reference (estimator/reference.py; tests/test_estimator_kernels.py pins one to the other).
    if cfg.compiled:
        r, J, cost, pts, Jp = _kernels.view_terms(chain, fields, angles, jacobian, cfg.delta_out_px, cfg.delta_in_px,
                                                  extra)
    else:
        rs, js, cost, pts, Jp = reference.view_terms(chain, fields, angles, jacobian, cfg)
        rows = sum(x.shape[1] for x in rs)
        r = np.empty((B, rows + extra))
        r[:, :rows] = np.concatenate(rs, axis=1)
        J = None
        if jacobian:
            J = np.empty((B, rows + extra, N))
            J[:, :rows] = np.concatenate(js, axis=1)
    at = r.shape[1] - extra
    # A weak preference for small angles keeps the chain from drifting to extreme twists
    # (self-crossing plates) where the silhouette barely constrains it. (Measured and
    # dropped: per-view 2-D image shifts against miscalibration, worse on occluded views;
    # a bend-smoothness term, no help: the wrong branches are chosen in the beam.)
    prior = params * cfg.angle_prior_px          # = params @ prior_J.T (diagonal), exactly
    r[:, at:at + N] = prior
    cost += 0.5 * np.sum(prior * prior, axis=1)
    if jacobian:
        J[:, at:at + N] = np.diag(np.full(N, cfg.angle_prior_px))
    if boxes:
        # The tape cannot pass through a scene box: its corners inside one are charged.
        corners = pts[:, ns:]
        depth, grad = _kernels_boxes.box_penetration(np.ascontiguousarray(corners.reshape(-1, 3)), *fields[0].box_arrays)
        pen = cfg.penetration_px_per_m * depth.reshape(B, -1)
        r[:, at + N:] = pen
        cost += 0.5 * np.sum(pen * pen, axis=1)
        if jacobian:
            g = cfg.penetration_px_per_m * grad.reshape(B, -1, 3)
            J[:, at + N:] = np.einsum("bpk,bpkn->bpn", g, Jp[:, ns:])
    return r, J, cost
