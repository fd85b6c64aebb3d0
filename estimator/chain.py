"""The plate chain: its sample points (edges, tip edge, centre line, joints' lines) and
corners for a batch of joint-angle sets, with their exact Jacobian through the chain's
kinematics."""
from __future__ import annotations

import functools

import numpy as np

from . import _kernels, reference
from .config import DEFAULT, FitConfig
from .tape import TapeSpec


@functools.lru_cache(maxsize=16)
def _chain_layout(n: int, tip_weight: float, edge_t: tuple, centre_t: tuple, tip_t: tuple, crease_t: tuple = ()):
    """The sample-point layout of an n-plate chain (see :class:`Chain`), built once per setting:
    (M, edge, weight, segments, moves, fold_of), shared: not to be written. ``crease_t``:
    sample points along each joint's line across the tape (FitConfig.crease_t; empty: the
    joints' lines are no part of the outline)."""
    m = n + 1
    rows, edge = [], []
    # corners: index k -> P_C[k], m + k -> P_L[k], 2m + k -> P_R[k]
    for side in (1, 2):
        for i in range(1, m):
            for t in edge_t:
                w = np.zeros(3 * m)
                w[side * m + i - 1] = 1 - t
                w[side * m + i] = t
                rows.append(w)
                edge.append(True)
    for t in tip_t:
        w = np.zeros(3 * m)
        w[m + n] = 1 - t
        w[2 * m + n] = t
        rows.append(w)
        edge.append(True)
    for i in range(1, m):
        for t in centre_t:
            w = np.zeros(3 * m)
            w[i - 1] = 1 - t
            w[i] = t
            rows.append(w)
            edge.append(False)
    # The joints' lines across the tape, where the tape folds in the image (FitConfig.crease_t):
    # sample points on the outline there, each counted only while its joint folds (fold_of).
    creases = [(k, t) for k in range(1, n) for t in crease_t]
    for k, t in creases:
        w = np.zeros(3 * m)
        w[m + k] = 1 - t
        w[2 * m + k] = t
        rows.append(w)
        edge.append(True)
    M = np.array(rows)
    edge = np.array(edge)
    # The tip is what the robot grasps: its plate's edges and the tip edge count more.
    tip = M[:, [m + n, 2 * m + n]].sum(axis=1) > 0
    weight = np.where(tip & edge, tip_weight, 1.0)
    # silhouette outline segments (K, 4): corner indices (s0, s1) and the two points whose
    # sides decide whether it counts (-1, -1: always): left, right, tip and base edges,
    # and with ``crease_t`` the joints' lines across the tape (FitConfig.crease_t),
    # each with the centre nodes either side of it (the fold test); (-1, -1) for the edges
    left = [(m + k, m + k + 1, -1, -1) for k in range(n)]
    right = [(2 * m + k, 2 * m + k + 1, -1, -1) for k in range(n)]
    edges = left + right + [(m + n, 2 * m + n, -1, -1), (m, 2 * m, -1, -1)]
    across = [(m + k, 2 * m + k, k - 1, k + 1) for k in range(1, n)] if crease_t else []
    segments = np.array(edges + across)
    # each sample point's joint line (its index in segments: joint k's is across[k - 1]), -1
    # for the others
    fold_of = np.full(len(M), -1, np.int64)
    fold_of[len(M) - len(creases):] = [len(edges) + k - 1 for k, _ in creases]
    # corner c belongs to the frame of node c % m: it moves with joints 1..c % m
    node_of = np.tile(np.arange(m), 3)
    moves = (node_of[:, None] >= np.arange(1, m)[None, :]).astype(float)  # (3m, n)
    return M, edge, weight, segments, moves, fold_of


class Chain:
    """Sample points on the chain's silhouette-relevant parts and their Jacobian, for a
    batch of B angle sets at once."""

    def __init__(self, spec: TapeSpec, edge_t: tuple | None = None, centre_t: tuple | None = None,
                 cfg: FitConfig = DEFAULT, crease_t: tuple | None = None):
        """edge_t, centre_t: where on each plate (fractions of its length) the edge and
        centre-line sample points lie; crease_t: where along each joint's line (fractions of
        the width); each by default the config's."""
        self.spec = spec
        self.n = spec.n
        self.cfg = cfg
        edge_t = cfg.edge_t if edge_t is None else edge_t
        centre_t = cfg.centre_t if centre_t is None else centre_t
        crease_t = cfg.crease_t if crease_t is None else crease_t
        self.M, self.edge, self.weight, self.segments, self.moves, self.fold_of = _chain_layout(
            spec.n, float(cfg.tip_weight), tuple(float(t) for t in edge_t), tuple(float(t) for t in centre_t),
            tuple(float(t) for t in cfg.tip_t), tuple(float(t) for t in crease_t))
        self.samples = len(self.M)

    def corners(self, angles: np.ndarray):
        """(n, 3) angles -> the corners P_C, P_L, P_R (3m, 3) and their Jacobian (3m, 3, 3n)."""
        a = np.asarray(angles, float).reshape(1, self.n, 3)
        pts, J = self.points(a, True)
        return pts[0, self.samples:], J[0, self.samples:]

    def tips(self, angles: np.ndarray) -> np.ndarray:
        """(B, n, 3) angles -> the chains' tips P_C[n] (B, 3)."""
        a = np.asarray(angles, float).reshape(-1, self.n, 3)
        pts, _ = self.points(a, False)
        return pts[:, self.samples + self.n]

    def quads(self, angles: np.ndarray) -> np.ndarray:
        """(B, n, 3) angles -> the plates' quads (B, n, 4, 3), as ``TapeShape.quads``."""
        a = np.asarray(angles, float).reshape(-1, self.n, 3)
        pts, _ = self.points(a, False)
        c = pts[:, self.samples:]
        m, i = self.n + 1, np.arange(self.n)
        return np.stack([c[:, m + i], c[:, m + i + 1], c[:, 2 * m + i + 1], c[:, 2 * m + i]], axis=2)

    def points(self, angles: np.ndarray, jacobian: bool):
        """(B, n, 3) angles -> (B, s + 3m, 3) sample points then corners and, if asked,
        their (B, s + 3m, 3, 3n) Jacobian (compiled, or the NumPy reference)."""
        a = np.ascontiguousarray(angles, float)
        return _kernels.points(self, a, jacobian) if self.cfg.compiled else reference.chain_points(self, a, jacobian)
