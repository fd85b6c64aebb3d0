"""Sim episodes end to end: one physical grasp with its recording, the batch runner
(parallel, resumable, summary) and refusals."""
from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from tapecell.cli.main import main
from tapecell.estimator import estimate
from tapecell.sim.episodes import EpisodeJob, append_result, load_results, run_episodes, summarize, wilson_interval
from tapecell.cell.recording import read_recording
from tapecell.cell.config import default_cell_path


def test_one_episode_grasps_the_tape_and_records_every_step(tmp_path, capsys):
    rrd = tmp_path / "ep.rrd"
    code = main(["episode", "--seed", "1", "--rrd", str(rrd)])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert code == 0, err
    assert doc["format"] == "tape-episode/1" and doc["seed"] == 1 and doc["cameras"] == 2
    assert doc["success"] is True and doc["failure"] is None
    assert doc["tip_error_mm"] < 3.0
    assert doc["pad_contacts"]["left"] > 0 and doc["pad_contacts"]["right"] > 0
    assert doc["lift_mm"] >= 20.0
    assert doc["grasp"]["inset_mm"] == 8.0 and set(doc["grasp"]) == {"inset_mm", "tilt_deg", "pitch_deg", "flipped"}
    assert set(doc["time_s"]) == {"capture", "estimate", "plan", "execute"}
    assert doc["recording"] == "ep.rrd"
    rows = read_recording(rrd)
    for entity in ("world/cameras/cam0/image/mask", "world/cameras/cam1/image/model",
                   "world/cameras/cam0/image/rgb", "estimator/cost", "world/tape/estimate",
                   "world/tape/truth", "world/arm/flange", "arm/joints", "world/plan/waypoints",
                   "gripper/opening", "grasp/result"):
        assert entity in rows, entity
    assert len(rows["estimator/cost"]) >= 2
    labels = [r for r in rows["world/plan/waypoints"] if "Points3D:labels" in r][-1]["Points3D:labels"]
    assert "grasp" in labels
    assert len(rows["world/arm/flange"]) >= 20  # the arm over time, not only per plan step
    # The arm, the mounted gripper and the true tape as the MuJoCo model's geometry, moving.
    for body in ("arm/upper_arm_link", "tools/gripper_finger_left", "tape/tape_29"):
        assert len(rows[f"world/bodies/{body}"]) >= 20, body
    assert "Capsules3D:radii" in rows["world/bodies/arm/upper_arm_link/capsule"][0]
    # One story, in order: capture, the fit's iterations, the verdict, the plan, the moves, the result.
    story = [r["TextLog:text"][0] for r in rows["story"]]
    first = {key: next(i for i, t in enumerate(story) if t.startswith(key))
             for key in ("capture", "estimate: iteration 1", "estimate: verdict ok", "plan:", "move_joints pregrasp",
                         "close_gripper", "result: grasped")}
    assert list(first.values()) == sorted(first.values()), first
    steps = [r["step"] for r in rows["story"]]
    assert all(a < b for a, b in zip(steps, steps[1:]))


def test_estimate_that_is_not_ok_is_refused_untouched(monkeypatch, capsys):
    """A robot acts only on "ok": an estimate the estimator calls hidden (with the arm out
    of every view, re-capturing cannot help) is refused, the arm never moves to the tape,
    and the episode says so apart from failures."""
    import dataclasses

    from tapecell.estimator import Verdict
    from tapecell.sim import episode

    real = episode.estimate

    def unsure(capture, **kw):
        return dataclasses.replace(real(capture, **kw), verdict=Verdict.AMBIGUOUS, verdict_reason="made up")

    monkeypatch.setattr(episode, "estimate", unsure)
    code = main(["episode", "--seed", "2"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert code == 1
    assert doc["success"] is False and doc["outcome"] == "refused" and doc["verdict"] == "ambiguous"
    assert doc["failure"] == "estimate rejected"
    assert "execute" not in doc["time_s"]
    assert "estimate rejected" in err


def test_bad_cell_file_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(default_cell_path().read_text() + "\n[episode_typo]\nx = 1\n")
    code = main(["episode", "--seed", "1", "--config", str(cfg)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "episode_typo" in err and str(cfg) in err


def test_episodes_in_parallel_then_resume(tmp_path, capsys):
    out_dir = tmp_path / "runs"
    code = main(["episodes", "--n", "2", "--seed", "1", "--jobs", "2", "--out", str(out_dir)])
    out, err = capsys.readouterr()
    assert code == 0, err
    results = load_results(out_dir / "results.jsonl")
    assert sorted(r["seed"] for r in results) == [1, 2]
    assert "episodes 2" in out and "95 % interval" in out
    code = main(["episodes", "--n", "2", "--seed", "1", "--jobs", "2", "--out", str(out_dir)])
    out, err = capsys.readouterr()
    assert "2 of 2 episodes already" in err
    assert len(load_results(out_dir / "results.jsonl")) == 2


def _fake_worker(job: EpisodeJob) -> dict:
    ok = job.seed % 3 != 0
    return {"format": "tape-episode/1", "seed": job.seed, "cameras": job.cameras, "success": ok,
            "failure": None if ok else "missed", "tip_error_mm": 0.1 * job.seed, "normal_error_deg": 1.0,
            "time_s": {"capture": 0.3, "estimate": 0.01}}


def test_runner_skips_done_seeds_and_survives_a_torn_line(tmp_path, capsys):
    calls = []

    def worker(job):
        calls.append(job.seed)
        return _fake_worker(job)

    out_dir = tmp_path / "r"
    run_episodes(range(0, 3), 2, out_dir, worker=worker)
    with open(out_dir / "results.jsonl", "a") as f:
        f.write('{"format": "tape-episode/1", "seed": 3, "cam')  # a crash mid-line
    results = run_episodes(range(0, 6), 2, out_dir, worker=worker)
    assert calls == [0, 1, 2, 3, 4, 5][:3] + [3, 4, 5]
    assert [r["seed"] for r in results] == [0, 1, 2, 3, 4, 5]
    text = summarize(results)
    assert "grasped  4/6" in text and "missed x2" in text
    assert "tip error mm:     median 0.25" in text


def test_summary_tells_refusals_from_failures():
    results = [{"seed": s, "cameras": 2, "success": True, "outcome": "grasped"} for s in range(7)]
    results += [{"seed": 7, "cameras": 2, "success": False, "outcome": "refused", "verdict": "hidden",
                 "failure": "estimate rejected"},
                {"seed": 8, "cameras": 2, "success": False, "outcome": "failed", "verdict": "ok", "failure": "missed"}]
    text = summarize(results)
    assert "grasped  7/9 = 77.8 %" in text
    assert "refused  1/9" in text and "estimate rejected (hidden) x1" in text
    assert "failed   1/9" in text and "missed x1" in text
    assert "95 % interval" in text


def test_results_file_lines_are_whole_json(tmp_path):
    path = tmp_path / "results.jsonl"
    for s in range(3):
        append_result(path, _fake_worker(EpisodeJob(s, 3, None, None)))
    assert [json.loads(line)["seed"] for line in path.read_text().splitlines()] == [0, 1, 2]


@pytest.mark.parametrize("k,n,lo,hi", [(0, 10, 0.0, 0.278), (10, 10, 0.722, 1.0), (196, 200, 0.9497, 0.9922)])
def test_wilson_interval(k, n, lo, hi):
    a, b = wilson_interval(k, n)
    assert a == pytest.approx(lo, abs=2e-3) and b == pytest.approx(hi, abs=2e-3)


def test_failures_are_blamed_on_a_stage():
    from tapecell.sim.episodes import blame
    assert blame({"success": True}) is None
    assert blame({"success": False, "failure": "estimate rejected", "tip_error_mm": 0.5}) == "estimator"
    assert blame({"success": False, "failure": "missed", "tip_error_mm": 9.0}) == "estimator"
    assert blame({"success": False, "failure": "missed", "tip_error_mm": 0.9}) == "execution"
    assert blame({"success": False, "failure": "unreachable", "tip_error_mm": 0.9}) == "planner"
    assert blame({"success": False, "failure": "crash"}) == "error"


def test_episode_estimates_with_the_cameras_file_the_cell_file_names(tmp_path, capsys):
    """[episode] cameras_file: a wrong calibration must show in the estimate."""

    import numpy as np

    from tapecell.estimator.capture import save_cameras
    from tapecell.estimator.geometry import rot_z
    from tapecell.sim.cell import SimCell
    from tapecell.cell.config import load_cell_config

    with SimCell(load_cell_config(), seed=1, n_cameras=2, tool="gripper") as cell:
        true = cell.cameras()
    # cam0 turned by 1 deg about its optical axis: a calibration gone wrong
    wrong = [true[0].with_pose(rot_z(np.radians(1.0)) @ true[0].R, true[0].t), true[1]]
    save_cameras(wrong, tmp_path / "cams.json")
    text, n = re.subn(r'(?m)^cameras_file = ""', 'cameras_file = "cams.json"', default_cell_path().read_text())
    assert n == 1
    (tmp_path / "cell.toml").write_text(text)
    main(["episode", "--seed", "1", "--config", str(tmp_path / "cell.toml")])
    doc = json.loads(capsys.readouterr().out)
    main(["episode", "--seed", "1"])
    ref = json.loads(capsys.readouterr().out)
    assert ref["tip_error_mm"] < 1.0
    assert doc["cost"] > ref["cost"] + 0.02 or doc["tip_error_mm"] > ref["tip_error_mm"] + 0.5


def test_needle_confirms_one_hypothesis_of_an_ambiguous_estimate():
    """An ambiguous estimate whose alternative is the true tape: the needle touches tape at
    the alternative's tip and not at the wrong one's, and the alternative is acted on."""
    import dataclasses

    from tapecell.cell.config import load_cell_config
    from tapecell.estimator import Alternative, Verdict
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.sim.episode import resolve_by_probing

    cfg = load_cell_config()
    with SimCell(cfg, seed=3, n_cameras=2, tool="gripper") as cell:
        arm = SimArm(cell, tool="gripper")
        est = estimate(cell.capture())
        truth = cell.tape_tip_frame()
        wrong = dataclasses.replace(est, tip_position=est.tip_position + np.array([0.03, -0.02, 0.0]),
                                    verdict=Verdict.AMBIGUOUS,
                                    alternatives=(Alternative(est.cost, truth[:3, 3], truth[:3, :3], est.angles),))
        chosen, touched = resolve_by_probing(cell, arm, wrong, cfg.tape.width)
    assert touched[0] is None or touched[0] > 4.0     # nothing (or something far) at the wrong tip
    assert touched[1] is not None and touched[1] < 4.0
    assert chosen.verdict is Verdict.OK and np.allclose(chosen.tip_position, truth[:3, 3])


def test_needle_measures_the_end_of_a_fit_the_views_say_is_short():
    """A poor_fit whose views show tape past the model's end: the needle touches the tip,
    steps on past it along the tape while it finds tape, and the end is moved there (or
    kept, where none is found 3 mm past it); a tip off the tape is left refused."""
    import dataclasses

    from tapecell.cell.config import load_cell_config
    from tapecell.estimator import Verdict
    from tapecell.estimator.verdict import PAST_END
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.sim.episode import measure_end_by_probing

    cfg = load_cell_config()
    with SimCell(cfg, seed=3, n_cameras=2, tool="gripper") as cell:
        arm = SimArm(cell, tool="gripper")
        est = estimate(cell.capture())
        truth = cell.tape_tip_frame()
        true_tip, trunk = truth[:3, 3], truth[:3, 0]

        def poor(tip):
            """The estimate with the true end frame at ``tip``, poor_fit for tape past it."""
            return dataclasses.replace(est, tip_position=tip, tip_rotation=truth[:3, :3], verdict=Verdict.POOR_FIT,
                                       verdict_reason=f"view 1 {PAST_END} over 40 px (> 30 px)")
        short, steps = measure_end_by_probing(cell, arm, poor(true_tip - 0.010 * trunk), cfg.tape.width)
        assert short.verdict is Verdict.OK and steps[:2] == [3.0, 6.0]
        assert np.linalg.norm(short.tip_position - true_tip) < 0.004
        right, steps = measure_end_by_probing(cell, arm, poor(true_tip), cfg.tape.width)
        assert right.verdict is Verdict.OK and steps == [] and np.allclose(right.tip_position, true_tip)
        off = true_tip + 0.025 * truth[:3, 1] + 0.01 * truth[:3, 2]
        missed, steps = measure_end_by_probing(cell, arm, poor(off), cfg.tape.width)
        assert missed.verdict is Verdict.POOR_FIT and steps == []


def test_needle_refits_an_end_it_touched_off_and_checks_the_corners():
    """Seed 2: the estimate is "hidden" (one camera sees the end) and its end 5 mm off
    along the unseen depth; the needle sent to its tip touches tape 4.8 mm away; the shape
    is refitted through the touch, and the refit's tip, its two corners and a point past it
    are probed before it is kept (within 1 mm of the end). Seed 4: a "tip" on the tape's side
    edge with its trunk pointing off the tape (tape at it, none 6 mm past it: what was
    confirmed before) is refused: one of its corners is in the air; beside the true end as
    another hypothesis, the true end is kept, the only touched tip whose corners are tape."""
    import dataclasses

    from tapecell.cell.config import load_cell_config
    from tapecell.cell.probe import PROBE_CONFIRM_M, PROBE_CORNER_M, REFIT_TOUCH_MAX_M
    from tapecell.estimator import Alternative, Verdict
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.sim.episode import resolve_by_probing

    cfg = load_cell_config()
    with SimCell(cfg, seed=2, n_cameras=2, tool="gripper") as cell:
        arm = SimArm(cell, tool="gripper")
        capture = cell.capture()
        est = estimate(capture)
        true_tip = cell.tape_tip_frame()[:3, 3]
        assert est.verdict is Verdict.HIDDEN and np.linalg.norm(est.tip_position - true_tip) > 0.004
        notes: dict = {}
        kept, touched = resolve_by_probing(cell, arm, est, cfg.tape.width, None, capture, notes)
    assert 1e3 * PROBE_CONFIRM_M < touched[0] <= 1e3 * REFIT_TOUCH_MAX_M
    assert kept.verdict is Verdict.OK and kept.verdict_reason.startswith("refitted through the needle's touch")
    assert np.linalg.norm(kept.tip_position - true_tip) < 0.001
    assert len(notes["probed_corners_mm"]) == 2 and max(notes["probed_corners_mm"]) < 1e3 * PROBE_CORNER_M

    with SimCell(cfg, seed=4, n_cameras=2, tool="gripper") as cell:
        arm = SimArm(cell, tool="gripper")
        est = estimate(cell.capture())
        truth = cell.tape_tip_frame()
        R = truth[:3, :3]
        side = dataclasses.replace(est, tip_position=truth[:3, 3] - 0.005 * R[:, 0] + (0.5 * cfg.tape.width - 0.0005) * R[:, 1],
                                   tip_rotation=np.column_stack([R[:, 1], -R[:, 0], R[:, 2]]),
                                   verdict=Verdict.HIDDEN, alternatives=())
        notes, probes = {}, []
        refused, touched = resolve_by_probing(cell, arm, side, cfg.tape.width, probes, None, notes)
        # The true end and that side-edge "tip" as two hypotheses of one shape: both tips are
        # tape with none past them, nothing tells where the shapes disagree (they are one
        # shape) nor which is clearly closer; only the true end has both corners on tape.
        both = dataclasses.replace(est, tip_position=truth[:3, 3], tip_rotation=R, verdict=Verdict.AMBIGUOUS,
                                   alternatives=(Alternative(est.cost, side.tip_position, side.tip_rotation,
                                                             est.angles),))
        kept, touched2 = resolve_by_probing(cell, arm, both, cfg.tape.width)
    assert touched[0] is not None and touched[0] < 1e3 * PROBE_CONFIRM_M          # tape at the "tip" ...
    assert all(p["touched"] is None for p in probes if p["label"].startswith("beyond"))   # ... none past it
    assert refused.verdict is Verdict.HIDDEN
    assert any(d is None or d > 1e3 * PROBE_CORNER_M for d in notes["probed_corners_mm"])
    assert all(d is not None and d < 1e3 * PROBE_CONFIRM_M for d in touched2)
    assert kept.verdict is Verdict.OK and "the only touched tip of 2 whose corners are tape" in kept.verdict_reason
    assert np.allclose(kept.tip_position, truth[:3, 3])


def test_two_touched_ends_a_few_millimetres_apart_are_one_end():
    """Seed 4: the true end and a "tip" 3 mm back along the same tape, as two hypotheses of
    one shape: both tips are tape with none past them, both have their corners on tape,
    nothing tells where the shapes disagree nor which is clearly closer. They lie within
    ONE_END_M of each other: one end, and the one farther out along the tape is kept (before,
    refused). Tips farther apart stay two ends."""
    import dataclasses

    from tapecell.cell.config import load_cell_config
    from tapecell.cell.probe import PROBE_CONFIRM_M
    from tapecell.estimator import Alternative, Verdict
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.sim.episode import ONE_END_M, one_end, outermost, resolve_by_probing

    cfg = load_cell_config()
    with SimCell(cfg, seed=4, n_cameras=2, tool="gripper") as cell:
        arm = SimArm(cell, tool="gripper")
        est = estimate(cell.capture())
        truth = cell.tape_tip_frame()
        R = truth[:3, :3]
        back = truth[:3, 3] - 0.003 * R[:, 0]
        both = dataclasses.replace(est, tip_position=back, tip_rotation=R, verdict=Verdict.AMBIGUOUS,
                                   alternatives=(Alternative(est.cost, truth[:3, 3], R, est.angles),))
        kept, touched = resolve_by_probing(cell, arm, both, cfg.tape.width)
    assert all(d is not None and d < 1e3 * PROBE_CONFIRM_M for d in touched)
    assert kept.verdict is Verdict.OK and "(one end)" in kept.verdict_reason, kept.verdict_reason
    assert np.allclose(kept.tip_position, truth[:3, 3])       # the one farther out: the end
    assert one_end([np.zeros(3), np.array([ONE_END_M, 0, 0]), np.array([0.5 * ONE_END_M, 0.002, 0])])
    assert not one_end([np.zeros(3), np.array([0.004, 0, 0]), np.array([-0.0045, 0, 0])])
    assert outermost([(np.array([0.003, 0, 0]), np.eye(3)), (np.array([0.005, 0.001, 0]), np.eye(3))]) == 1


def test_an_end_the_model_does_not_explain_is_measured_by_the_needle(capsys, monkeypatch):
    """Seed 520012: the tape's end hooks over within a few millimetres, which 30 mm plates
    cannot follow; the estimate is poor_fit ("does not explain the free end"). The needle
    touches tape at its tip and none 3 mm past it: the end is there, and the grasp is made.
    Which poor fits the needle settles: tape past the end or an unexplained end, not a view
    the model does not explain at all. (With the verdict's EDGE_PX at 10 px, as when this
    was found: at 8 px, since 2026-11-27, that view no longer locates the end, the estimate
    is not poor_fit, and the needle confirms its hypothesis instead, 1.7 mm off alike. And
    without correcting the cameras from the views, fit.SELF_CALIBRATE: since 2026-11-27 that
    is made with two cameras too, and it makes this capture "ok" 1.1 mm off, with turns of
    0.18 and 0.07 deg the right cameras do not have.)"""
    from tapecell.estimator import Verdict, fit
    from tapecell.estimator import verdict
    from tapecell.estimator.verdict import END_UNEXPLAINED, PAST_END
    from tapecell.cell.probe import end_measurable as end_to_measure

    monkeypatch.setattr(verdict, "EDGE_PX", 10)
    monkeypatch.setattr(fit, "SELF_CALIBRATE", False)
    code = main(["episode", "--seed", "520012"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert code == 0, err
    assert doc["outcome"] == "grasped" and doc["verdict"] == "ok"
    assert doc["verdict_reason"].startswith("the needle touched tape at the tip")
    assert doc["probed_past_end_mm"] == [] and doc["tip_error_mm"] < 3.0

    def est(verdict, reason, alternatives=()):
        return SimpleNamespace(verdict=verdict, verdict_reason=reason, alternatives=alternatives)
    assert end_to_measure(est(Verdict.POOR_FIT, f"view 0 {END_UNEXPLAINED}: mean boundary distance 3.1 px"))
    assert end_to_measure(est(Verdict.POOR_FIT, f"view 1 {PAST_END} over 40 px (> 30 px)"))
    assert not end_to_measure(est(Verdict.POOR_FIT, "view 0 is not explained: mean boundary distance 3.9 px > 3 px"))
    assert not end_to_measure(est(Verdict.HIDDEN, f"view 0 {END_UNEXPLAINED}"))
    # With an alternative shape its own end is measured (the alternatives are not probed).
    assert end_to_measure(est(Verdict.POOR_FIT, f"view 0 {END_UNEXPLAINED}", ("another shape",)))


def test_a_far_grasp_on_a_needle_measured_end_is_planned_about_the_tape_the_needle_touches(capsys, monkeypatch):
    """Seed 868005: the estimate is "hidden"; the needle walks its end 9 mm on and checks the
    corners and the trunk. Every grasp near the end is refused; the planner falls back to 20 mm
    in, beyond what the needle checked, where the estimated shape lies 5.7 mm off the tape
    (its end's trunk 25 deg off): planned there, a pad swept the tape aside on the approach and
    the jaw closed on air. The needle touches that grasp point first, and the grasp is planned
    again about the tape it found there: the jaw takes the tape. (So the estimator answers
    without the joints' lines in the model's outline, FitConfig.crease_t; with them its
    estimate is close enough for the needle to confirm it at once. The needle's refits keep
    the default, as in the episode this was found in.)"""
    import dataclasses
    import functools

    import tapecell.sim.episode as episode
    from tapecell.cell.probe import GRASP_CHECKED_M, GRASP_RECENTRE_M, GRASP_STATION_M, grasp_station
    from tapecell.estimator.config import DEFAULT

    monkeypatch.setattr(episode, "estimate",
                        functools.partial(episode.estimate, config=dataclasses.replace(DEFAULT, crease_t=())))
    code = main(["episode", "--seed", "868005"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert code == 0, err
    assert doc["verdict_reason"].startswith("hypothesis 0's end measured by the needle")
    assert doc["grasp"]["inset_mm"] > 1e3 * GRASP_CHECKED_M
    assert len(doc["probed_grasp_mm"]) == 3 and doc["probed_grasp_off"]["mm"] > 1e3 * GRASP_RECENTRE_M
    assert doc["probed_past_mm"] == [None]    # past the walked end along its measured frame: clear
    assert doc["outcome"] == "grasped", doc
    # What the touches say: the offset along the normal at the grasp point, the turn of the
    # line through the three about the tape's width.
    R = np.eye(3)[:, [1, 2, 0]]                      # trunk y, left z, normal x
    step = GRASP_STATION_M
    touched = {0: np.array([0.002, 0.001, -0.004]), -1: np.array([0.002 - step, -step, 0.0]),
               1: np.array([0.002 + step, step, 0.0])}
    offset, turn = grasp_station(np.zeros(3), R, touched)
    assert np.allclose(offset, [0.002, 0, 0]) and turn == pytest.approx(45.0)
    assert grasp_station(np.zeros(3), R, {0: touched[0], -1: None, 1: touched[1]})[1] is None


def test_a_walked_end_with_tape_past_it_along_its_measured_frame_is_not_grasped(capsys):
    """Fresh sweep episode 1046002 (3 cameras, each turned 0.5 deg for the estimator): the
    estimate is "hidden"; one hypothesis' tip is tape and so is the point 6 mm past it, and
    the needle walked on along a curl (none within 4 mm at 9 mm: the curl had turned away,
    6.6 mm off). Its corners' touches turned the "end's" frame 32 deg onto the tape, and
    along that frame tape lies 4.7 mm from the point 9 mm past it (a step further out than
    a confirmed tip's probe: a walked end is known only to a step). Not an end: refused
    (before, grasped 50 mm from the tape's end). The walked end of seed 868005 (the test
    above), its frame turned 26 deg, has no tape there and is grasped."""
    code = main(["episode", "--seed", "1046002", "--cameras", "3", "--randomize", "calib_rot_deg=0.5"])
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert doc["outcome"] == "refused", doc
    assert code == 1, err
    assert any(d is not None and d <= 12.0 for d in doc["probed_past_mm"]), doc["probed_past_mm"]


def test_episode_recording_shows_its_content_on_opening(tmp_path):
    """The real rerun viewer, opened on an episode's recording, shows the camera images and
    the 3-D scene at once (about 2 % of the screen was bright when everything was logged off
    the viewer's timeline; a filled layout gives about 10 %). Skips where the viewer cannot
    start (no ../shared tool, no rerun CLI, no virtual display)."""
    import os
    import shutil
    import subprocess
    import sys

    import cv2

    tool = Path(__file__).resolve().parents[2] / "shared" / "tools" / "rrd-screenshot"
    rerun_cli = Path(sys.executable).parent / "rerun"
    if not tool.exists() or not (rerun_cli.exists() or shutil.which("rerun")):
        pytest.skip("the rrd-screenshot tool or the rerun CLI is not here")
    from tapecell.sim.episode import run_episode

    rrd, png = tmp_path / "ep.rrd", tmp_path / "ep.png"
    doc = run_episode(1, 2, rrd)
    assert rrd.stat().st_size < 5e6 and doc["recording"] == "ep.rrd"
    env = {**os.environ, "PATH": f"{rerun_cli.parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    r = subprocess.run(["bash", str(tool), str(rrd), str(png)], capture_output=True, text=True, env=env,
                       timeout=300)
    if r.returncode != 0 or not png.exists():
        pytest.skip(f"the viewer could not start here: {r.stderr.strip()[-200:]}")
    bright = float((cv2.imread(str(png), cv2.IMREAD_GRAYSCALE) > 100).mean())
    assert bright > 0.06, f"only {100 * bright:.1f} % of the screen is bright"


def test_campaign_keeps_only_the_failures_recordings(tmp_path, monkeypatch):
    """--rrd failures: every episode records, and a grasped one's file is removed again."""
    from tapecell.sim import episode as episode_module
    from tapecell.sim.episodes import _worker

    def fake(seed, cameras, recording, config, randomize=None):
        recording.write_bytes(b"rrd")
        ok = seed % 2 == 0
        return {"format": "tape-episode/1", "seed": seed, "cameras": cameras, "success": ok,
                "outcome": "grasped" if ok else "failed",
                "recording": recording.name}

    monkeypatch.setattr(episode_module, "run_episode_safely", fake)
    out = tmp_path / "c"
    results = run_episodes(range(4), 2, out, rrd="failures", worker=_worker)
    assert sorted(p.name for p in out.glob("*.rrd")) == ["episode-0001.rrd", "episode-0003.rrd"]
    assert [r.get("recording") for r in results] == [None, "episode-0001.rrd", None, "episode-0003.rrd"]


def _sleep_long(seconds: float) -> float:
    import time

    time.sleep(seconds)
    return seconds


def test_an_interrupted_campaign_ends_its_workers_at_once():
    """Ctrl-C or SIGTERM while a pool runs episodes: the pool's processes end at once (the
    episodes in flight are lost; a rerun runs them), not after their episodes, and none is
    left behind (a second signal during that wait once left the command hanging)."""
    import multiprocessing as mp
    import time
    from concurrent.futures import ProcessPoolExecutor

    from tapecell.sim.episodes import _stopped_on_exit

    processes = []
    t0 = time.perf_counter()
    with pytest.raises(KeyboardInterrupt):
        with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool, _stopped_on_exit(pool):
            futures = [pool.submit(_sleep_long, 60.0) for _ in range(3)]
            time.sleep(1.0)
            processes = list(pool._processes.values())
            raise KeyboardInterrupt
    assert time.perf_counter() - t0 < 30.0
    # The pool's own manager thread reaps its workers too: right after the block a worker
    # already ended can still read as alive for a moment (seen in 1 of 5 runs), so allow
    # that moment (3 s was too short once, with another simulation running on this 2-core
    # machine); a worker left to finish its 60 s episode stays alive through it.
    deadline = time.perf_counter() + 10.0
    while any(p.is_alive() for p in processes) and time.perf_counter() < deadline:
        time.sleep(0.05)
    assert processes and not any(p.is_alive() for p in processes)
    assert futures[2].cancelled() or futures[2].done()


def test_the_held_point_is_found_and_followed_along_the_centre_line():
    """sim.episode.HeldPoint (with estimator.metrics.centerline_at): the success check's
    point where the pads hold the tape, by arc length along the true centre line, found on
    closing and read again after the lift. A
    tape lifted with the jaw does not lag; one sliding 10 mm along itself through the pads
    lags 10 mm, though the centre line's point nearest the jaw is as near as before."""
    from tapecell.estimator.capture import Truth
    from tapecell.estimator.metrics import centerline_at
    from tapecell.sim.episode import HeldPoint, nearest_arc_length

    s = np.array([0.0, 0.01, 0.02, 0.03])
    points = np.array([[0, 0, 0], [0.01, 0, 0], [0.01, 0.01, 0], [0.01, 0.02, 0]], float)
    assert nearest_arc_length(s, points, np.array([0.004, 0.003, 0.002])) == pytest.approx(0.004)
    assert nearest_arc_length(s, points, np.array([0.013, 0.015, 0.0])) == pytest.approx(0.025)
    assert nearest_arc_length(s, points, np.array([-1.0, 0.0, 0.0])) == pytest.approx(0.0)
    np.testing.assert_allclose(centerline_at(Truth(s, points, np.eye(3)), [0.025])[0], [0.01, 0.015, 0.0])
    # A repeated sample (a zero-length segment) is harmless.
    s2, p2 = np.insert(s, 2, 0.02), np.insert(points, 2, points[2], axis=0)
    assert nearest_arc_length(s2, p2, np.array([0.013, 0.01, 0.0])) == pytest.approx(0.02)

    straight = Truth(np.linspace(0, 0.1, 11), np.column_stack([np.linspace(0, 0.1, 11), np.zeros(11), np.zeros(11)]),
                     np.eye(3))
    held = HeldPoint.at(straight, np.array([0.043, 0.004, 0.0]))
    assert held.s == pytest.approx(0.043) and held.offset_m == pytest.approx(0.004)
    up = np.array([0.0, 0.0, 0.05])
    lifted = Truth(straight.s, straight.points + up, straight.tip_rotation)
    assert held.lag(lifted, up) == pytest.approx(0.0, abs=1e-12)
    slid = Truth(straight.s, straight.points + up + [0.01, 0.0, 0.0], straight.tip_rotation)
    assert held.lag(slid, up) == pytest.approx(0.01)


@pytest.mark.parametrize("seed, cameras, friction", [(915040, 2, None), (911062, 3, 0.1)])
def test_a_grasp_succeeds_where_the_tape_between_the_pads_follows_the_gripper(seed, cameras, friction, capsys,
                                                                            tmp_path):
    """915040 takes the tape 48 mm back from its end and holds it through the lift (the tape
    between the pads follows the gripper within ~1.3 mm) while the free end beyond the jaw
    swings 11.4 mm (7.9 mm since the needle measures the end's frame, 0.4 mm at the pads).
    911062 closes across the tape's end: with the cell file's friction it holds (its tape
    slid 10.6 mm out of the pads while the lift stopped every 10 mm; 5.8 mm since the lift is
    one blended path), with the pads and the tape at friction 0.1 the tape slides out of
    the pads on the lift. Only that one slipped."""
    args = ["episode", "--seed", str(seed), "--cameras", str(cameras)]
    if friction is not None:
        slippery = tmp_path / "slippery.toml"
        text, n = re.subn(r"(?m)^friction = [0-9.]+", f"friction = {friction}", default_cell_path().read_text())
        assert n == 2                                   # the tape's and the gripper's pads'
        slippery.write_text(text)
        args += ["--config", str(slippery)]
    code = main(args)
    doc = json.loads(capsys.readouterr().out)
    assert code == (0 if seed == 915040 else 1)   # 1: the task itself failed
    if seed == 915040:
        assert doc["outcome"] == "grasped" and doc["grasp"]["inset_mm"] > 30.0
        assert doc["held_follow_error_mm"] < 3.0 and doc["tip_follow_error_mm"] > 5.0
    else:
        assert doc["outcome"] == "failed" and doc["failure"] == "slipped"
        assert doc["held_follow_error_mm"] > 8.0
