"""The project's estimator (method="default") and the public :func:`estimate`: the stages
in order, each in a module of its own (views, search, refine with chain, residuals and
solver, strip), and the verdict.

Where the paper searches the XOR cost with a simplex, node by node, we fit the plate
chain's silhouette *boundary* to the observed one, which gives a smooth cost with an
analytic Jacobian:

1. Per view, clean the mask (drop speckles, fill pinholes), crop a region of interest and
   build the signed distance field (SDF) of the observed silhouette, negative inside.
2. Global stage, a beam search node by node: every kept partial chain is extended by a
   grid of joint angles (twist, out-of-plane and in-plane bend); a candidate's score
   asks that its plate edges lie on the observed boundary and its centre line inside the
   silhouette in every view (robust losses: Huber outside, Cauchy inside, so an edge
   hidden behind another part of the tape costs little). Keeping several chains escapes
   the wrong branches a greedy pass falls into (twist sign, a tape curled back).
3. Local stage: Levenberg-Marquardt on all 3n angles jointly, with the same residuals
   (re-weighted each iteration) and their exact Jacobian through the chain's kinematics
   and the camera projection.
4. The refined candidates are ranked by the paper's own silhouette cost (eq. 11); the
   best one is returned with its per-view costs on the full observed masks.
5. Only for a poor fit (a high cost, a view explained badly on average, or a thick region
   of a view left unexplained: ``FitConfig.wide_*``) a wide stage runs: a finer, larger
   beam plus the other branches next to the winner (mirrored bends, flipped or
   quarter-turned twists) and steady curls (:func:`refine.curls`); its result replaces the
   first only when its eq.-11 cost is clearly lower.
   The thorough look of a "hidden" estimate also refines the winner with its end hooked
   back out of sight behind the body (:func:`refine.hooks`), kept when it costs less.
6. Strip stage: a 30 mm plate cannot follow a tape that curls within its length, so its
   last plate is a chord and the tip lands mm off. From the winner, a continuous strip
   (a fine chain whose twist and bend rates vary linearly between knots at the model's
   nodes, in-plane bending held near zero as a tape's is) is fitted on the same
   residuals; the output plate chain is the one closest to the strip in 3-D at the
   model's nodes, tip first. A chain that explains the views far worse than the plate
   fit (the strip gone astray) is dropped for the plate fit.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import cv2
import numpy as np

from . import _kernels, recalibrate
from .capture import Capture, View
from .chain import Chain
from .config import DEFAULT, FitConfig
from .errors import EstimateError
from .geometry import Camera
from .refine import curls, hooks, hypotheses, mirrors, refine, variants
from .result import Alternative, CostHistory, Estimate, Verdict
from .search import beam_search
from .silhouette import OCCLUSION_CELLS, CostEvaluator, combine, make_target, project_quads
from .solver import levenberg_marquardt
from .strip import strip_stage
from .tape import forward_kinematics
from .verdict import (BASE_OFFSET_PX, DISTINCT_TIP_M, EDGEWISE, EDGEWISE_MAX_DEG, END_FOLD_DEG, FOLD_DEG, assess,
                      base_offsets, edgewise_bend, end_on, is_close_alternative, mask_fault, rival_reason,
                      unexplained_cut_px, view_offsets)
from .views import prepare

Callback = Callable[[int, float, np.ndarray], None]


class FirstStage:
    """What every look at one capture computes alike, done once and shared by the first look
    and the second, thorough one (:func:`estimate`): the views' preparation, the global
    search on the default grid, its refinement and the winner's mirrors (none of them
    depends on ``thorough``), and the strip stage of each plate fit (a function of its
    angles alone); its ``chain`` and ``silhouette_costs`` (eq. 11 of (B, n, 3) angles on
    its prepared views) serve the depth probes."""

    def __init__(self, capture: Capture, chain: Chain, cfg: FitConfig):
        self.fields = [prepare(v, capture.scene, cfg) for v in capture.views]
        evaluator = CostEvaluator([f.target for f in self.fields], capture.scene)

        def silhouette_costs(angles: np.ndarray) -> np.ndarray:
            return evaluator.costs(chain.quads(angles))

        starts = np.array(beam_search(capture.tape, self.fields, cfg=cfg))
        pool: list = []
        self.screens: dict = {}   # every start's screen, for both looks (refine.screened)
        angles, trace, cost = refine(chain, self.fields, starts, silhouette_costs, pool, cfg, self.screens)
        # The classic silhouette ambiguity, a bend towards or away from the cameras: the
        # winner's mirror images are refined too, as hypotheses (and the winner if better).
        a2, t2, c2 = refine(chain, self.fields, mirrors(angles), silhouette_costs, pool, cfg, self.screens)
        if c2 < cost:
            angles, trace, cost = a2, t2, c2
        self.angles, self.trace, self.cost, self.pool = angles, trace, cost, pool
        self.chain, self.silhouette_costs = chain, silhouette_costs
        self.evaluations = evaluator.evaluations
        self._strips: dict = {}

    def strip(self, chain: Chain, angles: np.ndarray, cfg: FitConfig):
        """:func:`strip_stage` from the plate fit ``angles``, once per distinct fit."""
        key = angles.tobytes()
        if key not in self._strips:
            self._strips[key] = strip_stage(chain, self.fields, angles, cfg)
        return self._strips[key]


def fit_default(capture: Capture, callback: Callback | None = None, thorough: bool = False,
                cfg: FitConfig = DEFAULT, first: FirstStage | None = None):
    """Fit by the project's method; returns (angles, trace, evaluations, fallback) where
    trace holds the winning candidate's angles after each local-stage iteration, and
    fallback (with the strip stage, else None) is (the plate fit's eq.-11 cost, [functions
    giving the chains to fall back to, in order, the plate fit last]) for estimate()'s
    guard. Then the hypotheses, and the strip stage's output (``.tip``: its end frame,
    ``.fine``: the strip's shape; None without the strip stage). ``first``: this capture's
    :class:`FirstStage` when another look made it."""
    chain = Chain(capture.tape, cfg=cfg)
    first = FirstStage(capture, chain, cfg) if first is None else first
    fields = first.fields
    evaluator = CostEvaluator([f.target for f in fields], capture.scene)
    evaluator.evaluations = first.evaluations

    def silhouette_costs(angles: np.ndarray) -> np.ndarray:
        return evaluator.costs(chain.quads(angles))

    angles, trace, cost, pool = first.angles, first.trace, first.cost, list(first.pool)
    uncurled = None
    worst_px = max(c * f.target.area / f.outline_px
                   for c, f in zip(evaluator.view_costs(chain.quads(angles)[0]), fields))
    # (misfit_px reads the disagreement images view_costs just drew for these quads.)
    if thorough or cost > cfg.wide_cost or worst_px > cfg.wide_offset_px or misfit_px(evaluator) > cfg.wide_misfit_px:
        # A poor fit: only these pay for a wider search (a finer, larger beam and the other
        # branches next to the winner, then steady curls); each replaces the answer only
        # when its silhouette cost is clearly lower.
        parts = [variants(angles)] if cfg.wide_variants else []
        if cfg.wide_beam:
            parts.append(np.array(beam_search(capture.tape, fields, cfg.grid_angles(wide=True),
                                              cfg.thorough_beam if thorough else cfg.wide_beam, cfg)))
        wide = np.concatenate(parts)
        a2, t2, c2 = refine(chain, fields, wide, silhouette_costs, pool, cfg, first.screens)
        if c2 < cfg.wide_gain * cost:
            angles, trace, cost = a2, trace + t2, c2
        if cfg.wide_curls:
            # Steady curls, refined on their own: screened with the rest, a curl a few
            # iterations from its best lost its place to the beam's chains (clean-922044).
            a4, t4, c4 = refine(chain, fields, curls(first.angles, cfg.wide_curls), silhouette_costs, pool, cfg,
                                first.screens)
            if c4 < cfg.wide_gain * cost:
                uncurled = (angles, trace, cost)
                angles, trace, cost = a4, trace + t4, c4
        if thorough and cfg.hook_bends:
            # An end hooked back, out of sight behind the body: refined from the first
            # stage's winner (the default beam's, before any wide search); every refined
            # chain joins the hypotheses the needle can check.
            a3, t3, c3 = refine(chain, fields, hooks(first.angles, cfg.hook_bends), silhouette_costs, pool, cfg,
                                 first.screens)
            if c3 < cost:
                angles, trace, cost = a3, first.trace + t3, c3
                uncurled = None   # the answer is the hook's, not a curl's
    fallback = None
    strip = None
    if cfg.strip:
        strip = first.strip(chain, angles, cfg)
        output = strip(cfg.strip_frame_weight)
        if uncurled is not None:
            # A curl replaced the plate fit: the strip from each, the one that explains the
            # views better stands (part-924052: the curl's plate fit cost less, but its strip
            # stuck on a worse branch, poor_fit; the other's strip explained the views).
            other = first.strip(chain, uncurled[0], cfg)
            theirs = other(cfg.strip_frame_weight)
            ours_cost, theirs_cost = silhouette_costs(np.array([output, theirs]))
            if theirs_cost < ours_cost:
                strip, output, (angles, trace, cost) = other, theirs, uncurled
        plate = angles
        # What estimate() falls back to, in order, while the chain's silhouette cost is
        # above the guard: the chain without the tip-frame pull, then the plate fit.
        alternatives = [lambda: strip(0.0)] if cfg.strip_frame_weight > 0 else []
        fallback = (cost, alternatives + [lambda: plate])
        angles = output
        trace = trace + [angles]
    winner = plate if cfg.strip else angles
    return angles, trace, evaluator.evaluations, fallback, hypotheses(chain, pool, winner), strip


def misfit_px(evaluator: CostEvaluator, quads: np.ndarray | None = None) -> float:
    """Half the thickness [px] of the thickest region where a view and the model of
    ``quads`` (m, 4, 3) disagree (observed tape the model leaves out, or model over the
    background), over all views: its largest distance to the region's edge. Without
    ``quads``: of the chain ``evaluator`` evaluated last (its disagreement images, not
    rendered again)."""
    if quads is not None:
        evaluator.view_costs(quads)
    return max(float(cv2.distanceTransform(np.pad(diff, 1), cv2.DIST_L2, 3).max())
               for diff in evaluator.last_diffs())


_warmed = False
RESOLVED_END_M = 0.002
"""An "ambiguous" answer whose one alternative is a rival (its tip more than DISTINCT_TIP_M
away) and, made the chain the estimator outputs (the strip from its plate fit), ends within
this of the answer's end [m] no longer has a rival (:func:`_cheapest_first`).
sim-chain-c2-981000: the rival, a plate fit 14 mm away, ended within 0.5 mm of the answer
as a strip. Not DISTINCT_TIP_M (10 mm), which says when two ends are distinct, not when
they are one: 2 mm is a few times the spread of one answer's tip between the estimator's
looks. (No capture seen between 2 and 10 mm; the choice is the cautious one.)"""


def warm() -> None:
    """Pay the default method's one-off costs of a process before any clock starts: the
    compiled kernels (see :func:`_kernels.warm`) and OpenCV's first calls of the filters a
    view's preparation uses (measured ~2 ms on the first fit of a process, then never)."""
    global _warmed
    _kernels.warm()
    if _warmed:
        return
    _warmed = True
    mask = np.zeros((24, 32), bool)
    mask[8:16, 6:26] = True
    ignore = np.zeros_like(mask)
    ignore[:, :4] = True
    camera = Camera("warm", 32, 24, np.array([[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]]))
    for view in (View(camera, mask), View(camera, mask, ignore)):
        prepare(view)


def _cost_roi(view: View, quads: np.ndarray) -> tuple[int, int, int, int] | None:
    """The smallest image rectangle (x0, y0, x1, y1) holding both the observed mask and the
    model's quads (m, 4, 3) in ``view``: every pixel outside it is background in both, so
    the cost there equals the full image's and renders far fewer pixels. None (the whole
    image) when the model does not project to finite pixels."""
    px = project_quads(view.camera, quads).reshape(-1, 2)
    if not np.all(np.isfinite(px)):
        return None
    x, y, w, h = cv2.boundingRect(view.mask.view(np.uint8))
    cam = view.camera
    lo = np.floor(px.min(axis=0)).astype(int) - 2
    hi = np.ceil(px.max(axis=0)).astype(int) + 3
    x0, y0 = max(0, min(x, lo[0])), max(0, min(y, lo[1]))
    x1, y1 = min(cam.width, max(x + w, hi[0])), min(cam.height, max(y + h, hi[1]))
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _costed(capture: Capture, angles: np.ndarray):
    """The chain's shape, its per-view silhouette costs (eq. 7), rendered only where the
    mask or the model is, and the evaluator that did it."""
    shape = forward_kinematics(capture.tape, angles)
    quads = shape.quads()
    evaluator = _evaluator(capture, quads)
    return shape, evaluator.view_costs(quads), evaluator


def _evaluator(capture: Capture, quads: np.ndarray) -> CostEvaluator:
    """An evaluator of ``capture``'s views rendering only where the mask or ``quads`` are."""
    return CostEvaluator([make_target(v, roi=_cost_roi(v, quads)) for v in capture.views], capture.scene)


def _seen_models(evaluator: CostEvaluator, quads: np.ndarray, cells: int = OCCLUSION_CELLS) -> list[np.ndarray]:
    """Each view's silhouette of ``quads`` where its pixels are known (not ignored); a plate
    a scene box's edge crosses cut into ``cells`` x ``cells`` cells."""
    return [m if t.valid is None else m & t.valid
            for m, t in zip(evaluator.model_masks(quads, cells=cells), evaluator.targets)]


def _seen_view(capture: Capture, quads: np.ndarray) -> tuple[CostEvaluator, list[np.ndarray]]:
    """An evaluator rendering only where the mask or ``quads`` (m, 4, 3) are, and each
    view's silhouette of them where its pixels are known."""
    evaluator = _evaluator(capture, quads)
    return evaluator, _seen_models(evaluator, quads)


def _offsets(capture: Capture, quads: np.ndarray, seen: tuple | None = None) -> np.ndarray:
    """Per view, the mean boundary distance [px] between ``quads``' (m, 4, 3) silhouette and
    the observed one (the verdict's measure, :func:`verdict.view_offsets`); ``seen``: their
    :func:`_seen_view` when already made."""
    evaluator, models = _seen_view(capture, quads) if seen is None else seen
    return view_offsets(evaluator.view_costs(quads), [t.observed for t in evaluator.targets], models)


def _judge(capture: Capture, evaluator: CostEvaluator, view_costs: np.ndarray, shape, tip_position: np.ndarray,
           tip_rotation: np.ndarray, best_cost: float, hypotheses: list, strip_shape=None):
    """(the :class:`~verdict.Judgement` of the output ``shape``, its verdict and reason
    final here, and the alternatives weighed) for the ``shape`` whose
    ``view_costs`` ``evaluator`` gave; ``best_cost``: the plate fit's eq.-11 cost, the
    scale of the ``hypotheses`` [:class:`Alternative`], those within the ambiguity margin
    of it weighed; ``strip_shape``: the strip the tip frame comes from, whose fit to the
    views may stand for the plate chain's (:func:`verdict.explaining_offsets`)."""
    near = [h for h in hypotheses if is_close_alternative(h.cost, best_cost)]
    targets = evaluator.targets
    quads = shape.quads()
    models = _seen_models(evaluator, quads)
    strip_offsets = None
    if strip_shape is not None:
        # The strip's silhouettes, rendered (when asked for) once for its offsets and its base.
        strip_quads = strip_shape.quads()
        strip_view = functools.cache(lambda: _seen_view(capture, strip_quads))
        strip_offsets = lambda: _offsets(capture, strip_quads, strip_view())  # noqa: E731
    j = assess(capture.views, capture.scene, capture.tape.width, view_costs, [t.observed for t in targets],
               models, [(t.x0, t.y0) for t in targets], tip_position, tip_rotation, best_cost,
               [(a.cost, a.tip_position) for a in near], strip_offsets,
               _cut_px(capture, evaluator, shape, tip_position, tip_rotation) if capture.scene else None)
    verdict, reason = j.verdict, j.reason
    base_px = float("nan")
    if verdict is Verdict.OK:
        # The base is fixed: the model must meet the observed tape there in every view. (Of
        # the plate chain, or of the strip where the strip explained the views for it.)
        base = _base(capture, evaluator, models, quads)
        if j.by_strip and strip_shape is not None:
            base = np.minimum(base, _base(capture, *strip_view(), strip_quads))
        worst = int(np.argmax(base))
        base_px = float(base[worst])
        if base[worst] > BASE_OFFSET_PX:
            verdict, reason = Verdict.POOR_FIT, (
                f"view {worst} ({capture.views[worst].camera.name}) does not meet the tape at its base: mean "
                f"boundary distance {base[worst]:.1f} px there > {BASE_OFFSET_PX:g} px (a camera's calibration or "
                f"the base's pose in the cell file is off?)")
    if verdict is Verdict.OK:
        bend, joint = edgewise_bend(shape.frames)
        if bend > EDGEWISE_MAX_DEG:
            # A tape hardly bends within its own plane: no tape takes this shape.
            verdict, reason = Verdict.POOR_FIT, (f"the shape {EDGEWISE} by {bend:.0f} deg at joint {joint} (> "
                                                 f"{EDGEWISE_MAX_DEG:g} deg): not a shape a tape takes")
    return dataclasses.replace(j, verdict=verdict, reason=reason, base_px=base_px), tuple(near)


def _cut_px(capture: Capture, evaluator: CostEvaluator, shape, tip_position: np.ndarray,
            tip_rotation: np.ndarray):
    """view k -> :func:`verdict.unexplained_cut_px` of ``shape`` (its tip frame
    ``tip_position``, ``tip_rotation``) in ``evaluator``'s crops; the chain before its last
    plate drawn (cut finely, BASE_OCCLUSION_CELLS) only where a view asks."""
    body = shape.quads()[:-1]
    half = 0.5 * capture.tape.width * tip_rotation[:, 1]
    tip_edge = np.array([tip_position - half, tip_position + half])
    base_edge = np.array([shape.left[0], shape.right[0]])

    @functools.cache
    def body_hidden() -> list[np.ndarray]:
        seen = evaluator.model_masks(body, cells=BASE_OCCLUSION_CELLS)      # boxes only, not ignore masks
        return [full & (1 - s) for full, s in zip(evaluator.model_masks(body, occluded=False), seen)]

    def cut_px(k: int) -> float:
        t = evaluator.targets[k]
        return unexplained_cut_px(capture.views[k], capture.scene, t.observed, (t.x0, t.y0), base_edge, tip_edge,
                                  lambda: body_hidden()[k])

    return cut_px


BASE_OCCLUSION_CELLS = 12
"""Cells along and across a plate (2.5 mm of a 30 mm one) in which a box's edge cuts the
model for the base check (:func:`_base`), where the fit's 3 (``OCCLUSION_CELLS``) put the
cut up to a third of a plate from where the box hides the tape: at a part's edge, next to
the tape's base, the first plate's cell drawn whole though the part hid its first few mm
left 10 px of model the view did not show, and the base check refused right answers
(part-993053, 6.5 px, 0.4 mm off; the base check keeps BASE_OCCLUDED_PX clear of where the
model is hidden, and the coarse cut hid almost nothing there)."""


def _base(capture: Capture, evaluator: CostEvaluator, models: list | None, quads: np.ndarray) -> np.ndarray:
    """:func:`verdict.base_offsets` of ``quads`` whose seen silhouettes ``models`` are
    ``evaluator``'s crops (None: not drawn yet); with scene boxes, of the model cut finer
    where a box hides it (BASE_OCCLUSION_CELLS)."""
    targets = evaluator.targets
    if capture.scene:
        models = _seen_models(evaluator, quads, BASE_OCCLUSION_CELLS)
    elif models is None:
        models = _seen_models(evaluator, quads)
    return base_offsets(capture.views, capture.tape.base_position, [t.observed for t in targets], models,
                        evaluator.model_masks(quads, occluded=False), [(t.x0, t.y0) for t in targets])


def _alternative(capture: Capture, cost: float, angles: np.ndarray) -> Alternative:
    """The plate chain ``angles`` (eq.-11 ``cost``) as an :class:`Alternative`, its tip frame
    the chain's end."""
    shape = forward_kinematics(capture.tape, angles)
    return Alternative(cost, shape.nodes[-1].copy(), shape.frames[-1].copy(), angles)


def _hypotheses(capture: Capture, found: list, best_cost: float) -> list[Alternative]:
    """The hypotheses ``found`` [(eq.-11 cost, angles)] within the ambiguity margin of
    ``best_cost``, as :class:`Alternative` (their tip frames the plate chains' ends)."""
    return [_alternative(capture, cost, a) for cost, a in found if is_close_alternative(cost, best_cost)]


def _second_look(first: Estimate, second: Estimate, folded: bool) -> Estimate:
    """Which answer stands after the second look: for a fold, the second's; else the one
    that explains the views better; an "ok" second look that explains them nearly as well
    (the ambiguity margin) only where its tip is within DISTINCT_TIP_M of the first's (the
    same hypothesis, now located). Further away, the first look, which explains the views
    better and did not locate the end there, stands as the estimate, ambiguous (or poor_fit,
    its reason kept), the second its alternative (a wrong "ok" 16.7 mm off on a fresh
    synthetic capture with the part in front: the first look's shape, 0.8 mm off, was
    hidden and cost less)."""
    if folded or second.cost < first.cost:
        return _rivals_kept(first, second)
    if not second.actionable or not is_close_alternative(second.cost, first.cost):
        return first
    d = float(np.linalg.norm(second.tip_position - first.tip_position))
    if d <= DISTINCT_TIP_M:
        return _rivals_kept(first, second)
    alternatives = tuple(first.alternatives)
    if all(np.linalg.norm(a.tip_position - second.tip_position) > DISTINCT_TIP_M for a in alternatives):
        alternatives = (Alternative(second.cost, second.tip_position, second.tip_rotation, second.angles),) + alternatives
    if first.verdict is Verdict.POOR_FIT:
        return dataclasses.replace(first, alternatives=alternatives)   # its reason stands (the needle reads it)
    return dataclasses.replace(first, verdict=Verdict.AMBIGUOUS, alternatives=alternatives,
                               verdict_reason=(f"a shape with its tip {1e3 * d:.0f} mm away explains the views nearly "
                                               f"as well (cost {second.cost:.3f} vs {first.cost:.3f}) and locates "
                                               f"the end where this one does not"))


def _rivals_kept(first: Estimate, second: Estimate) -> Estimate:
    """``second`` (the answer after the second look), ``ambiguous`` where it is "ok" while
    an alternative of ``first`` explains the views nearly as well as it does, with its tip
    more than DISTINCT_TIP_M from the second's: the thorough look does not refine again what
    the first look's wide search found, and may not make a rival vanish by not finding it
    (a wrong "ok" 24 mm off on a fresh clean capture, 866008: the first look was ambiguous
    with a shape 3.5 mm off costing 0.049 against 0.043; the second, at the same tip and
    0.043, had lost it). The margin is taken on the answer's own cost (its output chain's),
    which may be above the plate fit's cost the verdict weighs alternatives against: the
    rule errs towards "ambiguous". The answer's own alternatives are not kept: an "ok"
    answer has none within the margin. (An answer refused for bending within the tape's
    plane, verdict.EDGEWISE_MAX_DEG, stays refused: made ambiguous, the needle could confirm
    its tip and a robot act on a shape no tape takes.)"""
    if second.verdict is not Verdict.OK:
        return second
    rivals = tuple(a for a in first.alternatives
                   if rival_reason(second.cost, second.tip_position, [(a.cost, a.tip_position)]))
    if not rivals:
        return second
    reason = rival_reason(second.cost, second.tip_position, [(a.cost, a.tip_position) for a in rivals])
    return dataclasses.replace(second, verdict=Verdict.AMBIGUOUS, alternatives=rivals, verdict_reason=reason)


def _garbage(capture: Capture, faults: list, method: str, start: float, config: FitConfig) -> Estimate:
    """A "poor_fit" estimate of a capture whose views ``faults`` [(index, why)] hold no tape
    silhouette: the fit of the other views (a straight tape when none is left), costed on
    every view; nothing may act on it."""
    bad = {k for k, _ in faults}
    rest = [v for k, v in enumerate(capture.views) if k not in bad]
    if rest:
        # Its verdict is poor_fit whatever the other views' fit says: no second look.
        est = estimate(dataclasses.replace(capture, views=rest), method, config=config, second_look=False)
        angles, tip = est.angles, (est.tip_position, est.tip_rotation)
    else:
        angles = np.zeros((capture.tape.n, 3))
    shape, view_costs, _ = _costed(capture, angles)
    if not rest:
        tip = (shape.nodes[-1].copy(), shape.frames[-1].copy())
    k, why = faults[0]
    reason = f"view {k} ({capture.views[k].camera.name}) is not a tape silhouette: {why}"
    return Estimate(shape.nodes, angles, tip[0], tip[1], combine(view_costs), view_costs,
                    time.perf_counter() - start, method, verdict=Verdict.POOR_FIT, verdict_reason=reason,
                    view_offsets_px=np.full(len(capture.views), np.inf))


def estimate(capture: Capture, method: str = "default", callback: Callback | None = None,
             thorough: bool = False, config: FitConfig = DEFAULT, second_look: bool = True) -> Estimate:
    """Fit the plate chain to ``capture``'s silhouettes.

    method: "default" (ours) or "paper" (the reference reproduction).
    callback(iteration, cost, angles (n, 3)): called per optimiser iteration with the
    silhouette cost (eq. 11) of that iterate; for the default method after the fit (the
    winner's iterations, costed once the clock has stopped), for the paper's method live
    (the objective of the node being optimised).
    second_look: an unsure estimate (and an "ok" fold, an end seen end-on, a view still
    explained only roughly, an end located only as a hook across its tip edge) gets a
    second, thorough look before the answer (below); False
    answers from the first look. An answer that may be a calibration error's
    (:func:`_calibration_suspect`: ``poor_fit``, ``hidden`` or ``ambiguous`` off the tape's
    base, "ok" met at its base only roughly) is then estimated again with the cameras'
    rotations corrected from the views
    (:func:`_recalibrated`; not with ``second_look`` False, ``thorough`` or the paper's
    method); where that answer stands, its view costs and offsets are on the corrected
    cameras and the callback has seen the first look's iterations.
    Returns an :class:`Estimate`; ``time_s`` is the fitting time alone.
    """
    if method not in ("default", "paper"):
        raise EstimateError(f"unknown estimation method {method!r} (use 'default' or 'paper')")
    if not capture.views:
        raise EstimateError(f"{capture.name}: no camera views to fit")
    if method == "default":
        warm()  # once per process: compiling/loading the kernels is not fitting
    made: list = []
    est = _look(capture, method, callback, thorough, config, second_look, made=made)
    if method == "default" and second_look and not thorough and _calibration_suspect(capture, est):
        est = _recalibrated(capture, est, config, made[0].fields if made else None)
    return est


HOOKED_ACROSS_LOOK = True
"""An "ok" estimate one of whose locating views sees its end only as a hooked end with the tip
edge's both corners at the outline and its middle inside the silhouette
(``verdict.Judgement.hooked_across``) gets the second look: fresh part-1017027 (3 cameras)
was "ok" 9.45 mm off so, and the second look finds its end 1.9 mm off. On the development
captures of 976000- and 981000- (every bench kind, ~1,080) it changed no answer; refusing
such ends instead turned 24 right "ok"s into ``hidden``."""


SELF_CALIBRATE = True
"""With two cameras or more (``recalibrate.MIN_VIEWS``), a ``poor_fit`` answer, and a
``hidden`` or ``ambiguous`` one whose model misses the tape at its base, is estimated again
with each camera's rotation corrected from the views (:mod:`estimator.recalibrate`); the
corrected answer stands where it is "ok" and explains the views clearly better
(:func:`_recalibrated`). An "ok" answer only where its base is met to more than
``recalibrate.OK_BASE_PX`` and the corrected answer explains the views far better
(``recalibrate.OK_MIN_GAIN``): corrections of every "ok" answer on calibrated simulated captures
(976000-, 981000-, 3 cameras) made those whose views were explained only roughly (a tape that
is not the model) 1-2 mm worse. Every ``ambiguous`` answer, base or not, made one
3-camera shell capture turned 0.5 deg "ok" 6.2 mm off; the base asked for, two-camera
simulated captures with both cameras turned 0.5 deg (development 916500-916529) were "ok" 27
of 30 (0 before), 0.10-2.26 mm off, 14 of them from ``hidden`` or ``ambiguous``, and 1,886
calibrated development captures of every kind (1043000-, 1044000-) gave the same answers."""


def _calibration_suspect(capture: Capture, est: Estimate) -> bool:
    """Whether ``est`` (the answer of :func:`_look`) may be a calibration error's: cameras
    (recalibrate.MIN_VIEWS or more) whose masks were sound (finite offsets), and the answer
    ``poor_fit``, or ``hidden`` or ``ambiguous`` with a view that does not meet the tape at
    its base (BASE_OFFSET_PX, the "ok" answers' base check: the base cannot move), or "ok"
    with a view that meets it only to more than ``recalibrate.OK_BASE_PX``."""
    if not (SELF_CALIBRATE and len(capture.views) >= recalibrate.MIN_VIEWS
            and bool(np.all(np.isfinite(np.asarray(est.view_offsets_px, float))))):
        return False
    if est.verdict is Verdict.POOR_FIT:
        return True
    if est.verdict is Verdict.OK:
        return bool(est.base_offset_px > recalibrate.OK_BASE_PX)
    if est.verdict not in (Verdict.HIDDEN, Verdict.AMBIGUOUS):
        return False
    quads = forward_kinematics(capture.tape, est.angles).quads()
    return bool(np.max(_base(capture, _evaluator(capture, quads), None, quads)) > BASE_OFFSET_PX)


def _recalibrated(capture: Capture, est: Estimate, config: FitConfig, fields: list | None = None) -> Estimate:
    """The answer with every camera's rotation corrected from the views
    (:func:`recalibrate.camera_corrections`, from ``est``'s chain) where it is "ok" and
    explains the views clearly better (its cost at most ``recalibrate.MIN_GAIN`` of
    ``est``'s), its reason naming the corrections; for an "ok" ``est``, where it is "ok", explains
    them far better (``recalibrate.OK_MIN_GAIN``) and meets the base to within
    ``recalibrate.OK_BASE_PX`` (where it explains them far better but is not "ok", ``est`` made
    "ambiguous" with the corrected shape as an alternative); else ``est``. A correction beyond
    ``recalibrate.MAX_DEG`` for any camera is not taken, nor one whose answer leaves a view
    explained to more than ``recalibrate.CORRECTED_OFFSET_PX`` or whose shape the cameras as
    given explain nearly as well (``recalibrate.SUPPORT``: the gain is then the second
    search's, not the correction's). The time of both counts. The answer's nodes and tip are in
    the world frame, which the tape's base anchors; its views' costs and offsets are on the
    corrected cameras. ``fields``: the capture's views as the first look prepared them."""
    start = time.perf_counter()
    rotations = recalibrate.camera_corrections(capture, est.angles, config, fields)
    degrees = np.degrees(np.linalg.norm(rotations, axis=1))
    spent = time.perf_counter() - start
    if np.any(degrees > recalibrate.MAX_DEG):
        return dataclasses.replace(est, time_s=est.time_s + spent)
    # (``callback`` saw the first look's iterations; the corrected look's are in ``trace``.)
    again = _look(recalibrate.corrected(capture, rotations), "default", None, False, config, True)
    was_ok = est.verdict is Verdict.OK
    gain = recalibrate.OK_MIN_GAIN if was_ok else recalibrate.MIN_GAIN
    time_s = est.time_s + spent + again.time_s
    if not again.cost <= gain * est.cost or (again.verdict is not Verdict.OK and not was_ok):
        return dataclasses.replace(est, time_s=time_s)
    turns = ", ".join(f"{v.camera.name} {d:.2f}" for v, d in zip(capture.views, degrees))
    if was_ok and again.verdict is not Verdict.OK:
        # The corrected cameras explain the views far better but do not judge their answer
        # "ok": the first answer is not acted on. It stays the answer (on the cameras as
        # calibrated, which the needle's refits use), "ambiguous", the corrected answer's
        # shape its alternative, costed on those cameras (dev chain-c2-1046125, both cameras
        # turned 0.3 deg: "ok" 9.5 mm off; corrected, ambiguous 0.8 mm off).
        _, view_costs, _ = _costed(capture, again.angles)
        alternative = Alternative(combine(view_costs), again.tip_position, again.tip_rotation, again.angles)
        reason = (f"the cameras turned by {turns} deg explain the views far better (cost {again.cost / est.cost:.2f} "
                  f"of this answer's) and then the answer is {again.verdict.value}: {again.verdict_reason}")
        alternatives = tuple(sorted((alternative,) + tuple(est.alternatives), key=lambda a: a.cost))
        return dataclasses.replace(est, verdict=Verdict.AMBIGUOUS, verdict_reason=reason, alternatives=alternatives,
                                   time_s=est.time_s + time.perf_counter() - start)
    if was_ok and not again.base_offset_px <= recalibrate.OK_BASE_PX:
        return dataclasses.replace(est, time_s=time_s)   # the corrected cameras do not meet the base better
    if not bool(np.max(np.asarray(again.view_offsets_px, float)) <= recalibrate.CORRECTED_OFFSET_PX):
        return dataclasses.replace(est, time_s=time_s)   # a view still explained only roughly
    # The gain must be the corrected cameras': the corrected answer's shape on the cameras as
    # given, costed likewise (recalibrate.SUPPORT).
    _, given_costs, _ = _costed(capture, again.angles)
    time_s = est.time_s + time.perf_counter() - start
    if not again.cost <= recalibrate.SUPPORT * combine(given_costs):
        return dataclasses.replace(est, time_s=time_s)
    given = (f"its base {est.base_offset_px:.1f} px" if was_ok
             else f"its worst view {float(np.max(est.view_offsets_px)):.1f} px")
    # (Not the first answer's reason: its words are read elsewhere, cell.probe.end_measurable.)
    reason = (f"the cameras turned from their calibration by {turns} deg, fitted to the views ({est.verdict.value} "
              f"with the calibration as given, {given})")
    return dataclasses.replace(again, verdict_reason=reason, time_s=time_s)


def _look(capture: Capture, method: str, callback: Callback | None, thorough: bool, config: FitConfig,
          second_look: bool, first: FirstStage | None = None, final: bool = True, made: list | None = None) -> Estimate:
    """:func:`estimate` once its arguments are checked; ``first``: the capture's
    :class:`FirstStage` when the first look made it (its masks were judged sound then);
    ``final``: the answer (not the second look inside it), whose alternatives may not
    explain the views better than it does (:func:`_cheapest_first`); ``made``: a list this
    look's :class:`FirstStage` is appended to (for the cameras' correction, which reads its
    prepared views)."""
    from .paper import fit_paper

    start = time.perf_counter()
    if first is None:
        faults = [(k, mask_fault(v)) for k, v in enumerate(capture.views)]
        faults = [(k, f) for k, f in faults if f]
        if faults:
            return _garbage(capture, faults, method, start, config)
    fallback, found, strip = None, [], None
    if method == "default":
        first = FirstStage(capture, Chain(capture.tape, cfg=config), config) if first is None else first
        if made is not None:
            made.append(first)
        angles, trace, evaluations, fallback, found, strip = fit_default(capture, thorough=thorough, cfg=config,
                                                                         first=first)
    else:
        angles, history, evaluations = fit_paper(capture, callback)
    if fallback is not None:
        plate_cost, steps = fallback
        output = angles
        k, angles, shape, view_costs, evaluator = _within_guard(capture, [lambda: output] + steps, plate_cost,
                                                                config)
        if k:
            trace = trace[:-1] + ([angles] if k < len(steps) else [])
        if k == len(steps):
            strip = None   # back to the plate fit: the strip went astray
    else:
        shape, view_costs, evaluator = _costed(capture, angles)
    plate_cost = fallback[0] if fallback is not None else combine(view_costs)
    # The tip frame: the strip's end (it follows a tip that curls within one plate, where
    # the last plate is a chord), else the plate chain's F_n at P_C[n].
    tip_position, tip_rotation = (strip.tip if strip is not None
                                  else (shape.nodes[-1].copy(), shape.frames[-1].copy()))
    scale = min(plate_cost, combine(view_costs))
    j, alternatives = _judge(
        capture, evaluator, view_costs, shape, tip_position, tip_rotation, scale, _hypotheses(capture, found, scale),
        None if strip is None else strip.fine)
    verdict, reason, tip_views, offsets = j.verdict, j.reason, j.tip_views, j.offsets_px
    elapsed = time.perf_counter() - start
    if method == "default":
        # The cost per iteration on the eq.-11 scale, for recordings and plots: computed when
        # read (:class:`CostHistory`), or now for a callback.
        history = CostHistory(lambda: _trace_costs(capture, trace))
        if callback is not None:
            for k, (a, c) in enumerate(zip(trace, history), 1):
                callback(k, c, a)
    est = Estimate(shape.nodes, angles, tip_position, tip_rotation, combine(view_costs),
                   view_costs, elapsed, method, history, evaluations, verdict, reason, tip_views, alternatives,
                   trace=tuple(trace) if method == "default" else (), view_offsets_px=offsets,
                   base_offset_px=j.base_px)
    # A second, more thorough look (a larger global search on the widest grid, always)
    # before answering, for an unsure estimate, for an "ok" fold, over the whole tape or at
    # its end (its alternatives, the shapes folded the other way, are weighed afresh), and
    # for an "ok" end that a camera sees end-on (END_ON_DEG: its depth along that line is
    # less constrained), and for an "ok" one of whose views is still explained only to more
    # than FitConfig.recheck_offset_px (the search may have stopped on a wrong branch that
    # a calibration error or noise lets pass), and for an "ok" end that a view locates only
    # as a hook across its tip edge (HOOKED_ACROSS_LOOK). For a fold its answer stands; for the others when it is "ok"
    # (judged afresh) or explains the views better (:func:`_second_look`). The time of both
    # looks counts. What the looks compute alike (:class:`FirstStage`) is done once.
    ok = verdict is Verdict.OK
    folded = ok and (float(shape.frames[0][:, 0] @ tip_rotation[:, 0]) < np.cos(np.radians(FOLD_DEG))
                     or float(shape.frames[-2][:, 0] @ tip_rotation[:, 0]) < np.cos(np.radians(END_FOLD_DEG)))
    seen_end_on = ok and any(end_on(v, tip_position, tip_rotation) for v in capture.views)
    rough = ok and not bool(np.all(np.asarray(offsets, float) <= config.recheck_offset_px))
    # An "ok" whose views only the strip explains (verdict.explaining_offsets) was a poor fit
    # of the plate chain: it gets the look a poor fit gets.
    unsure = verdict in (Verdict.POOR_FIT, Verdict.AMBIGUOUS, Verdict.HIDDEN) or (ok and j.by_strip)
    across = ok and HOOKED_ACROSS_LOOK and j.hooked_across
    looked = method == "default" and second_look and not thorough and (folded or seen_end_on or unsure or rough
                                                                       or across)
    if looked:
        # An "ok" estimate (a fold, an end seen end-on, a rough view) gets a smaller thorough beam
        # (FitConfig.fold_beam).
        look = dataclasses.replace(config, thorough_beam=config.fold_beam) if ok and not j.by_strip else config
        if verdict is not Verdict.HIDDEN:
            # Hooked-back ends only where the end is out of sight: a hooked plate fit whose
            # strip cannot follow it lowered the scale alternatives are weighed on, and
            # made an ambiguous part capture 9.5 mm off "ok" (fresh 860000).
            look = dataclasses.replace(look, hook_bends=())
        second = _look(capture, method, None, True, look, True, first, final=False)
        est = dataclasses.replace(_second_look(est, second, folded), time_s=est.time_s + second.time_s)
    if final and looked and DEPTH_PROBES and est.verdict is Verdict.OK:
        est = _probed(capture, est, first, config)
    return _cheapest_first(capture, est, first, config) if final and method == "default" else est


DEPTH_PROBES = True
"""An answer "ok" after the second look (whatever sent it there: a fold, an end a camera sees
end-on, a view explained only roughly, an end located as a hook across its tip edge, an
unsure first answer) is probed in depth before it is given: the plate chain refitted from
it with its end pulled to its tip moved DEPTH_PROBE_M along each camera's line of sight to
it, either way (its depth alone: DEPTH_PROBES_ALONG), then let go (:func:`_depth_probes`).
A probe that ends more than DISTINCT_TIP_M from the answer and explains the views better
(a lower eq.-11 cost than the answer's chain costed on the same masks, and than the probes
that went back to the answer: PROBES_AT_THE_ANSWER) is a shape the searches missed: the answer is
``ambiguous``, and the probe becomes the answer where the chain the estimator outputs from
it explains them better too (:func:`_cheapest_first`). Fresh shell-c2-1061012 (2 cameras,
an arch whose end hangs beside its base) was "ok" 16.3 mm off: a probe along one camera's
line of sight found a shape 3.4 mm from the true end at 0.91 of the answer's cost; fresh
part-1052042, "ok" 14.8 mm off, probes at 0.81-0.88. (Probes within the ambiguity margin
but costlier, ``verdict.is_close_alternative``, made two right 3-camera shell answers of
the development captures 1044000- and 1061000- ``ambiguous``, at 1.02 and 1.25 of their
costs.) An answer made ``ambiguous`` here is no longer an "ok" one the cameras' correction
tries for a base met only roughly (``_calibration_suspect``): it is corrected only where
its base is off by more than BASE_OFFSET_PX, as other unsure answers. Off: no probes."""
DEPTH_PROBES_ALONG = True
"""The probes pull only the end's depth along each camera's line of sight to the moved tip,
and the views place it across the line; off: the end pulled to the moved tip itself (its
image in that camera held). Fresh clean-1091054 (2 cameras) was "ok" 12.0 mm off, and its
calib, distorted and calib_rot captures too (11.9-12.9 mm, a wrong "ok" in each kind): the
true shape explained the views better (0.020 against 0.030), but the probes pulled to a
point 2 mm from its end held bodies that cost 0.06 and went back to the answer when let
go; pulled in depth alone, the probe along the second camera's line ended 0.9 mm from the
true end at 0.0205. Pulled in depth alone, the probes find the shapes the point probes
found too (shell-c2-1061012 and part-1052042 ambiguous, 2.0 and 14.8 mm off, where the
point probes made them 3.4 and 21.5 mm off), and both kinds together (twice the probes)
gave the same answers as these alone on 1,957 development captures (1078000-, 1084000-,
1088000-, 1091000-)."""
PROBES_AT_THE_ANSWER = True
"""A probe is a rival of the answer only where it explains the views better than the answer's
own chain and than every probe that went back to the answer's end (within DISTINCT_TIP_M):
those are the answer's plate chain refitted, costed like the probes, where the answer's
chain is the strip's and may cost more than a plate fit does. With the probes in depth
alone (DEPTH_PROBES_ALONG), right answers whose strip chain cost 1.7-1.8 times their plate
fit were made "ambiguous" by a probe 13-15 mm away costing less than the strip chain but
more than the probes back at the answer (part-1091016 0.066 against 0.101 and 0.057,
shell-c2-1088007 0.069 against 0.078 and 0.045)."""
DEPTH_PROBE_M = 0.012
"""How far [m] the probes move the answer's tip along each camera's line of sight (more than
DISTINCT_TIP_M: a shape that stays there is a distinct one)."""
DEPTH_PROBE_PX_PER_M = 20000.0
"""Residual [px] per metre between a probe's chain end and its point while it is pulled
there (as the needle's touch, ``touch.TOUCH_PX_PER_M``)."""
DEPTH_PROBE_ITERATIONS = 8
"""Levenberg-Marquardt iterations pulling the probes, and again letting them go."""


def _depth_probes(capture: Capture, first: FirstStage, est: Estimate, config: FitConfig) -> list:
    """The plate chains refitted from ``est``'s with their ends pulled to its tip moved
    DEPTH_PROBE_M along each camera's line of sight, either way (in depth along that line
    alone: DEPTH_PROBES_ALONG), then let go: [(eq.-11 cost, angles (n, 3))], all refined
    together."""
    chain = first.chain
    points, along = [], []
    for v in capture.views:
        ray = est.tip_position - v.camera.center
        ray = ray / max(float(np.linalg.norm(ray)), 1e-12)
        points += [est.tip_position - DEPTH_PROBE_M * ray, est.tip_position + DEPTH_PROBE_M * ray]
        along += [ray if DEPTH_PROBES_ALONG else np.zeros(3)] * 2
    points = np.array(points)
    end = chain.samples + chain.n                  # P_C[n] among the chain's points
    start = np.repeat(np.asarray(est.angles, float).reshape(1, -1), len(points), axis=0)
    params, _, _ = levenberg_marquardt(chain, first.fields, start, DEPTH_PROBE_ITERATIONS, cfg=config,
                                       pull=(end, DEPTH_PROBE_PX_PER_M, points, np.array(along)))
    params, _, _ = levenberg_marquardt(chain, first.fields, params, DEPTH_PROBE_ITERATIONS, cfg=config)
    angles = params.reshape(len(points), chain.n, 3)
    return list(zip(first.silhouette_costs(angles).tolist(), angles))


def _probed(capture: Capture, est: Estimate, first: FirstStage, config: FitConfig) -> Estimate:
    """``est`` ("ok") after its depth probes (DEPTH_PROBES): ``ambiguous``, with the
    probes that end more than DISTINCT_TIP_M from it and from each other and explain the
    views better than it among its alternatives, where there are any. The time counts."""
    start = time.perf_counter()
    tips = [est.tip_position] + [a.tip_position for a in est.alternatives]
    # The answer's chain costed as the probes are (the first stage's cleaned masks and
    # crops, which may differ from the answer's own by a few per cent on noisy masks).
    own = float(first.silhouette_costs(np.asarray(est.angles, float)[None])[0])
    probes = _depth_probes(capture, first, est, config)
    if PROBES_AT_THE_ANSWER:
        # The probes let go back at the answer are its plate chain refitted, costed as the
        # others are: where one explains the views better than the answer's own chain (the
        # strip's, whose cost may be above a plate fit's), a probe must beat it too.
        ends = first.chain.tips(np.array([angles for _, angles in probes]))
        back = [cost for (cost, _), end in zip(probes, ends)
                if np.linalg.norm(end - est.tip_position) <= DISTINCT_TIP_M]
        own = min([own] + back)
    rivals = []
    for cost, angles in sorted(probes, key=lambda x: x[0]):
        if cost >= own:
            break
        rival = _alternative(capture, cost, angles)
        if all(np.linalg.norm(rival.tip_position - t) > DISTINCT_TIP_M for t in tips):
            rivals.append(rival)
            tips.append(rival.tip_position)
    spent = time.perf_counter() - start
    if not rivals:
        return dataclasses.replace(est, time_s=est.time_s + spent)
    alternatives = tuple(sorted(list(est.alternatives) + rivals, key=lambda a: a.cost))
    reason = rival_reason(est.cost, est.tip_position, [(a.cost, a.tip_position) for a in rivals])
    return dataclasses.replace(est, alternatives=alternatives, verdict=Verdict.AMBIGUOUS, verdict_reason=reason,
                               time_s=est.time_s + spent)


def _within_guard(capture: Capture, chains: list, plate_cost: float, config: FitConfig):
    """The first of ``chains`` (functions giving angles (n, 3), the plate fit last) that
    explains the views within FitConfig.strip_guard times the plate fit's eq.-11 cost
    ``plate_cost`` as the search gave it, else the last: (its index, angles, shape, view
    costs, evaluator). Before it, the chains taken from the strip explain the views far worse
    than the plate fit: the tip-frame pull overshot or the strip's fit went astray."""
    for k, make in enumerate(chains):
        angles = make()
        shape, view_costs, evaluator = _costed(capture, angles)
        if k == len(chains) - 1 or combine(view_costs) <= config.strip_guard * plate_cost:
            return k, angles, shape, view_costs, evaluator


def _output(capture: Capture, first: FirstStage, alt: Alternative, config: FitConfig):
    """The chain :func:`estimate` outputs from the plate fit of the hypothesis ``alt``, by
    the same stages and guard as its answer (the strip, its tip-frame pull; the chain
    without the pull, then the plate fit: :func:`_within_guard`): (it as an
    :class:`Alternative`, its shape, view costs, evaluator, the strip's shape or None)."""
    chains = [lambda: alt.angles]
    if config.strip:
        strip = first.strip(Chain(capture.tape, cfg=config), alt.angles, config)
        weights = ([config.strip_frame_weight] if config.strip_frame_weight > 0 else []) + [0.0]
        chains = [functools.partial(strip, w) for w in weights] + chains
    k, angles, shape, view_costs, evaluator = _within_guard(capture, chains, alt.cost, config)
    if k < len(chains) - 1:
        made = Alternative(combine(view_costs), strip.tip[0].copy(), strip.tip[1].copy(), angles)
        return made, shape, view_costs, evaluator, strip.fine
    made = Alternative(combine(view_costs), shape.nodes[-1].copy(), shape.frames[-1].copy(), angles)
    return made, shape, view_costs, evaluator, None


def _cheapest_first(capture: Capture, est: Estimate, first: FirstStage, config: FitConfig) -> Estimate:
    """``est`` such that no alternative it reports explains the views better than it does
    (issue 13). An alternative is a plate fit, costed as such; the answer is the chain the
    strip stage made of its own plate fit, whose cost may be above its plate fit's (up to
    FitConfig.strip_guard times). Compared like for like, each alternative cheaper than the
    answer is made the chain the estimator would output from it (:func:`_output`).

    Where one then still costs less, the cheapest becomes the answer, judged afresh, and
    the old answer joins its alternatives. Else, and for the others, each alternative is
    reported as the plate fit it is, with the cost of its output as ``output_cost`` where
    its own cost is below the answer's: its tip is where the needle probes it (reported as
    its output chain instead, an alternative whose plate fit the needle confirmed ended
    near the answer's end, and fresh episodes 941060 and 951030 lost it).

    The swap makes no new "ok" from a different end: where the new judgement is "ok" it is
    "ambiguous" (a search that answered with the costlier shape first is sure of neither;
    the needle may settle it among the shapes, the old answer one of them), but where the
    old answer was "ok" too and ends within DISTINCT_TIP_M of it (the same end, found twice:
    fresh part-948053, 1.2 and 1.7 mm off, 1 mm apart, was a needless refusal), and where
    the old answer was "ambiguous" with this one rival alone, which ends within
    RESOLVED_END_M of it as an output chain (one end, no rival left; the rival's plate fit,
    whose own end was the rival's, is not kept). Else a "hidden" or
    "ambiguous" answer stays one the needle probes ("ambiguous" where the new judgement is
    "poor_fit": every shape probed before is still there). A "poor_fit" answer takes the
    new judgement (its end measured only where that is "poor_fit" for the new end):
    refusing it outright lost a grasp on 945127, whose old answer's end the needle had
    measured. The time counts."""
    cheaper = [k for k, a in enumerate(est.alternatives) if a.cost < est.cost]
    if not cheaper:
        return est
    start = time.perf_counter()
    made = {k: _output(capture, first, est.alternatives[k], config) for k in cheaper}
    k_best = min(made, key=lambda k: made[k][0].cost)
    if made[k_best][0].cost >= est.cost:
        alternatives = tuple(dataclasses.replace(a, output_cost=made[k][0].cost) if k in made else a
                             for k, a in enumerate(est.alternatives))
        return dataclasses.replace(est, alternatives=alternatives, time_s=est.time_s + time.perf_counter() - start)
    alt, shape, view_costs, evaluator, strip_shape = made[k_best]
    cost = combine(view_costs)
    old = Alternative(est.cost, est.tip_position, est.tip_rotation, est.angles)
    # The others as they were, those cheaper than the new answer with their outputs' costs
    # (none below it: the new answer is the cheapest output).
    others = [dataclasses.replace(a, output_cost=made[k][0].cost) if a.cost < cost else a
              for k, a in enumerate(est.alternatives) if k != k_best]
    others = [a for a in others if np.linalg.norm(a.tip_position - alt.tip_position) > DISTINCT_TIP_M]
    others = sorted([old] + others, key=lambda a: a.cost)
    j, _ = _judge(capture, evaluator, view_costs, shape, alt.tip_position, alt.tip_rotation,
                  min(est.alternatives[k_best].cost, cost), others, strip_shape)
    verdict, reason, tip_views, offsets = j.verdict, j.reason, j.tip_views, j.offsets_px
    d = float(np.linalg.norm(old.tip_position - alt.tip_position))
    swapped = (f"the search answered first with a shape whose tip is {1e3 * d:.0f} mm away and explains the "
               f"views worse (cost {old.cost:.3f} vs {cost:.3f})")
    # The same end, found twice (the old answer "ok" too); or the one rival the old answer
    # was ambiguous with ends, made the chain the estimator outputs, where the old answer
    # does (within RESOLVED_END_M): no distinct end is left to be unsure of.
    lone_rival = (est.verdict is Verdict.AMBIGUOUS and len(est.alternatives) == 1
                  and float(np.linalg.norm(est.alternatives[k_best].tip_position - old.tip_position)) > DISTINCT_TIP_M)
    same_end = (est.verdict is Verdict.OK and d <= DISTINCT_TIP_M) or (lone_rival and d <= RESOLVED_END_M)
    probed_before = est.verdict is not Verdict.POOR_FIT
    if (verdict is Verdict.OK and not same_end) or (verdict is Verdict.POOR_FIT and probed_before):
        why = "not sure of either" if verdict is Verdict.OK else f"this one is judged: {reason}"
        verdict, reason = Verdict.AMBIGUOUS, f"{swapped}: {why}"
    elif verdict is Verdict.OK:
        others = [a for a in others if a is not old]   # the same end, found twice
    history = CostHistory(lambda: list(est.history) + [cost])
    return dataclasses.replace(
        est, nodes=shape.nodes, angles=alt.angles, tip_position=alt.tip_position, tip_rotation=alt.tip_rotation,
        cost=cost, view_costs=view_costs, history=history, verdict=verdict, verdict_reason=reason,
        tip_views=tip_views, alternatives=tuple(others), trace=tuple(est.trace) + (alt.angles,),
        view_offsets_px=offsets, base_offset_px=j.base_px, time_s=est.time_s + time.perf_counter() - start)


def _trace_costs(capture: Capture, trace: list) -> list[float]:
    """The eq.-11 cost of each of the angles (n, 3) in ``trace``, rendered only where the
    mask or one of them is (the same costs as on the whole images, :func:`_cost_roi`)."""
    if not trace:
        return []
    quads = np.array([forward_kinematics(capture.tape, a).quads() for a in trace])
    return _evaluator(capture, quads.reshape(-1, 4, 3)).costs(quads).tolist()
