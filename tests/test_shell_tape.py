"""The shell tape: a MuJoCo flexible sheet that is not the estimator's plate chain."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell import sim  # noqa: F401  (headless GL before mujoco)
from tapecell.cell.config import load_cell_config
from tapecell.estimator import estimate
from tapecell.estimator.metrics import errors
from tapecell.sim.shell import ShellCell


@pytest.fixture(scope="module")
def cfg():
    return load_cell_config()


def test_shell_tape_settles_under_gravity_and_is_seen(cfg):
    with ShellCell(cfg, 7000, 2) as cell:
        rest = cell.vertices()
        capture = cell.capture()
        settled = cell.vertices()
        assert cell.data.warning[mujoco_warning_index()].number == 0
    assert np.all(np.isfinite(settled))
    # Pinned at the base, free elsewhere: the base rows stay, the end moves under gravity.
    assert np.allclose(settled[:2], rest[:2], atol=1e-6)
    assert settled[-1, :, 2].mean() < rest[-1, :, 2].mean() - 0.005
    # The truth is the sheet's centre line: 150 mm long, base on the part, a proper frame.
    assert capture.truth.s[-1] == pytest.approx(cfg.tape.length, rel=0.02)
    assert np.allclose(capture.truth.points[0], cfg.tape.base_position, atol=1e-6)
    R = capture.truth.tip_rotation
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert [b.name for b in capture.scene] == ["part", "table"]
    assert all(v.mask.any() for v in capture.views)


def mujoco_warning_index() -> int:
    import mujoco

    return int(mujoco.mjtWarning.mjWARN_BADQACC)


def test_shell_seeds_differ_and_the_estimator_answers(cfg):
    """Two seeds give different tapes; the estimator gives every shell capture a verdict,
    and where it says "ok" the tip is within 5 mm."""
    with ShellCell(cfg, 7002, 3) as cell:
        a = cell.capture()
    with ShellCell(cfg, 7003, 3) as cell:
        b = cell.capture()
    assert np.linalg.norm(a.truth.points[-1] - b.truth.points[-1]) > 0.02
    for c in (a, b):
        est = estimate(c)
        if est.actionable:
            assert errors(est.nodes, est.tip_rotation, c.truth, est.tip_position).tip_m < 0.005
