"""The local stage: candidate chains refined together by Levenberg-Marquardt, screened by
the robust cost, the best refined to convergence and ranked by the paper's silhouette cost
(eq. 11); the winner's mirror images and other branches (the ambiguities a silhouette
leaves); and the distinct shapes among everything refined (the hypotheses the verdict
weighs)."""
from __future__ import annotations

import dataclasses

import numpy as np

from .chain import Chain
from .config import DEFAULT, FitConfig
from .solver import levenberg_marquardt, trace
from .verdict import DISTINCT_TIP_M
from .views import Field


def screened(chain: Chain, fields: list[Field], starts: np.ndarray, cfg: FitConfig = DEFAULT,
             cache: dict | None = None):
    """The screen of :func:`refine`: cfg.lm_screen Levenberg-Marquardt iterations on every
    start (B, n, 3). Returns (params (B, P), robust cost (B,), (residuals, Jacobian) at them,
    iterates: ``iterates[k]`` start k's iterated angles [(n, 3), ...], read on request).
    ``cache``: the screens of one capture's starts, by settings and start, filled and reused
    (a second look refines again the branches the first look's wide search refined): the
    batched solver treats every candidate on its own, so a start screened alone or in
    another batch ends the same, bit for bit."""
    flat = starts.reshape(len(starts), -1)
    keys = [s.tobytes() for s in flat]
    cache = _settings(cache, cfg)
    todo = [k for k, key in enumerate(keys) if cache is None or key not in cache]
    log: list = []
    if todo:
        p, c, (r, J, _) = levenberg_marquardt(chain, fields, flat[todo], cfg.lm_screen, log, cfg=cfg)
    if len(todo) == len(keys):
        # Nothing screened before (a look's first refinement): the solver's arrays as they are.
        if cache is not None:
            cache.update((keys[k], (p[k], c[k], r[k], J[k], log, k)) for k in todo)
        return p, c, (r, J), _Iterates([(log, k) for k in range(len(keys))], chain.n)
    done = {keys[k]: (p[i], c[i], r[i], J[i], log, i) for i, k in enumerate(todo)}
    cache.update(done)
    rows = [cache[key] for key in keys]
    params, cost, r, J = (np.array([row[i] for row in rows]) for i in range(4))
    return params, cost, (r, J), _Iterates([row[4:] for row in rows], chain.n)


def _settings(cache: dict | None, cfg: FitConfig) -> dict | None:
    """The part of a capture's ``cache`` (:func:`screened`, :func:`refine`) made under
    ``cfg``: a look's settings but the second look's own (its beam and hooks), which neither
    reads; what was made under any other setting is not reused."""
    if cache is None:
        return None
    return cache.setdefault(dataclasses.replace(cfg, thorough_beam=DEFAULT.thorough_beam, fold_beam=DEFAULT.fold_beam,
                                                hook_bends=DEFAULT.hook_bends), {})


class _Iterates:
    """Each start's iterates of a screen, read from the solver's logs when asked for
    (:func:`refine` needs its winner's alone): ``sources[k]`` = (log, index in its batch)."""

    def __init__(self, sources: list, n: int):
        self._sources, self._n = sources, n

    def __getitem__(self, k: int) -> list[np.ndarray]:
        log, index = self._sources[k]
        return trace(log, index, self._n)


def refine(chain: Chain, fields: list[Field], starts: np.ndarray, silhouette_costs, pool: list | None = None,
           cfg: FitConfig = DEFAULT, cache: dict | None = None):
    """Local stage on candidate chains (B, n, 3): a few iterations on all at once, the
    best cfg.refine (by the robust cost) to convergence, ranked by the silhouette cost (eq.
    11). Returns (angles (n, 3), trace, eq.-11 cost) of the winner; appends every refined
    chain as (eq.-11 cost, angles) to ``pool`` (the hypotheses the verdict weighs), with
    the best cfg.alternatives screened candidates whose tips lie more than DISTINCT_TIP_M from
    the refined ones' refined too (distinct shapes the robust cost ranked lower).
    ``cache``: the capture's screens and refinements already made (:func:`screened`; the
    second look refines again the starts the first look's wide search refined, the winner's
    branches and curls: the same numbers, taken from it)."""
    made = _settings(cache, cfg)
    key = None if made is None else ("refined", starts.shape, np.ascontiguousarray(starts, float).tobytes())
    if made is not None and key in made:
        winner, steps, best_cost, refined = made[key]
        if pool is not None:
            pool += refined
        return winner, list(steps), best_cost
    params, cost, (r, J), iterates = screened(chain, fields, starts, cfg, cache)
    # Screened by the robust cost (ranking all by eq. 11 was measured no better on the
    # samples and worse on sim captures); the silhouette cost (eq. 11) picks the winner.
    # The screen's residuals carry over: no re-evaluation at the kept candidates.
    keep = np.argsort(cost)[:cfg.refine]
    if pool is not None and cfg.alternatives > 0 and len(cost) > cfg.refine:
        # Distinct hypotheses: the best screened chains whose tips are far from every kept
        # one's, refined like the winner so that their costs compare.
        tips = chain.tips(params[:, :3 * chain.n].reshape(-1, chain.n, 3))
        extra = []
        for k in np.argsort(cost):
            d = np.linalg.norm(tips[k] - tips[np.concatenate([keep, extra]).astype(int)], axis=1)
            if np.all(d > DISTINCT_TIP_M) and k not in keep:
                extra.append(k)
                if len(extra) == cfg.alternatives:
                    break
        keep = np.concatenate([keep, np.array(extra, int)])
    if cfg.refine_eq11 > 0 and len(cost) > cfg.refine:
        # Plus the best screened ones by the silhouette cost: where the model cannot follow
        # the tape (a tight curl at the tip) the robust boundary cost may prefer a wrong
        # branch that eq. 11 does not (measured on sim tip-curl captures).
        order = np.argsort(cost)
        rest = order[cfg.refine:][cost[order[cfg.refine:]] < cfg.eq11_range * cost[order[0]]]
        eq11 = silhouette_costs(params[rest, :3 * chain.n].reshape(-1, chain.n, 3))
        keep = np.concatenate([keep, rest[np.argsort(eq11)[:cfg.refine_eq11]]]) if len(rest) else keep
    keep = keep[np.sort(np.unique(keep, return_index=True)[1])]   # one chosen twice is refined once
    converge: list = []
    params, _, _ = levenberg_marquardt(chain, fields, params[keep], cfg.lm_iterations, converge,
                                       (r[keep], J[keep], cost[keep]), cfg)
    refined = params[:, :3 * chain.n].reshape(-1, chain.n, 3)
    costs = silhouette_costs(refined)
    best = int(np.argmin(costs))
    found = [(float(c), a) for c, a in zip(costs, refined)]
    if pool is not None:
        pool += found
    steps = iterates[keep[best]] + trace(converge, best, chain.n)
    if made is not None:
        made[key] = (refined[best], steps, float(costs[best]), found)
    return refined[best], list(steps), float(costs[best])


def mirrors(angles: np.ndarray) -> np.ndarray:
    """(2, n, 3): ``angles`` with every out-of-plane bend mirrored (θy -> -θy), and with the
    twist mirrored as well (the same silhouette seen from a camera facing the tape)."""
    a, b = angles.copy(), angles.copy()
    a[:, 1] *= -1
    b[:, 1] *= -1
    b[:, 0] *= -1
    return np.array([a, b])


def variants(angles: np.ndarray) -> np.ndarray:
    """Chains near ``angles`` (n, 3) on other branches: from each joint on, the bend
    mirrored (θy -> -θy) or the twist turned by ±π/2 or flipped in sign — the ambiguities
    a silhouette leaves (a plate seen edge-on, a bend towards or away from a camera)."""
    out = []
    for j in range(len(angles)):
        for kind in range(4):
            a = angles.copy()
            if kind == 0:
                a[j:, 1] = -a[j:, 1]
            elif kind == 1:
                a[j, 0] = -a[j, 0]
            else:
                a[j, 0] += np.pi / 2 if kind == 2 else -np.pi / 2
            out.append(a)
    return np.array(out)


def curls(angles: np.ndarray, bends) -> np.ndarray:
    """Steady curls, untwisted: per bend of ``bends`` [rad] and either way, ``angles``' first
    joint kept and every later joint bent out of plane by it, then every joint bent by it
    (the first joint too: a start whose first joint is wrong, twisted the other way, leaves
    the rest of its curl on a wrong branch)."""
    out = []
    for bend in bends:
        for sign in (1.0, -1.0):
            every = np.zeros_like(angles)
            every[:, 1] = sign * bend
            kept = every.copy()
            kept[0] = angles[0]
            out += [kept, every]
    return np.array(out)


def hooks(angles: np.ndarray, bends) -> np.ndarray:
    """Chains like ``angles`` (n, 3) whose end hooks back: the last plate, or the last two
    together, bent out of plane by each of ``bends`` [rad] either way, untwisted. A tip
    that curls back behind the tape's own body (or over its top, towards or away from a
    camera) leaves the silhouette almost as a straight end does, and the beam's grid
    (bends up to 1.5 rad per joint) does not reach it in one step."""
    out = []
    n = len(angles)
    for j in range(max(n - 2, 0), n):
        for bend in bends:
            for sign in (1.0, -1.0):
                a = angles.copy()
                a[j:] = 0.0
                a[j, 1] = sign * bend
                out.append(a)
    return np.array(out)


def hypotheses(chain: Chain, pool: list, winner: np.ndarray) -> list:
    """The distinct shapes among the refined chains ``pool`` [(eq.-11 cost, angles)]: best
    first, each tip more than DISTINCT_TIP_M from the winner's plate fit and from every
    better one's; as (cost, angles)."""
    out, tips = [], [chain.tips(winner[None])[0]]
    for cost, a in sorted(pool, key=lambda x: x[0]):
        tip = chain.tips(a[None])[0]
        if all(np.linalg.norm(tip - t) > DISTINCT_TIP_M for t in tips):
            out.append((cost, a))
            tips.append(tip)
    return out
