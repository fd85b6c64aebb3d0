"""Residuals of the local stage: per view, the plate chain's edge and centre-line sample
points against the observed silhouette's signed distance field (robust: Huber outside,
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
    B = len(params)
    angles = params.reshape(B, chain.n, 3)
    ns = chain.samples
    # Compiled per-view terms (estimator/_kernels.py), or their NumPy reference
    # (estimator/reference.py; tests/test_estimator_kernels.py pins one to the other).
    if cfg.compiled:
        rs, js, cost, pts, J = _compiled_view_terms(chain, fields, angles, jacobian, cfg)
    else:
        rs, js, cost, pts, J = reference.view_terms(chain, fields, angles, jacobian, cfg)
    # A weak preference for small angles keeps the chain from drifting to extreme twists
    # (self-crossing plates) where the silhouette barely constrains it. (Measured and
    # dropped: per-view 2-D image shifts against miscalibration, worse on occluded views;
    # a bend-smoothness term, no help: the wrong branches are chosen in the beam.)
    prior_J = np.diag(np.full(params.shape[1], cfg.angle_prior_px))
    prior = params * cfg.angle_prior_px          # = params @ prior_J.T (diagonal), exactly
    rs.append(prior)
    cost += 0.5 * np.sum(prior * prior, axis=1)
    boxes = fields[0].boxes if fields else ()
    if boxes:
        # The tape cannot pass through a scene box: its corners inside one are charged.
        corners = pts[:, ns:]
        depth, grad = _kernels_boxes.box_penetration(np.ascontiguousarray(corners.reshape(-1, 3)), *fields[0].box_arrays)
        pen = cfg.penetration_px_per_m * depth.reshape(B, -1)
        rs.append(pen)
        cost += 0.5 * np.sum(pen * pen, axis=1)
        if jacobian:
            g = cfg.penetration_px_per_m * grad.reshape(B, -1, 3)
            js_pen = np.einsum("bpk,bpkn->bpn", g, J[:, ns:])
    r = np.concatenate(rs, axis=1)
    if not jacobian:
        return r, None, cost
    js.append(np.broadcast_to(prior_J, (B,) + prior_J.shape))
    if boxes:
        js.append(js_pen)
    return r, np.concatenate(js, axis=1), cost


def _compiled_view_terms(chain: Chain, fields: list[Field], angles: np.ndarray, jacobian: bool, cfg: FitConfig):
    """:func:`_kernels.view_terms` with each view's terms scaled by its weight (one call per
    view only when a view is down-weighted)."""
    if all(f.weight == 1.0 for f in fields):
        return _kernels.view_terms(chain, fields, angles, jacobian, cfg.delta_out_px, cfg.delta_in_px)
    rs, js, cost = [], [], np.zeros(len(angles))
    for f in fields:
        (r,), j, c, pts, J = _kernels.view_terms(chain, [f], angles, jacobian, cfg.delta_out_px, cfg.delta_in_px)
        w = np.sqrt(f.weight)
        rs.append(w * r)
        js += [w * jj for jj in j]
        cost += f.weight * c
    return rs, js, cost, pts, J
