"""Compiled scores of the global stage (numba): beam candidates' sample points against the
views' signed distance fields (exactly for the candidates that may be kept), complete
chains' coverage of the observed outline, the beam's candidate generation and diversity,
and the mask clean-up's label maps. Like :mod:`estimator._kernels`, each mirrors the NumPy
reference (:mod:`estimator.reference`) in the same order of arithmetic."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._kernels import _cell, _fma32, _folds, _huber, _project, _robust, camera_params
from ._kernels_boxes import HIDDEN_BEAM_COST, box_origins, segment_hits, views_box_arrays


@njit(cache=True, fastmath=False, inline="always")
def _lerp_flat(img, off, w, sx, sy, sx1, sy1, a, b):
    """:func:`_kernels._lerp2` on a single-channel plane stored flat (row length ``w``) from
    ``img[off]``: the same numbers."""
    p00 = img[off + sy * w + sx]
    p10 = img[off + sy1 * w + sx]
    top = _fma32(a, img[off + sy * w + sx1] - p00, p00)
    bottom = _fma32(a, img[off + sy1 * w + sx1] - p10, p10)
    return _fma32(b, bottom - top, top)


@njit(cache=True, fastmath=False)
def best_totals(pts, n_edge, cams, sdf, flag, offsets, sizes, origins, has_ignore, weights, eyes, bcent, brot, bhalf,
                hidden_cost, delta_out, delta_in, base, prior, extra, keep, order, perm):
    """The beam's totals (B G,) of its candidates (B G, s, 3) (candidate b G + g: parent b,
    grid angle g) over all views, as the NumPy reference (``reference.beam_edge_cost`` and
    ``search.beam_search``) sums them to float rounding, a view's losses in point order: per
    view the summed robust losses of the
    points, the first ``n_edge`` on plate edges (signed distance), the rest on the centre line
    (only outside counts), ignored pixels costing nothing, times the view's weight, added to
    the plate's score, then ``extra``
    (the box penetration term), then (``base[b]`` + that) + ``prior[g]``; but +inf for a
    candidate that cannot rank among the ``keep`` best. A candidate's points are scored in
    the order ``perm`` (the most telling first), in every view, and it is cut short once
    the sum of its non-negative losses so far is above the ``keep``-th best total found so
    far (by more than the summation's rounding: that sum is a lower bound of its total);
    the totals of the others are summed in their own order, so the ``keep`` best are exact.

    Views k: camera ``cams[k]``, signed distance plane ``sdf[offsets[k, 0]:]`` and ignore
    flag plane ``flag[offsets[k, 1]:]`` (used only where ``has_ignore[k]``), each ``sizes[k]``
    (h, w) with its top-left pixel at ``origins[k]``, its camera's centre ``eyes[k]``; a point
    the scene boxes (centres ``bcent`` (K, 3), rotations ``brot``, half edges ``bhalf``
    shrunk by the surface margin; K = 0 without boxes) hide from a view costs
    ``hidden_cost`` there (tested only for the points scored). ``order``: the
    candidates in the order they are tried (the sooner the best are, the more are cut short)."""
    C, s = pts.shape[0], pts.shape[1]
    G = prior.size
    V = weights.size
    boxes = bcent.shape[0] > 0
    local = np.empty((V, bcent.shape[0], 3))
    for k in range(V):
        local[k] = box_origins(eyes[k], bcent, brot)
    out = np.full(C, np.inf)
    heap = np.full(max(keep, 1), np.inf)     # max-heap of the best ``keep`` totals so far
    loss = np.zeros((V, s))
    partial = np.zeros(V)
    for c in order:
        b = c // G
        g = c - b * G
        limit = heap[0] * (1.0 + 1e-12)
        lead = base[b]
        tail = prior[g]
        partial[:] = 0.0
        pruned = False
        for p in perm:
            is_edge = p < n_edge
            bound = lead + tail
            for k in range(V):
                if boxes and segment_hits(local[k], pts[c, p, 0], pts[c, p, 1], pts[c, p, 2], bcent, brot, bhalf):
                    val = hidden_cost
                else:
                    cam = cams[k]
                    h, w = sizes[k, 0], sizes[k, 1]
                    u, v, x, y, z = _project(cam, pts[c, p, 0], pts[c, p, 1], pts[c, p, 2])
                    sx, sy, sx1, sy1, a, bb, ox, oy = _cell(h, w, origins[k, 0], origins[k, 1], u, v)
                    ext = abs(ox) + abs(oy)
                    d = np.float64(_lerp_flat(sdf, offsets[k, 0], w, sx, sy, sx1, sy1, a, bb)) + ext
                    if (has_ignore[k] and not ext > 0
                            and _lerp_flat(flag, offsets[k, 1], w, sx, sy, sx1, sy1, a, bb) > 0.5):
                        val = 0.0
                    else:
                        r = d if is_edge else max(d, 0.0)
                        val, _ = _robust(r, is_edge and d < 0, delta_out, delta_in)
                loss[k, p] = val
                partial[k] += val
                bound += weights[k] * partial[k]
            if bound > limit:
                pruned = True
                break
        if pruned:
            continue
        plate = 0.0
        for k in range(V):
            total = 0.0
            for p in range(s):
                total += loss[k, p]
            plate += weights[k] * total
        plate += extra[c]
        t = (lead + plate) + tail
        out[c] = t
        if t < heap[0]:
            # Replace the largest kept total and sift it down.
            i = 0
            n = heap.size
            while True:
                left = 2 * i + 1
                if left >= n:
                    break
                j = left
                if left + 1 < n and heap[left + 1] > heap[left]:
                    j = left + 1
                if heap[j] <= t:
                    break
                heap[i] = heap[j]
                i = j
            heap[i] = t
    return out


@njit(cache=True, fastmath=False)
def outline_cost(corners, segments, cam, obs, delta_out):
    """Coverage score of complete beam chains in one view: (C, M, 3) corners, outline
    segments (S, 4) as corner indices (s0, s1, a, b: counted only where ``a`` and ``b`` lie
    on one side of the segment's line, always for a < 0; see ``Chain.segments``), observed outline points (P, 2) -> (C,) summed Huber
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
    active = np.empty(S, np.bool_)
    for c in range(C):
        for k in range(M):
            u[k], v[k], x, y, z = _project(cam, corners[c, k, 0], corners[c, k, 1], corners[c, k, 2])
        for k in range(S):
            bx[k] = u[segments[k, 1]] - u[segments[k, 0]]
            by[k] = v[segments[k, 1]] - v[segments[k, 0]]
            den[k] = max(bx[k] * bx[k] + by[k] * by[k], 1e-9)
            active[k] = _folds(segments[k, 2], segments[k, 3], segments[k, 0], bx[k], by[k], u, v)
        total = 0.0
        for q in range(P):
            best = np.inf
            for k in range(S):
                if not active[k]:
                    continue
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


def pack_views(fields) -> tuple:
    """The views' beam-scoring inputs in :func:`best_totals`' form: (cams, sdf, flag,
    offsets, sizes, origins, has_ignore, weights, eyes, box centres, rotations, half edges);
    made once per beam search."""
    sdf, flag, offsets, at_sdf, at_flag = [], [], [], 0, 0
    for f in fields:
        plane, ignore = f.planes
        offsets.append((at_sdf, at_flag))
        sdf.append(plane.ravel())
        at_sdf += plane.size
        if f.has_ignore:
            flag.append(ignore.ravel())
            at_flag += ignore.size
    return (np.array([camera_params(f.camera) for f in fields]),
            np.concatenate(sdf).astype(np.float32, copy=False),
            np.concatenate(flag).astype(np.float32, copy=False) if flag else np.zeros(1, np.float32),
            np.array(offsets, np.int64), np.array([f.planes[0].shape for f in fields], np.int64),
            np.array([(f.x0, f.y0) for f in fields], np.int64), np.array([f.has_ignore for f in fields]),
            np.array([f.weight for f in fields], float),
            np.array([f.camera.center for f in fields], float).reshape(-1, 3), *views_box_arrays(fields))


def beam_totals(fields, packed: tuple, pts: np.ndarray, edge_count: int, perm: np.ndarray, base: np.ndarray,
                prior: np.ndarray, extra: np.ndarray, keep: int, delta_out: float, delta_in: float) -> np.ndarray:
    """The beam's totals of candidates ``pts`` (B, G, s, 3) over ``fields`` (``packed`` by
    :func:`pack_views`), exact for the ``keep`` best and +inf for candidates that cannot be
    among them (see :func:`best_totals`, which scores the points in the order ``perm``);
    (B G,). Where two of the ``keep`` best are equal,
    all totals are computed (which of two equal totals ranks first is then the sort's
    choice on the whole array, as without the bound)."""
    flat = np.ascontiguousarray(pts, float).reshape(-1, pts.shape[-2], 3)
    args = (flat, edge_count, *packed,
            HIDDEN_BEAM_COST, delta_out, delta_in, np.ascontiguousarray(base, float), prior, extra)
    # Tried in the order of what is known before scoring (the parent's score, the angles'
    # prior): the best come early and set a tight bound.
    order = np.argsort((base[:, None] + prior[None, :]).ravel(), kind="stable")
    total = best_totals(*args, keep, order, perm)
    if keep < len(total):
        best = np.sort(total)[:keep]
        if np.any(best[1:] == best[:-1]) or np.count_nonzero(total == best[-1]) > 1:
            total = best_totals(*args, len(total) + 1, order, perm)
    return total


def beam_outline_cost(field, corners: np.ndarray, segments: np.ndarray, obs: np.ndarray,
                      delta_out: float) -> np.ndarray:
    """Compiled coverage score of complete chains in one view (see :func:`outline_cost`)."""
    return outline_cost(np.ascontiguousarray(corners, float), np.ascontiguousarray(segments, np.int64),
                        camera_params(field.camera), np.ascontiguousarray(obs, float), delta_out)
