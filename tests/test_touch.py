"""Refitting through points the needle touched on the tape (estimator/touch.py)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tapecell.cell.probe import refit_acceptable
from tapecell.estimator import EstimateError, Verdict, estimate
from tapecell.estimator.chain import Chain
from tapecell.estimator.metrics import errors
from tapecell.estimator.synthetic import SyntheticOptions, make_capture_with_angles
from tapecell.estimator.touch import end_rows, refit


def test_end_rows_pull_the_end_with_the_cost_s_exact_gradient():
    """The rows' residual is the point's offset from the end of the chain's centre line, and
    their Jacobian gives the gradient of half its squared length (the cost the solver
    lowers) as finite differences do."""
    capture, angles = make_capture_with_angles(5, SyntheticOptions(kind="chain", cameras=2))
    chain = Chain(capture.tape)
    corners, _ = chain.corners(angles)
    n = len(corners) // 3 - 1
    trunk = (corners[n] - corners[n - 1]) / np.linalg.norm(corners[n] - corners[n - 1])
    side = np.cross(trunk, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    point = corners[n] - 0.0025 * trunk + 0.003 * side     # 3 mm beside the centre line, 2.5 mm from the end
    rows = end_rows(point, 0.004, 1.0)
    r, J = rows(*chain.corners(angles))
    assert np.linalg.norm(r) == pytest.approx(0.003, abs=1e-9)

    def half_square(x):
        return 0.5 * float(np.sum(rows(*chain.corners(x.reshape(angles.shape)))[0] ** 2))

    x, eps = angles.ravel(), 1e-7
    numeric = [(half_square(x + eps * e) - half_square(x - eps * e)) / (2 * eps) for e in np.eye(len(x))]
    assert np.allclose(r @ J, numeric, atol=1e-9)
    # Farther back than ``depth``: the offset is from the centre line's point ``depth`` from the end.
    far = end_rows(corners[n] - 0.010 * trunk, 0.004, 1.0)(*chain.corners(angles))[0]
    assert np.linalg.norm(far) == pytest.approx(0.006, abs=1e-6)


def test_refit_through_the_touched_end_moves_a_wrong_end_onto_the_tape():
    """A shape whose end is 8 mm off, refitted through a point just inside the true end (where
    a needle sent to the wrong end touches the tape), ends within a millimetre or two of the
    true end; through nothing it is an error, not a guess."""
    capture, _ = make_capture_with_angles(4102, SyntheticOptions(cameras=2))
    est = estimate(capture)
    assert est.verdict is Verdict.OK
    wrong = est.angles.copy()
    wrong[-1, 1] += 0.3                           # the last plate bent out of plane
    tip_before = Chain(capture.tape).tips(wrong[None])[0]
    true_tip, trunk = capture.truth.tip_position, capture.truth.tip_rotation[:, 0]
    assert np.linalg.norm(tip_before - true_tip) > 0.006
    touched = true_tip - 0.002 * trunk
    refitted = refit(capture, wrong, touched, 0.004)
    err = errors(refitted.nodes, refitted.tip_rotation, capture.truth, refitted.tip_position)
    assert err.tip_m < 0.002, f"{1e3 * err.tip_m:.2f} mm"
    assert refitted.verdict is Verdict.OK and not refitted.alternatives
    assert refit_acceptable(refitted, est)
    # A refit that explains the views far worse than the shape it started from is not probed.
    assert not refit_acceptable(dataclasses.replace(refitted, cost=3 * est.cost), est)
    for bad in ([], [np.nan, 0.0, 0.0]):
        with pytest.raises(EstimateError, match="touched point"):
            refit(capture, est.angles, np.array(bad), 0.004)


def test_the_real_cells_refit_keeps_its_tip_at_the_touch_and_never_moves_back_past_seen_tape():
    """The real cell refits through the operator's touch on the tape's end
    (cli.commands.run._refit_through): kept when the refit's tip lies at the touch; where the
    views show tape past the model's end, a touch 8 mm back along the tape (on its body, not
    its end) is refused: the end may not move back over tape the views see."""
    from tapecell.cli.commands.run import _refit_through
    from tapecell.estimator import forward_kinematics

    capture, _ = make_capture_with_angles(4102, SyntheticOptions(cameras=2))
    est = estimate(capture)
    angles = est.angles.copy()
    angles[-1, 1] += 0.3
    shape = forward_kinematics(capture.tape, angles)
    off = dataclasses.replace(est, angles=angles, nodes=shape.nodes, tip_position=shape.nodes[-1],
                              tip_rotation=shape.frames[-1], verdict=Verdict.HIDDEN)
    true_tip, trunk = capture.truth.tip_position, capture.truth.tip_rotation[:, 0]
    settled = _refit_through(capture, off, 0, true_tip, "the tip")
    assert settled is not None and settled.verdict is Verdict.OK
    assert np.linalg.norm(settled.tip_position - true_tip) < 0.002
    assert _refit_through(capture, off, 0, true_tip - 0.008 * trunk, "the tip", past_end=True) is None
