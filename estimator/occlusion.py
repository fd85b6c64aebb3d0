"""What the known scene boxes hide, and where the tape may not go.

A model point behind a box (seen from a camera) is unknown, neither tape nor background;
a point inside a box is a penetration the fit is charged for. Boxes are
:class:`~tapecell.estimator.scene.Box` (world frame, metres).
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .geometry import Camera
from .scene import Box

SURFACE_M = 0.001
"""Boxes are shrunk by this [m] for both tests: a point on a box's surface (the tape's
base lies on the part) is neither hidden by it nor inside it."""


def hidden(origin: np.ndarray, points: np.ndarray, boxes: Sequence[Box], margin: float = SURFACE_M) -> np.ndarray:
    """(N,) bool: which world points (N, 3) a box hides from ``origin`` (3,) [m], i.e.
    the open segment origin -> point crosses a box shrunk by ``margin``."""
    points = np.asarray(points, float).reshape(-1, 3)
    out = np.zeros(len(points), bool)
    for box in boxes:
        h = box.half - margin
        o = (np.asarray(origin, float) - box.center) @ box.rotation       # box frame
        d = (points - box.center) @ box.rotation - o                      # (N, 3) segment directions
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / d
            t1, t2 = (-h - o) * inv, (h - o) * inv
        lo = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))
        hi = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
        # A zero direction component: inside the slab (any t) or never.
        flat = d == 0
        outside_slab = flat & (np.abs(o) > h)
        lo = np.where(flat, -np.inf, lo)
        hi = np.where(flat, np.inf, hi)
        enter, leave = lo.max(axis=1), hi.min(axis=1)
        out |= (enter < leave) & (leave > 0.0) & (enter < 1.0 - 1e-9) & ~outside_slab.any(axis=1)
    return out


def hidden_in_views(cameras: Sequence[Camera], points: np.ndarray, boxes: Sequence[Box]) -> np.ndarray:
    """(views, N) bool: which world points (N, 3) each camera cannot see for the boxes."""
    if not boxes:
        return np.zeros((len(cameras), len(points)), bool)
    return np.array([hidden(c.center, points, boxes) for c in cameras])


def penetration(points: np.ndarray, boxes: Sequence[Box], margin: float = SURFACE_M):
    """How deep world points (N, 3) lie inside the boxes shrunk by ``margin``: (depth (N,)
    [m], 0 outside, and its gradient d depth / d point (N, 3))."""
    points = np.asarray(points, float).reshape(-1, 3)
    depth = np.zeros(len(points))
    grad = np.zeros((len(points), 3))
    for box in boxes:
        local = (points - box.center) @ box.rotation
        slack = (box.half - margin) - np.abs(local)                      # (N, 3) > 0 inside each slab
        axis = np.argmin(slack, axis=1)
        d = slack[np.arange(len(points)), axis]
        inside = d > depth
        if not inside.any():
            continue
        k = np.flatnonzero(inside)
        depth[k] = d[k]
        # Deeper when the point moves towards the box's centre along its nearest face's axis.
        sign = -np.sign(local[k, axis[k]])
        sign[sign == 0] = 1.0
        grad[k] = sign[:, None] * box.rotation[:, axis[k]].T
    return depth, grad
