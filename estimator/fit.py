"""The project's estimator (method="default") and the public :func:`estimate`.

Where the paper searches the XOR cost with a simplex, node by node, we fit the plate
chain's silhouette *boundary* to the observed one, which gives a smooth cost with an
analytic Jacobian:

1. Per view, clean the mask (drop speckles, fill pinholes), crop a region of interest and
   build the signed distance field (SDF) of the observed silhouette, negative inside.
2. Global stage, a beam search node by node: every kept partial chain is extended by a
   grid of joint angles (twist, out-of-plane and in-plane bend); a candidate's score
   asks that its plate edges lie on the observed boundary and its centre line inside the
   silhouette in every view (robust losses: Huber outside, Cauchy inside, so an edge
   hidden behind another part of the tape costs little). Keeping several chains escapes
   the wrong branches a greedy pass falls into (twist sign, a tape curled back).
3. Local stage: Levenberg-Marquardt on all 3n angles jointly, with the same residuals
   (re-weighted each iteration) and their exact Jacobian through the chain's kinematics
   and the camera projection.
4. The refined candidates are ranked by the paper's own silhouette cost (eq. 11); the
   best one is returned with its per-view costs on the full observed masks.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from .capture import Capture, View
from .errors import EstimateError
from .geometry import Camera, _distort
from .result import Estimate
from .silhouette import CostEvaluator, ViewTarget, combine, make_target
from .tape import TapeSpec, forward_kinematics, joint_rotations

Callback = Callable[[int, float, np.ndarray], None]

MARGIN_PX = 12
"""ROI margin around the observed tape [px]."""
OCCLUDED_MARGIN_PX = 60
"""ROI margin when an ignore mask may hide part of the tape [px]."""
SPECKLE_PX = 25
"""Connected regions (of tape or of background inside it) smaller than this are noise."""
DELTA_OUT_PX = 3.0
"""Huber scale for points outside the silhouette [px]."""
DELTA_IN_PX = 1.5
"""Cauchy scale for edge points inside the silhouette (possibly hidden edges) [px]."""
OUTLINE_POINTS = 48
"""Observed outline points per view in the coverage term."""
BEAM = 8
"""Partial chains kept per node in the global stage."""
REFINE = 2
"""Candidates refined to convergence after screening."""
LM_SCREEN = 4
"""Levenberg-Marquardt iterations every beam candidate gets before screening."""
LM_ITERATIONS = 10
ANGLE_PRIOR = 0.05
"""Weight of a weak preference for small joint angles in the global stage."""

_EDGE_T = np.array([0.25, 0.5, 0.75, 1.0])
_TIP_T = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
_CENTRE_T = np.array([0.5, 1.0])


def _angle_grid() -> np.ndarray:
    """Candidate joint angles (θx, θy, θz) of the global stage [rad]."""
    tx = np.array([-0.8, -0.4, 0.0, 0.4, 0.8])
    ty = np.linspace(-1.2, 1.2, 9)
    tz = np.array([0.0])
    return np.stack(np.meshgrid(tx, ty, tz, indexing="ij"), axis=-1).reshape(-1, 3)


_GRID = _angle_grid()
_GRID_R = joint_rotations(_GRID)


# --------------------------------------------------------------------------- views

@dataclass(frozen=True, eq=False)
class _Field:
    """One view prepared for the boundary fit.

    camera: its calibration; x0, y0: ROI origin [px]; field: (h, w, 3) float32 of the
    signed distance to the observed boundary [px] (negative inside) and its x/y gradient;
    ignore: (h, w) bool ROI of the ignore mask or None; target: the cleaned mask as a
    :class:`ViewTarget` for the silhouette cost.
    """

    camera: Camera
    x0: int
    y0: int
    field: np.ndarray
    ignore: np.ndarray | None
    target: ViewTarget
    outline: np.ndarray

    @property
    def flat(self) -> np.ndarray:
        """The field as (h*w, 3) rows for fast gathering."""
        return self.field.reshape(-1, 3)


def _clean_mask(mask: np.ndarray) -> np.ndarray:
    """The mask without speckles (small isolated regions); uint8 0/1."""
    m = mask.astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if count <= 2:
        return m
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.zeros(count, np.uint8)
    keep[1:] = areas >= min(SPECKLE_PX, areas.max())
    return keep[labels]


def _fill_pinholes(m: np.ndarray) -> np.ndarray:
    inv = (1 - m).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    small = np.zeros(count, bool)
    small[1:] = stats[1:, cv2.CC_STAT_AREA] < SPECKLE_PX
    out = m.copy()
    out[small[labels]] = 1
    return out


def _tape_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of the tape, ignoring isolated speckles: found on a
    4x area-downsampled copy where a lone pixel falls below the threshold."""
    small = cv2.resize(mask.view(np.uint8) * np.uint8(255), None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    x, y, w, h = cv2.boundingRect((small > 96).astype(np.uint8))
    if w == 0:
        x, y, w, h = cv2.boundingRect(mask.view(np.uint8))
        return x, y, x + w, y + h
    return 4 * x, 4 * y, 4 * (x + w), 4 * (y + h)


def _prepare(view: View) -> _Field:
    cam = view.camera
    bx0, by0, bx1, by1 = _tape_box(view.mask)
    margin = OCCLUDED_MARGIN_PX if view.ignore is not None else MARGIN_PX
    x0, y0 = max(0, bx0 - margin), max(0, by0 - margin)
    x1, y1 = min(cam.width, bx1 + margin), min(cam.height, by1 + margin)
    roi = _fill_pinholes(_clean_mask(view.mask[y0:y1, x0:x1]))
    ignore = None if view.ignore is None else view.ignore[y0:y1, x0:x1]
    # Unknown pixels get the benefit of the doubt: no boundary is drawn through them.
    solid = roi if ignore is None else (roi | ignore).astype(np.uint8)
    inside = cv2.distanceTransform(solid, cv2.DIST_L2, cv2.DIST_MASK_5)
    outside = cv2.distanceTransform(1 - solid, cv2.DIST_L2, cv2.DIST_MASK_5)
    sdf = np.where(solid > 0, 0.5 - inside, outside - 0.5).astype(np.float32)
    gx = cv2.Sobel(sdf, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(sdf, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    field = np.ascontiguousarray(np.dstack([sdf, gx, gy]))
    valid = None if ignore is None else (~ignore).astype(np.uint8)
    observed = roi if valid is None else roi & valid
    target = ViewTarget(cam, x0, y0, np.ascontiguousarray(observed), valid,
                        max(1.0, float(cv2.countNonZero(observed))))
    return _Field(cam, x0, y0, field, ignore, target, _outline(roi, ignore, x0, y0))


def _outline(roi: np.ndarray, ignore: np.ndarray | None, x0: int, y0: int) -> np.ndarray:
    """About OUTLINE_POINTS points spread evenly along the observed silhouette's outer
    boundary, in full-image pixels; none next to ignored pixels (not a real boundary)."""
    contours, _ = cv2.findContours(roi, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2))
    pts = np.concatenate([c.reshape(-1, 2) for c in contours])
    if ignore is not None:
        near = cv2.dilate(ignore.astype(np.uint8), np.ones((5, 5), np.uint8))
        pts = pts[near[pts[:, 1], pts[:, 0]] == 0]
    step = max(1, len(pts) // OUTLINE_POINTS)
    return pts[::step].astype(float) + np.array([x0, y0], float)


# --------------------------------------------------------------------------- sampling

def _sample(field: _Field, u: np.ndarray, v: np.ndarray, gradient: bool):
    """Bilinear look-up of the SDF (and its gradient) at pixel coordinates (u, v).

    Outside the ROI the SDF continues as the value at the ROI's edge plus the distance to
    it, so the fit is pulled back in. Returns (sdf, gx, gy, ignored).
    """
    h, w = field.field.shape[:2]
    x = u - field.x0
    y = v - field.y0
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():
        x = np.where(bad, 0.0, x)
        y = np.where(bad, 0.0, y)
    xc = np.clip(x, 0.0, w - 1.001)
    yc = np.clip(y, 0.0, h - 1.001)
    extra = np.abs(x - xc) + np.abs(y - yc)
    xi = xc.astype(np.intp)
    yi = yc.astype(np.intp)
    fx = (xc - xi)
    fy = (yc - yi)
    idx = yi * w + xi
    corners = np.take(field.flat, np.stack([idx, idx + 1, idx + w, idx + w + 1]), axis=0)
    wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])[..., None]
    val = np.sum(corners * wts, axis=0)
    sdf = val[..., 0] + extra
    if field.ignore is not None:
        ignored = field.ignore[np.rint(yc).astype(np.intp), np.rint(xc).astype(np.intp)] & (extra == 0)
    else:
        ignored = None
    if bad.any():
        sdf = np.where(bad, 1e3, sdf)
    gx, gy = val[..., 1], val[..., 2]
    if gradient and extra.any():
        # Beyond the ROI the pull points back towards it.
        ox = x - xc
        oy = y - yc
        gx = np.where(ox != 0, np.sign(ox), gx)
        gy = np.where(oy != 0, np.sign(oy), gy)
    return sdf, gx, gy, ignored


def _project(camera: Camera, pts: np.ndarray):
    """Pixels of world points and the camera-frame coordinates (for the Jacobian)."""
    pc = pts @ camera.R.T + camera.t
    z = pc[..., 2]
    z = np.where(z > 1e-6, z, 1e-6)
    x = pc[..., 0] / z
    y = pc[..., 1] / z
    if camera.has_distortion:
        xd, yd = _distort(x, y, camera.dist)
    else:
        xd, yd = x, y
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return u, v, x, y, z


def _robust(r: np.ndarray, inside_edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss ρ(r) and IRLS weight: Cauchy for edge points inside the silhouette,
    Huber otherwise."""
    a = np.abs(r)
    huber_rho = np.where(a <= DELTA_OUT_PX, 0.5 * r * r, DELTA_OUT_PX * (a - 0.5 * DELTA_OUT_PX))
    huber_w = np.where(a <= DELTA_OUT_PX, 1.0, DELTA_OUT_PX / np.maximum(a, 1e-12))
    q = (r / DELTA_IN_PX) ** 2
    cauchy_rho = 0.5 * DELTA_IN_PX ** 2 * np.log1p(q)
    cauchy_w = 1.0 / (1.0 + q)
    return np.where(inside_edge, cauchy_rho, huber_rho), np.where(inside_edge, cauchy_w, huber_w)


# --------------------------------------------------------------------------- the chain

class _Chain:
    """Sample points on the chain's silhouette-relevant parts and their Jacobian."""

    def __init__(self, spec: TapeSpec):
        self.spec = spec
        n = spec.n
        self.n = n
        m = n + 1
        rows, edge = [], []
        # corners: index k -> P_C[k], m + k -> P_L[k], 2m + k -> P_R[k]
        for side in (1, 2):
            for i in range(1, m):
                for t in _EDGE_T:
                    w = np.zeros(3 * m)
                    w[side * m + i - 1] = 1 - t
                    w[side * m + i] = t
                    rows.append(w)
                    edge.append(True)
        for t in _TIP_T:
            w = np.zeros(3 * m)
            w[m + n] = 1 - t
            w[2 * m + n] = t
            rows.append(w)
            edge.append(True)
        for i in range(1, m):
            for t in _CENTRE_T:
                w = np.zeros(3 * m)
                w[i - 1] = 1 - t
                w[i] = t
                rows.append(w)
                edge.append(False)
        self.M = np.array(rows)
        self.edge = np.array(edge)
        self.samples = len(rows)
        # silhouette outline segments as corner index pairs: left, right, tip and base edges
        left = [(m + k, m + k + 1) for k in range(n)]
        right = [(2 * m + k, 2 * m + k + 1) for k in range(n)]
        self.segments = np.array(left + right + [(m + n, 2 * m + n), (m, 2 * m)])
        # corner c belongs to the frame of node c % m: it moves with joints 1..c % m
        node_of = np.tile(np.arange(m), 3)
        self.moves = node_of[:, None] >= np.arange(1, m)[None, :]  # (3m, n)

    def points(self, angles: np.ndarray, jacobian: bool):
        """(s, 3) sample points and, if asked, their (s, 3, 3n) Jacobian."""
        spec = self.spec
        shape = forward_kinematics(spec, angles)
        corners = np.concatenate([shape.nodes, shape.left, shape.right])
        pts = np.concatenate([self.M @ corners, corners])
        if not jacobian:
            return pts, None
        frames = shape.frames
        Rz = joint_rotations(np.column_stack([np.zeros(self.n), np.zeros(self.n), angles[:, 2]]))
        axes = np.stack([frames[1:, :, 0],                                 # θx: F_j e_x
                         np.einsum("jab,jb->ja", frames[:-1], Rz[:, :, 1]),  # θy: F_{j-1} Rz e_y
                         frames[:-1, :, 2]], axis=1)                       # θz: F_{j-1} e_z
        pivots = shape.nodes[:-1]                                          # (n, 3)
        rel = corners[:, None, :] - pivots[None, :, :]                     # (3m, n, 3)
        Jc = np.cross(axes[None, :, :, :], rel[:, :, None, :])             # (3m, n, 3 axes, 3 xyz)
        Jc *= self.moves[:, :, None, None]
        Jc = Jc.transpose(0, 3, 1, 2).reshape(len(corners), 3, 3 * self.n)
        J = np.concatenate([np.einsum("sc,cxp->sxp", self.M, Jc), Jc])
        return pts, J


def _pixel_jacobian(camera: Camera, x, y, z, J: np.ndarray) -> np.ndarray:
    """(s, 2, N) d(u, v)/d(angles) of points with world Jacobian J (s, 3, N), pinhole part
    (lens distortion is a small correction the iterations absorb)."""
    K = camera.K
    inv_z = 1.0 / z
    du = np.stack([K[0, 0] * inv_z, K[0, 1] * inv_z, -(K[0, 0] * x + K[0, 1] * y) * inv_z], axis=1)
    dv = np.stack([np.zeros_like(z), K[1, 1] * inv_z, -K[1, 1] * y * inv_z], axis=1)
    duv = np.stack([du, dv], axis=1) @ camera.R                      # (s, 2, 3)
    return np.einsum("sax,sxp->sap", duv, J)


def _coverage(chain: "_Chain", f: _Field, u, v, x, y, z, J):
    """Observed outline points' distance to the model's outline: every part of the observed
    silhouette must be explained (the reverse of the edge term). Returns (robust cost,
    weighted residuals, Jacobian or None)."""
    obs = f.outline
    if len(obs) == 0:
        return 0.0, np.zeros(0), (np.zeros((0, J.shape[-1])) if J is not None else None)
    uv = np.stack([u, v], axis=1)
    a = uv[chain.segments[:, 0]]
    b = uv[chain.segments[:, 1]]
    ab = b - a
    den = np.maximum(np.einsum("kx,kx->k", ab, ab), 1e-9)
    t = np.clip(np.einsum("pkx,kx->pk", obs[:, None, :] - a[None], ab) / den, 0.0, 1.0)
    q = a[None] + t[..., None] * ab[None]
    diff = obs[:, None, :] - q
    d2 = np.einsum("pkx,pkx->pk", diff, diff)
    k = np.argmin(d2, axis=1)
    p = np.arange(len(obs))
    d = np.sqrt(d2[p, k]) + 1e-9
    rho, w = _robust(d, np.zeros(len(d), bool))
    sw = np.sqrt(w)
    if J is None:
        return float(rho.sum()), sw * d, None
    Juv = _pixel_jacobian(f.camera, x, y, z, J)                    # (corners, 2, N)
    tk = t[p, k][:, None, None]
    dq = (1 - tk) * Juv[chain.segments[k, 0]] + tk * Juv[chain.segments[k, 1]]
    n = diff[p, k] / d[:, None]
    g = -np.einsum("sa,sap->sp", n, dq)
    return float(rho.sum()), sw * d, sw[:, None] * g


def _residuals(chain: _Chain, fields: list[_Field], angles: np.ndarray, jacobian: bool):
    """Weighted residuals, Jacobian (or None) and robust cost over all views."""
    pts, J = chain.points(angles, jacobian)
    ns = chain.samples
    rs, js, cost = [], [], 0.0
    for f in fields:
        u_all, v_all, x_all, y_all, z_all = _project(f.camera, pts)
        u, v, x, y, z = u_all[:ns], v_all[:ns], x_all[:ns], y_all[:ns], z_all[:ns]
        c_cost, c_r, c_j = _coverage(chain, f, u_all[ns:], v_all[ns:], x_all[ns:], y_all[ns:], z_all[ns:],
                                     J[ns:] if jacobian else None)
        cost += c_cost
        rs.append(c_r)
        if jacobian:
            js.append(c_j)
        sdf, gx, gy, ignored = _sample(f, u, v, jacobian)
        inside_pt = ~chain.edge
        r = np.where(inside_pt, np.maximum(sdf, 0.0), sdf)
        rho, w = _robust(r, chain.edge & (sdf < 0))
        if ignored is not None:
            rho = np.where(ignored, 0.0, rho)
            w = np.where(ignored, 0.0, w)
        cost += float(rho.sum())
        sw = np.sqrt(w)
        rs.append(sw * r)
        if jacobian:
            K = f.camera.K
            inv_z = 1.0 / z
            # d(u, v)/d(camera point), pinhole part (distortion is a small correction)
            du = np.stack([K[0, 0] * inv_z, K[0, 1] * inv_z, -(K[0, 0] * x + K[0, 1] * y) * inv_z], axis=1)
            dv = np.stack([np.zeros_like(z), K[1, 1] * inv_z, -K[1, 1] * y * inv_z], axis=1)
            dsdf = (gx[:, None] * du + gy[:, None] * dv) @ f.camera.R          # (s, 3) world
            g = np.einsum("sx,sxp->sp", dsdf, J[:ns])
            g = np.where((inside_pt & (sdf <= 0))[:, None], 0.0, g)
            js.append(sw[:, None] * g)
    r = np.concatenate(rs)
    return r, (np.concatenate(js) if jacobian else None), cost


def _levenberg_marquardt(chain: _Chain, fields: list[_Field], angles: np.ndarray, iterations: int,
                         on_iteration: Callable[[np.ndarray, float], None] | None = None):
    """Robust (IRLS) Levenberg-Marquardt on all angles; returns (angles, robust cost)."""
    r, J, cost = _residuals(chain, fields, angles, True)
    mu = 1e-3
    for _ in range(iterations):
        A = J.T @ J
        g = J.T @ r
        step = np.linalg.solve(A + mu * (np.diag(np.diag(A)) + 1e-6 * np.eye(len(A))), -g)
        trial = angles + step.reshape(angles.shape)
        r2, J2, cost2 = _residuals(chain, fields, trial, True)
        if cost2 < cost:
            angles, r, J, cost = trial, r2, J2, cost2
            mu = max(mu * 0.3, 1e-7)
            converged = np.max(np.abs(step)) < 1e-4
        else:
            mu *= 10.0
            converged = mu > 1e4
        if on_iteration is not None:
            on_iteration(angles, cost)
        if converged:
            break
    return angles, cost


# --------------------------------------------------------------------------- global stage

def _beam_search(spec: TapeSpec, fields: list[_Field]) -> list[np.ndarray]:
    """Candidate chains (n, 3) from a node-by-node beam search, best first."""
    n = spec.n
    h = 0.5 * spec.width
    frames = spec.base_rotation[None]
    nodes = spec.base_position[None]
    scores = np.zeros(1)
    history = np.zeros((1, 0, 3))
    lefts = (nodes + h * frames[:, :, 1])[:, None, :]
    rights = (nodes - h * frames[:, :, 1])[:, None, :]
    for i in range(n):
        F = np.einsum("bij,gjk->bgik", frames, _GRID_R)              # (b, g, 3, 3)
        P = nodes[:, None, :] + spec.segment_lengths[i] * F[..., :, 0]
        L0 = (nodes + h * frames[:, :, 1])[:, None, None, :]
        R0 = (nodes - h * frames[:, :, 1])[:, None, None, :]
        L1 = (P + h * F[..., :, 1])[:, :, None, :]
        R1 = (P - h * F[..., :, 1])[:, :, None, :]
        t = _EDGE_T[None, None, :, None]
        parts = [L0 + (L1 - L0) * t, R0 + (R1 - R0) * t]
        edge_count = 2 * len(_EDGE_T)
        if i == n - 1:
            parts.append(L1 + (R1 - L1) * _TIP_T[None, None, :, None])
            edge_count += len(_TIP_T)
        tc = _CENTRE_T[None, None, :, None]
        parts.append(nodes[:, None, None, :] + (P[:, :, None, :] - nodes[:, None, None, :]) * tc)
        pts = np.concatenate(parts, axis=2)                            # (b, g, s, 3)
        is_edge = np.arange(pts.shape[2]) < edge_count
        plate = np.zeros(pts.shape[:2])
        for f in fields:
            u, v, *_ = _project(f.camera, pts)
            sdf, _, _, ignored = _sample(f, u, v, False)
            r = np.where(is_edge, sdf, np.maximum(sdf, 0.0))
            rho, _ = _robust(r, is_edge & (sdf < 0))
            if ignored is not None:
                rho = np.where(ignored, 0.0, rho)
            plate += rho.sum(axis=2)
        prior = ANGLE_PRIOR * np.sum(_GRID ** 2, axis=1)
        total = (scores[:, None] + plate + prior[None, :]).reshape(-1)
        last = i == n - 1
        keep = np.argsort(total)[:BEAM * (4 if last else 1)]
        b, gi = np.divmod(keep, len(_GRID))
        frames = F[b, gi]
        nodes = P[b, gi]
        scores = total[keep]
        history = np.concatenate([history[b], _GRID[gi][:, None, :]], axis=1)
        lefts = np.concatenate([lefts[b], L1[b, gi]], axis=1)
        rights = np.concatenate([rights[b], R1[b, gi]], axis=1)
    # Complete chains: add the coverage of the observed outline, keep the best.
    corners = np.concatenate([lefts, rights], axis=1)               # (c, 2(n+1), 3)
    m = n + 1
    seg = np.array([(k, k + 1) for k in range(n)] + [(m + k, m + k + 1) for k in range(n)]
                   + [(n, m + n), (0, m)])
    for f in fields:
        if len(f.outline) == 0:
            continue
        u, v, *_ = _project(f.camera, corners)
        uv = np.stack([u, v], axis=-1)
        a, ab = uv[:, seg[:, 0]], uv[:, seg[:, 1]] - uv[:, seg[:, 0]]   # (c, S, 2)
        den = np.maximum(np.sum(ab * ab, axis=-1), 1e-9)
        rel = f.outline[None, :, None, :] - a[:, None]                    # (c, P, S, 2)
        t = np.clip(np.sum(rel * ab[:, None], axis=-1) / den[:, None], 0.0, 1.0)
        d = np.sqrt(np.min(np.sum((rel - t[..., None] * ab[:, None]) ** 2, axis=-1), axis=2))
        rho, _ = _robust(d, np.zeros(d.shape, bool))
        scores = scores + rho.sum(axis=1)
    order = np.argsort(scores)[:BEAM]
    return [history[k] for k in order]


# --------------------------------------------------------------------------- public

def fit_default(capture: Capture, callback: Callback | None = None):
    """Fit by the project's method; returns (angles, history, evaluations)."""
    chain = _Chain(capture.tape)
    fields = [_prepare(v) for v in capture.views]
    candidates = _beam_search(capture.tape, fields)
    evaluator = CostEvaluator([f.target for f in fields])
    best, best_cost = None, np.inf
    history: list[float] = []
    iteration = 0
    # A few iterations on every candidate, then the best by silhouette cost to the end.
    scored = []
    for start in candidates:
        trace: list[tuple[np.ndarray, float]] = []
        angles, _ = _levenberg_marquardt(chain, fields, start, LM_SCREEN, lambda a, c: trace.append((a, c)))
        scored.append((evaluator.cost(forward_kinematics(capture.tape, angles).quads()), angles, trace))
    scored.sort(key=lambda x: x[0])
    for _, start, trace in scored[:REFINE]:
        angles, _ = _levenberg_marquardt(chain, fields, start, LM_ITERATIONS, lambda a, c: trace.append((a, c)))
        cost = evaluator.cost(forward_kinematics(capture.tape, angles).quads())
        if cost < best_cost:
            best, best_cost, best_trace = angles, cost, trace
    for a, c in best_trace:
        iteration += 1
        history.append(c)
        if callback is not None:
            callback(iteration, c, a)
    return best, history, evaluator.evaluations


def estimate(capture: Capture, method: str = "default", callback: Callback | None = None) -> Estimate:
    """Fit the plate chain to ``capture``'s silhouettes.

    method: "default" (ours) or "paper" (the reference reproduction).
    callback(iteration, cost, angles (n, 3)): called per optimiser iteration.
    Returns an :class:`Estimate`; ``time_s`` is the fitting time alone.
    """
    from .paper import fit_paper

    if method not in ("default", "paper"):
        raise EstimateError(f"unknown estimation method {method!r} (use 'default' or 'paper')")
    if not capture.views:
        raise EstimateError(f"{capture.name}: no camera views to fit")
    start = time.perf_counter()
    fit = fit_default if method == "default" else fit_paper
    angles, history, evaluations = fit(capture, callback)
    shape = forward_kinematics(capture.tape, angles)
    full = CostEvaluator([make_target(v) for v in capture.views])
    view_costs = full.view_costs(shape.quads())
    elapsed = time.perf_counter() - start
    return Estimate(shape.nodes, angles, shape.nodes[-1].copy(), shape.frames[-1].copy(), combine(view_costs),
                    view_costs, elapsed, method, history, evaluations)
