"""Compiled scores of the global stage (numba): a beam candidate's sample points against a
view's signed distance field, complete chains' coverage of the observed outline, the beam's
candidate generation and diversity, and the mask clean-up's label maps. Like
:mod:`estimator._kernels`, each mirrors the NumPy reference (:mod:`estimator.reference`) in
the same order of arithmetic."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._kernels import _cell, _fma32, _huber, _project, _robust, camera_params
from ._kernels_boxes import HIDDEN_BEAM_COST, hidden_points


@njit(cache=True, fastmath=False, inline="always")
def _lerp1(img, sx, sy, sx1, sy1, a, b):
    """_lerp2 on a single-channel image."""
    p00 = img[sy, sx]
    p10 = img[sy1, sx]
    top = _fma32(a, img[sy, sx1] - p00, p00)
    bottom = _fma32(a, img[sy1, sx1] - p10, p10)
    return _fma32(b, bottom - top, top)


@njit(cache=True, fastmath=False, inline="always")
def _sample_sdf(sdf_img, flag_img, x0, y0, has_ignore, u, v):
    """_sample without the gradient, from the field's sdf and ignore-flag planes: (sdf,
    ignored), the same numbers."""
    h, w = sdf_img.shape[0], sdf_img.shape[1]
    sx, sy, sx1, sy1, a, b, ox, oy = _cell(h, w, x0, y0, u, v)
    extra = abs(ox) + abs(oy)
    sdf = np.float64(_lerp1(sdf_img, sx, sy, sx1, sy1, a, b)) + extra
    ignored = has_ignore and not extra > 0 and _lerp1(flag_img, sx, sy, sx1, sy1, a, b) > 0.5
    return sdf, ignored


@njit(cache=True, fastmath=False)
def edge_cost(pts, n_edge, cam, sdf_img, flag_img, x0, y0, has_ignore, delta_out, delta_in, hidden, hidden_cost):
    """Beam score of one view: (C, s, 3) candidates' sample points, the first ``n_edge``
    on plate edges (signed distance, robust), the rest on the centre line (only outside
    counts) -> (C,) summed robust losses (ignored pixels cost nothing). sdf_img, flag_img:
    the field's channels 0 and 3 as (h, w) float32 planes; hidden: (C, s) points a scene
    box hides from this camera (cost ``hidden_cost`` each: a partial chain is not better
    for hiding behind the part)."""
    C, s = pts.shape[0], pts.shape[1]
    out = np.empty(C)
    for c in range(C):
        total = 0.0
        for p in range(s):
            u, v, x, y, z = _project(cam, pts[c, p, 0], pts[c, p, 1], pts[c, p, 2])
            sdf, ignored = _sample_sdf(sdf_img, flag_img, x0, y0, has_ignore, u, v)
            is_edge = p < n_edge
            r = sdf if is_edge else max(sdf, 0.0)
            rho, w = _robust(r, is_edge and sdf < 0, delta_out, delta_in)
            if hidden[c, p]:
                total += hidden_cost
            elif not ignored:
                total += rho
        out[c] = total
    return out


@njit(cache=True, fastmath=False)
def outline_cost(corners, segments, cam, obs, delta_out):
    """Coverage score of complete beam chains in one view: (C, M, 3) corners, outline
    segments (S, 2) as corner indices, observed outline points (P, 2) -> (C,) summed Huber
    losses of each point's distance to the nearest segment."""
    C, M = corners.shape[0], corners.shape[1]
    S = segments.shape[0]
    P = obs.shape[0]
    out = np.empty(C)
    u = np.empty(M)
    v = np.empty(M)
    bx = np.empty(S)
    by = np.empty(S)
    den = np.empty(S)
    for c in range(C):
        for k in range(M):
            u[k], v[k], x, y, z = _project(cam, corners[c, k, 0], corners[c, k, 1], corners[c, k, 2])
        for k in range(S):
            bx[k] = u[segments[k, 1]] - u[segments[k, 0]]
            by[k] = v[segments[k, 1]] - v[segments[k, 0]]
            den[k] = max(bx[k] * bx[k] + by[k] * by[k], 1e-9)
        total = 0.0
        for q in range(P):
            best = np.inf
            for k in range(S):
                rx = obs[q, 0] - u[segments[k, 0]]
                ry = obs[q, 1] - v[segments[k, 0]]
                t = min(max((rx * bx[k] + ry * by[k]) / den[k], 0.0), 1.0)
                rx -= t * bx[k]
                ry -= t * by[k]
                d2 = rx * rx + ry * ry
                if d2 < best:
                    best = d2
            rho, w = _huber(math.sqrt(best), delta_out)
            total += rho
        out[c] = total
    return out


@njit(cache=True, fastmath=False)
def beam_candidates(frames, nodes, grid_r, length, half, edge_t, tip_t, centre_t):
    """search.beam_search's candidates for one node: every kept partial chain (frames (B, 3,
    3), end nodes (B, 3)) extended by every joint rotation grid_r (G, 3, 3) by a plate of
    ``length`` and half-width ``half`` [m].

    Returns (frames (B G, 3, 3), ends (B G, 3, 3): the new plate's end node, left and right
    corner, sample points (B G, s, 3): left edge, right edge (edge_t), tip edge (tip_t,
    empty but on the last plate), centre line (centre_t)), candidate b * G + g.
    """
    B, G = frames.shape[0], grid_r.shape[0]
    ne, nt, nc = edge_t.size, tip_t.size, centre_t.size
    F = np.empty((B * G, 3, 3))
    E = np.empty((B * G, 3, 3))
    pts = np.empty((B * G, 2 * ne + nt + nc, 3))
    L0 = np.empty(3)
    R0 = np.empty(3)
    for b in range(B):
        for r in range(3):
            L0[r] = nodes[b, r] + half * frames[b, r, 1]
            R0[r] = nodes[b, r] - half * frames[b, r, 1]
        for g in range(G):
            c = b * G + g
            for i in range(3):
                for k in range(3):
                    F[c, i, k] = (frames[b, i, 0] * grid_r[g, 0, k] + frames[b, i, 1] * grid_r[g, 1, k]
                                  + frames[b, i, 2] * grid_r[g, 2, k])
            for r in range(3):
                p = nodes[b, r] + length * F[c, r, 0]
                left = p + half * F[c, r, 1]
                right = p - half * F[c, r, 1]
                E[c, 0, r] = p
                E[c, 1, r] = left
                E[c, 2, r] = right
                for q in range(ne):
                    pts[c, q, r] = L0[r] + (left - L0[r]) * edge_t[q]
                    pts[c, ne + q, r] = R0[r] + (right - R0[r]) * edge_t[q]
                for q in range(nt):
                    pts[c, 2 * ne + q, r] = left + (right - left) * tip_t[q]
                for q in range(nc):
                    pts[c, 2 * ne + nt + q, r] = nodes[b, r] + (p - nodes[b, r]) * centre_t[q]
    return F, E, pts


@njit(cache=True, fastmath=False)
def diverse(order, ends, count, min_dist):
    """search.diverse: up to ``count`` of the candidates ``order`` (best first) whose ends
    (N, 3, 3) lie at least ``min_dist`` from every better kept one's (each of the three
    points' squared distance summed as NumPy's einsum does), filled up with the best of
    the suppressed ones."""
    n = order.size
    thr = min_dist * min_dist
    kept = np.zeros(n, np.bool_)
    picked = np.empty(count, np.int64)
    npicked = 0
    for k in range(n):
        a = order[k]
        free = True
        for j in range(npicked):
            bb = picked[j]
            d2 = 0.0
            for p in range(3):
                dx = ends[a, p, 0] - ends[bb, p, 0]
                dy = ends[a, p, 1] - ends[bb, p, 1]
                dz = ends[a, p, 2] - ends[bb, p, 2]
                d2 = max(d2, (dx * dx + dz * dz) + dy * dy)
            if d2 < thr:
                free = False
                break
        if free:
            kept[k] = True
            picked[npicked] = a
            npicked += 1
            if npicked == count:
                break
    out = np.empty(min(count, n), np.int64)
    m = 0
    for k in range(n):
        if kept[k]:
            out[m] = order[k]
            m += 1
    for k in range(n):
        if m == out.size:
            break
        if not kept[k]:
            out[m] = order[k]
            m += 1
    return out


@njit(cache=True, fastmath=False)
def label_areas(labels, count):
    """np.bincount(labels.ravel(), minlength=count) of a (h, w) int32 label image."""
    areas = np.zeros(count, np.int64)
    for y in range(labels.shape[0]):
        for x in range(labels.shape[1]):
            areas[labels[y, x]] += 1
    return areas


@njit(cache=True, fastmath=False)
def map_labels(labels, lut, base):
    """(h, w) uint8 ``base | lut[labels]`` (``lut`` uint8 per label)."""
    out = np.empty(labels.shape, np.uint8)
    for y in range(labels.shape[0]):
        for x in range(labels.shape[1]):
            out[y, x] = base[y, x] | lut[labels[y, x]]
    return out


def beam_edge_cost(field, pts: np.ndarray, edge_count: int, delta_out: float, delta_in: float) -> np.ndarray:
    """Compiled beam score of one view (see :func:`edge_cost`): (..., s, 3) candidate
    sample points -> (...) summed robust losses."""
    lead = pts.shape[:-2]
    flat = np.ascontiguousarray(pts, float).reshape(-1, pts.shape[-2], 3)
    out = edge_cost(flat, edge_count, camera_params(field.camera), *field.planes, field.x0, field.y0,
                    field.has_ignore, delta_out, delta_in, hidden_points(field, flat), HIDDEN_BEAM_COST)
    return out.reshape(lead)


def beam_outline_cost(field, corners: np.ndarray, segments: np.ndarray, obs: np.ndarray,
                      delta_out: float) -> np.ndarray:
    """Compiled coverage score of complete chains in one view (see :func:`outline_cost`)."""
    return outline_cost(np.ascontiguousarray(corners, float), np.ascontiguousarray(segments, np.int64),
                        camera_params(field.camera), np.ascontiguousarray(obs, float), delta_out)
