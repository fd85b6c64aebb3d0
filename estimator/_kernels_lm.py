"""The least-squares fits of the default estimator compiled whole (numba), each the same
steps in the same order as the Python loop it stands for (``tests/test_estimator_kernels.py``
checks them against each other to float rounding):

- :func:`levenberg_marquardt`: :func:`estimator.solver.levenberg_marquardt`'s batched loop,
  with the residuals of :func:`estimator.residuals.residuals` (every view's terms, the angle
  prior, the scene boxes' penetration) and optionally a chain point pulled to a target (the
  depth probes), the damped normal equations and the loop in one call;
- :func:`strip_levenberg_marquardt`: :func:`estimator.solver.levenberg_marquardt_one` on the
  strip's fit to the views (:meth:`estimator.strip.Strip.residuals`);
- :func:`corner_levenberg_marquardt`: the same on :func:`estimator.solver.corner_fit`'s
  corners (and :func:`estimator.strip._tip_frame_rows`), the strip stage's 3-D fits.

A fit runs a few dozen iterations on batches of 1-8 candidates; in Python each iteration was
~20 small array calls and a call per view, whose overhead matched the arithmetic. A change to
a solver's steps (its damping, its tests) is made in both places. The compiled code holds
copies of the kernels it calls from ``_kernels.py`` and ``_kernels_boxes.py``: numba's cache
sees only this file change, so the cache's folder is named by a digest of every
``_kernels*.py`` (:func:`tapecell.kernel_sources_digest`)."""
from __future__ import annotations

import weakref

import numpy as np
from numba import njit

from ._kernels import _chain_arrays, camera_params, chain_points, view_residuals
from ._kernels_boxes import box_penetration, segments_hit_boxes, views_box_arrays


@njit(cache=True, fastmath=False)
def _solve(A, b):
    """np.linalg.solve(A, b), or NaNs where A or b holds a NaN or an infinity (NumPy's
    solve returns NaNs there, numba's raises: a step of NaNs is rejected as NumPy's was)."""
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        return np.full(b.shape[0], np.nan)
    return np.linalg.solve(A, b)


@njit(cache=True, fastmath=False)
def _evaluate(params, pull_at, pull_w, targets, pull_P, n, ns, pos, rot, lengths, width, pair, pair_w, edge, weight,
              segments, fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl, ooff, vweight,
              prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out, delta_in, extra):
    """residuals.residuals(..., jacobian=True) of (k, 3n) params: (r (k, R), J (k, R, 3n), cost (k,));
    with ``pull_at`` >= 0, three rows more, last: chain point ``pull_at`` pulled to ``targets``
    (k, 3) by ``pull_w`` [px/m], its offset from them taken through ``pull_P`` (k, 3, 3)
    (solver.levenberg_marquardt's ``pull``)."""
    k, N = params.shape
    angles = np.ascontiguousarray(params).reshape(k, n, 3)
    pts, Jp = chain_points(angles, pos, rot, lengths, width, pair, pair_w, True)
    V = cams.shape[0]
    R = extra + (3 if pull_at >= 0 else 0)
    for v in range(V):
        R += ooff[v + 1] - ooff[v] + ns
    res = np.empty((k, R))
    jac = np.empty((k, R, N))
    cost = np.zeros(k)
    row = 0
    samples = np.ascontiguousarray(pts[:, :ns]).reshape(k * ns, 3)
    hidden = np.zeros((k, ns), np.bool_)         # without boxes nothing is hidden, in any view
    for v in range(V):
        h, w, c = fshape[v, 0], fshape[v, 1], fshape[v, 2]
        field = fbuf[foff[v]:foff[v] + h * w * c].reshape((h, w, c))
        outline = outl[ooff[v]:ooff[v + 1]]
        if has_boxes:
            hidden = segments_hit_boxes(centers[v], samples, bcent, brot, bhalf).reshape(k, ns)
        cv = view_residuals(pts, Jp, True, cams[v], field, x0s[v], y0s[v], has_ign[v], outline, ns, edge, weight,
                            segments, fold_of, delta_out, delta_in, hidden, res, jac, row)
        stop = row + outline.shape[0] + ns
        if vweight[v] != 1.0:
            sw = np.sqrt(vweight[v])
            res[:, row:stop] *= sw
            jac[:, row:stop] *= sw
        for b in range(k):
            cost[b] += vweight[v] * cv[b]
        row = stop
    # The angle prior's rows, then the corners' penetration of the boxes.
    for b in range(k):
        s = 0.0
        for i in range(N):
            pr = params[b, i] * prior_px
            res[b, row + i] = pr
            s += pr * pr
        cost[b] += 0.5 * s
        for i in range(N):
            for j in range(N):
                jac[b, row + i, j] = prior_px if i == j else 0.0
    if has_boxes:
        nc = pts.shape[1] - ns
        corners = np.ascontiguousarray(pts[:, ns:]).reshape(k * nc, 3)
        depth, grad = box_penetration(corners, bcent, brot, bhalf)
        at = row + N
        for b in range(k):
            s = 0.0
            for q in range(nc):
                pen = pen_px * depth[b * nc + q]
                res[b, at + q] = pen
                s += pen * pen
                for j in range(N):
                    g = 0.0
                    for a in range(3):
                        g += pen_px * grad[b * nc + q, a] * Jp[b, ns + q, a, j]
                    jac[b, at + q, j] = g
            cost[b] += 0.5 * s
    if pull_at >= 0:
        at = R - 3
        for b in range(k):
            s = 0.0
            for a in range(3):
                d = 0.0
                for c in range(3):
                    d += pull_P[b, a, c] * (pts[b, pull_at, c] - targets[b, c])
                d *= pull_w
                res[b, at + a] = d
                s += d * d
                for j in range(N):
                    g = 0.0
                    for c in range(3):
                        g += pull_P[b, a, c] * Jp[b, pull_at, c, j]
                    jac[b, at + a, j] = pull_w * g
            cost[b] += 0.5 * s
    return res, jac, cost


@njit(cache=True, fastmath=False)
def levenberg_marquardt(params, iterations, rtol, r, J, cost, pull_at, pull_w, targets, pull_P, n, ns, pos, rot, lengths,
                        width, pair, pair_w, edge, weight, segments, fold_of, cams, centers, fbuf, foff, fshape, x0s,
                        y0s, has_ign, outl, ooff, vweight, prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out,
                        delta_in, extra):
    """solver.levenberg_marquardt's loop on (B, P) ``params`` from their (r, J, cost). Returns
    (params, cost, r, J, iterations taken, active (iterations, B) bool, their params
    (iterations, B, P)) -- the last two the solver's log. ``pull_at``, ``pull_w``, ``targets``
    (B, 3), ``pull_P`` (B, 3, 3): :func:`_evaluate`'s pull (``pull_at`` -1: none)."""
    B, N = params.shape
    na = 3 * n
    mu = np.full(B, 1e-3)
    active = np.arange(B)
    log_active = np.zeros((iterations, B), np.bool_)
    log_params = np.zeros((iterations, B, N))
    taken = 0
    for it in range(iterations):
        m = active.size
        trial = np.empty((m, N))
        steps = np.empty((m, N))
        for i in range(m):
            b = active[i]
            Jb = J[b]
            A = Jb.T @ Jb
            g = Jb.T @ r[b]
            for d in range(N):
                A[d, d] += mu[b] * (A[d, d] + 1e-6)
            step = _solve(A, -g)
            for d in range(N):
                steps[i, d] = step[d]
                trial[i, d] = params[b, d] + step[d]
        pulled = np.empty((m, 3))
        through = np.empty((m, 3, 3))
        if pull_at >= 0:
            for i in range(m):
                pulled[i] = targets[active[i]]
                through[i] = pull_P[active[i]]
        r2, J2, c2 = _evaluate(trial, pull_at, pull_w, pulled, through, n, ns, pos, rot, lengths, width, pair, pair_w, edge,
                               weight, segments, fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl,
                               ooff, vweight, prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out, delta_in,
                               extra)
        done = np.zeros(m, np.bool_)
        for i in range(m):
            b = active[i]
            ok = c2[i] < cost[b]
            flat = ok and (cost[b] - c2[i] < rtol * cost[b])
            if ok:
                params[b] = trial[i]
                cost[b] = c2[i]
                r[b] = r2[i]
                J[b] = J2[i]
                mu[b] = max(mu[b] * 0.3, 1e-7)
            else:
                mu[b] *= 10.0
            log_active[it, b] = True
            log_params[it, b] = params[b]
            small = True
            for d in range(na):
                if abs(steps[i, d]) >= 1e-4:
                    small = False
                    break
            done[i] = (ok and small) or flat or mu[b] > 1e4
        taken = it + 1
        active = active[~done]
        if active.size == 0:
            break
    return params, cost, r, J, taken, log_active, log_params


@njit(cache=True, fastmath=False, inline="always")
def _one_step(J, r, mu):
    """solver.levenberg_marquardt_one's step: the normal equations, each diagonal entry
    damped by ``mu`` times itself plus 1e-9."""
    A = J.T @ J
    for d in range(A.shape[0]):
        A[d, d] += mu * A[d, d] + 1e-9
    return _solve(A, -(J.T @ r))


@njit(cache=True, fastmath=False, inline="always")
def _one_outcome(cost, c2, mu, rtol):
    """solver.levenberg_marquardt_one's judgement of a trial of cost ``c2``: (taken, stop,
    the next damping): taken where it costs less (and stop where it gained less than
    ``rtol`` of the cost), else the damping ten times more (stop beyond 1e4)."""
    if c2 < cost:
        return True, cost - c2 < rtol * cost, max(mu * 0.3, 1e-7)
    mu = mu * 10.0
    return False, mu > 1e4, mu


@njit(cache=True, fastmath=False)
def _strip_evaluate(x, T, prior, n, ns, pos, rot, lengths, width, pair, pair_w, edge, weight, segments, fold_of,
                    cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl, ooff, vweight, prior_px, pen_px,
                    bcent, brot, bhalf, has_boxes, delta_out, delta_in, extra):
    """strip.Strip.residuals: the fine chain's residuals at angles T x, by x, and the strip's
    prior rows: (r (R + P,), J (R + P, P), cost)."""
    fine = np.ascontiguousarray(T @ x).reshape(1, T.shape[0])
    r, J, cost = _evaluate(fine, -1, 0.0, np.zeros((1, 3)), np.zeros((1, 3, 3)), n, ns, pos, rot, lengths, width, pair, pair_w, edge,
                           weight, segments, fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl, ooff,
                           vweight, prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out, delta_in, extra)
    p = prior @ x
    R, P = r.shape[1], x.size
    rr = np.empty(R + P)
    rr[:R] = r[0]
    rr[R:] = p
    JJ = np.empty((R + P, P))
    JJ[:R] = np.ascontiguousarray(J[0]) @ T
    JJ[R:] = prior
    return rr, JJ, cost[0] + (0.5 * p) @ p


@njit(cache=True, fastmath=False)
def strip_levenberg_marquardt(x, iterations, rtol, T, prior, n, ns, pos, rot, lengths, width, pair, pair_w, edge,
                              weight, segments, fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl,
                              ooff, vweight, prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out, delta_in,
                              extra):
    """solver.levenberg_marquardt_one on the strip's fit to the views (strip.Strip.residuals)."""
    r, J, cost = _strip_evaluate(x, T, prior, n, ns, pos, rot, lengths, width, pair, pair_w, edge, weight, segments,
                                 fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl, ooff, vweight,
                                 prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out, delta_in, extra)
    mu = 1e-3
    for _ in range(iterations):
        trial = x + _one_step(J, r, mu)
        r2, J2, c2 = _strip_evaluate(trial, T, prior, n, ns, pos, rot, lengths, width, pair, pair_w, edge, weight,
                                     segments, fold_of, cams, centers, fbuf, foff, fshape, x0s, y0s, has_ign, outl,
                                     ooff, vweight, prior_px, pen_px, bcent, brot, bhalf, has_boxes, delta_out,
                                     delta_in, extra)
        taken, stop, mu = _one_outcome(cost, c2, mu, rtol)
        if taken:
            x, r, J, cost = trial, r2, J2, c2
        if stop:
            break
    return x


@njit(cache=True, fastmath=False)
def _corner_rows(x, T, goal, w, frame, frame_s, length, width, pos, rot, lengths, chain_width, pair, pair_w):
    """solver.corner_fit's function at ``x`` on the chain of angles T x: its corners onto
    ``goal`` (k, 3) weighted by ``w`` (k,) and, with ``frame_s`` > 0, strip._tip_frame_rows
    (the last plate's direction and width axis onto ``frame`` (3, 3), ``frame_s`` times the
    last plate's ``length``): (r, J, cost)."""
    n = lengths.size
    m = n + 1
    s = pair.shape[0]
    angles = np.ascontiguousarray(T @ x).reshape(1, n, 3)
    pts, Jp = chain_points(angles, pos, rot, lengths, chain_width, pair, pair_w, True)
    k = goal.shape[0]
    P = x.size
    rows = 3 * k + (6 if frame_s > 0 else 0)
    r = np.empty(rows)
    J = np.empty((rows, P))
    Jc = np.ascontiguousarray(Jp[0, s:]).reshape(3 * k, 3 * n) @ T      # (3k, P): corner coordinates by x
    for q in range(k):
        for a in range(3):
            r[3 * q + a] = w[q] * (pts[0, s + q, a] - goal[q, a])
            for j in range(P):
                J[3 * q + a, j] = w[q] * Jc[3 * q + a, j]
    if frame_s > 0:
        for a in range(3):
            ex = (pts[0, s + n, a] - pts[0, s + n - 1, a]) / length
            ey = (pts[0, s + m + n, a] - pts[0, s + 2 * m + n, a]) / width
            r[3 * k + a] = frame_s * (ex - frame[a, 0])
            r[3 * k + 3 + a] = frame_s * (ey - frame[a, 1])
            for j in range(P):
                J[3 * k + a, j] = frame_s * ((Jc[3 * n + a, j] - Jc[3 * (n - 1) + a, j]) / length)
                J[3 * k + 3 + a, j] = frame_s * ((Jc[3 * (m + n) + a, j] - Jc[3 * (2 * m + n) + a, j]) / width)
    return r, J, (0.5 * r) @ r


@njit(cache=True, fastmath=False)
def corner_levenberg_marquardt(x, iterations, rtol, T, goal, w, frame, frame_s, length, width, pos, rot, lengths,
                               chain_width, pair, pair_w):
    """solver.levenberg_marquardt_one on :func:`_corner_rows`."""
    r, J, cost = _corner_rows(x, T, goal, w, frame, frame_s, length, width, pos, rot, lengths, chain_width, pair,
                              pair_w)
    mu = 1e-3
    for _ in range(iterations):
        trial = x + _one_step(J, r, mu)
        r2, J2, c2 = _corner_rows(trial, T, goal, w, frame, frame_s, length, width, pos, rot, lengths, chain_width,
                                  pair, pair_w)
        taken, stop, mu = _one_outcome(cost, c2, mu, rtol)
        if taken:
            x, r, J, cost = trial, r2, J2, c2
        if stop:
            break
    return x


class Packed:
    """A list of :class:`views.Field` in the compiled solver's form: their arrays copied into
    flat ones (a field's arrays are not to be written once made)."""

    def __init__(self, fields):
        V = len(fields)
        self.cams = np.array([camera_params(f.camera) for f in fields], float).reshape(V, -1)
        self.centers = np.array([f.camera.center for f in fields], float).reshape(V, 3)
        arrays = [np.ascontiguousarray(f.field, np.float32) for f in fields]
        self.fshape = np.array([a.shape for a in arrays], np.int64).reshape(V, 3)
        self.foff = np.concatenate([[0], np.cumsum([a.size for a in arrays])]).astype(np.int64)
        self.fbuf = np.concatenate([a.ravel() for a in arrays]) if arrays else np.zeros(0, np.float32)
        self.x0s = np.array([f.x0 for f in fields], np.int64)
        self.y0s = np.array([f.y0 for f in fields], np.int64)
        self.has_ign = np.array([f.has_ignore for f in fields], np.bool_)
        self.outl = np.ascontiguousarray(np.concatenate([f.outline for f in fields]) if fields
                                         else np.zeros((0, 2)), float).reshape(-1, 2)
        self.ooff = np.concatenate([[0], np.cumsum([len(f.outline) for f in fields])]).astype(np.int64)
        self.vweight = np.array([f.weight for f in fields], float)
        boxes = fields[0].boxes if fields else ()
        self.has_boxes = bool(boxes)
        # One set of boxes for every view (the kernels hide points and charge penetration by
        # the first view's, as residuals() charges penetration): views that differ go the
        # Python way (:func:`usable`).
        ids = [id(b) for b in boxes]
        self.same_boxes = all([id(b) for b in f.boxes] == ids for f in fields)
        self.boxes = views_box_arrays(fields)


_packed: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def packed(fields) -> Packed:
    """:class:`Packed` of ``fields`` (at least one), kept while its first field lives (for
    the same list of fields, by identity: the entry refers to them weakly)."""
    hit = _packed.get(fields[0])
    if hit is None or len(hit[0]) != len(fields) or any(r() is not f for r, f in zip(hit[0], fields)):
        hit = ([weakref.ref(f) for f in fields], Packed(fields))
        _packed[fields[0]] = hit
    return hit[1]


def usable(fields) -> bool:
    """Can the compiled fits take these views (some, all with the same scene boxes)?"""
    return bool(fields) and packed(fields).same_boxes


def _args(chain, fields, cfg) -> tuple:
    """The kernels' arguments after the parameters: ``chain``'s arrays, the packed views, the settings."""
    pair, pair_w, edge, weight, segments, fold_of, pos, rot, lengths, width = _chain_arrays(chain)
    p = packed(fields)
    extra = 3 * chain.n + (3 * (chain.n + 1) if p.has_boxes else 0)
    return (chain.n, chain.samples, pos, rot, lengths, width, pair, pair_w, edge, weight, segments, fold_of,
            p.cams, p.centers, p.fbuf, p.foff, p.fshape, p.x0s, p.y0s, p.has_ign, p.outl, p.ooff, p.vweight,
            float(cfg.angle_prior_px), float(cfg.penetration_px_per_m), *p.boxes, p.has_boxes,
            float(cfg.delta_out_px), float(cfg.delta_in_px), extra)


def pull_projections(along, count: int) -> np.ndarray:
    """(count, 3, 3) what a pull pulls of each candidate's offset from its target: all of it
    (identity) where ``along`` is None or a row of zeros, else its component along that
    row (a unit vector: its outer product with itself)."""
    P = np.zeros((count, 3, 3))
    P[:] = np.eye(3)
    if along is not None:
        along = np.asarray(along, float).reshape(count, 3)
        some = np.any(along != 0.0, axis=1)
        P[some] = along[some, :, None] * along[some, None, :]
    return P


def run(chain, fields, params: np.ndarray, iterations: int, state, cfg, pull=None, log: list | None = None):
    """The compiled loop on ``params`` (B, P) from ``state`` (r, J, cost; copied) or None:
    (params, cost, r, J); each iteration's (active (k,), params (k, P)) appended to ``log``.
    ``pull``: (chain point index, weight [px/m], targets (B, 3)[, along (B, 3) or None]) or
    None (solver.levenberg_marquardt)."""
    args = _args(chain, fields, cfg)
    params = np.array(params, float, order="C")
    B = len(params)
    if pull is None:
        pulled = (-1, 0.0, np.zeros((B, 3)), np.zeros((B, 3, 3)))
    else:
        at, weight, targets, along = (tuple(pull) + (None,))[:4]
        if not 0 <= int(at) < chain.samples + 3 * (chain.n + 1):
            raise IndexError(f"pull: the chain has no point {at}")
        pulled = (int(at), float(weight), np.array(targets, float, order="C").reshape(B, 3), pull_projections(along, B))
    if state is None:
        r, J, cost = _evaluate(params, *pulled, *args)
    else:
        r, J, cost = (np.array(s, float, order="C") for s in state)
    params, cost, r, J, taken, log_active, log_params = levenberg_marquardt(
        params, max(int(iterations), 0), float(cfg.lm_rtol), r, J, cost, *pulled, *args)
    if log is not None:
        for it in range(taken):
            act = np.flatnonzero(log_active[it])
            log.append((act, log_params[it, act]))
    return params, cost, r, J


def strip_fit(strip, fields, x: np.ndarray, iterations: int, rtol: float, cfg) -> np.ndarray:
    """The compiled :func:`solver.levenberg_marquardt_one` on ``strip``'s fit to ``fields``
    from its parameters ``x``."""
    return strip_levenberg_marquardt(np.array(x, float, order="C"), max(int(iterations), 0), float(rtol),
                                     np.ascontiguousarray(strip.T, float), np.ascontiguousarray(strip.prior, float),
                                     *_args(strip.chain, fields, cfg))


def corner_fit(chain, T: np.ndarray, goal: np.ndarray, weight, x: np.ndarray, iterations: int, rtol: float,
               frame: np.ndarray | None = None, frame_weight: float = 0.0) -> np.ndarray:
    """The compiled :func:`solver.levenberg_marquardt_one` on :func:`solver.corner_fit`: the
    corners of ``chain`` at angles ``T`` x (T (3n, P)) onto ``goal`` (3m, 3) weighted by
    ``weight`` (3m,) or a scalar and, with ``frame_weight`` > 0, its tip frame onto ``frame``
    (strip._tip_frame_rows), from ``x``."""
    pair, pair_w, _, _, _, _, pos, rot, lengths, width = _chain_arrays(chain)
    goal = np.ascontiguousarray(goal, float)
    w = np.array(np.broadcast_to(np.asarray(weight, float), (len(goal),)))
    length = float(chain.spec.segment_lengths[-1])
    frame = np.eye(3) if frame is None else np.ascontiguousarray(frame, float)
    return corner_levenberg_marquardt(np.array(x, float, order="C"), max(int(iterations), 0), float(rtol),
                                      np.ascontiguousarray(T, float),
                                      goal, w, frame, float(frame_weight) * length, length, float(width), pos, rot,
                                      lengths, float(width), pair, pair_w)


def warm(cam: np.ndarray, field: np.ndarray, box_arrays: tuple, pair: np.ndarray, pair_w: np.ndarray,
         segments: np.ndarray) -> None:
    """Compile or load the three fits (and :func:`_evaluate`) on tiny inputs of the fit's
    argument types (a 2-plate chain of one sample point, one view of ``field``): any number of
    views, 3 or 4 channels and the pull on or off are the same types. :func:`_kernels.warm`
    calls it."""
    n = 2
    fbuf = np.ascontiguousarray(field, np.float32).ravel()
    args = (n, 1, np.zeros(3), np.eye(3), np.full(n, 0.01), 0.01, pair, pair_w, np.ones(1, np.bool_), np.ones(1),
            segments, np.full(1, -1, np.int64), cam[None].copy(), np.zeros((1, 3)), fbuf, np.array([0, fbuf.size]),
            np.array([field.shape], np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64), np.ones(1, np.bool_),
            np.zeros((2, 2)), np.array([0, 2]), np.ones(1), 1.0, 1.0, *box_arrays, True, 3.0, 1.5,
            3 * n + 3 * (n + 1))
    params = np.zeros((1, 3 * n))
    r, J, cost = _evaluate(params, 0, 1.0, np.zeros((1, 3)), np.zeros((1, 3, 3)), *args)
    levenberg_marquardt(params, 1, 1e-3, r, J, cost, 0, 1.0, np.zeros((1, 3)), np.zeros((1, 3, 3)), *args)
    T = np.eye(3 * n)
    strip_levenberg_marquardt(np.zeros(3 * n), 1, 1e-3, T, np.eye(3 * n), *args)
    corner_levenberg_marquardt(np.zeros(3 * n), 1, 1e-3, T, np.zeros((3 * (n + 1), 3)), np.ones(3 * (n + 1)),
                               np.eye(3), 1.0, 0.01, 0.01, *args[2:8])
