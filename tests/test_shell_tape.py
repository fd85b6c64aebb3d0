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


def test_a_drooping_shell_tape_rests_on_the_part_not_in_it(cfg):
    """Seed 929000 (a soft bend) droops over the part's edge: without contacts with the part
    it sank 2.4 mm into it, its last 17 mm hidden inside, and the estimator was "ok" 17 mm off
    at the edge where it disappeared. It drapes over the edge and hangs down outside."""
    from tapecell.cell.config import scene_boxes

    with ShellCell(cfg, 929000, 2) as cell:
        cell.settle()
        vertices = cell.vertices().reshape(-1, 3)
    part = next(b for b in scene_boxes(cfg) if b.name == "part")
    assert not part.contains(vertices).any()
    assert vertices[-1, 2] < part.center[2] + part.half[2] - 0.01   # it hangs down past the top


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


def test_point_triangles_distance_matches_a_dense_sampling():
    """The needle's distance to the sheet: the exact point-triangle distance, against the
    closest of many points sampled on each triangle (vertex, edge and face regions alike)."""
    from tapecell.sim.shell import point_triangles_distance

    rng = np.random.default_rng(5)
    a, b, c = (rng.normal(size=(40, 3)) for _ in range(3))
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    inside = u + v <= 1.0
    u, v = u[inside], v[inside]
    for p in rng.normal(scale=2.0, size=(5, 3)):
        exact = point_triangles_distance(p, a, b, c)
        samples = a[:, None] + u[None, :, None] * (b - a)[:, None] + v[None, :, None] * (c - a)[:, None]
        dense = np.linalg.norm(samples - p, axis=2).min(axis=1)
        assert np.all(exact <= dense + 1e-12) and np.allclose(exact, dense, atol=0.02)


def test_the_whole_cell_with_the_shell_tape_grasps_it(tmp_path):
    """A grasp episode on the shell tape (``tape_model = "shell"``): the sheet in the whole
    cell settles, is seen and fitted, the pads close on it from both sides (contacts on each
    pad), the lift carries its tip along; the needle's distance to the sheet measures it;
    a cell built for one seed refuses another."""
    import json

    from tapecell.sim.episode import release_cell, run_episode
    from tapecell.sim.randomize import Randomize
    from tapecell.sim.shell import ShellSimCell
    from tapecell.sim.cell import SimError

    doc = run_episode(902001, 2, tmp_path / "shell.rrd", randomize=Randomize({"tape_model": "shell"}))
    release_cell()
    json.dumps(doc)
    assert doc["randomize"] == {"tape_model": "shell"}
    assert doc["outcome"] == "grasped", doc
    assert doc["pad_contacts"]["left"] > 0 and doc["pad_contacts"]["right"] > 0
    assert doc["tip_error_mm"] < 3.0 and doc["lift_mm"] > 40.0 and doc["held_follow_error_mm"] < 8.0
    assert (tmp_path / "shell.rrd").stat().st_size > 0

    cfg = load_cell_config()
    with ShellSimCell(cfg, 902001, 2, tool="needle") as cell:
        truth = cell.truth()
        assert np.allclose(truth.points[0], cfg.tape.base_position, atol=1e-6)
        assert np.allclose(cell.tape_tip_position(), truth.points[-1])
        capture = cell.capture()
        assert all(v.mask.any() for v in capture.views)
        # The needle's gap: its tip's distance to the sheet less the sheet's radius.
        needle = cell.model.geom("needle").id
        tip_body = cell.model.geom_bodyid[needle]
        gap = cell.tape_gap(needle)
        assert gap > 0.05
        assert gap == pytest.approx(np.linalg.norm(cell.data.xpos[tip_body] - cell.vertices().reshape(-1, 3), axis=1).min()
                                    - cell.model.flex_radius[0], abs=0.02)
        assert cell.reusable_for(902001) and not cell.reusable_for(902002)
        with pytest.raises(SimError, match="built for seed 902001"):
            cell.reset(902002)
        with pytest.raises(SimError, match="no plates"):
            cell.tape_frames()
