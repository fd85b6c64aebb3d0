"""Every number the default estimator's fit runs on, in one frozen, documented dataclass.

``estimate(capture, config=FitConfig(...))`` fits with other settings; ``DEFAULT`` is the
measured set (README, Benchmarks). The verdict's thresholds are in :mod:`estimator.verdict`.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FitConfig:
    """The fit's settings. Pixels [px], metres [m], radians [rad]."""

    # views and masks (estimator/views.py)
    margin_px: int = 12
    """ROI margin around the observed tape [px]."""
    occluded_margin_px: int = 60
    """ROI margin when an ignore mask may hide part of the tape [px]."""
    speckle_px: int = 25
    """Connected regions (of tape or of background inside it) smaller than this are noise."""
    outline_points: int = 48
    """Observed outline points per view in the coverage term."""
    box_edge_px: float = 3.0
    """Observed outline points this close [px] to a scene box's projected outline are where
    the tape goes behind the box, not the tape's own edge: the coverage term leaves them out."""
    thin_px: float = 15.0
    """A view whose silhouette is on average thinner than this [px] (2 area / perimeter) has
    its robust terms weighted by (thickness / thin_px)^2 (0: off)."""

    # robust residuals (estimator/residuals.py)
    delta_out_px: float = 3.0
    """Huber scale for points outside the silhouette [px]."""
    delta_in_px: float = 1.5
    """Cauchy scale for edge points inside the silhouette (possibly hidden edges) [px]."""
    tip_weight: float = 1.0
    """Weight of the residuals on the last plate's edges and the tip edge (others 1)."""
    angle_prior_px: float = 1.0
    """Residual [px] per radian of every joint angle in the local stage (a weak prior)."""
    penetration_px_per_m: float = 5000.0
    """Residual [px] per metre a chain point lies inside a scene box (1 mm inside costs like
    a boundary 5 px off): the tape cannot pass through the part or the table."""
    edge_t: tuple = (0.25, 0.5, 0.75, 1.0)
    """Edge sample points on each plate (fractions of its length)."""
    tip_t: tuple = (0.1, 0.3, 0.5, 0.7, 0.9)
    """Sample points on the tip edge (fractions of its width)."""
    centre_t: tuple = (0.5, 1.0)
    """Centre-line sample points on each plate (fractions of its length)."""

    crease_t: tuple = (0.25, 0.5, 0.75)
    """The model's outline holds, besides the plates' side, tip and base edges, each joint's
    line across the tape where the tape folds there in the image (the plates either side of
    it on one side of it): where a tape curls towards or away from a camera, the silhouette's
    edge is the fold. Coverage residuals measure the observed outline against it, and these
    sample points along it (fractions of the width) are edge points while it folds. Without
    it a curl's right shape paid for an outline its edges do not reach, and the fit
    preferred a shape ending at the fold. Empty: no joints' lines."""
    strip_crease_t: tuple = (0.25, 0.5, 0.75)
    """The same for the strip's fine chain (``crease_t``)."""

    # global search (estimator/search.py)
    beam: int = 8
    """Partial chains kept per node in the global stage."""
    diverse_m: float = 0.006
    """Plate ends of two kept partial chains differ by at least this [m] (beam diversity)."""
    diverse_pool: int = 2
    """The diverse beam picks from this many times its width of best candidates."""
    angle_prior: float = 0.05
    """Weight of a weak preference for small joint angles in the global stage."""
    beam_penetration: float = 50.0
    """Beam-score penalty per millimetre a candidate's sample point lies inside a scene box."""
    beam_edge_t: tuple = (0.25, 0.5, 0.75, 1.0)
    """Edge sample points of a beam candidate's plate (fractions of its length)."""
    beam_outline_step: int = 2
    """Every how many observed outline points rank the beam's complete chains."""
    grid: tuple = ((-0.8, -0.4, 0.0, 0.4, 0.8), tuple(np.linspace(-1.2, 1.2, 9).tolist()), (0.0,))
    """The global stage's joint angles: (twist, out-of-plane bend, in-plane bend) values [rad]."""
    wide_grid: tuple = (tuple(np.linspace(-1.2, 1.2, 7).tolist()), tuple(np.linspace(-1.5, 1.5, 11).tolist()),
                        (-0.4, 0.0, 0.4))
    """The wide search's joint angles [rad]."""

    # local stage (estimator/refine.py, estimator/solver.py)
    refine: int = 3
    """Candidates refined to convergence after screening."""
    refine_eq11: int = 1
    """Further screened candidates, the best by the silhouette cost (eq. 11), refined too..."""
    eq11_range: float = 2.0
    """... chosen among those whose robust cost is below this multiple of the best one's."""
    alternatives: int = 2
    """Distinct screened candidates (tips more than DISTINCT_TIP_M from the refined ones)
    refined as well, so that another shape explaining the views is found and weighed."""
    lm_screen: int = 4
    """Levenberg-Marquardt iterations every beam candidate gets before screening."""
    lm_iterations: int = 6
    """Levenberg-Marquardt iterations of the kept candidates."""
    lm_rtol: float = 3e-3
    """A local-stage step that lowers the robust cost by less than this fraction ends it."""

    # when to search wider (estimator/fit.py)
    wide_cost: float = 0.15
    """Eq.-11 cost above which a fit is poor enough to pay for the wide search."""
    wide_offset_px: float = 1.5
    """... or when a view's mean boundary distance (its XOR over its outline length) is above
    this [px]: a view the first search's winner does not explain (about 1 in 10 good fits)."""
    wide_misfit_px: float = 4.0
    """... or when the thickest region where a view and the model disagree is more than
    twice this [px] thick (the largest distance inside it to its edge): a fit that explains
    a view well on average but misses part of it (the search's winner on a wrong branch).
    4.5 until 2026-11-26: occluded-913036's wrong "ok" (``wide_curls``) had 4.1 px; on the 964
    tuning captures 4.0 changed no verdict."""
    wide_beam: int = 8
    """Partial chains kept per node in the wide search."""
    thorough_beam: int = 24
    """Partial chains kept per node in the second look an estimate that is not "ok" gets."""
    fold_beam: int = 16
    """Partial chains kept per node in the second look an "ok" fold gets (its alternatives,
    the shapes folded the other way, weighed afresh). 24 (thorough_beam) before: on 829
    tuning captures (seeds 550000-, 610000-, 620000-) 16 changed one answer, a fold 0.8 mm
    off from ambiguous to "ok" (an alternative 10 mm away no longer found), and cut the fit
    time's p95 by 5 %, its mean by 4 %; 8 turned a right "ok" into ambiguous. (16 for every
    second look cut the p95 by 13 %, but on fresh seeds 810000- missed the better shape
    that made two refused fits "ok" at 0.2 mm.)"""
    recheck_offset_px: float = 1.3
    """An "ok" estimate one of whose views' mean boundary distance is above this [px] after
    the first look (and its wide search, if ``wide_*`` asked for one) gets the second look an
    "ok" fold gets (``fold_beam``): calib-964050 (2 px of calibration error, a bench
    capture) was "ok" 7.5 mm off at 1.38 px, its cost (0.18) more than twice the true
    shape's; the second look found a shape 1.4 mm off at 0.55 px. On the 824 tuning
    captures of 963000- and 964000- 1.3 px sent 48 "ok" estimates (6 %) to the second look,
    and changed that one answer alone. (A trigger on the eq.-11 cost, above 0.15, sent 18 %
    of the "ok" estimates of 964000- to the look for that same answer: not kept.) Fresh
    970000- (noisy, calib, calib_rot): 9 of 169 "ok" estimates got the look, no answer
    changed."""
    wide_variants: bool = True
    """The wide search also refines the winner's other branches (mirrored bends, flipped or
    quarter-turned twists)."""
    hook_bends: tuple = (1.6, 2.2, 2.8)
    """In a thorough look (``estimate(thorough=True)``; as the second look, of a "hidden"
    estimate only), the first stage's winner (the default grid's beam, refined, and its
    mirrors; before any wide search) with its end hooked back by these out-of-plane
    bends [rad] of its last plate or last two (:func:`refine.hooks`) is refined too, and
    replaces the winner when it explains the views better: a tip curled back behind the
    tape's body, out of every camera's sight, which the beam's grid does not reach (empty:
    off)."""
    wide_curls: tuple = (0.2, 0.4, 0.6)
    """After the wide search, steady curls are refined on their own, untwisted: per bend of
    these [rad] and either way, the first stage's winner's first joint with every later joint
    bent by it, and every joint bent by it (:func:`refine.curls`). A tape that curls evenly
    leaves a silhouette the beam's plate-by-plate ranking may not follow: fresh
    occluded-913036's search returned a shape ending at the curl's fold, 18.7 mm off,
    costing 0.066 against the true shape's 0.023, as "ok"; fresh clean-922044's a zig-zag
    chain with its first joint twisted the wrong way, 4.7 mm off at 0.152 against 0.024.
    Screened with the wide search's other starts, the curl that leads to the true shape lost
    its place after a few iterations (922044); refined on their own, each group keeps its
    best. On 964 tuning captures (899000 mix, part 907000-/908000-, sim and shell 907000-),
    against no curls: 16 answers changed, 13 refusals now "ok" within 2.3 mm, two poor_fit
    16-25 mm off now hidden within 1 mm, an "ok" 0.6 mm off now ambiguous; no wrong "ok". Curls
    with the winner's first joint alone (screened with the rest) changed 7, and missed
    922044; curls with every joint bent alone, refined apart, made three answers worse.
    (As first-stage starts for every capture, in an earlier session: two new wrong "ok" on
    tuning captures; here a curl must beat the answer by ``wide_gain``.) Empty: off."""
    wide_gain: float = 0.85
    """The wide search's result replaces the first when its eq.-11 cost is below this
    fraction of the first's (only a clear difference counts)."""

    # strip stage (estimator/strip.py)
    strip: bool = True
    """After the plate chain's fit, refine a continuous strip on the same residuals and take
    the output chain and the tip frame from it (off: the plate chain's fit is the output)."""
    strip_plates: int = 4
    """Fine plates per model plate in the strip."""
    strip_edge_t: tuple = (1 / 3, 2 / 3, 1.0)
    strip_centre_t: tuple = (1.0,)
    """Sample points on each fine plate's edges and centre line (fractions of its length)."""
    strip_in_plane_px: float = 100.0
    """Residual [px] per radian (per model-plate length) of in-plane bending in the strip: a
    tape barely bends within its own plane, so this stays near zero unless the views insist."""
    strip_iterations: int = 15
    strip_rtol: float = 3e-3
    """The strip's fit ends when a step lowers its robust cost by less than this fraction."""
    strip_tip_weight: float = 10.0
    """Weight of the tip's corners when the output chain is fitted to the strip in 3-D."""
    strip_frame_weight: float = 1.0
    """Weight of the strip's tip frame (its direction and width axis) on the output chain's
    tip frame F_n, relative to a corner's position: on a tape curled within the last plate,
    F_n along the chord tilts from the tape's frame at the tip by half the curl, so the
    chain's last plate is pulled part of the way towards the strip's tip frame (measured:
    tip normal median 6.4 -> 4.8 deg on the samples, tip error unchanged)."""
    strip_guard: float = 2.0
    """The chain taken from the strip is dropped when its silhouette cost (eq. 11) exceeds
    this multiple of the plate chain's own fit (a strip fit gone astray)."""

    # implementation
    compiled: bool = True
    """Evaluate the hot loops with the compiled kernels (numba, estimator/_kernels*.py) and
    run the least-squares fits compiled whole (estimator/_kernels_lm.py); off: the NumPy
    reference (estimator/reference.py) and the solvers' Python loops (estimator/solver.py;
    same numbers to float rounding, ~10x slower per call)."""

    def grid_angles(self, wide: bool = False) -> np.ndarray:
        """(g, 3) the global stage's (or the wide search's) candidate joint angles [rad]."""
        return angle_grid(*(self.wide_grid if wide else self.grid))


@functools.lru_cache(maxsize=8)
def _angle_grid(tx: tuple, ty: tuple, tz: tuple) -> np.ndarray:
    return np.stack(np.meshgrid(tx, ty, tz, indexing="ij"), axis=-1).reshape(-1, 3)


def angle_grid(tx, ty, tz) -> np.ndarray:
    """Candidate joint angles (θx, θy, θz) of the global stage [rad]: every combination."""
    return _angle_grid(tuple(float(v) for v in tx), tuple(float(v) for v in ty), tuple(float(v) for v in tz))


@functools.lru_cache(maxsize=64)
def as_array(values: tuple) -> np.ndarray:
    """A config tuple of numbers as a float array (cached: built once; not to be written)."""
    return np.array(values, float)


DEFAULT = FitConfig()
