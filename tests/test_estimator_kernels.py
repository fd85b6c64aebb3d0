"""The compiled kernels (estimator/_kernels*.py) against the NumPy reference (estimator/reference.py),
and the fits compiled whole (estimator/_kernels_lm.py) against the solvers' Python loops."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import dataclasses

from tapecell.estimator import _kernels, _kernels_beam, reference
from tapecell.estimator.chain import Chain
from tapecell.estimator.config import DEFAULT, angle_grid, as_array
from tapecell.estimator.residuals import residuals
from tapecell.estimator.search import beam_search, diverse
from tapecell.estimator.tape import joint_rotations
from tapecell.estimator.views import clean_mask, fill_pinholes, prepare

NUMPY = dataclasses.replace(DEFAULT, compiled=False)
from tapecell.estimator.synthetic import SyntheticOptions, make_capture, make_capture_with_angles


@pytest.fixture(scope="module", params=[(21, False), (22, True)], ids=["plain", "occluded-distorted"])
def prepared(request):
    seed, hard = request.param
    c = make_capture(seed, SyntheticOptions(kind="strip", cameras=3, noise=hard, occluder=hard, distortion=hard))
    fields = [prepare(v) for v in c.views]
    assert any(f.has_ignore for f in fields) == hard
    assert any(f.camera.has_distortion for f in fields) == hard
    return Chain(c.tape), fields


def _relative(a, b):
    return float(np.max(np.abs(a - b)) / max(1e-300, np.max(np.abs(b))))


def test_lookup_reproduces_cv2_remap_exactly(prepared):
    _, fields = prepared
    rng = np.random.default_rng(0)
    for f in fields:
        h, w = f.field.shape[:2]
        u = rng.uniform(f.x0 - 15, f.x0 + w + 15, 3000)
        v = rng.uniform(f.y0 - 15, f.y0 + h + 15, 3000)
        u[:300] = np.round(u[:300])          # on pixel centres and the ROI's last row/column
        v[:100] = f.y0 + h - 1
        sdf, gx, gy, ignored = reference.lookup(f, u, v)
        k_sdf, k_gx, k_gy, k_ignored = _kernels.lookup(f.field, f.x0, f.y0, f.has_ignore, u, v)
        assert np.array_equal(k_sdf, sdf) and np.array_equal(k_gx, gx) and np.array_equal(k_gy, gy)
        assert np.array_equal(k_ignored, ignored if ignored is not None else np.zeros_like(k_ignored))


def test_chain_points_and_jacobian_match(prepared):
    chain, _ = prepared
    angles = np.random.default_rng(1).normal(scale=0.6, size=(6, chain.n, 3))
    pts, J = reference.chain_points(chain, angles, True)
    k_pts, k_J = _kernels.points(chain, angles, True)
    assert _relative(k_pts, pts) < 1e-12 and _relative(k_J, J) < 1e-12
    assert _kernels.points(chain, angles, False)[1] is None


def test_residuals_and_jacobian_match_reference(prepared):
    chain, fields = prepared
    rng = np.random.default_rng(2)
    # Near the straight chain (most samples on the tape) and far from it (most outside).
    for scale in (0.1, 0.8):
        params = rng.normal(scale=scale, size=(5, 3 * chain.n))
        r, J, cost = residuals(chain, fields, params, True)
        r0, _, cost0 = residuals(chain, fields, params, False)
        ref_r, ref_J, ref_cost = residuals(chain, fields, params, True, NUMPY)
        assert r.shape == ref_r.shape and J.shape == ref_J.shape
        assert _relative(r, ref_r) < 1e-9 and _relative(J, ref_J) < 1e-9
        assert np.allclose(cost, ref_cost, rtol=1e-12, atol=0)
        assert np.array_equal(r0, r) and np.array_equal(cost0, cost)
        # Both states of the joints' lines occur, and a line that does not fold has zero rows.
        rows = _crease_rows(chain, fields, params, r, J)
        assert rows["active"] and rows["inactive"] and rows["inactive_zero"]


def _crease_rows(chain, fields, params, r, J) -> dict:
    """Which joints' lines fold in the views' images for ``params`` (B, 3n), and whether the
    residual and Jacobian rows of the sample points on those that do not are all zero."""
    from tapecell.estimator.reference import folds

    out = {"active": False, "inactive": False, "inactive_zero": True}
    corners = np.array([chain.corners(p)[0] for p in params])                  # (B, 3m, 3)
    on_crease = chain.fold_of >= 0
    row = 0
    for f in fields:
        uv = np.array([f.camera.project(c) for c in corners])                  # (B, 3m, 2)
        active = folds(chain.segments, uv[..., 0], uv[..., 1])                 # (B, K)
        creases = chain.segments[:, 2] >= 0
        out["active"] |= bool(active[:, creases].any())
        out["inactive"] |= bool((~active[:, creases]).any())
        samples = slice(row + len(f.outline), row + len(f.outline) + chain.samples)
        off = on_crease[None, :] & ~np.take(active, np.maximum(chain.fold_of, 0), axis=1)
        out["inactive_zero"] &= bool(np.all(r[:, samples][off] == 0) and np.all(J[:, samples][off] == 0))
        row = samples.stop
    return out


def test_beam_scores_match_reference(prepared):
    chain, fields = prepared
    spec = chain.spec
    rng = np.random.default_rng(3)
    grid = angle_grid([-0.6, 0.0, 0.6], [-0.8, 0.0, 0.8], [0.0])
    compiled = beam_search(spec, fields, grid, 4)
    numpy = beam_search(spec, fields, grid, 4, NUMPY)
    assert len(compiled) == len(numpy) == 4
    assert all(np.array_equal(a, b) for a, b in zip(compiled, numpy))
    # the scores themselves, on random candidates' points and corners
    pts = spec.base_position + rng.normal(scale=0.03, size=(4, 20, 13, 3))
    base, prior, extra = rng.uniform(0, 50, 4), rng.uniform(0, 5, 20), np.zeros(80)
    is_edge = np.arange(13) < 8
    plate = sum(f.weight * reference.beam_edge_cost(f, pts, is_edge) for f in fields)
    want = (base[:, None] + plate + prior[None, :]).ravel()
    packed = _kernels_beam.pack_views(fields)
    perm = np.arange(13)[::-1].copy()
    args = (fields, packed, pts, 8, perm, base, prior, extra)
    full = _kernels_beam.beam_totals(*args, 81, DEFAULT.delta_out_px, DEFAULT.delta_in_px)
    assert np.allclose(full, want, rtol=1e-12, atol=0)
    # Kept to the 10 best: those exact, every other one cut short or above them.
    best = _kernels_beam.beam_totals(*args, 10, DEFAULT.delta_out_px, DEFAULT.delta_in_px)
    order = np.argsort(full)
    assert np.array_equal(np.argsort(best)[:10], order[:10]) and np.array_equal(best[order[:10]], full[order[:10]])
    assert np.all(best[order[10:]] >= full[order[9]]) and np.isinf(best).sum() > 20
    # The complete chains' coverage: edges always, joints' lines (the last two segments,
    # their neighbours either side) only where the points either side lie on one side.
    seg = np.array([(k, k + 1, -1, -1) for k in range(11)] + [(2, 8, 1, 3), (4, 10, 3, 5)])
    for f in fields:
        corners = pts[0, :, :12]
        cu, cv, *_ = reference.project(f.camera, corners)
        ax, ay = cu[:, seg[:, 0]], cv[:, seg[:, 0]]
        bx, by = cu[:, seg[:, 1]] - ax, cv[:, seg[:, 1]] - ay
        side = [bx[:, k] * (cv[:, n] - ay[:, k]) - by[:, k] * (cu[:, n] - ax[:, k]) for k, n in
                ((11, 1), (11, 3), (12, 3), (12, 5))]
        folds = np.ones(bx.shape, bool)
        folds[:, 11], folds[:, 12] = side[0] * side[1] > 0, side[2] * side[3] > 0
        assert folds[:, 11:].any() and not folds[:, 11:].all()    # both cases are tested
        rx = f.outline[None, :, 0, None] - ax[:, None]
        ry = f.outline[None, :, 1, None] - ay[:, None]
        t = np.clip((rx * bx[:, None] + ry * by[:, None]) / np.maximum(bx * bx + by * by, 1e-9)[:, None], 0.0, 1.0)
        d2 = np.where(folds[:, None], (rx - t * bx[:, None]) ** 2 + (ry - t * by[:, None]) ** 2, np.inf)
        d = np.sqrt(np.min(d2, axis=2))
        got = _kernels_beam.beam_outline_cost(f, corners, seg, f.outline, DEFAULT.delta_out_px)
        assert np.allclose(got, reference.huber(d)[0].sum(axis=1), rtol=1e-12, atol=0)
        assert np.allclose(got, reference.beam_outline_cost(f, corners, seg, f.outline), rtol=1e-12, atol=0)


def test_beam_candidates_match_reference(prepared):
    chain, _ = prepared
    spec = chain.spec
    rng = np.random.default_rng(4)
    grid = angle_grid([-0.8, 0.0, 0.4], [-1.2, 0.3, 1.2], [-0.4, 0.0])
    grid_r = joint_rotations(grid)
    frames = joint_rotations(rng.normal(scale=0.7, size=(5, 3))) @ spec.base_rotation
    nodes = spec.base_position + rng.normal(scale=0.02, size=(5, 3))
    for last in (False, True):
        F, ends, pts = reference.beam_candidates(frames, nodes, grid_r, 0.013, 0.004, last)
        tip = as_array(DEFAULT.tip_t) if last else np.zeros(0)
        kF, kends, kpts = _kernels_beam.beam_candidates(frames, nodes, grid_r, 0.013, 0.004,
                                                        as_array(DEFAULT.beam_edge_t), tip, as_array(DEFAULT.centre_t))
        assert np.array_equal(kF, F.reshape(-1, 3, 3))
        assert np.array_equal(kends, ends.reshape(-1, 3, 3))
        assert np.array_equal(kpts, pts.reshape(len(kpts), -1, 3))


def test_diverse_matches_reference():
    rng = np.random.default_rng(5)
    for trial in range(20):
        # clustered ends, so that many candidates lie within DIVERSE_M of each other
        centres = rng.normal(scale=0.01, size=(6, 3, 3))
        ends = centres[rng.integers(0, 6, 300)] + rng.normal(scale=0.004, size=(300, 3, 3))
        order = rng.permutation(300)[:rng.integers(5, 80)]
        count = int(rng.integers(1, 12))
        got = diverse(order, ends, count)
        ref = diverse(order, ends, count, NUMPY)
        assert np.array_equal(got, ref)


def test_mask_cleaning_matches_reference():
    rng = np.random.default_rng(6)
    m = np.zeros((120, 160), np.uint8)
    m[30:90, 20:140] = 1
    m[rng.random(m.shape) < 0.02] ^= 1          # speckles outside, pinholes inside
    got = fill_pinholes(clean_mask(m.astype(bool)))
    ref = fill_pinholes(clean_mask(m.astype(bool), NUMPY), NUMPY)
    assert got.dtype == ref.dtype == np.uint8 and np.array_equal(got, ref)
    assert 0 < int(got.sum()) < m.size and not np.array_equal(ref, m)


@pytest.mark.parametrize("part", [False, True], ids=["plain", "scene-boxes"])
def test_compiled_levenberg_marquardt_matches_the_python_loop(part):
    """solver.levenberg_marquardt compiled whole (_kernels_lm) takes the Python loop's steps:
    the same parameters, costs, residuals, Jacobian and log (each iteration's candidates and
    their parameters) to float rounding, from a fresh start and from a given state, with and
    without scene boxes (their penetration rows and hidden points) and view weights."""
    from tapecell.estimator.solver import _pull_rows, levenberg_marquardt

    c, truth = make_capture_with_angles(7, SyntheticOptions(kind="chain", cameras=3, part=part, noise=True))
    fields = [prepare(v, c.scene) for v in c.views]
    fields[1] = dataclasses.replace(fields[1], weight=0.6)
    assert bool(fields[0].boxes) == part
    chain = Chain(c.tape)
    rng = np.random.default_rng(3)
    params = (truth[None] + rng.normal(scale=0.08, size=(5, chain.n, 3))).reshape(5, -1)

    def nothing(which, p):     # an ``extra`` of no rows: the Python loop
        return np.zeros((len(which), 0)), np.zeros((len(which), 0, p.shape[1]))

    state = residuals(chain, fields, params, True)
    for given in (None, state):
        logs = [], []
        ours = levenberg_marquardt(chain, fields, params, 6, logs[0], given)
        python = levenberg_marquardt(chain, fields, params, 6, logs[1], given, extra=nothing)
        assert _relative(ours[0], python[0]) < 1e-9 and np.allclose(ours[1], python[1], rtol=1e-9, atol=0)
        assert _relative(ours[2][0], python[2][0]) < 1e-9 and _relative(ours[2][1], python[2][1]) < 1e-9
        assert len(logs[0]) == len(logs[1]) >= 2
        for (a, pa), (b, pb) in zip(*logs):
            assert np.array_equal(a, b) and _relative(pa, pb) < 1e-9
        assert np.all(ours[1] < state[2])      # every candidate improved
    assert np.array_equal(state[0], residuals(chain, fields, params, True)[0])   # the given state not written
    # The tip pulled to targets (the depth probes' rows): compiled, and as Python ``extra`` rows.
    end = chain.samples + chain.n
    targets = chain.tips(params.reshape(5, chain.n, 3)) + rng.normal(scale=0.01, size=(5, 3))
    logs = [], []
    ours = levenberg_marquardt(chain, fields, params, 6, logs[0], pull=(end, 20000.0, targets))
    python = levenberg_marquardt(chain, fields, params, 6, logs[1], extra=_pull_rows(chain, end, 20000.0, targets))
    assert _relative(ours[0], python[0]) < 1e-9 and np.allclose(ours[1], python[1], rtol=1e-9, atol=0)
    assert _relative(ours[2][1], python[2][1]) < 1e-9 and len(logs[0]) == len(logs[1])
    assert ours[2][0].shape[1] == state[0].shape[1] + 3
    moved = np.linalg.norm(chain.tips(ours[0].reshape(5, chain.n, 3)) - targets, axis=1)
    assert np.all(moved < np.linalg.norm(chain.tips(params.reshape(5, chain.n, 3)) - targets, axis=1))
    # Pulled along a direction only (the depth probes along a line of sight), a row of zeros
    # pulling all of it: compiled and Python alike; the pulled candidates meet their targets'
    # depth along the direction, not the targets.
    along = rng.normal(size=(5, 3))
    along /= np.linalg.norm(along, axis=1)[:, None]
    along[4] = 0.0
    logs = [], []
    ours = levenberg_marquardt(chain, fields, params, 6, logs[0], pull=(end, 20000.0, targets, along))
    python = levenberg_marquardt(chain, fields, params, 6, logs[1],
                                 extra=_pull_rows(chain, end, 20000.0, targets, along))
    assert _relative(ours[0], python[0]) < 1e-9 and np.allclose(ours[1], python[1], rtol=1e-9, atol=0)
    assert _relative(ours[2][1], python[2][1]) < 1e-9 and len(logs[0]) == len(logs[1])
    offset = chain.tips(ours[0].reshape(5, chain.n, 3)) - targets
    before = chain.tips(params.reshape(5, chain.n, 3)) - targets
    depth = np.abs(np.sum(offset * along, axis=1))[:4]
    assert np.all(depth < 1e-3) and np.all(depth < np.abs(np.sum(before * along, axis=1))[:4])
    assert np.linalg.norm(offset[:4], axis=1).max() > 3e-3     # across the direction: left to the views
    assert np.linalg.norm(offset[4]) < np.linalg.norm(before[4])
    whole = levenberg_marquardt(chain, fields, params[4:], 6, pull=(end, 20000.0, targets[4:]))
    assert np.array_equal(ours[0][4], whole[0][0])


def test_the_compiled_solver_takes_only_what_it_computes_alike(tmp_path):
    """Views whose scene boxes differ go the Python way (the kernels take the first view's
    boxes for all); a pull at a point the chain does not have is an error, not a read past
    its end; the kernels' cache is named by all their sources (a kernel compiled into
    _kernels_lm.py is not recompiled when only its own file changes)."""
    import shutil

    import tapecell
    from tapecell.estimator import _kernels_lm
    from tapecell.estimator.solver import levenberg_marquardt

    c = make_capture(9, SyntheticOptions(cameras=2, part=True))
    fields = [prepare(v, c.scene) for v in c.views]
    assert _kernels_lm.usable(fields) and not _kernels_lm.usable([])
    mixed = [fields[0], dataclasses.replace(fields[1], boxes=(), box_arrays=())]
    assert not _kernels_lm.usable(mixed)
    chain = Chain(c.tape)
    params = np.zeros((1, 3 * chain.n))
    with pytest.raises(IndexError):
        levenberg_marquardt(chain, fields, params, 2, pull=(chain.samples + 3 * (chain.n + 1), 1.0, np.zeros((1, 3))))
    source = Path(tapecell.__file__).resolve().parent / "estimator"
    for path in source.glob("_kernels*.py"):
        shutil.copy(path, tmp_path / path.name)
    before = tapecell.kernel_sources_digest(tmp_path)
    assert before == tapecell.kernel_sources_digest(source)
    with open(tmp_path / "_kernels_boxes.py", "a") as f:
        f.write("\n# changed\n")
    assert tapecell.kernel_sources_digest(tmp_path) != before


def test_compiled_strip_fits_match_the_python_loops():
    """The strip stage's compiled fits (_kernels_lm) take solver.levenberg_marquardt_one's
    steps: its fit to the views (against the Python loop, forced by touched-point rows of
    none) and the corner fits of the strip's start and of the output plate chain with its
    tip-frame rows, to float rounding."""
    from tapecell.estimator import _kernels_lm
    from tapecell.estimator.solver import corner_fit, levenberg_marquardt_one
    from tapecell.estimator.strip import _strip_for, _tip_frame_rows, strip_stage

    c, truth = make_capture_with_angles(8, SyntheticOptions(kind="chain", cameras=2, part=True))
    fields = [prepare(v, c.scene) for v in c.views]
    chain = Chain(c.tape)
    angles = truth + np.random.default_rng(4).normal(scale=0.05, size=truth.shape)

    def no_rows(corners, J):
        return np.zeros(0), np.zeros((0, J.shape[-1]))

    ours, python = strip_stage(chain, fields, angles), strip_stage(chain, fields, angles, extra=no_rows)
    assert _relative(ours.fine.nodes, python.fine.nodes) < 1e-9
    assert _relative(ours.tip[1], python.tip[1]) < 1e-9
    strip = _strip_for(chain.spec, DEFAULT)
    x0 = np.random.default_rng(5).normal(scale=0.1, size=strip.T.shape[1])
    goal = strip.corners(x0)[0] + 0.001
    want = levenberg_marquardt_one(corner_fit(strip.corners, goal), x0 * 0.5, 20, 1e-4)
    assert _relative(_kernels_lm.corner_fit(strip.chain, strip.T, goal, 1.0, x0 * 0.5, 20, 1e-4), want) < 1e-9
    goal = chain.corners(angles)[0] + 0.002
    w = np.linspace(1.0, 10.0, len(goal))
    frame = ours.tip[1]
    want = levenberg_marquardt_one(corner_fit(chain.corners, goal, w, _tip_frame_rows(chain, frame, 1.0)),
                                   truth.ravel().copy(), 10, 1e-4)
    got = _kernels_lm.corner_fit(chain, np.eye(3 * chain.n), goal, w, truth.ravel(), 10, 1e-4, frame, 1.0)
    assert _relative(got, want) < 1e-9 and _relative(got, truth.ravel()) > 1e-3


def test_warm_compiles_every_kernel_a_fit_calls():
    """After ``warm()`` a fit compiles nothing (its clock must not pay for it): a capture with
    scene boxes (the part, the table) and a camera whose read-only centre numba types apart
    adds no signature to any compiled kernel."""
    from tapecell.estimator import _kernels, _kernels_beam, _kernels_boxes, _kernels_lm, estimate
    from tapecell.estimator.synthetic import SyntheticOptions, make_capture

    def signatures():
        return {(m.__name__, name): len(f.signatures) for m in (_kernels, _kernels_beam, _kernels_boxes, _kernels_lm)
                for name, f in vars(m).items() if hasattr(f, "signatures") and hasattr(f, "py_func")}

    _kernels.warm()
    before = signatures()
    capture = make_capture(3, SyntheticOptions(cameras=3, part=True))
    assert capture.scene and capture.views[0].camera.center.flags.writeable is False
    estimate(capture)
    assert signatures() == before
