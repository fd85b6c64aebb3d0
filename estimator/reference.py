"""The NumPy reference of the estimator's compiled kernels (estimator/_kernels*.py): the
same arithmetic, in the same order, as plain array code. ``FitConfig(compiled=False)`` fits
with it (about 10x slower per call); ``tests/test_estimator_kernels.py`` and
``tests/test_jacobians.py`` pin the kernels to it."""
from __future__ import annotations

import cv2
import numpy as np

from . import _kernels_boxes
from .config import DEFAULT, FitConfig, as_array
from .geometry import Camera, _distort
from .tape import joint_rotations


def project(camera: Camera, pts: np.ndarray):
    """Pixels (u, v) of world points (..., 3) and their camera-frame x/z, y/z and z."""
    pc = pts @ camera.R.T + camera.t
    z = np.maximum(pc[..., 2], 1e-6)
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


def pixel_jacobian(camera: Camera, x, y, z, J: np.ndarray) -> np.ndarray:
    """(..., 2, N) d(u, v)/d(angles) of points with world Jacobian J (..., 3, N), pinhole
    part (lens distortion is a small correction the iterations absorb)."""
    K = camera.K
    inv_z = 1.0 / z
    duv = np.zeros(z.shape + (2, 3))
    duv[..., 0, 0] = K[0, 0] * inv_z
    duv[..., 0, 1] = K[0, 1] * inv_z
    duv[..., 0, 2] = -(K[0, 0] * x + K[0, 1] * y) * inv_z
    duv[..., 1, 1] = K[1, 1] * inv_z
    duv[..., 1, 2] = -K[1, 1] * y * inv_z
    return (duv @ camera.R) @ J


def lookup(field, u: np.ndarray, v: np.ndarray):
    """Bilinear look-up (one ``cv2.remap`` call) of the SDF, its gradient and the ignore
    flag at pixel coordinates (u, v) of any shape.

    Outside the ROI the SDF continues as the value at the ROI's edge plus the distance to
    it, and its gradient points back towards the ROI. Returns (sdf, gx, gy, ignored|None).
    """
    h, w = field.field.shape[:2]
    shape = u.shape
    x = (u - field.x0).reshape(-1)
    y = (v - field.y0).reshape(-1)
    xc = np.clip(x, 0.0, w - 1.0)
    yc = np.clip(y, 0.0, h - 1.0)
    ox = x - xc
    oy = y - yc
    n = x.size
    cols = 8192
    rows = -(-n // cols) if n > cols else 1
    width = cols if n > cols else n
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n] = xc
    my[:n] = yc
    val = cv2.remap(field.field, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE).reshape(-1, field.field.shape[2])[:n]
    extra = np.abs(ox) + np.abs(oy)
    outside = extra > 0
    sdf = val[:, 0] + extra
    gx = np.where(ox != 0, np.sign(ox), val[:, 1])
    gy = np.where(oy != 0, np.sign(oy), val[:, 2])
    ignored = ((val[:, 3] > 0.5) & ~outside).reshape(shape) if field.has_ignore else None
    return sdf.reshape(shape), gx.reshape(shape), gy.reshape(shape), ignored


def robust(r: np.ndarray, inside_edge: np.ndarray, cfg: FitConfig = DEFAULT) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss ρ(r) and IRLS weight: Cauchy for edge points inside the silhouette,
    Huber otherwise."""
    a = np.abs(r)
    small = a <= cfg.delta_out_px
    huber_rho = np.where(small, 0.5 * r * r, cfg.delta_out_px * (a - 0.5 * cfg.delta_out_px))
    huber_w = np.where(small, 1.0, cfg.delta_out_px / np.maximum(a, 1e-12))
    q = (r / cfg.delta_in_px) ** 2
    cauchy_rho = 0.5 * cfg.delta_in_px ** 2 * np.log1p(q)
    cauchy_w = 1.0 / (1.0 + q)
    return np.where(inside_edge, cauchy_rho, huber_rho), np.where(inside_edge, cauchy_w, huber_w)


def huber(d: np.ndarray, cfg: FitConfig = DEFAULT) -> tuple[np.ndarray, np.ndarray]:
    """Huber loss and IRLS weight of non-negative distances [px]."""
    small = d <= cfg.delta_out_px
    rho = np.where(small, 0.5 * d * d, cfg.delta_out_px * (d - 0.5 * cfg.delta_out_px))
    return rho, np.where(small, 1.0, cfg.delta_out_px / np.maximum(d, 1e-12))


def folds(segments: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(B, K) which outline segments (K, 4) count for corner pixels ``u``, ``v`` (B, .):
    every edge, and a joint's line only where the tape folds there in the image (the
    points either side of it lie on one side of its line)."""
    s0, s1, a, b = (segments[:, i] for i in range(4))
    bx, by = u[:, s1] - u[:, s0], v[:, s1] - v[:, s0]
    ca = bx * (v[:, a] - v[:, s0]) - by * (u[:, a] - u[:, s0])
    cb = bx * (v[:, b] - v[:, s0]) - by * (u[:, b] - u[:, s0])
    return (a < 0)[None, :] | (ca * cb > 0)


def coverage(chain, f, u, v, Juv, active: np.ndarray, cfg: FitConfig = DEFAULT):
    """Observed outline points' distance to the model's outline: every part of the observed
    silhouette must be explained (the reverse of the edge term). u, v: (B, 3m) corner
    pixels; Juv: their (B, 3m, 2, N) Jacobian or None; active: (B, K) which of the chain's
    segments count (:func:`folds`). Returns (robust cost (B,), weighted residuals (B, P),
    Jacobian (B, P, N) or None)."""
    obs = f.outline
    B = u.shape[0]
    if len(obs) == 0:
        return np.zeros(B), np.zeros((B, 0)), (None if Juv is None else np.zeros((B, 0, Juv.shape[-1])))
    s0, s1 = chain.segments[:, 0], chain.segments[:, 1]
    ax, ay = u[:, s0], v[:, s0]                                         # (B, K)
    bx, by = u[:, s1] - ax, v[:, s1] - ay
    inv_den = 1.0 / np.maximum(bx * bx + by * by, 1e-9)
    bx3, by3 = bx[:, None], by[:, None]
    rx = obs[None, :, 0, None] - ax[:, None, :]                         # (B, P, K)
    ry = obs[None, :, 1, None] - ay[:, None, :]
    t = rx * bx3
    t += ry * by3
    t *= inv_den[:, None]
    np.minimum(t, 1.0, out=t)
    np.maximum(t, 0.0, out=t)
    rx -= t * bx3
    ry -= t * by3
    d2 = rx * rx
    d2 += ry * ry
    d2 = np.where(active[:, None, :], d2, np.inf)
    k = np.argmin(d2, axis=2)[..., None]                                # (B, P, 1)
    d = np.sqrt(np.take_along_axis(d2, k, 2)[..., 0]) + 1e-9            # (B, P)
    rho, w = huber(d, cfg)
    sw = np.sqrt(w)
    if Juv is None:
        return rho.sum(axis=1), sw * d, None
    k = k[..., 0]
    tk = np.take_along_axis(t, k[..., None], 2)
    nx = np.take_along_axis(rx, k[..., None], 2) / d[..., None]         # (B, P, 1)
    ny = np.take_along_axis(ry, k[..., None], 2) / d[..., None]
    b = np.arange(B)[:, None]
    j0, j1 = Juv[b, s0[k]], Juv[b, s1[k]]                                # (B, P, 2, N)
    g = (nx * j0[..., 0, :] + ny * j0[..., 1, :]) * (tk - 1.0)
    g -= tk * (nx * j1[..., 0, :] + ny * j1[..., 1, :])
    return rho.sum(axis=1), sw * d, sw[..., None] * g


def beam_candidates(frames: np.ndarray, nodes: np.ndarray, grid_r: np.ndarray, length: float, h: float,
                    last: bool, cfg: FitConfig = DEFAULT):
    """Kept partial chains (frames (b, 3, 3), end nodes (b, 3)) extended by every joint
    rotation of ``grid_r`` (g, 3, 3) by a plate of ``length`` and half-width ``h`` [m]:
    (frames (b, g, 3, 3), ends (b, g, 3, 3): the plate's end node, left and right corner,
    sample points (b, g, s, 3): edges, on the last plate the tip edge, centre line).
    The NumPy reference of :func:`_kernels_beam.beam_candidates`."""
    F = np.einsum("bij,gjk->bgik", frames, grid_r)               # (b, g, 3, 3)
    P = nodes[:, None, :] + length * F[..., :, 0]
    L0 = (nodes + h * frames[:, :, 1])[:, None, None, :]
    R0 = (nodes - h * frames[:, :, 1])[:, None, None, :]
    L1 = (P + h * F[..., :, 1])[:, :, None, :]
    R1 = (P - h * F[..., :, 1])[:, :, None, :]
    t = as_array(cfg.beam_edge_t)[None, None, :, None]
    parts = [L0 + (L1 - L0) * t, R0 + (R1 - R0) * t]
    if last:
        parts.append(L1 + (R1 - L1) * as_array(cfg.tip_t)[None, None, :, None])
    tc = as_array(cfg.centre_t)[None, None, :, None]
    parts.append(nodes[:, None, None, :] + (P[:, :, None, :] - nodes[:, None, None, :]) * tc)
    ends = np.stack([P, L1[:, :, 0], R1[:, :, 0]], axis=2)
    return F, ends, np.concatenate(parts, axis=2)


def diverse(order: np.ndarray, ends: np.ndarray, count: int, min_dist: float) -> np.ndarray:
    """Up to ``count`` of the candidates ``order`` (best first) whose new plate ends
    (``ends[k]``: centre, left and right corner (3, 3) [m]) lie at least ``min_dist`` from
    every better kept one's (the NumPy reference of the beam's diversity; ``min_dist`` [m]): without this the beam fills with near copies of one chain
    (twist variants of the same bends) and the other bend branch is lost."""
    e = ends[order].reshape(len(order), -1, 3)
    diff = e[:, None] - e[None, :]
    d2 = np.einsum("abpk,abpk->abp", diff, diff).max(axis=-1)
    # Greedy pick over bitsets of the "too close" relation (rows as Python ints): far
    # cheaper than a NumPy reduction per candidate.
    close = np.packbits(d2 < min_dist * min_dist, axis=1, bitorder="little")
    kept_bits, picked = 0, []
    for k in range(len(order)):
        if not int.from_bytes(close[k].tobytes(), "little") & kept_bits:
            kept_bits |= 1 << k
            picked.append(k)
            if len(picked) == count:
                break
    kept = np.zeros(len(order), bool)
    kept[picked] = True
    chosen = order[kept]
    if len(chosen) < count:
        # Fill up with the best of the suppressed ones.
        chosen = np.concatenate([chosen, order[~kept][:count - len(chosen)]])
    return chosen


def chain_points(chain, angles: np.ndarray, jacobian: bool):
    """:meth:`Chain.points` in NumPy: (B, n, 3) angles -> (B, s + 3m, 3) sample points then
    corners and, if asked, their (B, s + 3m, 3, 3n) Jacobian."""
    spec = chain.spec
    B, n, m = len(angles), chain.n, chain.n + 1
    Rj = joint_rotations(angles.reshape(-1, 3)).reshape(B, n, 3, 3)
    frames = np.empty((B, m, 3, 3))
    nodes = np.empty((B, m, 3))
    frames[:, 0] = spec.base_rotation
    nodes[:, 0] = spec.base_position
    for i in range(n):
        frames[:, i + 1] = frames[:, i] @ Rj[:, i]
        nodes[:, i + 1] = nodes[:, i] + spec.segment_lengths[i] * frames[:, i + 1, :, 0]
    half = 0.5 * spec.width * frames[:, :, :, 1]
    corners = np.concatenate([nodes, nodes + half, nodes - half], axis=1)      # (B, 3m, 3)
    pts = np.concatenate([chain.M @ corners, corners], axis=1)
    if not jacobian:
        return pts, None
    cz, sz = np.cos(angles[:, :, 2])[..., None], np.sin(angles[:, :, 2])[..., None]
    axes = np.stack([frames[:, 1:, :, 0],                                      # θx: F_j e_x
                     cz * frames[:, :-1, :, 1] - sz * frames[:, :-1, :, 0],     # θy: F_{j-1} Rz e_y
                     frames[:, :-1, :, 2]], axis=2)                             # θz: F_{j-1} e_z
    a = axes[:, None]                                                          # (B, 1, n, 3, 3)
    r = (corners[:, :, None, :] - nodes[:, None, :-1, :])[:, :, :, None, :]   # (B, 3m, n, 1, 3)
    Jc = np.stack([a[..., 1] * r[..., 2] - a[..., 2] * r[..., 1],
                   a[..., 2] * r[..., 0] - a[..., 0] * r[..., 2],
                   a[..., 0] * r[..., 1] - a[..., 1] * r[..., 0]], axis=2)   # (B, 3m, 3, n, 3)
    Jc *= chain.moves[None, :, None, :, None]
    Jc = Jc.reshape(B, 3 * m, 3 * 3 * n)
    Js = (chain.M @ Jc)
    J = np.concatenate([Js, Jc], axis=1).reshape(B, -1, 3, 3 * n)
    return pts, J


def view_terms(chain, fields, angles: np.ndarray, jacobian: bool, cfg: FitConfig = DEFAULT):
    """The per-view part of :func:`estimator.residuals.residuals` in NumPy (the compiled
    kernels' reference): (residual blocks per view [coverage (B, P_k), edges (B, s)],
    Jacobian blocks alike or [], robust cost (B,), the chains' points (B, s + 3m, 3) and
    their Jacobian or None)."""
    B = len(angles)
    ns = chain.samples
    rs, js = [], []
    cost = np.zeros(B)
    centre = ~chain.edge
    pts, J = chain_points(chain, angles, jacobian)
    for f in fields:
        u, v, x, y, z = project(f.camera, pts)
        Juv = pixel_jacobian(f.camera, x, y, z, J) if jacobian else None
        active = folds(chain.segments, u[:, ns:], v[:, ns:])
        c_cost, c_r, c_j = coverage(chain, f, u[:, ns:], v[:, ns:], None if Juv is None else Juv[:, ns:], active, cfg)
        vw = np.sqrt(f.weight)
        cost += f.weight * c_cost
        rs.append(vw * c_r)
        if c_j is not None:
            c_j = vw * c_j
        sdf, gx, gy, ignored = lookup(f, u[:, :ns], v[:, :ns])
        if f.boxes:
            behind = _kernels_boxes.hidden_points(f, pts[:, :ns])
            ignored = behind if ignored is None else ignored | behind
        r = np.where(centre, np.maximum(sdf, 0.0), sdf)
        rho, w = robust(r, chain.edge & (sdf < 0), cfg)
        # A joint's line is outline only where the tape folds there in the image.
        fold_of = chain.fold_of
        off = (fold_of >= 0)[None, :] & ~np.take(active, np.maximum(fold_of, 0), axis=1)
        ignored = off if ignored is None else ignored | off
        if ignored is not None:
            rho = np.where(ignored, 0.0, rho)
            w = np.where(ignored, 0.0, w)
        cost += f.weight * (rho * chain.weight ** 2).sum(axis=1)
        sw = np.sqrt(w) * chain.weight * vw
        rs.append(sw * r)
        if jacobian:
            sw = np.where(centre & (sdf <= 0), 0.0, sw)
            g = gx[..., None] * Juv[:, :ns, 0] + gy[..., None] * Juv[:, :ns, 1]     # (B, s, 3n)
            js += [c_j, sw[..., None] * g]
    return rs, js, cost, pts, J


def beam_edge_cost(f, pts: np.ndarray, is_edge: np.ndarray, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """The beam's score of candidates' sample points (..., s, 3) in one view: their summed
    robust losses against the view's signed distance field (NumPy reference of the per-view
    sums in :func:`_kernels_beam.best_totals`)."""
    u, v, *_ = project(f.camera, pts)
    sdf, _, _, ignored = lookup(f, u, v)
    r = np.where(is_edge, sdf, np.maximum(sdf, 0.0))
    rho, _ = robust(r, is_edge & (sdf < 0), cfg)
    if ignored is not None:
        rho = np.where(ignored, 0.0, rho)
    return rho.sum(axis=2)


def beam_outline_cost(f, corners: np.ndarray, seg: np.ndarray, obs: np.ndarray, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """Complete chains' coverage of the observed outline points ``obs`` in one view (NumPy
    reference of :func:`_kernels_beam.beam_outline_cost`): (c,) summed Huber losses."""
    u, v, *_ = project(f.camera, corners)                          # (c, 2m)
    ax, ay = u[:, seg[:, 0]], v[:, seg[:, 0]]                       # (c, S)
    bx, by = u[:, seg[:, 1]] - ax, v[:, seg[:, 1]] - ay
    den = np.maximum(bx * bx + by * by, 1e-9)[:, None]
    rx = obs[None, :, 0, None] - ax[:, None]                        # (c, P, S)
    ry = obs[None, :, 1, None] - ay[:, None]
    t = np.clip((rx * bx[:, None] + ry * by[:, None]) / den, 0.0, 1.0)
    rx -= t * bx[:, None]
    ry -= t * by[:, None]
    d2 = rx * rx + ry * ry
    d2 = np.where(folds(seg, u, v)[:, None, :], d2, np.inf)
    d = np.sqrt(np.min(d2, axis=2))
    rho, _ = huber(d, cfg)
    return rho.sum(axis=1)
