"""The estimator's result and its `tape-estimate/1` JSON form."""
from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np


class Verdict(str, enum.Enum):
    """Whether a robot may act on an estimate (formats.md, `verdict`)."""

    OK = "ok"
    """The shape explains every view, two or more cameras see the free end, and no distinct
    alternative comes close: a robot may act on it."""
    AMBIGUOUS = "ambiguous"
    """A distinct alternative (tip more than 10 mm away) explains the views nearly as well."""
    HIDDEN = "hidden"
    """Fewer than two cameras see the free end."""
    POOR_FIT = "poor_fit"
    """The silhouettes are not explained (bad calibration or segmentation, the wrong tape)."""


class CostHistory(Sequence):
    """A sequence of costs computed when first read (``compute()`` -> the list): what an
    estimate's ``history`` costs to render (about 10 ms a look, rendering every iterate) is
    paid by whoever reads it (recordings, plots), not by every fit's caller. Pickles (and
    compares) as the list it holds."""

    def __init__(self, compute: Callable[[], list]):
        self._compute: Callable[[], list] | None = compute
        self._values: list | None = None

    def _list(self) -> list:
        if self._values is None:
            self._values = [float(c) for c in self._compute()]
            self._compute = None          # drop what it held (the capture, the iterates)
        return self._values

    def __getitem__(self, k):
        return self._list()[k]

    def __len__(self) -> int:
        return len(self._list())

    def __eq__(self, other: object) -> bool:
        return self._list() == (list(other) if isinstance(other, Sequence) else other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return repr(self._list())

    def __reduce__(self):
        return list, (self._list(),)


@dataclass(frozen=True, eq=False)
class Alternative:
    """Another distinct shape that explains the views almost as well as the estimate.

    cost: its silhouette cost (eq. 11); tip_position (3,) [m] and tip_rotation (3, 3) its
    end frame; angles (n, 3) its plate chain [rad]. output_cost: where its cost is below
    the estimate's, the eq.-11 cost of the chain the estimator would output from it (its
    strip stage, like the estimate's own chain), which is not (``fit._cheapest_first``);
    else None."""

    cost: float
    tip_position: np.ndarray
    tip_rotation: np.ndarray
    angles: np.ndarray
    output_cost: float | None = None

    def to_json(self) -> dict[str, Any]:
        out = {"cost": float(self.cost), "tip": {"position": np.asarray(self.tip_position).tolist(),
                                                 "rotation": np.asarray(self.tip_rotation).tolist()}}
        if self.output_cost is not None:
            out["output_cost"] = float(self.output_cost)
        return out

    @property
    def compared_cost(self) -> float:
        """Its cost compared like for like with an estimate's: as the estimator's output."""
        return self.cost if self.output_cost is None else self.output_cost


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
    verdict: whether a robot may act on it (:class:`Verdict`); verdict_reason: one line why.
    tip_views: how many cameras see the free end.
    view_offsets_px: per camera, the mean distance between the model's and the observed
    silhouette boundaries [px] (what the verdict judges a view's fit by: the plate chain's,
    or the strip's where :func:`verdict.explaining_offsets` takes them).
    trace: the plate chain's angles (n, 3) after each optimiser iteration of the winner
    (``history`` holds their eq.-11 costs); for plots and recordings.
    alternatives: other distinct shapes within the verdict's cost margin, best first, none
    cheaper than the estimate when compared as the estimator's output
    (:attr:`Alternative.compared_cost`); where the answer was swapped for such a cheaper
    alternative (``fit._cheapest_first``), every shape reported before, the first answer
    among them.
    """

    nodes: np.ndarray
    angles: np.ndarray
    tip_position: np.ndarray
    tip_rotation: np.ndarray
    cost: float
    view_costs: np.ndarray
    time_s: float
    method: str = "default"
    history: Sequence[float] = field(default_factory=list)
    evaluations: int = 0
    verdict: Verdict = Verdict.OK
    verdict_reason: str = ""
    tip_views: int = 0
    alternatives: tuple[Alternative, ...] = ()
    trace: tuple[np.ndarray, ...] = ()
    view_offsets_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    base_offset_px: float = float("nan")
    """The worst view's mean boundary distance around the tape's base [px] where the base
    check measured it (answers the first judgement found "ok", whatever they became after;
    NaN where not measured). Not written to JSON: the estimator's own, read by its
    self-calibration (``fit._calibration_suspect``) on :func:`estimate`'s own answers alone;
    the needle's adopted and refitted estimates do not keep it up to date."""

    @property
    def actionable(self) -> bool:
        """A robot may act on this estimate (its verdict is "ok")."""
        return self.verdict is Verdict.OK

    def to_json(self) -> dict[str, Any]:
        return {
            "format": "tape-estimate/1",
            "nodes": np.asarray(self.nodes).tolist(),
            "angles": np.asarray(self.angles).tolist(),
            "tip": {"position": np.asarray(self.tip_position).tolist(),
                    "rotation": np.asarray(self.tip_rotation).tolist()},
            "cost": float(self.cost),
            "view_costs": [float(c) for c in self.view_costs],
            "verdict": Verdict(self.verdict).value,
            "verdict_reason": self.verdict_reason,
            "tip_views": int(self.tip_views),
            "view_offsets_px": [round(float(o), 3) for o in self.view_offsets_px],
            "alternatives": [a.to_json() for a in self.alternatives],
            "time_s": float(self.time_s),
            "method": self.method,
            "evaluations": int(self.evaluations),
        }
