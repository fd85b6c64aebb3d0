"""The least-squares solver: Levenberg-Marquardt, on a batch of robust (IRLS) image fits at
once (:func:`levenberg_marquardt`: every beam candidate refined together, the residuals and
weights of :mod:`estimator.residuals`), and on one parameter vector for the strip stage's
3-D fits (:func:`levenberg_marquardt_one`, with :func:`corner_fit`'s residuals). The two
share the method but not the damping: the batched one damps each candidate by its own
diagonal (plus 1e-6) and drops converged candidates from the batch; the single one adds
1e-9. Joining them would change every estimate's numbers (pinned by the golden test).
With ``FitConfig.compiled`` both run compiled whole (:mod:`estimator._kernels_lm`: the
batched loop here, the single one for the strip stage's fits), the same steps: a change to
either loop is made there too."""
from __future__ import annotations

import numpy as np

from . import _kernels_lm
from .chain import Chain
from .config import DEFAULT, FitConfig
from .residuals import residuals
from .views import Field


def levenberg_marquardt(chain: Chain, fields: list[Field], params: np.ndarray, iterations: int,
                        log: list | None = None, state=None, cfg: FitConfig = DEFAULT, extra=None, pull=None):
    """Robust (IRLS) Levenberg-Marquardt on a batch of (B, P) parameter vectors (see
    :func:`estimator.residuals.residuals`) at once. ``state``: (residuals, Jacobian, cost) at ``params`` when
    already known. Returns (params (B, P), robust cost (B,), final state); appends to ``log``
    each iteration's (candidates still iterated (k,), their parameters (k, P)), from which
    :func:`trace` reads one candidate's iterates. ``extra``: (candidates (k,), their
    parameters (k, P)) -> (residuals (k, e), Jacobian (k, e, P)), rows appended to the
    views' (their half squared sum added to the cost, the returned cost and state included;
    a ``state`` passed in must hold them too). ``pull``: (index of one of the chain's points
    (``Chain.points``), weight [px/m], targets (B, 3) [m][, along (B, 3)]): three such rows,
    that point of each candidate pulled to its target (not with ``extra``); with ``along``,
    only its offset's component along that candidate's unit row (a row of zeros: all of it)."""
    compiled = cfg.compiled and _kernels_lm.usable(fields)
    if pull is not None:
        if extra is not None:
            raise ValueError("levenberg_marquardt: pull and extra rows together")
        if not compiled:
            extra = _pull_rows(chain, *pull)
    if compiled and extra is None:
        params, cost, r, J = _kernels_lm.run(chain, fields, params, iterations, state, cfg, pull, log)
        return params, cost, (r, J, cost)
    params = np.array(params, float)
    B, N = params.shape
    na = 3 * chain.n
    diag = np.arange(N)

    def residuals_at(which: np.ndarray, p: np.ndarray):
        r, J, cost = residuals(chain, fields, p, True, cfg)
        if extra is None:
            return r, J, cost
        re, Je = extra(which, p)
        return np.concatenate([r, re], axis=1), np.concatenate([J, Je], axis=1), cost + 0.5 * np.sum(re * re, axis=1)

    r, J, cost = residuals_at(np.arange(B), params) if state is None else (s.copy() for s in state)
    mu = np.full(B, 1e-3)
    active = np.arange(B)
    for _ in range(iterations):
        # Whole-batch iterations (the common case) take the arrays as they are: no copies.
        whole = active.size == B
        Ja, ra = (J, r) if whole else (J[active], r[active])
        JT = Ja.transpose(0, 2, 1)
        A = JT @ Ja
        g = (JT @ ra[..., None])[..., 0]
        damp = mu[active, None] * (A[:, diag, diag] + 1e-6)
        A[:, diag, diag] += damp
        step = np.linalg.solve(A, -g[..., None])[..., 0]
        trial = params[active] + step
        r2, J2, c2 = residuals_at(active, trial)
        ok = c2 < cost[active]
        # Converged when a step gains less than RTOL of the cost (its noise floor).
        flat = ok & (cost[active] - c2 < cfg.lm_rtol * cost[active])
        acc = active[ok]
        params[acc], cost[acc] = trial[ok], c2[ok]
        if whole and acc.size == B:
            r, J = r2, J2
        else:
            r[acc], J[acc] = r2[ok], J2[ok]
        mu[acc] = np.maximum(mu[acc] * 0.3, 1e-7)
        mu[active[~ok]] *= 10.0
        if log is not None:
            log.append((active, params[active]))
        small = np.max(np.abs(step[:, :na]), axis=1) < 1e-4
        done = (ok & small) | flat | (mu[active] > 1e4)
        active = active[~done]
        if active.size == 0:
            break
    return params, cost, (r, J, cost)


def _pull_rows(chain: Chain, at: int, weight: float, targets: np.ndarray, along: np.ndarray | None = None):
    """``pull`` as ``extra`` rows: (candidates (k,), their parameters (k, P)) -> (residuals
    (k, 3), Jacobian (k, 3, P))."""
    targets = np.asarray(targets, float)
    P = _kernels_lm.pull_projections(along, len(targets))

    def rows(which: np.ndarray, params: np.ndarray):
        pts, J = chain.points(params.reshape(len(params), chain.n, 3), True)
        Pk = P[which]
        return (weight * np.einsum("kac,kc->ka", Pk, pts[:, at] - targets[which]),
                weight * np.einsum("kac,kcp->kap", Pk, J[:, at]))

    return rows


def trace(log: list, b: int, n: int) -> list[np.ndarray]:
    """Candidate ``b``'s iterated angles (n, 3), one per iteration it took part in, from a
    :func:`levenberg_marquardt` ``log``."""
    out = []
    for active, params in log:
        k = np.searchsorted(active, b)
        if k < active.size and active[k] == b:
            out.append(params[k, :3 * n].reshape(n, 3))
    return out


def levenberg_marquardt_one(fun, x: np.ndarray, iterations: int, rtol: float) -> np.ndarray:
    """Levenberg-Marquardt on one parameter vector: fun(x) -> (residuals, Jacobian, cost)."""
    r, J, cost = fun(x)
    mu = 1e-3
    for _ in range(iterations):
        A = J.T @ J
        d = np.arange(len(x))
        A[d, d] += mu * A[d, d] + 1e-9
        step = np.linalg.solve(A, -(J.T @ r))
        r2, J2, c2 = fun(x + step)
        if c2 < cost:
            flat = cost - c2 < rtol * cost
            x, r, J, cost, mu = x + step, r2, J2, c2, max(mu * 0.3, 1e-7)
            if flat:
                break
        else:
            mu *= 10.0
            if mu > 1e4:
                break
    return x


def with_rows(fun, corners, extra):
    """``fun`` (x -> residuals, Jacobian, cost) with ``extra``'s rows (corners (k, 3),
    Jacobian (k, 3, P)) -> (residuals, Jacobian) on ``corners(x)`` appended, their half
    squared sum added to the cost: for :func:`levenberg_marquardt_one`."""
    def joined(x):
        r, J, cost = fun(x)
        re, Je = extra(*corners(x))
        return np.concatenate([r, re]), np.vstack([J, Je]), cost + 0.5 * re @ re

    return joined


def corner_fit(corners, goal: np.ndarray, weight: np.ndarray | float = 1.0, extra=None):
    """Residual function for :func:`levenberg_marquardt_one` pulling ``corners(x)`` -> (c (k, 3), J
    (k, 3, P)) onto ``goal`` (k, 3), each corner weighted by ``weight`` ((k,) or scalar);
    ``extra(c, J)`` -> (residuals (e,), Jacobian (e, P)): more rows on the same corners."""
    w = np.broadcast_to(np.asarray(weight, float), (len(goal),))

    def fun(x):
        c, J = corners(x)
        r = (w[:, None] * (c - goal)).ravel()
        Jr = (w[:, None, None] * J).reshape(len(r), -1)
        if extra is not None:
            re, Je = extra(c, J)
            r, Jr = np.concatenate([r, re]), np.vstack([Jr, Je])
        return r, Jr, 0.5 * r @ r

    return fun
