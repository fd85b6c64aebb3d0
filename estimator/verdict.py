"""The estimator's verdict: may a robot act on this estimate? (formats.md, `verdict`).

Judged per view, so a threshold means the same with 2 or 3 cameras.
"""
from __future__ import annotations

import numpy as np

from .result import Verdict

POOR_VIEW_COST = 0.35
"""A view whose silhouette cost (eq. 7) is above this is not explained by the fit."""


def judge(view_costs: np.ndarray) -> tuple[Verdict, str, int]:
    """(verdict, reason, tip_views) from the per-view costs alone."""
    view_costs = np.asarray(view_costs, float)
    worst = int(np.argmax(view_costs))
    if view_costs[worst] > POOR_VIEW_COST:
        return Verdict.POOR_FIT, f"view {worst} cost {view_costs[worst]:.3f} > {POOR_VIEW_COST}", len(view_costs)
    return Verdict.OK, "", len(view_costs)
