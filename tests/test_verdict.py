"""The estimator's verdict, each on a capture built for it (estimator/verdict.py)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from tapecell.estimator import Verdict, View, estimate
from tapecell.estimator.metrics import errors
from tapecell.estimator.occlusion import hidden, penetration
from tapecell.estimator.scene import Box
from tapecell.estimator.synthetic import SyntheticOptions, make_capture
from tapecell.estimator.config import DEFAULT as DEFAULT_CONFIG
from tapecell.estimator.verdict import POOR_OFFSET_PX, boundary_offsets, judge

DATA = Path(__file__).resolve().parent / "data" / "captures"


# The search as it was before the joints' lines joined the model's outline
# (FitConfig.crease_t) and the wide search got steady curls (wide_curls, with
# wide_misfit_px 4.0), both 2026-11-26: the mechanism tests below were built on captures that
# search answered, and run their mechanism on it.
BEFORE_LINES = dataclasses.replace(DEFAULT_CONFIG, crease_t=(), wide_misfit_px=4.5, wide_curls=())


def _tip_mm(capture, est) -> float:
    return 1e3 * errors(est.nodes, est.tip_rotation, capture.truth, est.tip_position).tip_m


@pytest.mark.parametrize("seed", [71014, 71017, 71018])
def test_tip_behind_the_part_is_never_ok(seed):
    """The true tip is hidden behind the part from one of two cameras: the estimate must
    not be "ok" (nothing may act on it), whatever shape it found."""
    capture = make_capture(seed, SyntheticOptions(part=True, cameras=2))
    assert sum(not hidden(v.camera.center, capture.truth.points[-1:], capture.scene)[0] for v in capture.views) == 1
    est = estimate(capture)
    assert est.verdict is not Verdict.OK, f"ok with tip error {_tip_mm(capture, est):.1f} mm"
    assert est.tip_views <= 2


@pytest.mark.parametrize("seed", [877038, 877054])
def test_a_shape_bent_within_the_tapes_plane_is_not_ok(seed):
    """Fresh part captures (a tape standing on a box that hides what goes behind it) that the
    fit explained with a twist and an edgewise bend (21 and 33 deg within the tape's plane),
    answered "ok" 17 and 69 mm off. No tape bends so within its plane: poor_fit
    (verdict.EDGEWISE_MAX_DEG)."""
    capture = make_capture(seed, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert est.verdict is not Verdict.OK, f"ok {_tip_mm(capture, est):.1f} mm off"
    # The rule itself, on the shape the fit found before the joints' lines were outline
    # (FitConfig.crease_t; now it finds another shape, refused as well).
    est = estimate(capture, config=BEFORE_LINES)
    assert est.verdict is Verdict.POOR_FIT and "bends within the tape's plane" in est.verdict_reason


def test_a_curl_whose_fold_is_the_silhouettes_edge_is_not_taken_for_its_end():
    """A fresh part capture (907000) whose tape curls through 150 deg, its end going behind
    the part from one camera: the silhouette's edge at the curl is the tape's fold, not its
    end. The model's outline lacked the joints' lines (FitConfig.crease_t), so the shape
    ending at the fold cost less, and it was "ok" 42 mm off."""
    capture = make_capture(907000, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert est.verdict is not Verdict.OK or _tip_mm(capture, est) < 5.0, f"ok {_tip_mm(capture, est):.1f} mm off"


def test_a_steady_curl_the_beam_misses_is_found_by_the_wide_search():
    """A fresh occluded capture (913036): the tape curls evenly (~0.4 rad a joint), its end
    behind the arm's band in one view and seen end-on in the other. The beam's winner ended
    at the curl's fold, 18.7 mm off, "ok"; the true shape costs a third of it. The wide
    search's steady curls (FitConfig.wide_curls) find it; its end is then seen by one camera
    alone (hidden)."""
    capture = make_capture(913036, SyntheticOptions(occluder=True, cameras=2))
    est = estimate(capture)
    assert _tip_mm(capture, est) < 3.0 and est.verdict is Verdict.HIDDEN, (est.verdict, _tip_mm(capture, est))
    without = estimate(capture, config=dataclasses.replace(DEFAULT_CONFIG, wide_curls=()))
    assert _tip_mm(capture, without) > 10.0 and without.cost > 1.5 * est.cost


def test_a_curl_whose_first_joint_the_beam_twisted_is_found():
    """A fresh clean capture (922044): a gentle curl (~0.2 rad a joint, a little twist). The
    beam's winner twisted its first joint the wrong way and zig-zagged after it: "ok" 4.7
    mm off, costing six times the true shape. The steady curls with every joint bent,
    refined on their own (FitConfig.wide_curls), find the true shape."""
    capture = make_capture(922044, SyntheticOptions(cameras=2))
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 1.0, (est.verdict, _tip_mm(capture, est))
    without = estimate(capture, config=dataclasses.replace(DEFAULT_CONFIG, wide_curls=()))
    assert _tip_mm(capture, without) > 3.0 and without.cost > 3.0 * est.cost


def test_where_a_curl_replaces_the_plate_fit_the_better_strip_stands(monkeypatch):
    """A fresh part capture (924052) whose plate chain explains the views poorly (cost
    0.57-0.77); the strip stage explains them. A steady curl gave the cheaper plate fit, but
    the strip from it stuck on a worse branch: poor_fit (5.7 px), the tip 0.8 mm off. The
    strip from the plate fit the curl replaced explains the views: "ok" with the view
    threshold it was built on (3 px; its worst view is at 2.99 px, which POOR_OFFSET_PX = 2.5,
    from 2026-11-27, refuses: part-1010016 was "ok" 10.4 mm off at 2.72 px)."""
    monkeypatch.setattr("tapecell.estimator.verdict.POOR_OFFSET_PX", 3.0)
    capture = make_capture(924052, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 1.5, (est.verdict_reason, _tip_mm(capture, est))


def test_edgewise_bend_of_a_plate_chain():
    """verdict.edgewise_bend: an in-plane bend of 0.5 rad at joint 2 is 28.6 deg edgewise
    there; the same bend out of the plane (flatwise) is not edgewise at all; at the last joint
    (the tip's plate, pulled towards the strip's tip frame) it is not counted."""
    from tapecell.estimator import forward_kinematics
    from tapecell.estimator.verdict import edgewise_bend

    spec = make_capture(4100, SyntheticOptions(cameras=2)).tape
    angles = np.zeros((spec.n, 3))
    angles[2, 2] = 0.5
    bend, joint = edgewise_bend(forward_kinematics(spec, angles).frames)
    assert bend == pytest.approx(np.degrees(0.5), abs=0.01) and joint == 2
    flat = np.zeros((spec.n, 3))
    flat[2, 1] = 0.5
    assert edgewise_bend(forward_kinematics(spec, flat).frames)[0] == pytest.approx(0.0, abs=1e-6)
    last = np.zeros((spec.n, 3))
    last[-1, 2] = 0.5
    assert edgewise_bend(forward_kinematics(spec, last).frames)[0] == pytest.approx(0.0, abs=1e-6)


def test_a_view_the_strip_explains_is_explained(monkeypatch):
    """A part capture (synthetic, seed 891011, 3 cameras) whose tape bends within one plate's
    length: the plate chain misses that stretch's outline by 3.3 px on average in one view
    (poor_fit before), while the strip the tip frame comes from follows it (2.5 px). The
    strip's offsets stand: "ok", the tip within 1.5 mm. verdict.explaining_offsets takes
    the strip's only where its worst view is better explained. (Built on the view threshold
    of its time, 3 px; from 2026-11-27 it is 2.5 px, and the default plate chain's 2.75 px
    goes to the strip's offsets as well. The base check of its time, 4.5 px, is pinned too:
    this capture's base shows 3.1 px with the true cameras, where the part hides part of
    it, and the 3 px threshold of 2026-11-27 refuses it.)"""
    from tapecell.estimator import forward_kinematics
    from tapecell.estimator.fit import _offsets
    from tapecell.estimator.verdict import STRIP_PLATE_MAX_PX, explaining_offsets

    POOR_OFFSET_PX = 3.0
    monkeypatch.setattr("tapecell.estimator.verdict.POOR_OFFSET_PX", POOR_OFFSET_PX)
    monkeypatch.setattr("tapecell.estimator.fit.BASE_OFFSET_PX", 4.5)
    capture = make_capture(891011, SyntheticOptions(part=True, cameras=3))
    est = estimate(capture)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert _tip_mm(capture, est) < 1.5
    # The plate chain whose model outline holds the joints' lines (FitConfig.crease_t)
    # explains that stretch itself; the one without them (nor in the strip) is the case here.
    assert _offsets(capture, forward_kinematics(capture.tape, est.angles).quads()).max() <= POOR_OFFSET_PX
    plain = dataclasses.replace(BEFORE_LINES, strip_crease_t=())
    est = estimate(capture, config=plain)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert _tip_mm(capture, est) < 1.5
    plate = _offsets(capture, forward_kinematics(capture.tape, est.angles).quads())
    assert plate.max() > POOR_OFFSET_PX >= est.view_offsets_px.max()
    # Such an "ok" gets the second look a poor fit gets (its time counts both looks).
    first = estimate(capture, second_look=False, config=plain)
    assert first.verdict is Verdict.OK and est.time_s > first.time_s
    a, b, c = np.array([1.0, 3.5]), np.array([2.0, 2.5]), np.array([3.2, 0.5])
    assert explaining_offsets(a, lambda: b) is b and explaining_offsets(a, lambda: c) is c
    assert explaining_offsets(c, lambda: a) is c and explaining_offsets(a, None) is a
    # Not computed where the plate chain explains every view, nor where it is far off.
    assert explaining_offsets(b, lambda: pytest.fail("computed")) is b
    far = np.array([1.0, STRIP_PLATE_MAX_PX + 0.1])
    assert explaining_offsets(far, lambda: b) is far
    assert explaining_offsets(np.array([np.inf, 1.0]), lambda: b)[0] == np.inf


@pytest.mark.parametrize("seed", [4100, 4101, 4102])
def test_clean_captures_are_ok_and_accurate(seed):
    capture = make_capture(seed, SyntheticOptions(cameras=2 + seed % 2))
    est = estimate(capture)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert est.tip_views == len(capture.views)
    assert _tip_mm(capture, est) < 3.0


def test_white_mask_is_a_poor_fit():
    capture = make_capture(4200, SyntheticOptions(cameras=2))
    v = capture.views[1]
    white = dataclasses.replace(capture, views=[capture.views[0], View(v.camera, np.ones_like(v.mask))])
    est = estimate(white)
    assert est.verdict is Verdict.POOR_FIT
    assert "view 1" in est.verdict_reason


def test_miscalibrated_camera_is_accurate_or_poor_fit():
    """A camera turned by 0.5 deg (12 px at the tape): the fit stays within 5 mm, or says
    it does not explain the views; never a confident wrong answer."""
    capture = make_capture(4300, SyntheticOptions(cameras=2))
    cam = capture.views[0].camera
    dR = cv2.Rodrigues(np.array([0.0, 1.0, 0.0]) * np.radians(0.5))[0]
    views = [View(cam.with_pose(dR @ cam.R, cam.t), capture.views[0].mask)] + list(capture.views[1:])
    est = estimate(dataclasses.replace(capture, views=views))
    assert est.verdict is Verdict.POOR_FIT or _tip_mm(capture, est) < 5.0


def test_judge_thresholds_per_view_not_per_camera_count():
    """The same per-view offsets give the same verdict with 2 and 3 cameras, and one view
    above the threshold is a poor fit however good the others are."""
    tip = np.zeros(3)
    assert judge(np.array([1.0, 1.2]), 2, 0.1, tip, [])[0] is Verdict.OK
    assert judge(np.array([1.0, 1.2, 1.1]), 3, 0.17, tip, [])[0] is Verdict.OK
    assert judge(np.array([0.5, 0.5, POOR_OFFSET_PX + 0.1]), 3, 0.1, tip, [])[0] is Verdict.POOR_FIT
    assert judge(np.array([1.0, 1.0, 1.0]), 1, 0.1, tip, [])[0] is Verdict.HIDDEN
    near, far = (0.105, np.array([0.005, 0, 0])), (0.105, np.array([0.03, 0, 0]))
    assert judge(np.array([1.0, 1.0]), 2, 0.1, tip, [near])[0] is Verdict.OK        # same hypothesis
    assert judge(np.array([1.0, 1.0]), 2, 0.1, tip, [far])[0] is Verdict.AMBIGUOUS
    assert judge(np.array([1.0, 1.0]), 2, 0.1, tip, [(0.5, far[1])])[0] is Verdict.OK  # clearly worse


def test_boundary_offset_is_xor_over_outline():
    assert np.allclose(boundary_offsets(np.array([0.1]), np.array([1000.0]), np.array([50.0])), [2.0])


def test_occlusion_geometry():
    box = Box("part", np.array([0.0, 0.0, 0.05]), np.array([0.1, 0.1, 0.1]), np.eye(3))
    eye = np.array([1.0, 0.0, 0.15])
    pts = np.array([[-0.1, 0.0, 0.05], [0.1, 0.0, 0.05], [0.0, 0.0, 0.1], [-0.1, 0.0, 0.2], [0.0, 0.0, 0.05]])
    # Behind the box; in front of it; on its top face (seen from above); above and behind
    # it; inside it.
    assert hidden(eye, pts, [box]).tolist() == [True, False, False, False, True]
    depth, grad = penetration(np.array([[0.0, 0.04, 0.05], [0.0, 0.2, 0.0]]), [box])
    assert depth[1] == 0.0 and np.isclose(depth[0], 0.05 - 0.04 - 0.001)
    # The gradient is the finite difference of the depth.
    p = np.array([[0.01, 0.02, 0.06]])
    d0, g = penetration(p, [box])
    fd = [(penetration(p + 1e-7 * e, [box])[0][0] - d0[0]) / 1e-7 for e in np.eye(3)]
    assert np.allclose(g[0], fd, atol=1e-5)


def test_compiled_occlusion_matches_reference():
    """The kernels' segment-box and penetration tests equal estimator/occlusion.py."""
    from tapecell.estimator import _kernels_boxes

    rng = np.random.default_rng(5)
    for _ in range(10):
        box = Box("b", rng.normal(size=3) * 0.1, rng.uniform(0.05, 0.2, 3), cv2.Rodrigues(rng.normal(size=3))[0])
        pts, eye = rng.normal(size=(300, 3)) * 0.2, rng.normal(size=3)
        arrays = _kernels_boxes.box_arrays([box])
        assert np.array_equal(hidden(eye, pts, [box]), _kernels_boxes.segments_hit_boxes(eye, pts, *arrays))
        d_ref, g_ref = penetration(pts, [box])
        d, g = _kernels_boxes.box_penetration(pts, *arrays)
        assert np.allclose(d, d_ref) and np.allclose(g[d > 0], g_ref[d > 0])
    # A table under the tape and a part on it, the camera above both: most points lie beyond
    # the table's top face with the camera (the kernel's shortcut), some beyond a face of the
    # part with it, some behind the part, on a face or inside a box.
    table = Box("table", np.array([0.0, 0.0, -0.5]), np.array([2.0, 2.0, 1.0]), np.eye(3))
    part = Box("part", np.array([0.1, 0.0, 0.05]), np.array([0.1, 0.2, 0.1]), cv2.Rodrigues(np.array([0, 0, 0.3]))[0])
    pts = rng.uniform([-0.2, -0.2, -0.05], [0.3, 0.2, 0.2], size=(2000, 3))
    pts[:20, 2] = 0.0                                   # on the table's top face
    for eye in (np.array([0.3, 0.2, 0.8]), np.array([0.1, 0.0, 0.4]), np.array([-0.5, 0.0, 0.05])):
        arrays = _kernels_boxes.box_arrays([table, part])
        got = _kernels_boxes.segments_hit_boxes(eye, pts, *arrays)
        assert np.array_equal(hidden(eye, pts, [table, part]), got)
        assert 0 < got.sum() < len(pts)
    # A sheet thinner than twice the surface margin: its shrunk half is negative, where the
    # shortcut does not hold; the kernel still agrees with the reference.
    sheet = Box("sheet", np.array([0.0, 0.0, 0.05]), np.array([0.2, 0.2, 0.0015]), np.eye(3))
    eye = np.array([0.0, 0.0, 0.5])
    pts = np.array([[0.0, 0.0, 0.0], [0.05, 0.02, -0.1], [0.0, 0.0, 0.2], [0.01, 0.0, 0.05]])   # the last in it
    arrays = _kernels_boxes.box_arrays([sheet])
    assert np.array_equal(hidden(eye, pts, [sheet]), _kernels_boxes.segments_hit_boxes(eye, pts, *arrays))


def test_curl_seen_from_one_direction_is_ambiguous():
    """Two cameras 20 mm apart at 600 mm see a curled tape from nearly one direction: the
    silhouettes leave the tip's depth open, so the estimate is "ambiguous" (or "hidden");
    never "ok"."""
    from tapecell.estimator import Camera, Capture, TapeSpec, forward_kinematics
    from tapecell.estimator.capture import Truth
    from tapecell.estimator.geometry import look_at
    from tapecell.estimator.silhouette import render_view

    trunk, left = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    normal = np.cross(trunk, left)
    spec = TapeSpec(np.full(5, 0.03), 0.03, np.zeros(3), np.column_stack([trunk, left, normal]))
    angles = np.zeros((5, 3))
    angles[1:, 1] = 0.45
    shape = forward_kinematics(spec, angles)
    target = np.array([0.0, 0.0, 0.075])
    views = []
    for k, dy in enumerate([-0.01, 0.01]):
        center = target + np.array([0.0, dy, 0.0]) + 0.6 * normal
        R = look_at(center, target, trunk).T
        cam = Camera(f"cam{k}", 640, 480, np.array([[1371.0, 0, 319.5], [0, 1371.0, 239.5], [0, 0, 1]]),
                     np.zeros(5), R, -R @ center)
        views.append(View(cam, render_view(cam, shape)))
    est = estimate(Capture(spec, views, Truth(np.arange(6) * 0.03, shape.nodes, shape.frames[-1])))
    # Either reason: the end's depth is open, or a distinct shape explains the views as well.
    assert est.verdict in (Verdict.AMBIGUOUS, Verdict.HIDDEN), est.verdict_reason


def test_unexplained_regions_near_the_tip():
    """Tape going on past the model's end (a thin sliver, as an end seen edge-on) is measured
    only where it reaches the tip's window."""
    from tapecell.estimator.verdict import unexplained_px

    model = np.zeros((120, 200), np.uint8)
    model[40:80, 20:100] = 1                      # the model ends at x = 100
    observed = model.copy()
    observed[58:60, 100:160] = 1                  # a 2-px sliver 60 px long past its end
    assert 55 <= unexplained_px(observed, model, np.array([100.0, 59.0])) <= 60
    # The same sliver seen from a tip far from it does not count.
    assert unexplained_px(observed, model, np.array([20.0, 59.0])) == 0.0
    # Model over background is not tape past the end.
    assert unexplained_px(model, observed, np.array([100.0, 59.0])) == 0.0
    # Offsets within the margin (calibration error of a few pixels) are explained.
    shifted = np.roll(model, 2, axis=1)
    assert unexplained_px(shifted, model, np.array([100.0, 59.0])) == 0.0
    # With the trunk's direction (+x, towards the tip): the sliver goes on 60 px past the
    # tip; a band of tape beside the end, behind the tip (a plate cutting across a curl),
    # is no tape past the end.
    trunk = np.array([10.0, 0.0])
    assert 55 <= unexplained_px(observed, model, np.array([100.0, 59.0]), trunk) <= 61
    beside = model.copy()
    beside[84:88, 40:101] = 1                     # 4 px below the model, ending at the tip
    assert unexplained_px(beside, model, np.array([100.0, 79.0])) >= 55
    assert unexplained_px(beside, model, np.array([100.0, 79.0]), trunk) <= 10
    # A thin band along the tip edge, 5 px past it (an end edge a little curved or tilted
    # against the model's, as a shell tape's; shell 891007, 3 cameras, was poor_fit 1.3 mm
    # off): measured from the tip edge it goes on 5 px, from the tip's middle 20 px; the
    # sliver past the end goes on as far either way.
    from tapecell.estimator.verdict import unexplained

    band = model.copy()
    band[40:80, 104:106] = 1
    tip, half = np.array([100.0, 59.5]), np.array([0.0, 20.0])
    assert unexplained(band, model, tip, trunk)[1] >= 19
    assert unexplained(band, model, tip, trunk, half)[1] <= 7
    assert 55 <= unexplained(observed, model, tip, trunk, half)[1] <= 61
    # A tip edge seen edge-on projects along the trunk: only its part across the trunk
    # counts, so the sliver past the end is measured in full; a corner projected near the
    # camera's plane (a huge half vector) counts no farther than 3 times the trunk's 10 mm.
    assert 55 <= unexplained(observed, model, tip, trunk, np.array([45.0, 0.0]))[1] <= 61
    assert 55 <= unexplained(observed, model, tip, trunk, np.array([40.0, 10.0]))[1] <= 61
    long_band = model.copy()
    long_band[:, 104:106] = 1                     # past the tip edge and 40 px beyond its corners
    short_trunk = np.array([5.0, 0.0])            # 10 mm of trunk over 5 px: the cap is 15 px
    assert unexplained(long_band, model, tip, short_trunk, half)[1] >= 39
    assert unexplained(long_band, model, tip, short_trunk, np.array([0.0, 1e9]))[1] >= 44
    assert unexplained(band, model, tip, np.array([10.0, 0.0]), np.array([np.nan, 1.0]))[1] >= 19


def test_a_band_along_the_models_edge_does_not_keep_a_view_from_locating_the_end():
    """The third measure of ``unexplained``: unexplained tape near the tip counts against a
    view locating the end only where it departs from the model's silhouette by more than
    LOCATE_BAND_PX; a band along the model's edge (a curled corner, calibration error) does
    not, tape going on past the end does."""
    from tapecell.estimator.verdict import LOCATE_BAND_PX, LOCATE_UNEXPLAINED_PX, unexplained

    model = np.zeros((120, 200), np.uint8)
    model[40:80, 20:100] = 1                      # the model ends at x = 100
    tip, trunk, half = np.array([100.0, 70.0]), np.array([10.0, 0.0]), np.array([0.0, 10.0])
    near = int(np.floor(LOCATE_BAND_PX))          # rows 1..near px below the model (7 of 7.5)
    band = model.copy()
    band[80:80 + near, 60:101] = 1                # 40 px along the model's lower edge, to the tip
    longest, _, departing = unexplained(band, model, tip, trunk, half)
    assert longest > LOCATE_UNEXPLAINED_PX and departing == 0.0
    wide = model.copy()
    wide[80:80 + near + 1, 60:101] = 1            # one row more, 8 px from the model: it departs
    assert unexplained(wide, model, tip, trunk, half)[2] > LOCATE_UNEXPLAINED_PX
    past = model.copy()
    past[58:60, 100:160] = 1                      # a sliver going on 60 px past the end
    assert 55 <= unexplained(past, model, tip, trunk, half)[2] <= 61


def test_a_curled_corner_beside_a_right_end_is_located_and_a_stretch_the_model_misses_is_not():
    """Simulated captures. sim-chain-c2-981017: the end's corner curls, leaving a band of
    observed tape 21 px long along the model's edge, at most 7.4 px from it, in the view
    that locates the end besides another: "ok", within 1 mm (it was "hidden"). And
    sim-shell-c3-964007: observed tape the plate chain leaves out near the tip, 76-79 px
    long and 9.6-11.2 px from the model in two views; a band rule 11 px wide made an
    answer 8.7 mm off "ok". It must not be "ok" off by more than 3 mm."""
    from tapecell.estimator import load_capture

    good = load_capture(DATA / "sim-chain-c2-981017")
    est = estimate(good)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert _tip_mm(good, est) < 1.0
    bad = load_capture(DATA / "sim-shell-c3-964007")
    est = estimate(bad)
    assert est.verdict is not Verdict.OK or _tip_mm(bad, est) < 3.0, f"ok at {_tip_mm(bad, est):.1f} mm"


def test_an_ambiguous_answer_whose_one_rival_ends_where_it_does_is_ok():
    """sim-chain-c2-981000: the first answer (its strip's chain, cost 0.075) was ambiguous
    with one rival, a plate fit 14 mm away (0.069). Made the chain the estimator outputs,
    the rival's strip ends within 0.5 mm of the answer's end: one end, no rival left. "ok"
    within 0.5 mm (it was "ambiguous": "not sure of either")."""
    from tapecell.estimator import load_capture

    capture = load_capture(DATA / "sim-chain-c2-981000")
    est = estimate(capture)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert _tip_mm(capture, est) < 0.5


def test_tape_past_the_models_end_is_never_ok():
    """One view shows the tape going on 60 px past where every 5-plate chain of its length
    must end (a sliver, as an end seen edge-on): the estimate must not be "ok"."""
    capture = make_capture(4101, SyntheticOptions(cameras=2))
    v = capture.views[0]
    tip = v.camera.project(capture.truth.points[-1:])[0]
    back = v.camera.project(capture.truth.points[-5:-4])[0]
    d = (tip - back) / np.linalg.norm(tip - back)
    mask = v.mask.copy()
    far = tip + 60 * d
    cv2.line(mask.view(np.uint8), tuple(int(x) for x in np.rint(tip)), tuple(int(x) for x in np.rint(far)), 1, 2)
    views = [View(v.camera, mask)] + list(capture.views[1:])
    est = estimate(dataclasses.replace(capture, views=views))
    assert est.verdict is not Verdict.OK, f"ok at {_tip_mm(capture, est):.1f} mm"


def test_a_tape_seen_end_on_does_not_locate_its_tip():
    """The tip edge's corners near the outline and its middle deep inside the silhouette (a
    tape seen along its length): that view does not locate the end."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _on_outline

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    observed = np.zeros((200, 200), np.uint8)
    observed[60:140, 60:140] = 1
    # Pixels (u, v) = 100 x / z + 100 at z = 1: u 65, 100, 135 on the row v = 100.
    end_on = np.array([[-0.35, 0.0, 1.0], [0.0, 0.0, 1.0], [0.35, 0.0, 1.0]])
    assert not _on_outline(View(cam, observed.astype(bool)), observed, (0, 0), end_on)
    on_edge = end_on + np.array([0.0, 0.37, 0.0])   # the row v = 137, 3 px in from the edge
    assert _on_outline(View(cam, observed.astype(bool)), observed, (0, 0), on_edge)


def test_an_end_at_an_occluders_edge_is_not_located():
    """A silhouette that ends where a scene box (or ignored pixels) starts hiding the tape's
    continuation does not locate the end: the tape may go on behind it."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _continuation_visible

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    view = View(cam, np.zeros((200, 200), bool))
    tip = np.array([0.0, 0.0, 1.0])
    tip_rotation = np.eye(3)            # trunk +x, left +y
    width = 0.03
    assert _continuation_visible(view, (), tip, tip_rotation, width)
    # A box in front of the camera covering x >= 0.002 at the tape's depth.
    box = Box("part", np.array([0.052, 0.0, 0.9]), np.array([0.1, 0.2, 0.05]), np.eye(3))
    assert not _continuation_visible(view, (box,), tip, tip_rotation, width)
    # The same box behind the tape hides nothing.
    behind = Box("part", np.array([0.052, 0.0, 1.2]), np.array([0.1, 0.2, 0.05]), np.eye(3))
    assert _continuation_visible(view, (behind,), tip, tip_rotation, width)
    # Ignored pixels past the tip (an arm in the way).
    ignore = np.zeros((200, 200), bool)
    ignore[:, 100:] = True
    assert not _continuation_visible(View(cam, view.mask, ignore), (), tip, tip_rotation, width)


def test_an_end_seen_edge_on_as_a_sliver_is_told():
    """Every pixel of a 1-3 px sliver is on its outline: a view whose tape near the tip's
    projection is that thin says nothing by its outline about where along it the end is
    (such a view locates the end only as below)."""
    from tapecell.estimator.verdict import _thin_at

    def band(rows: int) -> np.ndarray:
        m = np.zeros((60, 80), np.uint8)
        m[30 - rows // 2:30 - rows // 2 + rows, 5:71] = 1
        return m
    tip = np.array([70.0, 30.0])
    assert _thin_at(band(3), (0, 0), tip) and _thin_at(band(4), (0, 0), tip)      # seen edge-on
    assert not _thin_at(band(6), (0, 0), tip) and not _thin_at(band(13), (0, 0), tip)
    assert not _thin_at(band(3), (0, 0), tip + [200.0, 0.0])       # no tape near the tip: not this rule's
    # In a crop that starts elsewhere in the image, the tip's image pixel is shifted alike.
    assert _thin_at(band(3), (100, 50), tip + [100.0, 50.0]) and not _thin_at(band(3), (100, 50), tip)


def test_an_end_hooked_over_the_body_is_located_by_the_part_of_its_edge_against_the_background():
    """The tip edge's middle over the body, but a quarter of the edge from one corner on the
    outline (a notch's side): that view locates the end; the same edge well inside the
    silhouette does not."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _on_outline

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    observed = np.zeros((200, 200), np.uint8)
    observed[40:160, 60:140] = 1      # the body
    observed[40:101, 140:180] = 1     # the end hooked over it, its edge on the row v = 100
    # The edge from u = 60 (the body's side) to u = 180 (the hook's corner), 9 points: its
    # middle (u = 120) 20 px deep in the body.
    edge = np.column_stack([np.linspace(-0.4, 0.8, 9), np.zeros(9), np.ones(9)])
    view = View(cam, observed.astype(bool))
    assert _on_outline(view, observed, (0, 0), edge)
    inside = edge - np.array([0.0, 0.15, 0.0])   # the row v = 85: 15 px inside the hook
    assert not _on_outline(view, observed, (0, 0), inside)
    # A model edge reaching out over the background (u 20-50, left of the body) and then deep
    # into it: no stretch of it is on the outline (a wrong "ok" 41 mm off in an episode).
    out_over = np.column_stack([np.linspace(-0.8, 0.4, 9), np.zeros(9), np.ones(9)])
    body = np.zeros((200, 200), np.uint8)
    body[40:160, 60:140] = 1
    assert not _on_outline(View(cam, body.astype(bool)), body, (0, 0), out_over)


def test_a_tip_edge_running_from_the_outline_into_the_body_does_not_locate_the_end():
    """One corner of the tip edge on the outline, its middle 9 px in and its other corner 17 px
    in: the edge runs into the body, the end lies over it, and the silhouette's edge there
    is the body's (part-990066 was "ok" 32.6 mm off so; below). Both corners and the middle
    must be near the background (or a long enough stretch from a corner on the outline)."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _on_outline

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    observed = np.zeros((200, 200), np.uint8)
    observed[40:160, 60:140] = 1      # the body; its left side at u = 60
    view = View(cam, observed.astype(bool))
    # From (61, 100) to (77, 112) in the image: 20 px long, at ~53 deg to the outline.
    into = np.column_stack([np.linspace(-0.39, -0.23, 9), np.linspace(0.0, 0.12, 9), np.ones(9)])
    assert not _on_outline(view, observed, (0, 0), into)
    # The same edge turned along the outline, 3 px in: located.
    along = np.column_stack([np.full(9, -0.37), np.linspace(0.0, 0.2, 9), np.ones(9)])
    assert _on_outline(view, observed, (0, 0), along)
    # An end hooked over the body: half its edge along the outline 5 px in (u = 64; the
    # background starts at u = 59), then diving into the body. Its stretch from the corner
    # locates it (EDGE_RUN_PX = 5, Euclidean; a shell tape's hooked end, 2 mm off).
    hooked = np.column_stack([np.r_[np.full(5, -0.36), np.linspace(-0.26, 0.04, 4)],
                              np.r_[np.linspace(0.0, 0.3, 5), np.full(4, 0.3)], np.ones(9)])
    assert _on_outline(view, observed, (0, 0), hooked)
    # The same stretch 4 px out over the background (u = 56): no edge seen there, the tape
    # must be within 3 px (EDGE_RUN_TAPE_PX; occluded-996052 was "ok" 6.2 mm off with 5).
    assert not _on_outline(view, observed, (0, 0), hooked - np.array([0.08, 0.0, 0.0]))


def test_the_rule_that_locates_a_tip_edge_is_named():
    """outline_rule says which rule put a tip edge at the outline: "edge" (both corners and
    the middle near background), "hook" (a stretch from one corner), "hook_across" (a
    stretch from a corner, both corners near background, the middle inside: the estimate
    then gets the second look, fit.HOOKED_ACROSS_LOOK), "" (none)."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import outline_rule

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    body = np.zeros((200, 200), np.uint8)
    body[40:160, 60:140] = 1
    view = View(cam, body.astype(bool))
    along = np.column_stack([np.full(9, -0.37), np.linspace(0.0, 0.2, 9), np.ones(9)])
    assert outline_rule(view, body, (0, 0), along) == "edge"
    hooked = np.column_stack([np.r_[np.full(5, -0.36), np.linspace(-0.26, 0.04, 4)],
                              np.r_[np.linspace(0.0, 0.3, 5), np.full(4, 0.3)], np.ones(9)])
    assert outline_rule(view, body, (0, 0), hooked) == "hook"
    into = np.column_stack([np.linspace(-0.39, -0.23, 9), np.linspace(0.0, 0.12, 9), np.ones(9)])
    assert outline_rule(view, body, (0, 0), into) == ""
    hook = body.copy()
    hook[40:101, 140:180] = 1          # an end hooked over the body, its edge on the row v = 100
    across = np.column_stack([np.linspace(-0.4, 0.8, 9), np.zeros(9), np.ones(9)])
    assert outline_rule(View(cam, hook.astype(bool)), hook, (0, 0), across) == "hook_across"


def test_an_end_located_across_a_hook_gets_the_second_look(monkeypatch):
    """Fresh bench capture part-1017027 (3 cameras, the true cameras): the first look's end
    was "ok" 9.45 mm off, one view locating it as a hooked end whose tip edge had both
    corners on the outline and its middle inside the silhouette. Such an "ok" gets the
    second look (fit.HOOKED_ACROSS_LOOK), which finds the end within 2.5 mm."""
    from tapecell.estimator import fit

    capture = make_capture(1017027, SyntheticOptions(cameras=3, part=True))
    monkeypatch.setattr(fit, "HOOKED_ACROSS_LOOK", 0)
    first = estimate(capture)
    assert first.verdict is Verdict.OK and _tip_mm(capture, first) > 8.0
    monkeypatch.setattr(fit, "HOOKED_ACROSS_LOOK", 1)
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 2.5


def test_a_tip_edge_inside_a_views_outline_all_along_does_not_locate_the_end():
    """A fresh part capture (997000): one view sees the tape face on, its end curled over
    the body, and the silhouette's edge there a fold. The fit's tip edge lay 10-11 px inside
    that outline all along, and within EDGE_PX = 10 it located the end: "ok" 9.4 mm off.
    With 8 px it does not."""
    capture = make_capture(997000, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert not (est.verdict is Verdict.OK and _tip_mm(capture, est) > 5.0), f"ok {_tip_mm(capture, est):.1f} mm off"


def test_a_view_explained_to_under_3_px_but_over_2_5_px_is_not_ok():
    """A fresh part capture (1010016): the tape comes out from behind the part and its end
    curls back; the fit bent it the wrong way, its end's image a few px from the true one in
    both views, and "ok" 10.4 mm off with one view explained only to 2.72 px. Above
    POOR_OFFSET_PX = 2.5 such a view is not explained (3.0 before)."""
    capture = make_capture(1010016, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert not (est.verdict is Verdict.OK and _tip_mm(capture, est) > 5.0), f"ok {_tip_mm(capture, est):.1f} mm off"


def test_background_within_a_disc():
    """The run of the tip edge on the outline is measured in Euclidean pixels: background 4 px
    across and 4 px down (5.7 px) is not within 5 px; 5 px straight across is."""
    from tapecell.estimator.verdict import _background_within

    tape = np.ones((40, 40), np.uint8)
    tape[24, 24] = 0                     # one background pixel
    assert not _background_within(tape, 20, 20, 5.0)
    assert _background_within(tape, 19, 24, 5.0) and _background_within(tape, 20, 20, 5.7)
    assert _background_within(tape, 2, 20, 5.0)       # the crop's outside is background


def test_an_end_over_the_body_behind_which_the_part_hides_its_base_is_not_ok():
    """A fresh part capture (990066): the tape rises from behind the part and folds back
    down towards one camera, its end over its own body in that view. The fit's end, 33 mm
    off, had one corner of its tip edge on that view's outline and the rest running into
    the body: it was "ok" with two views locating it. Now that view does not locate it."""
    capture = make_capture(990066, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert not (est.verdict is Verdict.OK and _tip_mm(capture, est) > 5.0), f"ok {_tip_mm(capture, est):.1f} mm off"
    if _tip_mm(capture, est) > 10.0:
        assert est.tip_views < 2, est.verdict_reason


def test_disagreement_at_a_boxs_edge_does_not_make_a_view_unexplained():
    """Where a view is not explained, the pixels where it and the model disagree within
    BOX_OUTLINE_PX of a scene box's projected outline (where the tape comes out from behind
    the box: its pose and the calibration, known to a few pixels) do not count; the same
    disagreement far from every box's outline counts in full."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import POOR_OFFSET_PX, box_edge_offsets, view_offsets

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    # A box whose projected outline's left side is the column u = 100 (x = 0 at every depth),
    # rows v = 64-136.
    box = Box("part", np.array([0.25, 0.0, 1.5]), np.array([0.5, 1.0, 0.2]), np.eye(3))
    model = np.zeros((200, 200), np.uint8)
    model[70:130, 30:97] = 1            # the model's tape stops 3 px short of the box
    observed = model.copy()
    observed[70:130, 97:100] = 1        # the view's goes on to the box's edge
    offsets = np.array([4.0])           # (as if) not explained
    view = View(cam, observed.astype(bool))
    assert box_edge_offsets([view], (box,), [observed], [model], [(0, 0)], offsets)[0] == 0.0
    # The same band far from the box's edge: unchanged.
    shifted, shifted_model = np.roll(observed, -40, axis=1), np.roll(model, -40, axis=1)
    assert box_edge_offsets([view], (box,), [shifted], [shifted_model], [(0, 0)], offsets)[0] == 4.0
    # Half of the disagreement at the edge, half far from it: half counts.
    both = shifted.copy()
    both[70:130, 97:100] = 1
    assert box_edge_offsets([view], (box,), [both], [shifted_model], [(0, 0)], offsets)[0] == 2.0
    # Without boxes, or for a view already explained, nothing changes.
    assert box_edge_offsets([view], (), [observed], [model], [(0, 0)], offsets)[0] == 4.0
    assert box_edge_offsets([view], (box,), [observed], [model], [(0, 0)], np.array([POOR_OFFSET_PX]))[0] == POOR_OFFSET_PX
    assert view_offsets(np.array([0.5]), [observed], [model])[0] > 0


def test_the_base_check_cuts_the_model_finely_where_the_part_hides_it(monkeypatch):
    """A fresh part capture (993053, 3 cameras) fitted within 0.5 mm: the tape's base is at
    the part's edge, and the fit's coarse occlusion (3 x 3 cells a plate) drew the first
    plate's cell whole though the part hides its first few mm, 10 px of model the view does
    not show next to the base: the base check refused it (6.5 px). Cut in 2.5 mm cells for
    the base check (fit.BASE_OCCLUSION_CELLS) the model meets the tape there."""
    from tapecell.estimator import fit

    capture = make_capture(993053, SyntheticOptions(part=True, cameras=3))
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 1.0, est.verdict_reason
    monkeypatch.setattr(fit, "BASE_OCCLUSION_CELLS", 3)
    # (Three cameras: the cameras corrected from the views, fit.SELF_CALIBRATE, make the coarse
    # cut's poor_fit "ok" as well, by turning them to meet the base; the check alone is tested.)
    monkeypatch.setattr(fit, "SELF_CALIBRATE", False)
    coarse = estimate(capture)
    assert coarse.verdict is Verdict.POOR_FIT and "at its base" in coarse.verdict_reason


def test_an_end_short_of_the_image_border_is_located_one_at_the_border_is_not():
    """The tape's continuation past the tip would leave the image: where the view shows
    background between the tip and the border the silhouette's end is the tape's; where the
    silhouette runs into the border it may go on beyond it."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _continuation_visible

    cam = Camera("c", 200, 200, np.array([[1000.0, 0, 100], [0, 1000.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    # 1 px per mm at z = 1 m: the tip on the row v = 194, the tape hanging down the image (+y).
    tip = np.array([0.0, 0.094, 1.0])
    tip_rotation = np.column_stack([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    ends_short = np.zeros((200, 200), np.uint8)
    ends_short[100:195, 85:116] = 1
    view = View(cam, ends_short.astype(bool))
    assert _continuation_visible(view, [], tip, tip_rotation, 0.030, ends_short, (0, 0))
    at_border = np.zeros((200, 200), np.uint8)
    at_border[100:200, 85:116] = 1
    assert not _continuation_visible(View(cam, at_border.astype(bool)), [], tip, tip_rotation, 0.030, at_border,
                                     (0, 0))


def test_a_second_look_does_not_trade_a_better_unsure_shape_for_a_worse_ok_one():
    """After the second look, an "ok" shape that costs more than the first look's unsure one
    and ends elsewhere makes the first look ambiguous (the second its alternative); the same
    hypothesis (tips within 10 mm) located is taken; a clearly worse one is not."""
    from tapecell.estimator.fit import _second_look

    est = estimate(make_capture(3, SyntheticOptions(cameras=2)))
    first = dataclasses.replace(est, verdict=Verdict.HIDDEN, cost=0.070, alternatives=())
    far = dataclasses.replace(est, verdict=Verdict.OK, cost=0.090, tip_position=est.tip_position + [0.016, 0, 0])
    out = _second_look(first, far, folded=False)
    assert out.verdict is Verdict.AMBIGUOUS and out.cost == 0.070
    assert len(out.alternatives) == 1 and np.allclose(out.alternatives[0].tip_position, far.tip_position)
    near = dataclasses.replace(far, tip_position=est.tip_position + [0.004, 0, 0])
    assert _second_look(first, near, folded=False) is near
    worse = dataclasses.replace(far, cost=0.200)
    assert _second_look(first, worse, folded=False) is first
    better = dataclasses.replace(far, cost=0.050)
    assert _second_look(first, better, folded=False) is better
    # A poor fit keeps its verdict and reason (an episode's needle reads it), the far "ok"
    # shape added as its alternative.
    poor = dataclasses.replace(first, verdict=Verdict.POOR_FIT, verdict_reason="view 0 shows tape past the end")
    out = _second_look(poor, far, folded=False)
    assert out.verdict is Verdict.POOR_FIT and out.verdict_reason == poor.verdict_reason
    assert len(out.alternatives) == 1


def test_background_just_short_of_a_box_does_not_locate_the_end():
    """The tape's continuation would go behind a box: a gap of a pixel or two between the
    silhouette's end and the box's projected outline (segmentation at an occluding edge) is
    no background seen; a clear gap is."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _continuation_visible

    cam = Camera("c", 400, 400, np.array([[1000.0, 0, 200], [0, 1000.0, 200], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    tip_rotation = np.column_stack([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    # A box in front of the tape (z 0.5-0.6 m) whose top edge projects on the row v = 205.
    box = Box("part", np.array([0.0, 0.05 + 0.0025, 0.55]), np.array([0.2, 0.1 + 0.005, 0.1]), np.eye(3))
    top = box.center[1] - box.size[1] / 2
    edge_row = 1000.0 * top / (box.center[2] - box.size[2] / 2) + 200.0
    tip = np.array([0.0, 0.0, 1.0])
    for gap, located in ((1, False), (2, False), (12, True)):
        v_tip = edge_row - gap
        tip[1] = (v_tip - 200.0) / 1000.0
        mask = np.zeros((400, 400), np.uint8)
        mask[100:int(round(v_tip)) + 1, 185:216] = 1
        view = View(cam, mask.astype(bool))
        assert _continuation_visible(view, [box], tip, tip_rotation, 0.030, mask, (0, 0)) is located, gap


def test_a_sliver_view_locates_the_end_only_where_the_model_explains_all_of_it():
    """verdict._explained: a sliver the model covers is explained; the same sliver going on
    as dots past the model's end (segmentation breaks up a thinning sliver) is not, however
    small the dots."""
    from tapecell.estimator.verdict import _explained

    observed = np.zeros((60, 200), np.uint8)
    observed[29:32, 5:100] = 1
    model = observed.copy()
    assert _explained(observed, model)
    dotted = observed.copy()
    dotted[30, 110:190:6] = 1                     # single pixels every 6 px
    assert not _explained(dotted, model)
    shifted = np.roll(model, 2, axis=0)           # a model 2 px off explains it (the margin)
    assert _explained(observed, shifted)


def test_sliver_views_on_simulated_captures():
    """MuJoCo captures (2 cameras, `tapecell sim`'s renderer) whose one view sees the end
    edge-on as a sliver. sim-chain-c2-610001: the model explains that view whole and the
    other view locates the end: "ok", the tip within 1.5 mm (it was "hidden").
    sim-chain-c2-880028: the same, while the locating view has a few dozen observed pixels
    the plate chain leaves out along the body (46 in 4 regions): "ok" within 0.5 mm (it was
    "hidden" while every view had to be explained whole). Shell tape 550008: an earlier fit
    ended 81 mm short where the sliver broke into dots, and was "ok"; it must never be "ok"
    far from the end (today's fit ends within 1 mm)."""
    from tapecell.estimator import load_capture

    for name, within in (("sim-chain-c2-610001", 1.5), ("sim-chain-c2-880028", 0.5)):
        good = load_capture(DATA / name)
        est = estimate(good)
        assert est.verdict is Verdict.OK, f"{name}: {est.verdict_reason}"
        assert _tip_mm(good, est) < within
    bad = load_capture(DATA / "sim-shell-c2-550008")
    est = estimate(bad)
    assert est.verdict is not Verdict.OK or _tip_mm(bad, est) < 3.0, f"ok at {_tip_mm(bad, est):.1f} mm"


def test_a_view_of_the_tape_edge_on_is_fitted_not_cropped():
    """A simulated episode's capture (seed 832078, 2 cameras) whose first camera sees the
    upper tape edge-on: a line one pixel wide above the base, with too few pixels per row
    for the crop's speckle rule, which cropped it off, and the fit went 43 mm astray
    (poor_fit). The view's crop holds the whole line, and the fit is within 1 mm; that view
    sees the end only as a sliver, so the verdict is "hidden" (the needle confirms it) or,
    were that view's sliver explained whole, "ok"; never poor_fit."""
    from tapecell.estimator import load_capture
    from tapecell.estimator.views import prepare

    capture = load_capture(DATA / "sim-chain-c2-832078")
    view = capture.views[0]
    ys, xs = np.nonzero(view.mask)
    field = prepare(view, capture.scene)
    h, w = field.planes[0].shape
    assert field.y0 <= ys.min() and field.y0 + h >= ys.max() + 1
    assert field.x0 <= xs.min() and field.x0 + w >= xs.max() + 1
    est = estimate(capture)
    assert _tip_mm(capture, est) < 1.0
    assert est.verdict in (Verdict.OK, Verdict.HIDDEN), est.verdict_reason


def test_a_hairpin_fold_at_the_end_gets_the_thorough_look():
    """A simulated episode's capture (seed 850037, 2 cameras): the tape's end folds back over
    its body in a hairpin. The first look misses the hairpin and returns a shape bending
    sideways at the end, 20 mm off, that it calls "ok"; its end turns more than END_FOLD_DEG
    from the plate before the last, so it gets the thorough look, which finds the
    hairpin: not "ok", the true shape an alternative within 1.5 mm (0.4 mm before the joints'
    lines were outline, FitConfig.crease_t; 1.2 mm with them: the alternative's chain
    differs, the answer and the verdict do not). Since FitConfig.wide_misfit_px is 4.0 (4.5
    before), the first look's wide search finds the hairpin itself, as an alternative; the
    mechanism is tested with 4.5, and the default answer must be as safe. Since no
    alternative may explain the views better than the answer (fit._cheapest_first), the
    hairpin, 0.9 mm off and cheaper once its end is fitted, is the answer ("hidden"), the
    shape 20 mm off its alternative."""
    from tapecell.estimator import forward_kinematics, load_capture
    from tapecell.estimator.verdict import END_FOLD_DEG

    capture = load_capture(DATA / "sim-chain-c2-850037")
    before = dataclasses.replace(DEFAULT_CONFIG, wide_misfit_px=4.5)
    first = estimate(capture, second_look=False, config=before)
    assert first.verdict is Verdict.OK and _tip_mm(capture, first) > 10.0
    frames = forward_kinematics(capture.tape, first.angles).frames
    assert frames[-2][:, 0] @ first.tip_rotation[:, 0] < np.cos(np.radians(END_FOLD_DEG))
    for config in (before, DEFAULT_CONFIG):
        est = estimate(capture, config=config)
        assert est.verdict is not Verdict.OK
        assert _tip_mm(capture, est) < 1.5
        assert all(a.compared_cost >= est.cost for a in est.alternatives)


def test_an_end_hooked_back_out_of_sight_is_found_by_the_thorough_look():
    """A simulated episode's capture (seed 857182, 2 cameras): the tape rises and its end
    hooks back down behind its own body, out of sight from both cameras. The first look
    returns a shape 45 mm off, "hidden" (a poor_fit since 2026-11-27, below); the thorough
    look a "hidden" answer gets refines the first stage's winner with
    its end hooked back (FitConfig.hook_bends) and finds the true shape within 2 mm, which
    explains the views better, with the first as an alternative for the needle. Without
    the hooks the thorough look does not find it. (So it is without the joints' lines in
    the model's outline, FitConfig.crease_t; with them the first look finds the hook.)"""
    from tapecell.estimator import load_capture

    capture = load_capture(DATA / "sim-chain-c2-857182")
    now = estimate(capture, second_look=False)
    assert _tip_mm(capture, now) < 2.0
    assert _tip_mm(capture, estimate(capture)) < 2.0
    plain = BEFORE_LINES
    first = estimate(capture, second_look=False, config=plain)
    assert first.verdict is not Verdict.OK and _tip_mm(capture, first) > 10.0
    # The thorough look a "hidden" first look gets. (Since 2026-11-27 this first look is a
    # poor_fit, not hidden: verdict.EDGE_RUN_PX now lets view 0 see its end, and tape goes
    # on past it there. Its second look then has no hooks; the default config finds the
    # hook in the first look, above.)
    est = estimate(capture, thorough=True, config=plain)
    assert _tip_mm(capture, est) < 2.0 and est.cost < first.cost
    assert est.verdict is not Verdict.OK   # the first look's shape is a close rival: the needle decides
    assert any(np.linalg.norm(a.tip_position - first.tip_position) < 0.001 for a in est.alternatives)
    unhooked = estimate(capture, thorough=True, config=dataclasses.replace(plain, hook_bends=()))
    assert _tip_mm(capture, unhooked) > 10.0


def test_an_end_seen_end_on_gets_the_thorough_look():
    """A simulated episode's capture (seed 839020, 2 cameras): the first look's answer is
    "ok" 14.9 mm off, its end 13 deg from the second camera's line of sight (END_ON_DEG).
    That view leaves the end's depth less constrained, so the estimate gets the thorough
    look, which finds the true shape (within 2 mm) and explains the views better. (So it
    is without the joints' lines in the model's outline, FitConfig.crease_t; with them the
    first look's answer is "hidden".)"""
    from tapecell.estimator import load_capture
    from tapecell.estimator.verdict import end_on

    capture = load_capture(DATA / "sim-chain-c2-839020")
    now = estimate(capture)
    assert now.verdict is not Verdict.OK or _tip_mm(capture, now) < 2.0
    plain = BEFORE_LINES
    first = estimate(capture, second_look=False, config=plain)
    assert first.verdict is Verdict.OK and _tip_mm(capture, first) > 10.0
    assert any(end_on(v, first.tip_position, first.tip_rotation) for v in capture.views)
    est = estimate(capture, config=plain)
    assert _tip_mm(capture, est) < 2.0 and est.cost < first.cost


def test_the_crop_keeps_thin_lines_and_drops_speckles():
    """views._crop_box: a one-pixel line on a blob is kept in the crop; speckles (smaller
    than speckle_px) far away do not stretch it."""
    from tapecell.estimator.views import _crop_box

    m = np.zeros((200, 300), bool)
    m[150:180, 100:140] = True            # the tape's base, seen face-on
    m[40:150, 120] = True                 # the tape above it, edge-on: one pixel per row
    m[10, 280] = m[190, 5] = m[100, 250] = True
    assert _crop_box(m, DEFAULT_CONFIG) == (100, 40, 140, 180)


def test_an_end_where_the_tape_leaves_the_image_is_not_located():
    """verdict._clear_of_border: observed tape on the image's border within 20 px of the tip
    edge: the tape may go on out of view, so that view does not locate the end; the same end
    far from the border, or tape that leaves the image far from it, does, and so does an end
    that touches the border with a corner only (a stretch shorter than half its tip edge)."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import _clear_of_border

    cam = Camera("c", 200, 200, np.array([[100.0, 0, 100], [0, 100.0, 100], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    # A band leaving the image at the bottom; the crop is its rows 120..199, columns 80..119.
    observed = np.zeros((80, 40), np.uint8)
    observed[:, 10:30] = 1
    view = View(cam, np.zeros((200, 200), bool))
    # The tip edge's points at pixel rows 190 (near the border) and 130 (clear of it), z = 1.
    near = np.array([[-0.1, 0.9, 1.0], [0.0, 0.9, 1.0], [0.1, 0.9, 1.0]])
    far = near - np.array([0.0, 0.6, 0.0])
    assert not _clear_of_border(view, observed, (80, 120), near)
    assert _clear_of_border(view, observed, (80, 120), far)
    # The same crop not on the image's border (its rows 100..179): nothing leaves the image.
    assert _clear_of_border(view, observed, (80, 100), near - np.array([0.0, 0.2, 0.0]))
    # An end short of the border whose one corner touches it (3 of the 20 px of its tip edge,
    # less than BORDER_RUN_FRACTION: shell-963019): the tape does not cross the border there.
    corner = np.zeros((80, 40), np.uint8)
    corner[:75, 10:30] = 1
    corner[75:, 10:13] = 1
    assert _clear_of_border(view, corner, (80, 120), near)
    corner[75:, 10:21] = 1           # 11 px: more than half the tip edge, the tape may go on
    assert not _clear_of_border(view, corner, (80, 120), near)
    # A band crossing the border with its border row cut by ignored pixels (8 + 9 px, each
    # stretch shorter than half the tip edge): counted whole, it crosses.
    split = np.zeros((80, 40), np.uint8)
    split[:, 10:28] = 1
    ignore = np.zeros((200, 200), bool)
    ignore[199, 98] = True
    split[79, 18] = 0
    assert not _clear_of_border(View(cam, np.zeros((200, 200), bool), ignore), split, (80, 120), near)


def test_a_garbage_view_is_refused_without_a_second_look(monkeypatch):
    """A white mask makes the estimate poor_fit whatever the other view's fit says: that fit
    gets no second, thorough look (it cannot change the verdict, and it doubled the time)."""
    from tapecell.estimator import fit

    looks = []
    real = fit.fit_default

    def counted(capture, callback=None, thorough=False, cfg=fit.DEFAULT, first=None):
        looks.append(thorough)
        return real(capture, callback, thorough, cfg, first)

    monkeypatch.setattr(fit, "fit_default", counted)
    capture = make_capture(4200, SyntheticOptions(cameras=2))
    v = capture.views[1]
    est = estimate(dataclasses.replace(capture, views=[capture.views[0], View(v.camera, np.ones_like(v.mask))]))
    assert est.verdict is Verdict.POOR_FIT
    assert looks == [False]


def test_a_rival_the_first_look_found_is_not_lost_by_the_second():
    """Synthetic capture 866008 (2 cameras): the first look's answer is 24 mm off and
    ambiguous, with a shape 3.5 mm off that explains the views nearly as well. The thorough
    look does not refine that shape again (the first look's wide search found it) and
    answered "ok" at the same tip: a wrong "ok". The first look's rival, still close in
    cost to the final answer, keeps it ambiguous, the rival among its alternatives. (So it
    is without the joints' lines in the model's outline, FitConfig.crease_t; with them
    both looks find a shape within 5 mm, and one camera alone sees its end.)"""
    capture = make_capture(866008, SyntheticOptions(cameras=2))
    now = estimate(capture)
    assert now.verdict is not Verdict.OK or _tip_mm(capture, now) < 5.0
    plain = BEFORE_LINES
    first = estimate(capture, second_look=False, config=plain)
    assert first.verdict is Verdict.AMBIGUOUS and _tip_mm(capture, first) > 10.0
    est = estimate(capture, config=plain)
    assert est.verdict is Verdict.AMBIGUOUS
    assert min(np.linalg.norm(a.tip_position - capture.truth.tip_position) for a in est.alternatives) < 0.005



def test_no_reported_alternative_explains_the_views_better_than_the_answer():
    """Issue 13: never return a shape whose cost is beaten by one of the reported
    alternatives. A part capture (908080, the end behind the part from one camera) whose
    curl-replaced plate fit was output as a chain costing 0.543 (poor_fit, 23 mm off) while
    an alternative plate fit cost 0.307: made the chain the estimator outputs, that
    alternative costs 0.222 and its end is 3.5 mm off. It becomes the answer, the old
    answer among its alternatives; judged "ok" afresh, it is "ambiguous" (a swap never
    makes an answer "ok": the needle settles it)."""
    capture = make_capture(908080, SyntheticOptions(part=True, cameras=2))
    est = estimate(capture)
    assert all(a.compared_cost >= est.cost for a in est.alternatives), (est.cost, est.alternatives)
    assert _tip_mm(capture, est) < 5.0
    assert est.verdict is Verdict.AMBIGUOUS and "explains the views worse" in est.verdict_reason
    old = [a for a in est.alternatives if np.linalg.norm(a.tip_position - capture.truth.tip_position) > 0.015]
    assert any(a.cost == pytest.approx(0.543, abs=0.002) for a in old)


def test_an_answer_beaten_by_its_alternative_swaps_places_with_it_and_is_never_ok():
    """The rule's mechanism (fit._cheapest_first) on a clean capture's right answer, handed
    over as the alternative of a wrong "ok" answer (its chain bent the other way) that costs
    more: the right shape becomes the answer, "ambiguous" (a search that answered with the
    costlier shape first is sure of neither), with the wrong one among its alternatives, and
    the time it took counts."""
    from tapecell.estimator import fit as F
    from tapecell.estimator.chain import Chain
    from tapecell.estimator.refine import mirrors
    from tapecell.estimator.result import Alternative
    from tapecell.estimator.silhouette import combine

    capture = make_capture(61003, SyntheticOptions(cameras=2))
    right = estimate(capture, second_look=False)
    assert right.verdict is Verdict.OK and _tip_mm(capture, right) < 2.0
    first = F.FirstStage(capture, Chain(capture.tape, cfg=DEFAULT_CONFIG), DEFAULT_CONFIG)
    wrong_angles = mirrors(first.angles)[0]
    shape, view_costs, _ = F._costed(capture, wrong_angles)
    assert float(np.linalg.norm(shape.nodes[-1] - right.tip_position)) > 0.010
    fitted = F.forward_kinematics(capture.tape, first.angles)
    first_tip = fitted.nodes[-1]
    plate = Alternative(first.cost, first_tip, fitted.frames[-1], first.angles)
    wrong = dataclasses.replace(right, angles=wrong_angles, nodes=shape.nodes, tip_position=shape.nodes[-1],
                                tip_rotation=shape.frames[-1], cost=combine(view_costs), view_costs=view_costs,
                                alternatives=(plate,), trace=(), history=[], time_s=0.0)
    assert wrong.cost > plate.cost
    out = F._cheapest_first(capture, wrong, first, DEFAULT_CONFIG)
    assert out.verdict is Verdict.AMBIGUOUS and "explains the views worse" in out.verdict_reason
    assert _tip_mm(capture, out) < 2.0 and float(np.linalg.norm(out.tip_position - first_tip)) < 0.010
    assert out.cost < wrong.cost and all(a.compared_cost >= out.cost for a in out.alternatives)
    assert any(np.allclose(a.tip_position, wrong.tip_position) for a in out.alternatives)
    assert out.time_s > 0.0 and len(out.history) == 1 and out.history[0] == pytest.approx(out.cost)


def test_an_alternative_cheaper_only_as_a_plate_fit_is_reported_with_its_outputs_cost():
    """A clean capture's answer (its output chain, from the strip stage, costs 0.071) with
    its own plate fit (0.049) handed over as an alternative: made the chain the estimator
    outputs, the plate fit is the answer again, no cheaper. It stays reported as the plate
    fit it is (its tip is where the needle would probe it), with ``output_cost`` the cost
    compared with the answer's; nothing else changes."""
    from tapecell.estimator import fit as F
    from tapecell.estimator.chain import Chain
    from tapecell.estimator.result import Alternative

    capture = make_capture(61003, SyntheticOptions(cameras=2))
    est = estimate(capture, second_look=False)
    first = F.FirstStage(capture, Chain(capture.tape, cfg=DEFAULT_CONFIG), DEFAULT_CONFIG)
    fitted = F.forward_kinematics(capture.tape, first.angles)
    plate = Alternative(first.cost, fitted.nodes[-1], fitted.frames[-1], first.angles)
    assert plate.cost < est.cost
    out = F._cheapest_first(capture, dataclasses.replace(est, alternatives=(plate,)), first, DEFAULT_CONFIG)
    (alt,) = out.alternatives
    assert alt.cost == plate.cost and alt.tip_position is plate.tip_position
    assert alt.output_cost == pytest.approx(est.cost, rel=1e-6) and alt.compared_cost >= out.cost
    assert out.verdict is est.verdict and out.cost == est.cost and out.tip_position is est.tip_position
    assert alt.to_json()["output_cost"] == pytest.approx(est.cost, rel=1e-6)


def test_an_ok_fit_that_leaves_a_view_unexplained_gets_the_second_look():
    """Bench capture calib-964050 (2 cameras, ~2 px of calibration error): the first look
    answers "ok" 7.5 mm off, a view's mean boundary distance 1.38 px, its cost more than
    twice the true shape's. Above FitConfig.recheck_offset_px the estimate gets the second
    look, which finds a shape within 2 mm that explains the views better."""
    capture = make_capture(964050, SyntheticOptions(cameras=2, miscalibration_px=2.0))
    first = estimate(capture, config=dataclasses.replace(DEFAULT_CONFIG, recheck_offset_px=float("inf")))
    assert first.verdict is Verdict.OK and _tip_mm(capture, first) > 5.0
    assert max(first.view_offsets_px) > DEFAULT_CONFIG.recheck_offset_px
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 2.0 and est.cost < first.cost
    assert max(est.view_offsets_px) < DEFAULT_CONFIG.recheck_offset_px


def test_a_camera_turned_off_its_calibration_is_told_at_the_tapes_base(monkeypatch):
    """Simulated capture 610001 (2 cameras) with every camera turned by 0.5 deg about a
    random axis (the campaign's calib_rot_deg, draw 2): the fit bends the tape to make up for
    the cameras and is "ok" 5.6 mm off without the base check; the observed tape around the
    base, which cannot move, lies 6.3 px from the model there, so the estimate is a poor fit.
    With the true cameras the base fits and the estimate is "ok". (With the cameras corrected
    from the views, anchored at that base, it is "ok" 2.3 mm off: tests/test_recalibrate.py.)"""
    from tapecell.estimator import fit, load_capture
    from tapecell.sim.randomize import apply_to_capture

    capture = load_capture(DATA / "sim-chain-c2-610001")
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 1.0
    turned = apply_to_capture(capture, {"calib_rot_deg": 0.5}, 2)
    corrected = estimate(turned)
    assert corrected.verdict is Verdict.OK and "turned from their calibration" in corrected.verdict_reason
    assert _tip_mm(capture, corrected) < 3.0
    monkeypatch.setattr(fit, "SELF_CALIBRATE", False)
    est = estimate(turned)
    assert est.verdict is Verdict.POOR_FIT and "at its base" in est.verdict_reason
    monkeypatch.setattr(fit, "BASE_OFFSET_PX", float("inf"))
    unchecked = estimate(turned)
    assert unchecked.verdict is Verdict.OK and _tip_mm(capture, unchecked) > 5.0


@pytest.mark.parametrize("seed", [1015010, 1015014])
def test_two_cameras_turned_half_a_degree_are_not_ok_far_off(monkeypatch, seed):
    """Simulated captures of a sweep's episodes (2 cameras) with every camera turned 0.5 deg
    (``calib_rot_deg``, drawn from the episode's seed, as the sweep drew it): the grasps went
    for "ok" estimates 13.7 and 10.2 mm off, the views explained to 1-2 px, their bases
    3.5-4.0 px off, under the 4.5 px BASE_OFFSET_PX had then. Now they are poor fits, at
    the base; with the true cameras the bases fit (0.2 px) and the estimates are "ok". With
    the cameras corrected from the views (anchored at the base) they are "ok" 4.4 and 2.3 mm
    off."""
    from tapecell.estimator import fit, load_capture
    from tapecell.sim.randomize import apply_to_capture

    capture = load_capture(DATA / f"sim-chain-c2-{seed}")
    est = estimate(capture)
    assert est.verdict is Verdict.OK and _tip_mm(capture, est) < 4.0
    turned = apply_to_capture(capture, {"calib_rot_deg": 0.5}, seed)
    corrected = estimate(turned)
    assert corrected.verdict is Verdict.OK and _tip_mm(capture, corrected) < 5.0
    monkeypatch.setattr(fit, "SELF_CALIBRATE", False)
    est = estimate(turned)
    assert est.verdict is Verdict.POOR_FIT and "at its base" in est.verdict_reason
    monkeypatch.setattr(fit, "BASE_OFFSET_PX", 4.5)
    before = estimate(turned)
    assert before.verdict is Verdict.OK and _tip_mm(capture, before) > 8.0


def test_base_offsets_measure_the_tape_at_its_base_clear_of_occluders():
    from tapecell.estimator.verdict import BASE_OFFSET_PX, base_offsets

    capture = make_capture(4300, SyntheticOptions(cameras=2))
    view, base = capture.views[0], capture.tape.base_position
    u, v = np.round(view.camera.project(base[None])[0]).astype(int)
    x0, y0 = u - 100, v - 100                           # crops, as the fit's targets are
    model = np.zeros((200, 200), np.uint8)
    model[85:115, 40:160] = 1                           # a band across the base's projection
    one, six = np.roll(model, 1, axis=0), np.roll(model, 6, axis=0)   # the observed tape 1 or 6 px off

    def offset(observed, seen, unoccluded=None):
        return base_offsets([view], base, [observed], [seen], [seen if unoccluded is None else unoccluded],
                            [(x0, y0)])[0]
    assert offset(model, model) == 0.0
    assert 0.0 < offset(one, model) < 1.5 < BASE_OFFSET_PX < offset(six, model)
    # Where an occluder hides the model, its outline is the occluder's: not counted, within
    # BASE_OCCLUDED_PX of it; the rest of the window still is.
    hidden_left = model.copy()
    hidden_left[:, :100] = 0
    assert offset(six, hidden_left, model) > BASE_OFFSET_PX
    hidden_all = model.copy()
    hidden_all[:, 40:160] = 0
    assert offset(six, hidden_all, model) == 0.0
    # Too little observed outline near the base (a broken sliver): not judged.
    dots = np.zeros_like(model)
    dots[100, 95:98] = 1
    assert offset(dots, model) == 0.0


def test_base_offsets_count_only_the_window_around_the_base():
    """base_offsets reads only a window around the base's projection (its erosion and its
    occluders' dilation from margins around it): the same numbers as the whole crop's
    operations, on random masks with the base anywhere in, near or off the crop."""
    from tapecell.estimator.verdict import BASE_MIN_OUTLINE_PX, BASE_OCCLUDED_PX, BASE_WINDOW_PX, base_offsets

    def whole_crop(camera, base, o, m, full, x0, y0):
        col, row = camera.project(base[None])[0] - (x0, y0)
        h, w = o.shape
        yy, xx = np.ogrid[0:h, 0:w]
        near = (xx - col) ** 2 + (yy - row) ** 2 <= BASE_WINDOW_PX ** 2
        hid = (full.astype(bool) & ~m.astype(bool)).astype(np.uint8)
        size = 2 * BASE_OCCLUDED_PX + 1
        if hid.any():
            near &= ~cv2.dilate(hid, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))).astype(bool)
        obs = o.astype(bool)
        outline = np.count_nonzero(obs & ~cv2.erode(o, np.ones((3, 3), np.uint8)).astype(bool) & near)
        return np.count_nonzero((obs ^ m.astype(bool)) & near) / outline if outline >= BASE_MIN_OUTLINE_PX else 0.0

    rng = np.random.default_rng(7)
    camera = make_capture(4300, SyntheticOptions(cameras=2)).views[0].camera
    judged = 0
    for _ in range(300):
        h, w = rng.integers(20, 200, 2)
        masks = [np.zeros((h, w), np.uint8) for _ in range(3)]
        for m in masks:
            for _ in range(rng.integers(1, 5)):
                x, y = int(rng.integers(-20, w)), int(rng.integers(-20, h))
                cv2.rectangle(m, (x, y), (x + int(rng.integers(2, 80)), y + int(rng.integers(2, 80))), 1, -1)
        o, m, full = masks[0], masks[1], masks[2] | masks[1]
        base = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05)])
        u, v = camera.project(base[None])[0]
        x0, y0 = int(u) - int(rng.integers(-30, w + 30)), int(v) - int(rng.integers(-30, h + 30))
        got = base_offsets([View(camera, np.zeros((camera.height, camera.width), bool))], base, [o], [m], [full],
                           [(x0, y0)])[0]
        assert got == whole_crop(camera, base, o, m, full, x0, y0)
        judged += got > 0
    assert judged > 50


def test_tape_going_behind_a_box_where_the_model_does_not():
    """verdict.box_cuts and unexplained_cut_px: the observed tape goes behind a box (its
    outline along the box's projected outline, the box across it); the model accounts for
    it with its tip edge there, its base edge there, or its chain before the last plate
    going behind the box there; a tape passing in front of the box's edge is no cut; the
    same cut from any crop, with the tape a pixel into the box, and none under ignored
    pixels."""
    from tapecell.estimator import Camera
    from tapecell.estimator.verdict import BOX_CUT_PX, box_cuts, unexplained_cut_px

    cam = Camera("c", 400, 400, np.array([[1000.0, 0, 200], [0, 1000.0, 200], [0, 0, 1]]), np.zeros(5),
                 np.eye(3), np.zeros(3))
    # A box in front of the tape (z 0.5-0.6 m) whose top edge projects on the row v = 210
    # (its far top edge, y = 0.006 m at z = 0.6 m).
    box = Box("part", np.array([0.0, 0.056, 0.55]), np.array([0.2, 0.1, 0.1]), np.eye(3))
    mask = np.zeros((400, 400), np.uint8)
    mask[100:210, 185:216] = 1                       # a strip 31 px wide down to the box
    view = View(cam, mask.astype(bool))
    cut = box_cuts(view, [box], mask, (0, 0))
    assert 25 <= len(cut) <= 40
    assert np.all(cut[:, 1] >= 205)                  # along the strip's bottom, at the box

    def at(u, v):                                    # the world point at pixel (u, v), 1 m away
        return np.array([(u - 200) / 1000.0, (v - 200) / 1000.0, 1.0])

    none = lambda: np.zeros((400, 400), np.uint8)  # noqa: E731
    far = np.array([at(100, 20), at(100, 30)])
    side = np.array([at(215, 120), at(215, 150)])    # a tip edge down the strip's side
    bottom = np.array([at(185, 209), at(215, 209)])  # the tip edge at the cut
    assert unexplained_cut_px(view, [box], mask, (0, 0), far, side, none) >= BOX_CUT_PX
    assert unexplained_cut_px(view, [box], mask, (0, 0), far, bottom, none) == 0
    assert unexplained_cut_px(view, [box], mask, (0, 0), bottom, side, none) == 0
    behind = np.zeros((400, 400), np.uint8)
    behind[211:240, 185:216] = 1                     # the model's chain behind the box there
    assert unexplained_cut_px(view, [box], mask, (0, 0), far, side, lambda: behind) == 0
    # The tape passing in front of the box's edge (over its projection too) is no cut.
    front = mask.copy()
    front[210:260, 185:216] = 1
    assert len(box_cuts(View(cam, front.astype(bool)), [box], front, (0, 0))) == 0
    # The same cut whatever the crop: the mask's own bounding box (the judging crop may end
    # on the tape's last row), at its origin.
    crop, origin = mask[100:210, 185:216], (185, 100)
    assert np.array_equal(box_cuts(view, [box], crop, origin), cut)
    # Segmentation a pixel into the box at the occluding edge: still a cut.
    over = mask.copy()
    over[210, 185:216] = 1
    assert 25 <= len(box_cuts(View(cam, over.astype(bool)), [box], over, (0, 0))) <= 45
    # Ignored pixels over the cut (an arm in the way): nothing is known there.
    ignore = np.zeros((400, 400), bool)
    ignore[205:230, 170:230] = True
    assert len(box_cuts(View(cam, mask.astype(bool), ignore), [box], mask, (0, 0))) == 0
    # A tape's side passing through a box's corner (a box up and to the right of it, its
    # corner at pixel (250, 190)): outline pixels near two of its edges, a few along each.
    corner_box = Box("part", np.array([0.13, -0.106, 0.55]), np.array([0.2, 0.2, 0.1]), np.eye(3))
    yy, xx = np.mgrid[0:400, 0:400]
    diagonal = ((xx - yy >= 30) & (xx - yy <= 60) & (yy >= 100) & (yy <= 300)).astype(np.uint8)
    grazing = View(cam, diagonal.astype(bool))
    assert len(box_cuts(grazing, [corner_box], diagonal, (0, 0))) >= BOX_CUT_PX
    assert unexplained_cut_px(grazing, [corner_box], diagonal, (0, 0), far, far, none) < BOX_CUT_PX


def test_an_end_folded_along_the_side_of_a_tape_going_on_behind_the_part_is_not_ok():
    """Shell tape 1052024 (2 cameras, a fresh bench capture of 2026-11-27): the part hides the
    tape's lower end in both views; the model folded its last plate so that its tip edge ran
    down the silhouette's side, and was "ok" 56.5 mm off. One view shows the tape's leg going
    behind the part away from the model's tip edge and body (verdict.BOX_CUT_PX): that view
    does not locate the end. Shell tape 1043025, whose end meets the part's outline in one
    view along its tip edge (24 outline pixels going behind the box), stays "ok"."""
    from tapecell.estimator import load_capture
    from tapecell.estimator.verdict import BEHIND_BOX

    bad = load_capture(DATA / "sim-shell-c2-1052024")
    est = estimate(bad)
    assert est.verdict is not Verdict.OK or _tip_mm(bad, est) < 10.0, f"ok at {_tip_mm(bad, est):.1f} mm"
    assert est.verdict is Verdict.HIDDEN, est.verdict_reason
    assert BEHIND_BOX in est.verdict_reason
    good = load_capture(DATA / "sim-shell-c2-1043025")
    est = estimate(good)
    assert est.verdict is Verdict.OK, est.verdict_reason
    assert _tip_mm(good, est) < 1.0


def test_an_ok_answer_probed_in_depth_is_ambiguous_where_a_shape_the_searches_missed_ends_elsewhere(monkeypatch):
    """Shell tape 1061012 (2 cameras, a fresh bench capture of 2026-11-27): an arch whose end
    hangs beside its base; the searches answered "ok" 16.3 mm off. Its depth probes
    (fit.DEPTH_PROBES: the plate chain refitted with its end pulled along each camera's line
    of sight, then let go) find a shape ending 13 mm away that explains the views better: it
    becomes the answer (3.4 mm off), ambiguous with the old one. Without the probes, the
    wrong "ok"."""
    from tapecell.estimator import fit, load_capture

    capture = load_capture(DATA / "sim-shell-c2-1061012")
    est = estimate(capture)
    assert est.verdict is Verdict.AMBIGUOUS, est.verdict_reason
    assert _tip_mm(capture, est) < 5.0
    # The searches' answer, 16 mm off, is kept as the rival.
    assert any(np.linalg.norm(a.tip_position - capture.truth.points[-1]) > 0.010 for a in est.alternatives)
    monkeypatch.setattr(fit, "DEPTH_PROBES", False)
    before = estimate(capture)
    assert before.verdict is Verdict.OK and _tip_mm(capture, before) > 5.0


def test_a_corrected_answer_stands_only_where_the_correction_explains_the_gain(monkeypatch):
    """Shell tape 1095002 (2 cameras, calibrated; a fresh bench capture of 2026-11-28): the
    first answer is poor_fit 10.4 mm off; the cameras' correction, 0.08 and 0.14 deg, and a
    second search found a shape 11.6 mm off that explains the corrected views at 0.71 of the
    first answer's cost, "ok". That shape explains the views as given nearly as well (the
    corrected cameras' cost 0.77 of it: recalibrate.SUPPORT) and leaves a view at 2.2 px
    (recalibrate.CORRECTED_OFFSET_PX): the first answer stands, by either rule alone."""
    from tapecell.estimator import fit, load_capture, recalibrate

    capture = load_capture(DATA / "sim-shell-c2-1095002")
    est = estimate(capture)
    assert est.verdict is Verdict.POOR_FIT and "turned" not in est.verdict_reason, est.verdict_reason
    monkeypatch.setattr(recalibrate, "SUPPORT", 0.9)
    assert estimate(capture).verdict is Verdict.POOR_FIT
    monkeypatch.setattr(recalibrate, "SUPPORT", 0.7)
    monkeypatch.setattr(recalibrate, "CORRECTED_OFFSET_PX", 2.5)
    assert estimate(capture).verdict is Verdict.POOR_FIT
    monkeypatch.setattr(recalibrate, "SUPPORT", 0.9)
    before = estimate(capture)
    assert before.verdict is Verdict.OK and _tip_mm(capture, before) > 10.0
    assert "turned from their calibration" in before.verdict_reason


def test_depth_probes_pull_the_end_in_depth_alone_and_weigh_rivals_like_for_like(monkeypatch):
    """Synthetic 1091054 (2 cameras, a fresh bench capture of 2026-11-28): "ok" 12 mm off, the
    true shape explaining the views better. The probes pulled to a point held bodies that cost
    more and went back to the answer; pulled in depth alone along the second camera's line of
    sight (fit.DEPTH_PROBES_ALONG), one ends within 2 mm of the true end at two thirds of the
    answer's cost: "ambiguous", that shape among the alternatives. Synthetic part capture
    1091016 (2 cameras), "ok" 0.7 mm off: a probe 15 mm away costs less than the answer's
    strip chain but more than the probes that went back to the answer (its plate chain
    refitted, fit.PROBES_AT_THE_ANSWER): no rival; weighed against the strip chain alone, a
    needless "ambiguous"."""
    from tapecell.estimator import fit

    capture = make_capture(1091054, SyntheticOptions(cameras=2))
    est = estimate(capture)
    assert est.verdict is Verdict.AMBIGUOUS, est.verdict_reason
    assert min(np.linalg.norm(a.tip_position - capture.truth.points[-1]) for a in est.alternatives) < 0.002
    part = make_capture(1091016, SyntheticOptions(cameras=2, part=True))
    est = estimate(part)
    assert est.verdict is Verdict.OK and _tip_mm(part, est) < 1.0, est.verdict_reason
    monkeypatch.setattr(fit, "PROBES_AT_THE_ANSWER", False)
    assert estimate(part).verdict is Verdict.AMBIGUOUS
    monkeypatch.setattr(fit, "DEPTH_PROBES_ALONG", False)
    before = estimate(capture)
    assert before.verdict is Verdict.OK and _tip_mm(capture, before) > 10.0
