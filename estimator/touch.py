"""Refitting to a point measured on the tape: a probe (the cell's needle) touched the tape's
end, and the chain is refitted to the views and through that point.

Where fewer than two cameras see the free end, the views leave the end's depth open, and an
estimate's tip can be some millimetres off along a camera's ray; an end hooked over within a
few millimetres leaves it off too. A needle sent to such a tip touches the tape a few
millimetres from where it was aimed: that touch is a point of the tape. The refit starts from
the estimate's shape and adds the touched point's offset from the end of the chain's centre
line to the views' residuals, in the plate fit and in the strip stage.
The result is judged like any estimate; what may act on it is for the caller to say (the
cell's needle touches the refitted tip before anything acts on it).
"""
from __future__ import annotations

import time

import numpy as np

from .capture import Capture
from .chain import Chain
from .config import DEFAULT, FitConfig
from .errors import EstimateError
from .result import Estimate
from .residuals import residuals
from .silhouette import combine
from .solver import levenberg_marquardt_one, with_rows
from .strip import strip_stage
from .views import prepare

TOUCH_PX_PER_M = 20000.0
"""Residual [px] per metre between the touched point and the chain's end: 1 mm counts like
an outline 20 px off, so the refit passes through the touch (a needle measures to a fraction
of a millimetre) unless the views insist strongly."""


def end_rows(point: np.ndarray, depth: float, weight: float = TOUCH_PX_PER_M):
    """Residual rows pulling a chain's end onto ``point`` (3,) [m]: ``weight`` times the
    point's offset from the nearest point of its centre line's last ``depth`` [m] (where a
    needle aimed just inside the end's middle lands on a tape whose end the views leave
    off along the needle's way): a function (corners (3m, 3), Jacobian (3m, 3, P)) ->
    (residuals (3,), Jacobian (3, P)), for corners laid out as :meth:`Chain.corners` gives
    them (P_C, then P_L, then P_R, each n + 1). The nearest point's place on the centre line
    is held fixed for the Jacobian (exact for the cost's gradient where it is inside). The
    last ``depth`` is taken within the last plate (``depth`` at most its length: 4 mm of the
    strip's 7.5 mm plates)."""
    point = np.asarray(point, float)

    def rows(c: np.ndarray, J: np.ndarray):
        n = len(c) // 3 - 1
        a, b = c[n - 1], c[n]                     # the last plate's centre line P_C[n-1] -> P_C[n]
        u = b - a
        uu = float(u @ u)
        s = float(np.clip((point - a) @ u / uu, max(0.0, 1.0 - depth / np.sqrt(uu)), 1.0))
        return weight * ((1 - s) * a + s * b - point), weight * ((1 - s) * J[n - 1] + s * J[n])

    return rows


def refit(capture: Capture, angles: np.ndarray, point: np.ndarray, depth: float, cfg: FitConfig = DEFAULT) -> Estimate:
    """The plate chain refitted from ``angles`` (n, 3) to ``capture``'s views and with its
    end through the touched ``point`` (3,) [m] (within ``depth`` [m] of the end along its
    centre line, :func:`end_rows`), with its verdict (judged as any estimate, with no
    alternatives: the touch chose the shape). ``time_s`` is the refit's time."""
    from .fit import _costed, _judge, warm

    point = np.asarray(point, float)
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise EstimateError(f"{capture.name}: the touched point to refit through must be 3 finite coordinates, "
                            f"not {point.tolist()}")
    warm()
    start = time.perf_counter()
    chain = Chain(capture.tape, cfg=cfg)
    fields = [prepare(v, capture.scene, cfg) for v in capture.views]
    rows = end_rows(point, depth)

    def views(x: np.ndarray):
        r, J, cost = residuals(chain, fields, x[None], True, cfg)
        return r[0], J[0], cost[0]

    fun = with_rows(views, lambda x: chain.corners(x.reshape(chain.n, 3)), rows)
    x = levenberg_marquardt_one(fun, np.asarray(angles, float).ravel().copy(), cfg.lm_iterations * 3, cfg.lm_rtol)
    plate = x.reshape(chain.n, 3)
    tip, fine = None, None
    angles_out = plate
    shape, view_costs, evaluator = _costed(capture, plate)
    if cfg.strip:
        # The strip's end frame, unless its chain explains the views far worse than the
        # plate fit (as estimate()'s guard).
        output = strip_stage(chain, fields, plate, cfg, extra=rows)
        out = output(cfg.strip_frame_weight)
        costed = _costed(capture, out)
        if combine(costed[1]) <= cfg.strip_guard * combine(view_costs):
            angles_out, tip, fine = out, output.tip, output.fine
            shape, view_costs, evaluator = costed
    tip_position, tip_rotation = tip if tip is not None else (shape.nodes[-1].copy(), shape.frames[-1].copy())
    j, _ = _judge(capture, evaluator, view_costs, shape, tip_position, tip_rotation, combine(view_costs), [], fine)
    return Estimate(shape.nodes, angles_out, tip_position, tip_rotation, combine(view_costs), view_costs,
                    time.perf_counter() - start, "default", verdict=j.verdict, verdict_reason=j.reason,
                    tip_views=j.tip_views, view_offsets_px=j.offsets_px)
