"""Measuring the true tape with the needle on the arm (the paper's sec. 4.1, Fig. 6).

The simulated cell's prober is ``tapecell.sim.prober.SimProber``. Real cell: the arm is put in freedrive (teach mode), the operator guides
the needle onto the tape, and Enter records the TCP; teach mode ends in every case.

The error of an estimate at a measured point is the paper's ``e`` (eq. 12): the
Euclidean distance between estimated and measured positions.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from tapecell.estimator.errors import TapecellError, TaskFailed
from tapecell.estimator.result import Verdict
from tapecell.estimator.verdict import END_UNEXPLAINED, PAST_END

from .poses import pose6_to_matrix

PROBE_LABELS = ("tip", "tip_left", "tip_right")


class ProbeError(TaskFailed):
    """A point could not be probed (no contact, unreachable, nothing recorded)."""


@dataclass(frozen=True)
class ProbeParams:
    """inset: target points lie this far inside the tape's end and edges, so the needle
    lands on the tape, not beside it [m]. standoff: approach starts this far from the
    surface along the normal [m]. coarse_step [m], speed and far_speed [m/s]: the simulated
    needle, which knows its distance to the tape, approaches at far_speed while farther than
    two coarse steps from it (stopping a coarse step short), then at speed; it backs off
    at far_speed."""

    inset: float = 0.002
    standoff: float = 0.02
    coarse_step: float = 0.002
    speed: float = 0.01
    far_speed: float = 0.05


@dataclass(frozen=True, eq=False)
class ProbedPoint:
    """label: which point; position: (3,) measured needle tip [m]; target: (3,) where it
    was sent [m] (None when guided by hand)."""

    label: str
    position: np.ndarray
    target: np.ndarray | None = None


PROBE_CONFIRM_M = 0.004
"""A hypothesis is confirmed when the needle touched tape within this distance of the point
it stands for [m] ..."""
PROBE_MARGIN_M = 0.0015
"""... and at least this much closer than any other hypothesis' point [m]."""


def confirmed(distances: Sequence[float | None]) -> int | None:
    """The one hypothesis the needle confirms, given per hypothesis the distance [m] from its
    point to where the needle touched tape (None: nothing touched): the closest, when it is
    within PROBE_CONFIRM_M, clearly closer (PROBE_MARGIN_M) than every other, and no other is
    within PROBE_CONFIRM_M too; else None. Two hypotheses whose points both touch tape
    (a tip on the tape's body is tape as the true end is) are not told apart by which is
    closer: a simulated episode kept the one 0.8 mm from tape over the one 2.3 mm away,
    and it was 28 mm from the true end (the caller probes where the shapes disagree)."""
    return _closest(distances, PROBE_MARGIN_M, alone=True)


def _closest(distances: Sequence[float | None], margin: float, alone: bool) -> int | None:
    """The hypothesis touched within PROBE_CONFIRM_M whose every rival touched at least
    ``margin`` [m] farther (or not at all) and, with ``alone``, none within PROBE_CONFIRM_M;
    else None."""
    order = sorted((d, k) for k, d in enumerate(distances) if d is not None)
    if not order or order[0][0] > PROBE_CONFIRM_M:
        return None
    if len(order) > 1 and ((alone and order[1][0] <= PROBE_CONFIRM_M) or order[1][0] < order[0][0] + margin):
        return None
    return order[0][1]


PROBE_WIDE_MARGIN_M = 0.0025
"""Where several hypotheses' tips touch tape and the probes where the shapes disagree tell
nothing, the closest is kept when every other touched at least this much farther [m]
(:func:`clearly_closest`): simulated episodes kept right ones at 2.6-3.4 mm, and a wrong
one (28 mm from the end) at 1.5 mm."""


def clearly_closest(distances: Sequence[float | None]) -> int | None:
    """The hypothesis whose point the needle touched within PROBE_CONFIRM_M and every other's
    at least PROBE_WIDE_MARGIN_M farther (or not at all); else None. Only after the probes
    where the shapes disagree were inconclusive (see :func:`confirmed`)."""
    return _closest(distances, PROBE_WIDE_MARGIN_M, alone=False)


PAST_END_MAX_M = 0.025
"""The needle measures a roughly placed end at most this far past the model's end [m]
(the simulated cell's last step past the end; the real cell's operator's touch)."""


def hypotheses_to_probe(est: Any) -> bool:
    """Does the needle settle ``est`` (an ``estimator.Estimate``) by touching its hypotheses'
    tips (its own and its alternatives')? Where too few cameras see the end ("hidden") and
    where distinct shapes explain the views nearly as well ("ambiguous"): each hypothesis
    may be the tape, only the views cannot tell. (Not the alternatives of a ``poor_fit``:
    see :func:`end_measurable`.)"""
    return est.verdict is Verdict.HIDDEN or (est.verdict is Verdict.AMBIGUOUS and bool(est.alternatives))


def end_measurable(est: Any) -> bool:
    """Does the needle settle ``est`` (an ``estimator.Estimate``) by measuring its end? For
    a ``poor_fit`` whose views show tape past the model's end, or whose free end the model
    does not explain: both reasons say the end is about there but not where exactly. (A fit
    that does not explain a whole view is not measured: its end may be anywhere.) Its own
    end is measured even where it has alternatives; they are not probed (two alternatives
    of such fits, 38 and 83 mm from the end, lay on the tape's body near its edge with tape
    at their tips and corners and none past them, and simulated grasps failed). On 25
    simulated episodes of earlier campaigns refused for an unexplained end, the needle made
    12 grasps (tips 0.2-5.7 mm off) and kept all the far ones (23-35 mm off: no tape at
    their tips) refused; none failed. On 17 such refused episodes whose fits had
    alternatives, it made 9 grasps (tips 0.9-4.5 mm off, two through a refit) and kept the
    far ones (9-34 mm) refused; none failed."""
    return (est.verdict is Verdict.POOR_FIT
            and (PAST_END in est.verdict_reason or END_UNEXPLAINED in est.verdict_reason))


PROBE_CORNER_M = 0.010
"""Before the simulated cell acts on a tip the needle confirmed, it touches the tip's two
corners (the paper's tip_left, tip_right, ``inset`` inside the end and the edges): each must
be tape within this distance of the point [m], else that corner is in the air. A "tip" at
the tape's side edge, or on its body with the end turned away, leaves a corner in the air:
simulated episodes kept such tips (touched within 0.3 mm, nothing 6 mm past them), 16 and
22 mm from the end, and failed; with the corners probed both are refused (a corner not
touched at all, the other not or 14 mm away). The corners of tips that were grasped touched
within 8.7 mm in 150 simulated episodes (a twist some degrees off, or a curled corner, moves
a corner 13 mm from the centre line by several mm along the normal); 6 mm refused 8 of
them, 3-5 mm off, all grasped before."""


def corners_on_tape(distances: Sequence[float | None]) -> bool:
    """Were both tip corners touched within PROBE_CORNER_M (see there)?"""
    return all(d is not None and d <= PROBE_CORNER_M for d in distances)


TRUNK_CHECK_M = 0.012
TRUNK_TOUCH_M = 0.007
"""Before a cell acts on an end the needle confirmed, the needle touches the tape's centre
line TRUNK_CHECK_M [m] back from the tip along the end's trunk, where the pads will hold it
(the grasp point is the cell file's ``inset``, 8 mm, in from the tip; the pads reach 6 mm
either side): it must be tape within TRUNK_TOUCH_M [m] of the trunk (about a 30 deg bend off
it there). In the simulated cell a tip and corners touched within 1.4-2.4 mm passed an end
whose trunk was 38 deg off (838095, 3 cameras: the jaw closed on air); there the check
touches 8.4 mm off. In 70 grasped probing episodes of 830000-844000 it touched within 3.5
mm; on fresh 848000 one grasp (848005, tip 3.0 mm off) touched 5.4 mm off, which 5 mm
refused. The simulated needle touches along the end's normal at that point
(``sim.episode._Needle.trunk_on_tape``); on the real cell the operator puts the needle on the
centre line there, and :func:`trunk_touch_problem` judges the touch."""


def trunk_point(tip_position: np.ndarray, tip_rotation: np.ndarray) -> np.ndarray:
    """(3,) the point on the centre line TRUNK_CHECK_M back from the end at ``tip_position``
    along its trunk (``tip_rotation``'s first column): where the trunk check touches."""
    return np.asarray(tip_position, float) - TRUNK_CHECK_M * np.asarray(tip_rotation, float)[:, 0]


def trunk_touch_problem(tip_position: np.ndarray, tip_rotation: np.ndarray, touched: np.ndarray) -> str | None:
    """Why the operator's touch ``touched`` (3,) [m] on the tape's centre line, about
    TRUNK_CHECK_M back from the end at ``tip_position`` (frame ``tip_rotation``: trunk, left,
    normal), does not pass the trunk check: it must lie TRUNK_CHECK_M / 2 to 1.5 TRUNK_CHECK_M
    back along the trunk (6-18 mm: where the pads hold the tape), and the tape there may bend
    away from the trunk by no more than the check allows at TRUNK_CHECK_M, atan(TRUNK_TOUCH_M /
    TRUNK_CHECK_M) (about 30 deg), wherever in that stretch it was touched. None when it
    passes."""
    trunk = np.asarray(tip_rotation, float)[:, 0]
    v = np.asarray(tip_position, float) - np.asarray(touched, float)
    back = float(v @ trunk)
    off = float(np.linalg.norm(v - back * trunk))
    if not TRUNK_CHECK_M / 2 <= back <= 1.5 * TRUNK_CHECK_M:
        return (f"the needle's touch on the centre line is {1e3 * back:.1f} mm back from the end along its trunk "
                f"(it must be {500 * TRUNK_CHECK_M:.0f}-{1.5e3 * TRUNK_CHECK_M:.0f} mm back, where the pads will "
                f"hold the tape)")
    bend, most = np.degrees(np.arctan2(off, back)), np.degrees(np.arctan2(TRUNK_TOUCH_M, TRUNK_CHECK_M))
    if bend > most:
        return (f"the tape {1e3 * back:.0f} mm back from the end is {1e3 * off:.1f} mm off the estimated end's trunk, "
                f"a {bend:.0f} deg bend (> {most:.0f} deg): it bends away from the estimate where the pads would "
                f"hold it")
    return None


GRASP_CHECKED_M = 0.018
"""How far in from an end the needle measured its own checks reach [m] (the trunk check's
stretch, 1.5 TRUNK_CHECK_M). A grasp planned farther in (the planner's fallback insets, where
no closer grasp passed) holds the tape along a shape the views could not settle and the needle
did not check: the simulated cell's needle first touches the grasp point
(``sim.episode._grasp_point_touch``)."""
GRASP_RECENTRE_M = 0.003
GRASP_SHIFT_MAX_M = 0.010
GRASP_STATION_M = 0.006
GRASP_TURN_MAX_DEG = 30.0
"""The needle touches the grasp point and the centre line GRASP_STATION_M [m] either side of
it along the estimated trunk (where the pads, 12 mm long, will hold the tape), each along the
estimated normal (:func:`grasp_station`). Where the tape at the grasp point lies more than
GRASP_RECENTRE_M [m] off the estimate along its normal, the grasp is planned again with the
estimated tape moved onto the touch (the whole estimate, its measured end too: a
simplification), at that inset or farther in within the touched stretch (up to
GRASP_STATION_M farther). Where a touch finds no tape, the tape lies more than
GRASP_SHIFT_MAX_M off, the line through the outer touches turns more than GRASP_TURN_MAX_DEG
off the estimated trunk about the tape's width, or no plan passes, the grasp is refused: the
pads would hold the tape across their edges, or where the needle did not touch it. In the simulated cell the grasp points of 43 such grasps (probed episodes
of 830000-873000, 20-48 mm in) were touched 0.0-7.3 mm off, their lines 0-26 deg off. Two
failed as planned: 868005 (5.7 mm and 26 deg off: a pad swept the tape aside on the approach
and the jaw closed on air), which grasps when planned about the touch, as the 9 others more
than 3 mm off still do; and 874132 (8.5 mm off, the tape 49 deg off the estimate, no tape
touched 6 mm farther in: planned about the touch, the pads held the tape on their edges and
it slipped on the lift), now refused. Turning the estimate onto the touched line, instead of
refusing, made three of those grasps refusals (collisions) and one a slip. One of the 43,
864185, found a plan only 10 mm farther in than its touches (48 mm): it is refused now."""


def grasp_station_aims(est: Any, cfg: Any, inset: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """(the grasp point (3,) [m], its frame (3, 3): trunk, left, normal, the points the needle
    aims at keyed -1, 0, 1 as :func:`grasp_station` takes them) of a grasp ``inset`` [m] in
    from the end of the estimate ``est``, as the planner places it
    (:func:`tapecell.cell.planner.grasp_frame`, the cell file ``cfg``'s inset)."""
    from .planner import GraspParams, TipFrame, grasp_frame

    position, rotation = grasp_frame(TipFrame.from_estimate(est), inset, GraspParams.from_config(cfg.grasp).inset,
                                     est.nodes)
    return position, rotation, {k: position + k * GRASP_STATION_M * rotation[:, 0] for k in (0, -1, 1)}


def grasp_station(position: np.ndarray, rotation: np.ndarray, touched: dict) -> tuple[np.ndarray, float | None]:
    """(the tape's offset (3,) [m] from the grasp point ``position`` along the normal, the
    turn [deg] of the touched line off the trunk about the tape's width, None when an outer
    touch is missing) from the needle's touches at a grasp point (frame ``rotation``: trunk,
    left, normal). ``touched``: the touched points (3,) [m] keyed -1, 0, 1 (GRASP_STATION_M
    towards the base along the trunk, at the grasp point, past it), each approached along the
    normal; 0 must be there. The turn is that of the line through the outer two in the
    trunk-normal plane (over 90 deg when they lie the wrong way round); the offset is the
    middle one's displacement along the normal (the needle's approach leaves the rest
    unknown)."""
    R = np.asarray(rotation, float)
    p = np.asarray(position, float)
    trunk, normal = R[:, 0], R[:, 2]

    def along(k: int) -> float:
        return float((np.asarray(touched[k], float) - p) @ normal)

    turn = None
    if touched.get(-1) is not None and touched.get(1) is not None:
        # The line's run along the trunk is where the two outer touches are (a hand puts
        # them a few mm from the points aimed at; touches on the wrong sides turn it round).
        run = float((np.asarray(touched[1], float) - np.asarray(touched[-1], float)) @ trunk)
        turn = float(np.degrees(np.arctan2(abs(along(1) - along(-1)), run)))
    return along(0) * normal, turn


def grasp_station_problem(offset: np.ndarray, turn: float | None) -> str | None:
    """Why the tape the needle touched at a grasp point (:func:`grasp_station`'s ``offset``
    and ``turn``) may not be grasped there: no tape GRASP_STATION_M to a side (``turn``
    None), more than GRASP_SHIFT_MAX_M off the estimate, or turned more than
    GRASP_TURN_MAX_DEG; None when it may."""
    off = 1e3 * float(np.linalg.norm(offset))
    if turn is None:
        return (f"no tape {1e3 * GRASP_STATION_M:.0f} mm to a side of the grasp point along the estimated tape: the "
                f"pads would not hold it square")
    if off > 1e3 * GRASP_SHIFT_MAX_M:
        return (f"the tape at the grasp point lies {off:.1f} mm off the estimate (> {1e3 * GRASP_SHIFT_MAX_M:.0f} "
                f"mm): the shape there is not the estimate's")
    if turn > GRASP_TURN_MAX_DEG:
        return (f"the tape at the grasp point turns {turn:.0f} deg off the estimate (> {GRASP_TURN_MAX_DEG:.0f} "
                f"deg): the pads would not hold it square")
    return None


def replan_insets(params: Any, inset: float) -> list[float]:
    """The grasp insets [m] a grasp planned ``inset`` in may be planned again at about the
    tape the needle touched there: the planner's (``cell.planner.grasp_insets`` of
    ``params``) from ``inset`` to GRASP_STATION_M farther in, the stretch the touches cover."""
    from .planner import grasp_insets

    return [i for i in grasp_insets(params) if inset - 1e-9 <= i <= inset + GRASP_STATION_M + 1e-9]


REFIT_TOUCH_MAX_M = 0.012
"""A needle sent to a tip that touched tape farther than PROBE_CONFIRM_M from it, but within
this [m], refits the shape through the touch (:func:`tapecell.estimator.touch.refit`): the
views leave such an end a few millimetres off (its depth where one camera sees it, an end
hooked over); the refitted tip is then probed afresh."""
REFIT_COST_RATIO = 2.5
"""A refit whose silhouette cost (eq. 11) exceeds this multiple of the best hypothesis'
(the estimate's or an alternative's) explains the views too badly to be probed (2 until a
simulated episode's refit 1.1 mm from the end came out at 2.07x; the simulated needle then
probes the refit's tip, past it and its corners). The real cell's refit through the
operator's touch is judged by it too; there the refit must also end within 4 mm of the
touch, which the operator put on the end."""
PROBE_PAST_CLEAR_M = 0.012
"""Past a refitted tip (see REFIT_TOUCH_MAX_M) no tape may be touched within this distance
[m] of the point probed there: a touch on the tape's body, refitted as its end, has tape
around the point past it (a simulated episode touched it 8.9 mm away, and the refit was
23 mm from the end)."""


def refit_acceptable(refitted: Any, estimate: Any) -> bool:
    """May ``refitted`` (an ``estimator.Estimate`` refitted through a touch) be confirmed by
    the needle? Its views must be explained about as well as the best hypothesis of
    ``estimate`` (its own cost or an alternative's; REFIT_COST_RATIO) and as a whole: "ok",
    "hidden", or a ``poor_fit`` for its end alone (tape past it, an end left unexplained),
    never ambiguous."""
    best = min([float(estimate.cost)] + [float(a.cost) for a in estimate.alternatives])
    if refitted.cost > REFIT_COST_RATIO * best:
        return False
    if refitted.verdict is Verdict.POOR_FIT:
        return PAST_END in refitted.verdict_reason or END_UNEXPLAINED in refitted.verdict_reason
    return refitted.verdict in (Verdict.OK, Verdict.HIDDEN)


def hypothesis(estimate: Any, k: int) -> Any:
    """Hypothesis ``k`` of ``estimate`` (an ``estimator.Estimate``): 0 itself, else its
    alternative k - 1; either has ``angles``, ``tip_position``, ``tip_rotation``, ``cost``."""
    return estimate if k == 0 else estimate.alternatives[k - 1]


def refit_hypothesis(capture: Any, estimate: Any, k: int, touched: np.ndarray, depth: float,
                     angles: np.ndarray | None = None) -> Any:
    """Hypothesis ``k`` of ``estimate`` (0: itself, else its alternative k - 1) refitted to
    ``capture``'s views with its end through the needle's touch ``touched`` (3,) [m] (within
    ``depth`` [m] of the end: :func:`tapecell.estimator.touch.refit`), when the refit may be
    confirmed (:func:`refit_acceptable`); else None. ``angles``: start from these instead
    (an earlier refit of the hypothesis), judged against ``estimate`` all the same. What
    confirms it is the caller's: the simulated needle probes it, the real cell's operator
    put the needle on the end."""
    from tapecell.estimator.touch import refit

    if angles is None:
        angles = hypothesis(estimate, k).angles
    refitted = refit(capture, angles, touched, depth)
    return refitted if refit_acceptable(refitted, estimate) else None


def measured_end(tip_position: np.ndarray, trunk: np.ndarray, touched: np.ndarray) -> np.ndarray | None:
    """Where the tape's end is, from a needle touch ``touched`` (3,) [m] on it, for an end
    estimated at ``tip_position`` (3,) with the trunk direction ``trunk`` (3,): the touch
    must lie within PROBE_CONFIRM_M of the trunk's line, from PROBE_CONFIRM_M before the tip
    to PAST_END_MAX_M past it; the end moves along the trunk to it (never back: the views
    show the tape at least as far as the model's end). None where the touch is elsewhere."""
    trunk = np.asarray(trunk, float) / np.linalg.norm(trunk)
    d = np.asarray(touched, float) - np.asarray(tip_position, float)
    along = float(d @ trunk)
    lateral = float(np.linalg.norm(d - along * trunk))
    if lateral > PROBE_CONFIRM_M or not -PROBE_CONFIRM_M <= along <= PAST_END_MAX_M:
        return None
    return np.asarray(tip_position, float) + max(along, 0.0) * trunk


def adopt(estimate: Any, k: int, spec: Any, reason: str) -> Any:
    """``estimate`` (an ``estimator.Estimate``) with hypothesis ``k`` (0: itself, else its
    alternative k - 1) as the answer, verdict "ok" for ``reason``: what a probe that
    confirmed it makes of it. ``spec``: the capture's tape model (its plate chain)."""
    import dataclasses

    from tapecell.estimator import Verdict, forward_kinematics

    if k == 0:
        return dataclasses.replace(estimate, verdict=Verdict.OK, verdict_reason=reason)
    alt = estimate.alternatives[k - 1]
    shape = forward_kinematics(spec, alt.angles)
    return dataclasses.replace(estimate, angles=alt.angles, nodes=shape.nodes, tip_position=alt.tip_position,
                               tip_rotation=alt.tip_rotation, cost=alt.cost, verdict=Verdict.OK, verdict_reason=reason)


def tape_points(tip_position: np.ndarray, tip_rotation: np.ndarray, width: float, inset: float) -> dict[str, np.ndarray]:
    """The probe points of a tape end: tip (on the centre line) and the two tip corners,
    each ``inset`` inside the tape [m]. Columns of ``tip_rotation``: trunk, left, normal."""
    trunk, left = tip_rotation[:, 0], tip_rotation[:, 1]
    back = tip_position - inset * trunk
    return {"tip": back, "tip_left": back + (width / 2 - inset) * left,
            "tip_right": back - (width / 2 - inset) * left}


def needle_world_from_tcp(point: np.ndarray, approach: np.ndarray) -> np.ndarray:
    """4x4 needle TCP frame at ``point`` with the needle axis (TCP z) along ``approach``."""
    z = approach / np.linalg.norm(approach)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = point
    return T


def approach_normal(point: np.ndarray, normal: np.ndarray, robot_side: np.ndarray) -> np.ndarray:
    """The tape normal's sign that faces ``robot_side`` (a direction towards the robot)."""
    return normal if normal @ robot_side >= 0 else -normal


# ----------------------------------------------------------------------------- real cell
def guided_probe(arm, flange_from_needle: Any, labels: Sequence[str], prompt: Callable[[str], str] | None = None,
                 log: Callable[[str], None] = print) -> list[ProbedPoint]:
    """Freedrive probing on a connected :class:`cell.arm.Arm`.

    Starts teach mode, then for each label waits for Enter (the operator has put the needle
    on the point) and records the needle tip = reported flange pose composed with
    ``flange_from_needle``. Typing ``s`` skips a point, ``q`` stops. Teach mode is ended
    on every path: on Ctrl-C, an error (then a failure to end it does not hide the error),
    or normal return.
    """
    F = pose6_to_matrix(flange_from_needle) if np.shape(flange_from_needle) == (6,) else np.asarray(flange_from_needle)
    prompt = prompt or (lambda text: input(text))
    points = []
    arm.freedrive(True)
    try:
        for label in labels:
            answer = prompt(f"guide the needle onto the tape's {label}, then press Enter "
                            "(s = skip, q = stop): ").strip().lower()
            if answer == "q":
                break
            if answer == "s":
                continue
            world_from_needle = pose6_to_matrix(arm.tcp_pose()) @ F
            points.append(ProbedPoint(label, world_from_needle[:3, 3].copy()))
            log(f"{label}: {np.round(1000 * world_from_needle[:3, 3], 2).tolist()} mm")
    except BaseException:
        try:
            arm.freedrive(False)
        except TapecellError:
            pass    # the arm is gone (it was told to stop): the first error says why
        raise
    arm.freedrive(False)
    if not points:
        raise ProbeError("no point was recorded")
    return points


def truth_fragment(points: Sequence[ProbedPoint], capture: str | None = None) -> dict[str, Any]:
    """A ``tape-truth/1`` fragment: probed points with labels (no full centre line), for
    the capture at ``capture``."""
    doc: dict[str, Any] = {"format": "tape-truth/1", "fragment": True, "units": "m",
                           "probed": [{"label": p.label, "position": np.asarray(p.position).tolist()}
                                      for p in points]}
    if capture is not None:
        doc["capture"] = str(capture)
    tip = [p for p in points if p.label == "tip"]
    if tip:
        doc["tip"] = {"position": np.asarray(tip[0].position).tolist()}
    return doc


def estimate_errors(points: Sequence[ProbedPoint], estimated: dict[str, np.ndarray]) -> dict[str, float]:
    """The paper's e (eq. 12) per probed label: |estimated - measured| [m]."""
    return {p.label: float(np.linalg.norm(estimated[p.label] - p.position)) for p in points if p.label in estimated}
