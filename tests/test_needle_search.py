"""The simulated needle's searches (sim/episode.py) against an analytic tape, with a needle
that touches where a line along the probe's approach meets the tape: the trace along a
hooked end, the walk past a tip whose tape goes on, the twist found at the corners."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.cell.probe import ProbeParams
from tapecell.estimator import TapeSpec
from tapecell.sim.episode import _Needle, _trace, _walk_past

WIDTH = 0.03
RADIUS = 0.01


def hooked_tape(straight: float = 0.10, curl_deg: float = 90.0, step: float = 0.0004):
    """Centre line points and frames (trunk, left, normal = trunk x left: rotations, as the
    estimator's) of a tape standing up along +z, its faces towards -x and +x, then curled
    towards +x about its left axis (+y) with RADIUS."""
    pts, frames = [], []
    for z in np.arange(0.0, straight, step):
        pts.append([0.0, 0.0, z])
        frames.append(np.column_stack([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]]))
    for a in np.arange(0.0, np.radians(curl_deg) + 1e-9, step / RADIUS):
        trunk = np.array([np.sin(a), 0.0, np.cos(a)])
        normal = np.cross(trunk, [0, 1.0, 0])
        pts.append([RADIUS * (1 - np.cos(a)), 0.0, straight + RADIUS * np.sin(a)])
        frames.append(np.column_stack([trunk, [0, 1.0, 0], normal]))
    return np.array(pts), np.array(frames)


class LineNeedle(_Needle):
    """A needle whose probe touches the tape surface point nearest to its approach line
    (within 0.4 mm of it), the one nearest the aimed point along it (within the standoff)."""

    def __init__(self, centre: np.ndarray, frames: np.ndarray):
        self.params, self.probes, self.notes = ProbeParams(), None, None
        across = np.linspace(-WIDTH / 2, WIDTH / 2, 61)
        self.surface = (centre[:, None, :] + across[None, :, None] * frames[:, None, :, 1]).reshape(-1, 3)
        self.touches = 0

    def touch(self, label, target, R):
        self.touches += 1
        n = R[:, 2] / np.linalg.norm(R[:, 2])
        d = self.surface - target
        along = d @ n
        perp = np.linalg.norm(d - along[:, None] * n, axis=1)
        ok = (perp < 0.0004) & (np.abs(along) < self.params.standoff)
        if not ok.any():
            return None
        k = np.flatnonzero(ok)[np.argmin(np.abs(along[ok]))]
        return float(np.linalg.norm(self.surface[k] - target)), self.surface[k].copy()


def mounted(centre: np.ndarray, frames: np.ndarray) -> type:
    """A :class:`LineNeedle` class on the tape (``centre``, ``frames``) that
    ``resolve_by_probing`` can mount as its ``_Needle`` (no arm: entering does nothing)."""

    class Needle(LineNeedle):
        def __init__(self, *args):
            super().__init__(centre, frames)
            if len(args) == 4:                  # resolve_by_probing's (cell, arm, probes, notes)
                self.probes, self.notes = args[2], args[3]

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

    return Needle


def straight_cell(monkeypatch):
    """A straight tape 120 mm up, its :class:`LineNeedle` mounted as ``resolve_by_probing``'s
    needle (no arm): (the episode module, a cell with the bundled cell file, a zero chain's
    angles, the tape's tip, its frame there, the needle class)."""
    import types

    import tapecell.sim.episode as E
    from tapecell.cell.config import load_cell_config

    centre, frames = hooked_tape(straight=0.12, curl_deg=0.0)
    Needle = mounted(centre, frames)
    monkeypatch.setattr(E, "_Needle", Needle)
    cell = types.SimpleNamespace(config=load_cell_config())
    return E, cell, np.zeros((cell.config.tape.estimator_plates, 3)), centre[-1], frames[-1], Needle


def test_the_trace_follows_a_hooked_end_past_the_model():
    """A 5-plate model standing straight 100 mm up; the tape curls over a quarter turn past
    it. The trace from 10 mm back from the model's end follows the curl to the tape's end
    (within a step) and finds the end's frame turned with it."""
    centre, frames = hooked_tape()
    needle = LineNeedle(centre, frames)
    spec = TapeSpec(np.full(5, 0.02), WIDTH, np.zeros(3), frames[0])
    out = _trace(needle, np.zeros((5, 3)), spec, WIDTH)
    assert out is not None
    end, frame, back, walked = out
    assert back == 0.010
    assert np.linalg.norm(end - centre[-1]) < 0.005
    assert frame[:, 0] @ frames[-1][:, 0] > np.cos(np.radians(35))    # the trunk turned with the curl
    assert walked > 0.015
    assert needle.end_frame(end, frame, WIDTH, plane=False) is not None   # its corners are tape


def test_the_trace_starts_on_the_plate_before_the_last_where_the_last_is_off_the_tape():
    """A tape standing straight 158 mm up; the model (5 plates of 30 mm) has its last plate
    bent a right angle away from it (an end hidden behind the part, guessed wrong), the
    plate before that on the tape. No tape 10 or 20 mm back along the wrong plate: the trace
    starts 35 mm back from the model's end, on the plate before (115 mm up), and walks up
    the tape to its end."""
    centre, frames = hooked_tape(straight=0.158, curl_deg=0.0)
    needle = LineNeedle(centre, frames)
    spec = TapeSpec(np.full(5, 0.03), WIDTH, np.zeros(3), frames[0])
    angles = np.zeros((5, 3))
    angles[-1, 1] = np.radians(90.0)            # the last plate bent out of the tape's plane
    out = _trace(needle, angles, spec, WIDTH)
    assert out is not None
    end, frame, back, walked = out
    assert back == 0.035
    assert np.linalg.norm(end - centre[-1]) < 0.005
    assert walked == pytest.approx(0.158 - 0.115, abs=0.005)
    assert frame[:, 0] @ frames[-1][:, 0] > np.cos(np.radians(5))


def test_the_trace_refuses_where_no_tape_is_at_its_start():
    centre, frames = hooked_tape()
    needle = LineNeedle(centre, frames)
    away = frames[0].copy()
    spec = TapeSpec(np.full(5, 0.02), WIDTH, np.array([0.05, 0.0, 0.0]), away)   # 50 mm beside the tape
    assert _trace(needle, np.zeros((5, 3)), spec, WIDTH) is None


def test_the_walk_past_a_tip_stops_at_the_end():
    """A straight tape 108 mm long; a tip estimated at 100 mm: the walk finds tape 6 mm past
    it and none at 9 mm, and the end's corners are tape."""
    centre, frames = hooked_tape(straight=0.108, curl_deg=0.0)
    needle = LineNeedle(centre, frames)
    last, end = _walk_past(needle, np.array([0.0, 0.0, 0.100]), frames[0], WIDTH, (0.003, 0.006, 0.009, 0.012), 0.0)
    assert last == 0.006 and end is not None


def test_the_corners_find_a_twist_the_estimate_missed():
    """The end's frame turned 40 deg about its trunk: its corners are in the air; the frame
    the corners find has its lateral axis within 10 deg of the tape's."""
    centre, frames = hooked_tape(straight=0.12, curl_deg=0.0)
    needle = LineNeedle(centre, frames)
    a = np.radians(40.0)
    turned = frames[-1] @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    tip = centre[-1]
    assert not needle.corners_on_tape(tip, turned, WIDTH)
    frame = needle.end_frame(tip, turned, WIDTH)
    assert frame is not None
    assert abs(frame[:, 1] @ frames[-1][:, 1]) > np.cos(np.radians(10))


def test_the_trunk_check_refuses_an_end_bent_off_where_the_pads_would_hold_it():
    """A straight tape and its end's frame at the true tip, once right and once with its trunk
    bent 40 deg out of the tape's plane: both have their tip and corners on the tape (within a
    few mm near the tip), but only the right one has tape TRUNK_CHECK_M back along its trunk,
    where the pads would hold it (838095: the pads closed on air)."""
    from tapecell.cell.probe import TRUNK_CHECK_M, TRUNK_TOUCH_M

    centre, frames = hooked_tape(straight=0.12, curl_deg=0.0)
    tip, right = centre[-1], frames[-1]
    a = np.radians(40.0)
    bent = right @ np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    needle = LineNeedle(centre, frames)
    assert needle.corners_on_tape(tip, right, WIDTH) and needle.corners_on_tape(tip, bent, WIDTH)
    assert needle.end_frame(tip, right, WIDTH) is right
    assert needle.end_frame(tip, bent, WIDTH) is None
    hit = needle.touch("trunk", tip - TRUNK_CHECK_M * bent[:, 0], bent)
    assert hit is None or hit[0] > TRUNK_TOUCH_M


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    from tapecell.cell.poses import rotation_angle_between

    return float(np.degrees(rotation_angle_between(a, b)))


def test_the_touches_measure_the_frame_of_an_end_whose_corners_are_tape():
    """A straight tape; the end's frame at the true tip, twisted 25 deg about its trunk,
    pitched 20 deg about its width axis, or both. Each is confirmed as it is (both corners
    touched within PROBE_CORNER_M, tape at the trunk point), but a jaw pitched by such a
    normal closed one pad on air (fresh 945075, 38 deg off). The frame the needle returns is
    the one its touches measure (before: the estimate's, 20-25 deg off): its normal, the
    pads' closing direction, within 2 deg, the frame within 6 deg (a corner touched along a
    normal both twisted and pitched lies a little along the tape: the frame turns a little
    within the tape's plane); a frame already right is returned as it is. A traced end
    (``plane=False``) keeps its pitch: only the corners' twist is measured."""
    from tapecell.cell.probe import PROBE_CORNER_M
    from tapecell.estimator.geometry import rot_x, rot_y

    centre, frames = hooked_tape(straight=0.12, curl_deg=0.0)
    tip, right = centre[-1], frames[-1]
    needle = LineNeedle(centre, frames)
    assert needle.end_frame(tip, right, WIDTH) is right
    for turn in (rot_x(np.radians(25.0)), rot_x(np.radians(-25.0)), rot_y(np.radians(20.0)), rot_y(np.radians(-20.0)),
                 rot_x(np.radians(20.0)) @ rot_y(np.radians(15.0))):
        wrong = right @ turn
        touches = needle.corner_touches(tip, wrong, WIDTH)
        assert all(h is not None and h[0] <= PROBE_CORNER_M for h in touches)
        frame = needle.end_frame(tip, wrong, WIDTH)
        assert frame is not None
        normal_deg = np.degrees(np.arccos(np.clip(frame[:, 2] @ right[:, 2], -1.0, 1.0)))
        assert normal_deg < 2.0 and _angle_deg(frame, right) < 6.0, (turn, normal_deg, _angle_deg(frame, right))
    pitched = right @ rot_y(np.radians(20.0))
    assert needle.end_frame(tip, pitched, WIDTH, plane=False) is pitched
    twisted = right @ rot_x(np.radians(25.0))
    assert _angle_deg(needle.end_frame(tip, twisted, WIDTH, plane=False), right) < 5.0


def test_hypotheses_ending_at_the_same_point_are_probed_once(monkeypatch):
    """An ambiguous estimate whose alternative ends where the answer does (a plate fit 22 mm
    away whose output chain ends at the answer's end, fit._cheapest_first; 949140): probed
    as two, both tips touched alike and nothing told them apart, and the episode was
    refused. The needle probes the same end once (SAME_END_M) and confirms it."""
    from tapecell.estimator import Alternative, Estimate, Verdict

    E, cell, angles, tip, right, _ = straight_cell(monkeypatch)
    est = Estimate(np.zeros((3, 3)), angles, tip, right, 0.0557, np.zeros(2), 0.0, verdict=Verdict.AMBIGUOUS,
                   verdict_reason="a shape with its tip 22 mm away explains the views nearly as well",
                   alternatives=(Alternative(0.0563, tip + 1e-4, right, angles),))
    kept, touched = E.resolve_by_probing(cell, None, est, WIDTH)
    assert kept.verdict is Verdict.OK and kept.verdict_reason.startswith("hypothesis 0 confirmed")
    assert touched[0] is not None and touched[1] is None
    # Probed as two (and without the rule that tips within ONE_END_M of each other are one
    # end, which would take the one touched closest): refused.
    one_end_m = E.ONE_END_M
    monkeypatch.setattr(E, "SAME_END_M", 0.0)
    monkeypatch.setattr(E, "ONE_END_M", 0.0)
    kept, touched = E.resolve_by_probing(cell, None, est, WIDTH)
    assert kept.verdict is Verdict.AMBIGUOUS and None not in touched[:2]
    monkeypatch.setattr(E, "ONE_END_M", one_end_m)
    kept, touched = E.resolve_by_probing(cell, None, est, WIDTH)
    assert kept.verdict is Verdict.OK and "(one end)" in kept.verdict_reason and None not in touched[:2]


def test_a_touched_tip_with_tape_near_the_point_past_it_is_not_the_end(monkeypatch):
    """Two hypotheses' tips both touched on the tape: the true end (nothing past it) and a
    "tip" on the tape's body, its trunk 53 deg out of the tape's plane, so that the point
    6 mm past it is 8 mm off the tape (tape near it, not on its trunk's line; 956082). Both
    tips' corners are tape, and nothing else tells them apart: the episode was refused.
    Tape within PROBE_PAST_CLEAR_M of the point past a tip means a tip on the body, as for
    a refit's: the true end is confirmed."""
    from tapecell.estimator import Alternative, Estimate, Verdict

    E, cell, angles, tip, right, Needle = straight_cell(monkeypatch)
    a = np.radians(53.0)
    body_tip = np.array([0.0, 0.0, 0.06])
    body_frame = np.column_stack([[np.sin(a), 0.0, np.cos(a)], [0.0, 1.0, 0.0], [-np.cos(a), 0.0, np.sin(a)]])
    past = Needle().distance("past", body_tip + E.PROBE_BEYOND_M * body_frame[:, 0], body_frame)
    assert E.PROBE_CONFIRM_M < past <= E.PROBE_PAST_CLEAR_M
    est = Estimate(np.zeros((3, 3)), angles, body_tip, body_frame, 0.0557, np.zeros(2), 0.0,
                   verdict=Verdict.AMBIGUOUS, verdict_reason="a shape with its tip 60 mm away explains the views",
                   alternatives=(Alternative(0.0563, tip, right, angles),))
    kept, touched = E.resolve_by_probing(cell, None, est, WIDTH)
    assert kept.verdict is Verdict.OK and kept.verdict_reason.startswith("hypothesis 1 confirmed")
    assert np.allclose(kept.tip_position, tip)
    assert touched[0] is None and touched[1] is not None


def test_a_tip_on_the_body_is_not_confirmed_where_tape_lies_past_it_along_the_measured_frame(monkeypatch):
    """A straight tape. A "tip" on its body, its frame pitched 40 deg out of the tape's plane:
    tape at its tip, and 6 mm past it along that frame tape only 5 mm from the point (more
    than PROBE_CONFIRM_M, so not "the tape goes on"; a lone touched tip is not refused for it).
    Where the touches measure the end's frame onto the tape (the tilt :meth:`_plane_frame`
    makes, here stood in for: the straight analytic tape gives no trunk point to tilt onto),
    the needle probes past the tip again along the measured frame: tape there, so it is not
    the end and the estimate stays refused (simulated episodes grasped three such
    "ends", 12-44 mm from the tape's, every camera turned 0.5 deg). The true end, twisted
    25 deg, gets its frame measured (unpatched) and is confirmed: nothing past it."""
    from tapecell.estimator import Estimate, Verdict
    from tapecell.estimator.geometry import rot_x, rot_y

    E, cell, angles, tip, right, Needle = straight_cell(monkeypatch)

    def hidden(at, frame):
        return Estimate(np.zeros((3, 3)), angles, at, frame, 0.05, np.zeros(2), 0.0, verdict=Verdict.HIDDEN,
                        verdict_reason="1 camera(s) see the free end, 2 needed")

    notes: dict = {}
    kept, _ = E.resolve_by_probing(cell, None, hidden(tip, right @ rot_x(np.radians(25.0))), WIDTH, None, None, notes)
    assert kept.verdict is Verdict.OK and kept.verdict_reason.endswith("its frame measured by the needle's touches")
    assert np.allclose(kept.tip_position, tip) and notes["probed_past_mm"] == [None]

    body = np.array([0.0, 0.0, 0.06])
    pitched = right @ rot_y(np.radians(40.0))
    past = Needle().distance("past", body + E.PROBE_BEYOND_M * pitched[:, 0], pitched)
    assert E.PROBE_CONFIRM_M < past <= E.PROBE_PAST_CLEAR_M
    assert Needle().distance("past", body + E.PROBE_BEYOND_M * right[:, 0], right) < E.PROBE_CONFIRM_M
    monkeypatch.setattr(Needle, "end_frame", lambda self, at, R, width, plane=True: right)
    notes.clear()
    kept, touched = E.resolve_by_probing(cell, None, hidden(body, pitched), WIDTH, None, None, notes)
    assert touched[0] is not None and touched[0] < 1e3 * E.PROBE_CONFIRM_M      # tape at the "tip" ...
    assert kept.verdict is Verdict.HIDDEN                                         # ... but not the end
    assert notes["probed_past_mm"][0] < 1e3 * E.PROBE_CONFIRM_M
    monkeypatch.setattr(Needle, "clear_past", lambda self, at, R, label: True)     # without the check:
    kept, _ = E.resolve_by_probing(cell, None, hidden(body, pitched), WIDTH)
    assert kept.verdict is Verdict.OK                                             # confirmed, as before
