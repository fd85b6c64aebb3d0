"""Accuracy of an estimate against ground truth, as the project reports it.

The true tape need not be a plate chain, so errors are taken at equal arc length along
the estimate's polyline and the true centre line, and at the tip.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .capture import Truth


@dataclass(frozen=True)
class Errors:
    """tip_m: tip position error [m] (the paper's e, eq. 12).
    node_max_m: worst node error at equal arc length [m].
    node_m: (n+1,) error of every node at its arc length [m].
    normal_deg: angle between estimated and true tip normals, as axes (the pads close
    across the thickness either way) [deg].
    """

    tip_m: float
    node_max_m: float
    node_m: np.ndarray
    normal_deg: float


def centerline_at(truth: Truth, s: np.ndarray) -> np.ndarray:
    """The true centre line at arc lengths ``s`` [m], linearly interpolated."""
    s = np.clip(np.asarray(s, float), truth.s[0], truth.s[-1])
    return np.stack([np.interp(s, truth.s, truth.points[:, k]) for k in range(3)], axis=1)


def errors(nodes: np.ndarray, tip_rotation: np.ndarray, truth: Truth,
           tip_position: np.ndarray | None = None) -> Errors:
    """Errors of an estimated node polyline (n+1, 3) and tip frame against ``truth``; the
    tip is ``tip_position`` (3,) when given (an estimator's finer end), else the last node."""
    nodes = np.asarray(nodes, float)
    tip_position = nodes[-1] if tip_position is None else np.asarray(tip_position, float)
    s_nodes = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes, axis=0), axis=1))])
    node_err = np.linalg.norm(nodes - centerline_at(truth, s_nodes), axis=1)
    tip = float(np.linalg.norm(tip_position - truth.points[-1]))
    c = abs(float(np.dot(tip_rotation[:, 2], truth.tip_rotation[:, 2])))
    normal = float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
    return Errors(tip, float(node_err.max()), node_err, normal)
