"""Compiled inner loops of the default estimator (numba), numerically the same as the
NumPy code in :mod:`estimator.reference` they replace.

A fit evaluates its residuals and their Jacobian a few dozen times and scores a few
thousand beam candidates per node; in NumPy each evaluation is ~100 small array calls
whose overhead, not arithmetic, dominates. Here each is one loop per view.

Every kernel mirrors its NumPy counterpart's arithmetic in the same order, so results
agree to float rounding (``tests/test_estimator_kernels.py`` checks them against the
NumPy reference). The SDF look-up reproduces ``cv2.remap``'s bilinear interpolation
as OpenCV 5 computes it: coordinates rounded to float32, two fused multiply-add lerps
along x then one along y in float32, edge pixels replicated.

Compiled once per machine (``cache=True``); :func:`warm` loads them before a fit's
clock starts so no compile or cache load is ever timed.
"""
from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit

from .geometry import Camera
from .scene import Box
from ._kernels_boxes import hidden_points

_camera_cache: "weakref.WeakKeyDictionary[Camera, np.ndarray]" = weakref.WeakKeyDictionary()


def camera_params(camera: Camera) -> np.ndarray:
    """(34,) float64: K (9), R (9), t (3), 12 distortion terms, has_distortion flag."""
    p = _camera_cache.get(camera)
    if p is None:
        d = np.zeros(12)
        d[: camera.dist.size] = camera.dist
        p = np.concatenate([np.asarray(camera.K, float).ravel(), np.asarray(camera.R, float).ravel(),
                            np.asarray(camera.t, float), d, [1.0 if camera.has_distortion else 0.0]])
        _camera_cache[camera] = p
    return p


# --------------------------------------------------------------------------- scalars

@njit(cache=True, fastmath=False, inline="always")
def _project(cam, px, py, pz):
    """Pixel (u, v) of a world point and its camera-frame x/z, y/z, z (reference.project)."""
    cx = px * cam[9] + py * cam[10] + pz * cam[11] + cam[18]
    cy = px * cam[12] + py * cam[13] + pz * cam[14] + cam[19]
    cz = px * cam[15] + py * cam[16] + pz * cam[17] + cam[20]
    z = max(cz, 1e-6)
    x = cx / z
    y = cy / z
    if cam[33] != 0.0:
        k1, k2, p1, p2, k3, k4, k5, k6 = cam[21], cam[22], cam[23], cam[24], cam[25], cam[26], cam[27], cam[28]
        s1, s2, s3, s4 = cam[29], cam[30], cam[31], cam[32]
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        radial = (1 + k1 * r2 + k2 * r4 + k3 * r6) / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    else:
        xd = x
        yd = y
    u = cam[0] * xd + cam[1] * yd + cam[2]
    v = cam[4] * yd + cam[5]
    return u, v, x, y, z


@njit(cache=True, fastmath=False, inline="always")
def _duv_world(cam, x, y, z):
    """Rows of d(u, v)/d(world point), pinhole part (reference.pixel_jacobian: (duv @ R))."""
    inv_z = 1.0 / z
    a00 = cam[0] * inv_z
    a01 = cam[1] * inv_z
    a02 = -(cam[0] * x + cam[1] * y) * inv_z
    a11 = cam[4] * inv_z
    a12 = -cam[4] * y * inv_z
    # (duv @ R): duv[1, 0] is 0.
    u0 = a00 * cam[9] + a01 * cam[12] + a02 * cam[15]
    u1 = a00 * cam[10] + a01 * cam[13] + a02 * cam[16]
    u2 = a00 * cam[11] + a01 * cam[14] + a02 * cam[17]
    v0 = 0.0 * cam[9] + a11 * cam[12] + a12 * cam[15]
    v1 = 0.0 * cam[10] + a11 * cam[13] + a12 * cam[16]
    v2 = 0.0 * cam[11] + a11 * cam[14] + a12 * cam[17]
    return u0, u1, u2, v0, v1, v2


@njit(cache=True, fastmath=False, inline="always")
def _fma32(x, y, z):
    """float32 x * y + z rounded once, as OpenCV's SIMD remap computes it (the float32
    product is exact in float64)."""
    return np.float32(np.float64(x) * np.float64(y) + np.float64(z))


@njit(cache=True, fastmath=False, inline="always")
def _lerp2(field, sx, sy, sx1, sy1, a, b, c):
    """Channel ``c`` of ``field`` interpolated between pixels (sx..sx1, sy..sy1)."""
    p00 = field[sy, sx, c]
    p10 = field[sy1, sx, c]
    top = _fma32(a, field[sy, sx1, c] - p00, p00)
    bottom = _fma32(a, field[sy1, sx1, c] - p10, p10)
    return _fma32(b, bottom - top, top)


@njit(cache=True, fastmath=False, inline="always")
def _cell(h, w, x0, y0, u, v):
    """Bilinear cell of full-image pixel (u, v) in a (h, w) ROI at (x0, y0), as cv2.remap
    with BORDER_REPLICATE: (sx, sy, sx1, sy1, a, b) in float32 as OpenCV 5 computes them,
    and (ox, oy), how far the point lies outside the ROI [px]."""
    x = u - x0
    y = v - y0
    if not (math.isfinite(x) and math.isfinite(y)):
        # A point behind the camera or at infinity: far outside, and never an index.
        return 0, 0, min(1, w - 1), min(1, h - 1), np.float32(0.0), np.float32(0.0), 1e6, 1e6
    xc = min(max(x, 0.0), w - 1.0)
    yc = min(max(y, 0.0), h - 1.0)
    ox = x - xc
    oy = y - yc
    xf = np.float32(xc)
    yf = np.float32(yc)
    sx = int(math.floor(xf))
    sy = int(math.floor(yf))
    a = xf - np.float32(sx)
    b = yf - np.float32(sy)
    sx1 = min(sx + 1, w - 1)
    sy1 = min(sy + 1, h - 1)
    return sx, sy, sx1, sy1, a, b, ox, oy


@njit(cache=True, fastmath=False, inline="always")
def _sample(field, x0, y0, has_ignore, u, v):
    """reference.lookup at one pixel: (sdf, gx, gy, ignored) with cv2.remap's bilinear maths."""
    h, w = field.shape[0], field.shape[1]
    sx, sy, sx1, sy1, a, b, ox, oy = _cell(h, w, x0, y0, u, v)
    sdf0 = _lerp2(field, sx, sy, sx1, sy1, a, b, 0)
    gx0 = _lerp2(field, sx, sy, sx1, sy1, a, b, 1)
    gy0 = _lerp2(field, sx, sy, sx1, sy1, a, b, 2)
    flag = _lerp2(field, sx, sy, sx1, sy1, a, b, 3) if has_ignore else np.float32(0.0)
    extra = abs(ox) + abs(oy)
    sdf = np.float64(sdf0) + extra
    gx = np.float64(gx0) if ox == 0 else (1.0 if ox > 0 else -1.0)
    gy = np.float64(gy0) if oy == 0 else (1.0 if oy > 0 else -1.0)
    ignored = has_ignore and flag > 0.5 and not extra > 0
    return sdf, gx, gy, ignored


@njit(cache=True, fastmath=False, inline="always")
def _robust(r, inside_edge, delta_out, delta_in):
    """reference.robust for one residual: (rho, IRLS weight)."""
    if inside_edge:
        q = (r / delta_in) ** 2
        return 0.5 * delta_in ** 2 * math.log1p(q), 1.0 / (1.0 + q)
    a = abs(r)
    if a <= delta_out:
        return 0.5 * r * r, 1.0
    return delta_out * (a - 0.5 * delta_out), delta_out / max(a, 1e-12)


@njit(cache=True, fastmath=False, inline="always")
def _huber(d, delta_out):
    """reference.huber for one distance: (rho, IRLS weight)."""
    if d <= delta_out:
        return 0.5 * d * d, 1.0
    return delta_out * (d - 0.5 * delta_out), delta_out / max(d, 1e-12)


# --------------------------------------------------------------------------- kernels

@njit(cache=True, fastmath=False)
def lookup(field, x0, y0, has_ignore, u, v):
    """reference.lookup on flat (N,) pixel coordinates: (sdf, gx, gy, ignored) arrays."""
    n = u.size
    sdf = np.empty(n)
    gx = np.empty(n)
    gy = np.empty(n)
    ign = np.zeros(n, np.bool_)
    for i in range(n):
        sdf[i], gx[i], gy[i], ign[i] = _sample(field, x0, y0, has_ignore, u[i], v[i])
    return sdf, gx, gy, ign


@njit(cache=True, fastmath=False)
def chain_points(angles, base_position, base_rotation, segment_lengths, width, pair, pair_w, jacobian):
    """Chain.points: (B, n, 3) angles -> sample points then corners (B, s + 3m, 3)
    and, if ``jacobian``, their Jacobian (B, s + 3m, 3, 3n) (else shape (0, 0, 3, 0)).

    pair, pair_w: (s, 2) corner indices and weights of each sample point (the two non-zero
    entries of the chain's interpolation matrix M); corners are P_C, then P_L, then P_R.
    """
    B, n = angles.shape[0], angles.shape[1]
    m = n + 1
    s = pair.shape[0]
    frames = np.empty((m, 3, 3))
    nodes = np.empty((m, 3))
    corners = np.empty((3 * m, 3))
    pts = np.empty((B, s + 3 * m, 3))
    J = np.zeros((B if jacobian else 0, s + 3 * m if jacobian else 0, 3, 3 * n if jacobian else 0))
    Rj = np.empty((3, 3))
    axes = np.empty((n, 3, 3))   # joint j, angle a -> world axis
    half = 0.5 * width
    for b in range(B):
        for r in range(3):
            nodes[0, r] = base_position[r]
            for c in range(3):
                frames[0, r, c] = base_rotation[r, c]
        for i in range(n):
            ax, ay, az = angles[b, i, 0], angles[b, i, 1], angles[b, i, 2]
            cx, sx = np.cos(ax), np.sin(ax)
            cy, sy = np.cos(ay), np.sin(ay)
            cz, sz = np.cos(az), np.sin(az)
            Rj[0, 0] = cz * cy
            Rj[0, 1] = cz * sy * sx - sz * cx
            Rj[0, 2] = cz * sy * cx + sz * sx
            Rj[1, 0] = sz * cy
            Rj[1, 1] = sz * sy * sx + cz * cx
            Rj[1, 2] = sz * sy * cx - cz * sx
            Rj[2, 0] = -sy
            Rj[2, 1] = cy * sx
            Rj[2, 2] = cy * cx
            for r in range(3):
                for c in range(3):
                    frames[i + 1, r, c] = (frames[i, r, 0] * Rj[0, c] + frames[i, r, 1] * Rj[1, c]
                                           + frames[i, r, 2] * Rj[2, c])
                nodes[i + 1, r] = nodes[i, r] + segment_lengths[i] * frames[i + 1, r, 0]
            if jacobian:
                for r in range(3):
                    axes[i, 0, r] = frames[i + 1, r, 0]                              # θx: F_j e_x
                    axes[i, 1, r] = cz * frames[i, r, 1] - sz * frames[i, r, 0]      # θy: F_{j-1} Rz e_y
                    axes[i, 2, r] = frames[i, r, 2]                                  # θz: F_{j-1} e_z
        for k in range(m):
            for r in range(3):
                hv = half * frames[k, r, 1]
                corners[k, r] = nodes[k, r]
                corners[m + k, r] = nodes[k, r] + hv
                corners[2 * m + k, r] = nodes[k, r] - hv
        for p in range(s):
            i0, i1 = pair[p, 0], pair[p, 1]
            for r in range(3):
                pts[b, p, r] = pair_w[p, 0] * corners[i0, r] + pair_w[p, 1] * corners[i1, r]
        for c in range(3 * m):
            for r in range(3):
                pts[b, s + c, r] = corners[c, r]
        if not jacobian:
            continue
        for c in range(3 * m):
            node = c % m               # corner c moves with joints 1..node
            for j in range(node):
                rx = corners[c, 0] - nodes[j, 0]
                ry = corners[c, 1] - nodes[j, 1]
                rz = corners[c, 2] - nodes[j, 2]
                for a in range(3):
                    e0, e1, e2 = axes[j, a, 0], axes[j, a, 1], axes[j, a, 2]
                    col = 3 * j + a
                    J[b, s + c, 0, col] = e1 * rz - e2 * ry
                    J[b, s + c, 1, col] = e2 * rx - e0 * rz
                    J[b, s + c, 2, col] = e0 * ry - e1 * rx
        for p in range(s):
            i0, i1 = s + pair[p, 0], s + pair[p, 1]
            w0, w1 = pair_w[p, 0], pair_w[p, 1]
            for r in range(3):
                for col in range(3 * n):
                    J[b, p, r, col] = w0 * J[b, i0, r, col] + w1 * J[b, i1, r, col]
    return pts, J


@njit(cache=True, fastmath=False)
def _folds(a, b, s0, bx, by, u, v):
    """Whether an outline segment counts: always for an edge (``a`` < 0); for a joint's
    line across the tape (from corner ``s0`` along (bx, by) in the image [px]), only where
    the tape folds there in the image: the points ``a`` and ``b`` either side of it (pixels
    ``u``, ``v``) lie on the same side of its line. A switch, not a weight: the local
    stage's Jacobian does not see it flip, and where a neighbour lies on the line itself the
    kernel and the NumPy reference may decide it differently (measure zero). Callers in
    other files cache their compiled code: after changing this, clear numba's cache."""
    if a < 0:
        return True
    ca = bx * (v[a] - v[s0]) - by * (u[a] - u[s0])
    cb = bx * (v[b] - v[s0]) - by * (u[b] - u[s0])
    return ca * cb > 0.0


@njit(cache=True, fastmath=False)
def view_residuals(pts, J, jacobian, cam, field, x0, y0, has_ignore, outline, ns, edge, weight, segments,
                   fold_of, delta_out, delta_in, hidden, res, jac, row0):
    """One view's part of residuals.residuals (no view shifts): coverage residuals of the
    observed outline (P) then the sample points' (ns) residuals.

    pts: (B, ns + 3m, 3) sample points then corners; J: their Jacobian (B, ., 3, N);
    hidden: (B, ns) sample points a scene box hides from this camera (cost nothing).
    segments: (K, 4) the outline's segments (``Chain.segments``); fold_of: (ns,) each sample
    point's joint line in them, or -1: a point on a joint that does not fold costs nothing.
    Writes the weighted residuals to ``res[:, row0:row0 + P + ns]`` and, with ``jacobian``,
    their Jacobian to ``jac[:, row0:row0 + P + ns]`` (B, ., N); returns the robust cost (B,).
    """
    B = pts.shape[0]
    nc = pts.shape[1] - ns
    N = J.shape[3] if jacobian else 0
    P = outline.shape[0]
    K = segments.shape[0]
    cost = np.zeros(B)
    cu = np.empty(nc)
    cv = np.empty(nc)
    cduv = np.empty((nc, 2, N))
    bx = np.empty(K)
    by = np.empty(K)
    inv_den = np.empty(K)
    active = np.empty(K, np.bool_)
    for b in range(B):
        # corners: pixels and pixel Jacobian
        for c in range(nc):
            p = ns + c
            u, v, x, y, z = _project(cam, pts[b, p, 0], pts[b, p, 1], pts[b, p, 2])
            cu[c] = u
            cv[c] = v
            if jacobian:
                u0, u1, u2, v0, v1, v2 = _duv_world(cam, x, y, z)
                for col in range(N):
                    cduv[c, 0, col] = u0 * J[b, p, 0, col] + u1 * J[b, p, 1, col] + u2 * J[b, p, 2, col]
                    cduv[c, 1, col] = v0 * J[b, p, 0, col] + v1 * J[b, p, 1, col] + v2 * J[b, p, 2, col]
        # coverage: each observed outline point's distance to the model outline
        for k in range(K):
            s0, s1 = segments[k, 0], segments[k, 1]
            bx[k] = cu[s1] - cu[s0]
            by[k] = cv[s1] - cv[s0]
            inv_den[k] = 1.0 / max(bx[k] * bx[k] + by[k] * by[k], 1e-9)
            active[k] = _folds(segments[k, 2], segments[k, 3], s0, bx[k], by[k], cu, cv)
        rho_sum = 0.0
        for q in range(P):
            best = np.inf
            kb = 0
            tb = 0.0
            rxb = 0.0
            ryb = 0.0
            for k in range(K):
                if not active[k]:
                    continue
                s0 = segments[k, 0]
                rx = outline[q, 0] - cu[s0]
                ry = outline[q, 1] - cv[s0]
                t = rx * bx[k]
                t += ry * by[k]
                t *= inv_den[k]
                t = max(min(t, 1.0), 0.0)
                rx -= t * bx[k]
                ry -= t * by[k]
                d2 = rx * rx
                d2 += ry * ry
                if d2 < best:
                    best = d2
                    kb = k
                    tb = t
                    rxb = rx
                    ryb = ry
            d = math.sqrt(best) + 1e-9
            rho, w = _huber(d, delta_out)
            rho_sum += rho
            sw = math.sqrt(w)
            res[b, row0 + q] = sw * d
            if jacobian:
                nx = rxb / d
                ny = ryb / d
                s0, s1 = segments[kb, 0], segments[kb, 1]
                for col in range(N):
                    g = (nx * cduv[s0, 0, col] + ny * cduv[s0, 1, col]) * (tb - 1.0)
                    g -= tb * (nx * cduv[s1, 0, col] + ny * cduv[s1, 1, col])
                    jac[b, row0 + q, col] = sw * g
        cost[b] += rho_sum
        # sample points: signed distance to the observed boundary
        rho_sum = 0.0
        for p in range(ns):
            u, v, x, y, z = _project(cam, pts[b, p, 0], pts[b, p, 1], pts[b, p, 2])
            sdf, gx, gy, ignored = _sample(field, x0, y0, has_ignore, u, v)
            centre = not edge[p]
            r = max(sdf, 0.0) if centre else sdf
            rho, w = _robust(r, edge[p] and sdf < 0, delta_out, delta_in)
            if ignored or hidden[b, p] or (fold_of[p] >= 0 and not active[fold_of[p]]):
                rho = 0.0
                w = 0.0
            rho_sum += rho * weight[p] ** 2
            sw = math.sqrt(w) * weight[p]
            res[b, row0 + P + p] = sw * r
            if jacobian:
                if centre and sdf <= 0:
                    sw = 0.0
                u0, u1, u2, v0, v1, v2 = _duv_world(cam, x, y, z)
                for col in range(N):
                    ju = u0 * J[b, p, 0, col] + u1 * J[b, p, 1, col] + u2 * J[b, p, 2, col]
                    jv = v0 * J[b, p, 0, col] + v1 * J[b, p, 1, col] + v2 * J[b, p, 2, col]
                    jac[b, row0 + P + p, col] = sw * (gx * ju + gy * jv)
        cost[b] += rho_sum
    return cost


# --------------------------------------------------------------------------- wrappers

_chain_cache: "weakref.WeakKeyDictionary[object, tuple]" = weakref.WeakKeyDictionary()


_pairs_cache: dict = {}


def _pairs(M: np.ndarray) -> tuple:
    """A chain's sample matrix M (s, 3m), at most two corners a row, as (pair (s, 2) corner
    indices, pair_w (s, 2) weights); cached per matrix (chains of one plate count share it)."""
    hit = _pairs_cache.get(id(M))
    if hit is not None and hit[0] is M:
        return hit[1], hit[2]
    Mf = np.asarray(M, float)
    pair = np.zeros((len(Mf), 2), np.int64)
    pair_w = np.zeros((len(Mf), 2))
    rows, cols = np.nonzero(Mf)                   # row-major: each row's columns ascending
    count = np.bincount(rows, minlength=len(Mf))
    if np.any(count > 2):
        raise ValueError("a chain sample point mixes more than two corners")
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(count) - count, count)
    pair[rows, slot] = cols
    pair_w[rows, slot] = Mf[rows, cols]
    if len(_pairs_cache) > 32:
        _pairs_cache.clear()
    _pairs_cache[id(M)] = (M, pair, pair_w)
    return pair, pair_w


def _chain_arrays(chain) -> tuple:
    """The chain's fixed arrays in kernel form: (pair, pair_w, edge, weight, segments, fold_of,
    base position, base rotation, segment lengths, width); cached per chain."""
    arrays = _chain_cache.get(chain)
    if arrays is None:
        pair, pair_w = _pairs(chain.M)
        spec = chain.spec
        arrays = (pair, pair_w, np.ascontiguousarray(chain.edge, np.bool_),
                  np.ascontiguousarray(chain.weight, float), np.ascontiguousarray(chain.segments, np.int64),
                  np.ascontiguousarray(chain.fold_of, np.int64),
                  np.ascontiguousarray(spec.base_position, float), np.ascontiguousarray(spec.base_rotation, float),
                  np.ascontiguousarray(spec.segment_lengths, float), float(spec.width))
        _chain_cache[chain] = arrays
    return arrays


def points(chain, angles: np.ndarray, jacobian: bool):
    """Compiled ``Chain.points``: (B, n, 3) angles -> points (B, s + 3m, 3), Jacobian
    (B, s + 3m, 3, 3n) or None."""
    pair, pair_w, _, _, _, _, pos, rot, lengths, width = _chain_arrays(chain)
    pts, J = chain_points(np.ascontiguousarray(angles, float), pos, rot, lengths, width, pair, pair_w, jacobian)
    return pts, (J if jacobian else None)


def view_terms(chain, fields, angles: np.ndarray, jacobian: bool, delta_out: float, delta_in: float, extra: int):
    """Compiled per-view part of ``residuals.residuals`` without view shifts, its blocks
    already in place: (residuals (B, R), Jacobian (B, R, 3n) or None, robust cost (B,), the
    chains' points (B, s + 3m, 3) and their Jacobian (B, s + 3m, 3, 3n) or None), where rows
    0..R - ``extra`` hold each view's (coverage P_k, then the s sample points; a view's
    weight w scales its rows by sqrt(w) and its cost by w) and the last ``extra`` rows are
    left for the caller to fill."""
    pair, pair_w, edge, weight, segments, fold_of, pos, rot, lengths, width = _chain_arrays(chain)
    pts, J = chain_points(np.ascontiguousarray(angles, float), pos, rot, lengths, width, pair, pair_w, jacobian)
    B = len(pts)
    ns = chain.samples
    R = sum(len(f.outline) + ns for f in fields) + extra
    res = np.empty((B, R))
    jac = np.empty((B, R, 3 * chain.n) if jacobian else (0, 0, 0))
    cost = np.zeros(B)
    row = 0
    for f in fields:
        c = view_residuals(pts, J, jacobian, camera_params(f.camera), f.field, f.x0, f.y0, f.has_ignore,
                           f.outline, ns, edge, weight, segments, fold_of, delta_out, delta_in,
                           hidden_points(f, pts[:, :ns]),
                           res, jac, row)
        rows = slice(row, row + len(f.outline) + ns)
        if f.weight != 1.0:
            w = np.sqrt(f.weight)
            res[:, rows] *= w
            if jacobian:
                jac[:, rows] *= w
        cost += f.weight * c
        row = rows.stop
    return res, (jac if jacobian else None), cost, pts, (J if jacobian else None)


def rotation_terms(chain, fields, angles: np.ndarray, delta_out: float, delta_in: float) -> np.ndarray:
    """The Jacobian (R, 3K) of :func:`view_terms`' rows (each view's coverage, then its sample
    points, view after view) by each camera's rotation vector (its own frame, about its optical
    centre), for one chain ``angles`` (n, 3); the robust weights held as for the joint angles.
    Turning a camera by w moves a point's camera-frame position p to p + w x p: as the world
    point moving by -R^T [p]x w, which :func:`view_residuals` takes as a point Jacobian of three
    columns. A view's rows depend on its own camera alone."""
    pair, pair_w, edge, weight, segments, fold_of, pos, rot, lengths, width = _chain_arrays(chain)
    pts, _ = chain_points(np.ascontiguousarray(angles, float)[None], pos, rot, lengths, width, pair, pair_w, False)
    ns = chain.samples
    rows = [len(f.outline) + ns for f in fields]
    out = np.zeros((sum(rows), 3 * len(fields)))
    row = 0
    for k, (f, n) in enumerate(zip(fields, rows)):
        cam = f.camera
        p = pts[0] @ cam.R.T + cam.t
        skew = np.zeros((len(p), 3, 3))
        skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -p[:, 2], p[:, 1], -p[:, 0]
        skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = p[:, 2], -p[:, 1], p[:, 0]
        point_jacobian = np.ascontiguousarray(-(cam.R.T @ skew)[None])
        res, jac = np.empty((1, n)), np.empty((1, n, 3))
        view_residuals(pts, point_jacobian, True, camera_params(cam), f.field, f.x0, f.y0, f.has_ignore, f.outline,
                       ns, edge, weight, segments, fold_of, delta_out, delta_in, hidden_points(f, pts[:, :ns]), res,
                       jac, 0)
        out[row:row + n, 3 * k:3 * k + 3] = jac[0] * np.sqrt(f.weight)
        row += n
    return out


_warm = False
_WARM_BOX = Box("warm", np.zeros(3), np.full(3, 0.1), np.eye(3))


def warm() -> float:
    """Compile or load (from numba's cache) every kernel once in this process, on tiny
    inputs of the exact argument types the fit uses, so that no fit's timed region pays
    for it. Returns the seconds this took (0 after the first call)."""
    global _warm
    if _warm:
        return 0.0
    import time

    from ._kernels_beam import beam_candidates, best_totals, diverse, label_areas, map_labels, outline_cost
    from ._kernels_boxes import box_arrays, box_penetration, segments_hit_boxes

    start = time.perf_counter()
    cam = np.concatenate([np.eye(3).ravel() * 100.0, np.eye(3).ravel(), [0.0, 0.0, 1.0], np.zeros(12), [1.0]])
    field = np.zeros((4, 4, 4), np.float32)
    n = 2
    angles = np.zeros((1, n, 3))
    pair = np.array([[n + 1, n + 2]], np.int64)
    pair_w = np.array([[0.5, 0.5]])
    segments = np.array([[n + 1, n + 2, -1, -1]], np.int64)
    args = (np.zeros(3), np.eye(3), np.full(n, 0.01), 0.01, pair, pair_w)
    for jac in (False, True):
        pts, J = chain_points(angles, *args, jac)
        view_residuals(pts, J, jac, cam, field, 0, 0, True, np.zeros((2, 2)), 1, np.ones(1, np.bool_),
                       np.ones(1), segments, np.full(1, -1, np.int64), 3.0, 1.5, np.zeros((1, 1), np.bool_),
                       np.empty((1, 3)),
                       np.empty((1, 3, 3 * n) if jac else (0, 0, 0)), 0)
    outline_cost(pts, segments, cam, np.zeros((2, 2)), 3.0)
    best_totals(pts, 1, cam[None], field[:, :, 0].ravel(), field[:, :, 3].ravel(), np.zeros((1, 2), np.int64),
                np.full((1, 2), 4, np.int64), np.zeros((1, 2), np.int64), np.ones(1, np.bool_), np.ones(1),
                np.zeros((1, 3)), *box_arrays([_WARM_BOX]), 2.0, 3.0, 1.5, np.zeros(1), np.zeros(1), np.zeros(1), 1,
                np.arange(pts.shape[0]), np.arange(pts.shape[1]))
    lookup(field, 0, 0, True, np.zeros(2), np.zeros(2))
    t = np.array([0.5])
    F, E, _ = beam_candidates(np.eye(3)[None], np.zeros((1, 3)), np.eye(3)[None], 0.01, 0.005, t, t, t)
    diverse(np.arange(1), E, 1, 0.001)
    origin = np.zeros(3)
    segments_hit_boxes(origin, np.ones((1, 3)), *box_arrays([_WARM_BOX]))
    origin.setflags(write=False)     # a camera's centre is read-only (Camera.center): typed apart
    segments_hit_boxes(origin, np.ones((1, 3)), *box_arrays([_WARM_BOX]))
    box_penetration(np.ones((1, 3)), *box_arrays([_WARM_BOX]))
    from ._kernels_lm import warm as warm_lm
    warm_lm(cam, field, box_arrays([_WARM_BOX]), pair, pair_w, segments)
    lab = np.zeros((2, 2), np.int32)
    map_labels(lab, np.zeros(label_areas(lab, 1).size, np.uint8), np.zeros((2, 2), np.uint8))
    _warm = True
    return time.perf_counter() - start
