"""The estimator's result and its `tape-estimate/1` JSON form."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class Estimate:
    """A fitted tape.

    nodes: (n+1, 3) P_C[0..n] in the world frame [m], base first.
    angles: (n, 3) joint angles (θx, θy, θz) [rad].
    tip_position: (3,) P_C[n] [m]; tip_rotation: (3, 3) F_n (trunk, left, normal columns).
    cost: the combined silhouette cost (eq. 11); view_costs: per camera (eq. 7), in the
    order of the capture's views.
    time_s: fitting time alone [s].
    method: "default" or "paper".
    history: cost after each optimiser iteration (for plots and logs).
    evaluations: number of cost evaluations.
    """

    nodes: np.ndarray
    angles: np.ndarray
    tip_position: np.ndarray
    tip_rotation: np.ndarray
    cost: float
    view_costs: np.ndarray
    time_s: float
    method: str = "default"
    history: list[float] = field(default_factory=list)
    evaluations: int = 0

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "tape-estimate/1",
            "nodes": np.asarray(self.nodes).tolist(),
            "angles": np.asarray(self.angles).tolist(),
            "tip": {"position": np.asarray(self.tip_position).tolist(),
                    "rotation": np.asarray(self.tip_rotation).tolist()},
            "cost": float(self.cost),
            "view_costs": [float(c) for c in self.view_costs],
            "time_s": float(self.time_s),
            "method": self.method,
            "evaluations": int(self.evaluations),
        }
