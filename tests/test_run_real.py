"""`tapecell run` (the real cell) on images rendered by the sim: it plans without moving,
and never moves without --execute and a terminal to confirm on."""
from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from tapecell.cli.main import main
from tapecell.estimator.capture import save_cameras
from tapecell.sim.cell import SimCell
from tapecell.cell.config import default_cell_path, load_cell_config


@pytest.fixture(scope="module")
def real_like(tmp_path_factory) -> tuple[Path, Path]:
    """Camera images as the real cell's folder source expects them, and their cameras file."""
    root = tmp_path_factory.mktemp("real")
    with SimCell(load_cell_config(), seed=4, n_cameras=2, tool="gripper") as cell:
        (root / "images" / "000").mkdir(parents=True)
        for cam in cell.cameras():
            rgb = cell.render_rgb(cam.name)
            cv2.imwrite(str(root / "images" / "000" / f"{cam.name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        save_cameras(cell.cameras(), root / "cameras.json")
    return root / "images", root / "cameras.json"


@pytest.fixture
def no_robot(monkeypatch):
    from tapecell.cell import ur as cell_ur

    def refuse(*a, **k):
        raise AssertionError("the dry run must not touch the robot")
    monkeypatch.setattr(cell_ur, "URArm", refuse)


def test_dry_run_plans_and_moves_nothing(real_like, no_robot, tmp_path, capsys):
    images, cameras = real_like
    saved = tmp_path / "saved"
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--save-capture", str(saved), "--rrd", str(tmp_path / "run.rrd")])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "grasp plan" in out and "pregrasp" in out and "grasp " in out
    assert "nothing moved" in out
    assert (saved / "capture.json").exists() and (saved / "cam0_rgb.png").exists()
    assert main(["estimate", str(saved)]) == 0  # the saved capture replays
    from tapecell.cell.recording import read_recording

    rows = read_recording(tmp_path / "run.rrd")
    story = [r["TextLog:text"][0] for r in rows["story"]]
    assert story[0].startswith("capture: 2 cameras") and story[-1].startswith("planned; nothing moved")
    assert any(t.startswith("estimate: verdict ok") for t in story) and any(t.startswith("plan:") for t in story)
    # The arm (the UR5e's DH model as capsules, the gripper's boxes) shown where the plan grasps.
    assert "Capsules3D:radii" in rows["world/bodies/arm/link2/capsule"][0]
    assert len(rows["world/bodies/arm/link6/box"][0]["Boxes3D:half_sizes"]) == 3
    assert "world/scene" in rows          # the part and the table, which the estimate knew


def test_execute_without_a_terminal_refuses_before_connecting(real_like, no_robot, monkeypatch, capsys):
    images, cameras = real_like
    monkeypatch.setattr("sys.stdin.isatty", lambda: False)
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute"])
    out, err = capsys.readouterr()
    assert code == 2
    assert "confirmation on a terminal" in err and "nothing moved" in err


def test_missing_images_is_one_line(real_like, tmp_path, capsys):
    _, cameras = real_like
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras),
                 "--images", str(tmp_path / "nowhere")])
    out, err = capsys.readouterr()
    assert code == 2 and err.count("\n") == 1 and "nowhere" in err


def _expected_plan(images, cameras, q_start):
    from tapecell.cli.commands.run import grab_capture
    from tapecell.cell.planner import GraspParams, GripperGeometry, TipFrame, plan_grasp
    from tapecell.cell.safety import SafetyLimits
    from tapecell.estimator import estimate
    from tapecell.estimator.capture import load_cameras

    cfg = load_cell_config()
    est = estimate(grab_capture(cfg, load_cameras(cameras), images))
    return plan_grasp(TipFrame.from_estimate(est), GraspParams.from_config(cfg.grasp),
                      GripperGeometry.from_config(cfg.tools.gripper), SafetyLimits.from_config(cfg.limits),
                      q_start=q_start, tape_points=est.nodes)


@pytest.mark.parametrize("answer", ["yes", "no"])
def test_execute_sends_exactly_the_plan_after_confirmation(real_like, monkeypatch, capsys, answer):
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    images, cameras = real_like
    q0 = np.array(load_cell_config().arm.park_joints)
    robot = FakeRobot(q0)
    install_fake_rtde(monkeypatch, robot, probe=False)
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    asked = []

    def ask(prompt=""):
        asked.append((prompt, len(robot.log)))
        return answer
    monkeypatch.setattr("builtins.input", ask)
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute"])
    out, err = capsys.readouterr()
    motions = [c for c in robot.log if c[0] in ("moveJ", "moveL", "setStandardDigitalOut")]
    # Asked once, with the robot's address, before any connection was opened.
    assert len(asked) == 1 and asked[0][1] == 0 and "192.168.1.10:30004" in asked[0][0]
    assert "robot: UR arm at 192.168.1.10:30004" in err and "grasp plan" in out
    if answer == "no":
        assert code == 1 and "cancelled; nothing connected, nothing moved" in err
        assert robot.log == []
        return
    assert code == 0, err
    plan = _expected_plan(images, cameras, q0)
    expected = []
    for step in plan.steps:
        if step.action == "move_joints":
            expected.append(("moveJ", plan.waypoint(step.waypoint).q))
        elif step.action == "move_linear":
            expected.append(("moveL", plan.waypoint(step.waypoint).flange_pose))
        elif step.action == "move_linear_path":      # the lift: one moveL(path), not a stop every 10 mm
            expected.append(("moveL", [plan.waypoint(n).flange_pose for n in step.targets], step.blend))
        else:
            expected.append(("setStandardDigitalOut", step.action))
    assert len(expected) >= 5 and [m[0] for m in motions] == [e[0] for e in expected]
    limits = load_cell_config().limits
    assert sum(len(m) == 2 for m in motions if m[0] == "moveL") == 1          # the lift's one path
    for m, e in zip(motions, expected):
        if m[0] == "moveL" and len(m) == 2:
            path = np.array(m[1])
            assert len(e) == 3 and path.shape == (len(e[1]), 9)
            assert np.allclose(path[:, :6], e[1], atol=1e-9)
            assert np.all((0 < path[:, 6]) & (path[:, 6] <= limits.max_tcp_speed))
            assert np.all((0 < path[:, 7]) & (path[:, 7] <= limits.max_tcp_accel))
            assert np.all(path[:-1, 8] == e[2]) and path[-1, 8] == 0.0
        elif m[0] == "moveL":
            assert np.allclose(m[1], e[1], atol=1e-9)
            assert 0 < m[2] <= limits.max_tcp_speed and 0 < m[3] <= limits.max_tcp_accel
        elif m[0] == "moveJ":
            assert np.allclose(m[1], e[1], atol=1e-9)
            assert 0 < m[2] <= limits.max_joint_speed
    # each motion is preceded by the controller's own safety check
    for i, call in enumerate(robot.log):
        if call[0] == "moveL":
            assert robot.log[i - 1][0] in ("speedStop", "servoStop", "isPoseWithinSafetyLimits")
    assert any(c[0] == "isPoseWithinSafetyLimits" for c in robot.log)
    # The planner's kinematics were checked against the controller's before each motion:
    # forward kinematics of each joint target, inverse kinematics of each linear target.
    for i, call in enumerate(robot.log):
        if call[0] == "moveJ":
            fk_calls = [c for c in robot.log[:i] if c[0] == "getForwardKinematics"]
            assert fk_calls and np.allclose(fk_calls[-1][1], call[1]) and fk_calls[-1][2] == [0.0] * 6
        if call[0] == "moveL":
            ik_calls = [c for c in robot.log[:i] if c[0] == "getInverseKinematics"]
            targets = [r[:6] for r in call[1]] if len(call) == 2 else [call[1]]
            assert len(ik_calls) >= len(targets)
            assert np.allclose([c[1] for c in ik_calls[-len(targets):]], targets)
    assert "grasp executed" in out


def _fake_controller(monkeypatch, offset_m):
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    robot.calibration[:3, 3] = offset_m      # the calibrated arm puts the flange here off the nominal model
    install_fake_rtde(monkeypatch, robot, probe=False)
    return robot


def test_execute_plans_in_the_controllers_kinematics(real_like, monkeypatch, capsys):
    """A real UR's calibration moves the tool 2-3 mm from the nominal model: the joint
    targets come from the controller's inverse kinematics, so its flange reaches the plan."""
    import numpy as np
    from tapecell.cell.kinematics import fk
    from tapecell.cell.poses import pose6_to_matrix

    images, cameras = real_like
    robot = _fake_controller(monkeypatch, [0.0025, -0.001, 0.0015])
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--yes"])
    out, err = capsys.readouterr()
    assert code == 0, err
    plan = _expected_plan(images, cameras, np.array(load_cell_config().arm.park_joints))
    q_sent = next(c[1] for c in robot.log if c[0] == "moveJ")
    target = pose6_to_matrix(plan.waypoint("pregrasp").flange_pose)
    assert np.linalg.norm(robot.world_from_flange(q_sent)[:3, 3] - target[:3, 3]) < 1e-6
    assert np.linalg.norm(fk(q_sent)[:3, 3] - target[:3, 3]) > 0.002     # not the nominal model's joints


def test_execute_refuses_when_the_kinematics_disagree(real_like, monkeypatch, capsys):
    images, cameras = real_like
    robot = _fake_controller(monkeypatch, [0.02, 0.0, 0.0])
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--yes"])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()          # the address, the action, "confirmed by --yes", the error
    assert code == 3 and len(lines) == 4 and lines[-1].startswith("tapecell: error: ")
    assert "differ from the planner's UR5e model by 20.0 mm" in err and "nothing was sent" in err
    assert not any(c[0] in ("moveJ", "moveL", "setStandardDigitalOut") for c in robot.log)
    assert robot.log[-3:] == [("control.disconnect",), ("receive.disconnect",), ("io.disconnect",)]


def test_refused_verdict_moves_nothing(real_like, monkeypatch, no_robot, capsys, tmp_path):
    """An estimate a robot must not act on ends with exit 1 before any plan or connection
    (the estimator's verdict is its own business: here it is forced to "ambiguous")."""
    import dataclasses

    import tapecell.estimator as estimator
    from tapecell.estimator.result import Verdict

    real_estimate = estimator.estimate

    def ambiguous(*a, **k):
        return dataclasses.replace(real_estimate(*a, **k), verdict=Verdict.AMBIGUOUS,
                                   verdict_reason="a distinct shape explains the views as well")
    monkeypatch.setattr(estimator, "estimate", ambiguous)
    images, cameras = real_like
    rrd = tmp_path / "refused.rrd"
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--yes", "--rrd", str(rrd)])
    out, err = capsys.readouterr()
    assert code == 1 and err.count("\n") == 1
    assert "verdict is ambiguous (a distinct shape explains the views as well): a robot must not act on it" in err
    assert "grasp plan" not in out
    # The recording keeps what a reviewer needs: what was seen, what was believed, why it was refused.
    from tapecell.cell.recording import read_recording

    rows = read_recording(rrd)
    story = [r["TextLog:text"][0] for r in rows["story"]]
    assert story[-1].startswith("refused: the estimate's verdict is ambiguous")
    assert rows["story"][-1]["TextLog:level"] == ["WARN"] and "plan:" not in " ".join(story)


def test_real_cell_path_never_loads_the_simulator(real_like, tmp_path):
    """`tapecell run --images ...` (the real cell's path) imports neither MuJoCo nor
    tapecell.sim: checked on the interpreter's own import log (-X importtime)."""
    import subprocess
    import sys

    images, cameras = real_like
    env = {**__import__("os").environ, "PYTHONPROFILEIMPORTTIME": "1"}
    r = subprocess.run([sys.executable, "-m", "tapecell.cli.main", "run", "--config", str(default_cell_path()),
                        "--cameras", str(cameras), "--images", str(images)],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    imported = [line.rsplit("|", 1)[-1].strip() for line in r.stderr.splitlines() if line.startswith("import time:")]
    assert any(m.startswith("tapecell.estimator") for m in imported), r.stderr[-2000:]
    assert any(m.startswith("tapecell.cell.planner") for m in imported)
    assert not [m for m in imported if m.split(".")[0] == "mujoco" or m.startswith("tapecell.sim")]


def _ambiguous_with_alternative(monkeypatch, offset_m):
    """The real estimate, forced "ambiguous" with one alternative whose tip lies
    ``offset_m`` (3,) from the estimate's."""
    import dataclasses

    import numpy as np

    import tapecell.estimator as estimator
    from tapecell.estimator.result import Alternative, Verdict

    real_estimate = estimator.estimate

    def ambiguous(*a, **k):
        est = real_estimate(*a, **k)
        alt = Alternative(est.cost * 1.05, est.tip_position + np.asarray(offset_m), est.tip_rotation, est.angles)
        return dataclasses.replace(est, verdict=Verdict.AMBIGUOUS, alternatives=(alt,),
                                   verdict_reason="a shape with its tip 20 mm away explains the views nearly as well")
    monkeypatch.setattr(estimator, "estimate", ambiguous)
    return real_estimate


def _guide_needle_to(robot, target, monkeypatch, behind=None, grasp=None):
    """Every prompt answers Enter after 'guiding' the arm so the needle tip is at ``target``
    (what an operator does in freedrive), or, asked for the centre line behind the end, at
    ``behind`` (3,) [m] (a string: that answer, e.g. "s" to skip the point), or, asked for a
    point whose prompt holds a key of ``grasp``, at that key's point (3,) [m]."""
    import numpy as np

    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.poses import invert, pose6_to_matrix

    needle = pose6_to_matrix(load_cell_config().tools.needle.flange_from_tcp)
    prompts = []

    def ask(prompt=""):
        prompts.append(prompt)
        if "needle" in prompt:
            world_from_needle = np.eye(4)
            world_from_needle[:3, :3] = np.diag([1.0, -1.0, -1.0])       # pointing down
            if "centre line" in prompt and isinstance(behind, str):
                return behind                                             # e.g. "s": skipped
            world_from_needle[:3, 3] = behind if "centre line" in prompt and behind is not None else target
            for key, point in (grasp or {}).items():
                if key in prompt:
                    world_from_needle[:3, 3] = point
            robot.q = ik_nearest(world_from_needle @ invert(needle), robot.q)
        return ""
    monkeypatch.setattr("builtins.input", ask)
    return prompts


def _behind(est, back_m: float = 0.012, off_m: float = 0.0):
    """The point ``back_m`` behind ``est``'s tip along its trunk, ``off_m`` off it along the
    tape's normal: where the operator touches the centre line for the trunk check."""
    return est.tip_position - back_m * est.tip_rotation[:, 0] + off_m * est.tip_rotation[:, 2]


def test_probe_settles_an_ambiguous_estimate_with_the_needle_then_grasps(real_like, monkeypatch, capsys):
    """--execute --probe: freedrive, the operator puts the needle on the tape's end, the
    hypothesis it confirms is planned for and grasped; freedrive ends before any motion."""
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    images, cameras = real_like
    real_estimate = _ambiguous_with_alternative(monkeypatch, [0.0, 0.0, 0.02])
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.estimator.capture import load_cameras
    from tapecell.cli.commands.run import grab_capture

    truth = real_estimate(grab_capture(load_cell_config(), load_cameras(cameras), images))
    truth_tip = truth.tip_position
    prompts = _guide_needle_to(robot, truth_tip + [0.001, 0.0, 0.0], monkeypatch,   # 1 mm off hypothesis 0
                               _behind(truth))
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "hypothesis 0 confirmed by the needle (1.0 mm from its tip)" in out and "grasp executed" in out
    assert any("needle onto the tape's tip" in p for p in prompts)
    names = [c[0] for c in robot.log]
    assert names.index("teachMode") < names.index("endTeachMode") < names.index("moveJ")
    assert "started freedrive" not in err


@pytest.mark.parametrize("behind, message", [("off", "off the estimated end's trunk, a 40 deg bend (> 30 deg)"),
                                             ("s", "was not put on the tape's centre line")])
def test_probe_whose_trunk_touch_fails_moves_nothing(real_like, monkeypatch, capsys, behind, message):
    """--execute --probe: the needle on the tape's end confirms hypothesis 0, but the tape 12
    mm back from the end is 10 mm off that end's trunk (it bends away where the pads would
    hold it), or the operator skips that touch: refused after freedrive, nothing moved."""
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    images, cameras = real_like
    real_estimate = _ambiguous_with_alternative(monkeypatch, [0.0, 0.0, 0.02])
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.estimator.capture import load_cameras
    from tapecell.cli.commands.run import grab_capture

    truth = real_estimate(grab_capture(load_cell_config(), load_cameras(cameras), images))
    _guide_needle_to(robot, truth.tip_position, monkeypatch, _behind(truth, off_m=0.010) if behind == "off" else behind)
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    assert code == 1 and message in err.strip().splitlines()[-1]
    assert not any(c[0] in ("moveJ", "moveL", "setStandardDigitalOut") for c in robot.log)
    names = [c[0] for c in robot.log]
    assert "teachMode" in names and names.index("teachMode") < names.index("endTeachMode")


@pytest.mark.parametrize("off_m, across_m, rise_m", [(0.005, 0.0, 0.0), (0.001, 0.0, 0.002), (0.0, 0.02, 0.0),
                                                     (0.002, 0.0, 0.008), (0.012, 0.0, 0.0)])
def test_a_grasp_farther_in_than_the_needle_checked_touches_the_grasp_point_first(real_like, monkeypatch, capsys,
                                                                                   off_m, across_m, rise_m):
    """--execute --probe, with the needle's checks taken to reach only 4 mm in from the end
    (GRASP_CHECKED_M; 18 mm in the cell), so that the usual grasp 8 mm in lies beyond them:
    after settling the end, the operator also touches the tape where the jaw will hold it and
    6 mm either side. Tape 5 mm off the estimate along its normal there: the grasp is planned
    again about it, then run; 1 mm off, 19 deg turned: planned as it was; a touch 20 mm across
    the tape from the grasp point, the tape turned 53 deg there, or 12 mm off (more than
    GRASP_SHIFT_MAX_M): refused, nothing moved."""
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    from tapecell.cell import probe
    from tapecell.cell.planner import TipFrame, grasp_frame

    images, cameras = real_like
    real_estimate = _ambiguous_with_alternative(monkeypatch, [0.0, 0.0, 0.02])
    monkeypatch.setattr(probe, "GRASP_CHECKED_M", 0.004)
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.estimator.capture import load_cameras
    from tapecell.cli.commands.run import grab_capture

    truth = real_estimate(grab_capture(load_cell_config(), load_cameras(cameras), images))
    position, R = grasp_frame(TipFrame.from_estimate(truth), 0.008, 0.008, truth.nodes)
    at = position + off_m * R[:, 2]
    prompts = _guide_needle_to(robot, truth.tip_position, monkeypatch, _behind(truth),
                               grasp={"where the jaw": at + across_m * R[:, 1],
                                      "farther from the end": at - 0.006 * R[:, 0] - rise_m * R[:, 2],
                                      "nearer the end": at + 0.006 * R[:, 0] + rise_m * R[:, 2]})
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    assert sum("mm in from its end" in p for p in prompts) == 3
    names = [c[0] for c in robot.log]
    if across_m or rise_m > 0.005 or off_m > probe.GRASP_SHIFT_MAX_M:
        last = err.strip().splitlines()[-1]
        want = ("20.0 mm from that point across the tape" if across_m else
                "turns 53 deg off the estimate (> 30 deg)" if rise_m else "lies 12.0 mm off the estimate (> 10 mm)")
        assert code == 1 and want in last, last
        assert not any(c[0] in ("moveJ", "moveL", "setStandardDigitalOut") for c in robot.log)
        return
    assert code == 0, err
    assert ("planned again about it" in out) == (off_m > probe.GRASP_RECENTRE_M) and "grasp executed" in out
    assert names.count("teachMode") == 2 and names.index("endTeachMode") < names.index("moveJ")


def test_probe_that_confirms_no_hypothesis_moves_nothing(real_like, monkeypatch, capsys):
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    images, cameras = real_like
    real_estimate = _ambiguous_with_alternative(monkeypatch, [0.0, 0.0, 0.02])
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.estimator.capture import load_cameras
    from tapecell.cli.commands.run import grab_capture

    tip = real_estimate(grab_capture(load_cell_config(), load_cameras(cameras), images)).tip_position
    _guide_needle_to(robot, tip + [0.0, 0.0, 0.010], monkeypatch)       # halfway between the two
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    assert code == 1 and "confirms none of the 2 hypotheses" in err and "(their tips are 10.0, 10.0 mm away" in err
    assert not any(c[0] in ("moveJ", "moveL", "setStandardDigitalOut") for c in robot.log)
    names = [c[0] for c in robot.log]
    assert "teachMode" in names and "endTeachMode" in names


def test_probe_refits_a_hidden_end_through_the_touch_then_grasps(real_like, monkeypatch, capsys):
    """--execute --probe on a "hidden" estimate whose end is some 7 mm off (the views left
    its depth open): the operator's touch on the tape's end confirms no hypothesis, but lies
    a few mm from the one there is; the shape is refitted through the touch, still explains
    the views, and is grasped."""
    import dataclasses

    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    import tapecell.estimator as estimator
    from tapecell.estimator import Verdict, forward_kinematics

    images, cameras = real_like
    real_estimate = estimator.estimate

    def hidden_and_off(capture, *a, **k):
        est = real_estimate(capture, *a, **k)
        angles = est.angles.copy()
        angles[-1, 1] += 0.25                    # the last plate bent: its end ~7 mm off
        shape = forward_kinematics(capture.tape, angles)
        return dataclasses.replace(est, angles=angles, nodes=shape.nodes, tip_position=shape.nodes[-1],
                                   tip_rotation=shape.frames[-1], verdict=Verdict.HIDDEN, alternatives=(),
                                   verdict_reason="1 camera(s) see the free end, 2 needed")
    monkeypatch.setattr(estimator, "estimate", hidden_and_off)
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.cli.commands.run import grab_capture
    from tapecell.estimator.capture import load_cameras

    capture = grab_capture(load_cell_config(), load_cameras(cameras), images)
    true_tip, off_tip = real_estimate(capture).tip_position, hidden_and_off(capture).tip_position
    assert 0.005 < np.linalg.norm(off_tip - true_tip) < 0.010
    _guide_needle_to(robot, true_tip, monkeypatch, _behind(real_estimate(capture)))
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "refitted through the needle's touch on the tape's end" in out and "grasp executed" in out
    names = [c[0] for c in robot.log]
    assert names.index("endTeachMode") < names.index("moveJ")


def test_without_probe_an_ambiguous_estimate_says_how_to_settle_it(real_like, monkeypatch, no_robot, capsys):
    images, cameras = real_like
    _ambiguous_with_alternative(monkeypatch, [0.0, 0.0, 0.02])
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--yes"])
    out, err = capsys.readouterr()
    assert code == 1 and "nothing moved (--execute --probe settles it with the needle" in err


def _poor_fit_past_the_end(monkeypatch):
    """The real estimate, forced "poor_fit" for tape past the model's end, no alternatives."""
    import dataclasses

    import tapecell.estimator as estimator
    from tapecell.estimator.result import Verdict
    from tapecell.estimator.verdict import PAST_END

    real_estimate = estimator.estimate

    def poor(*a, **k):
        return dataclasses.replace(real_estimate(*a, **k), verdict=Verdict.POOR_FIT, alternatives=(),
                                   verdict_reason=f"view 1 {PAST_END} over 40 px (> 30 px)")
    monkeypatch.setattr(estimator, "estimate", poor)
    return real_estimate


@pytest.mark.parametrize("along_mm, side_mm, measured", [(10.0, 1.0, True), (10.0, 8.0, False), (40.0, 0.0, False)])
def test_probe_measures_the_end_of_a_fit_that_shows_tape_past_it(real_like, monkeypatch, capsys,
                                                                  along_mm, side_mm, measured):
    """--execute --probe on a poor_fit whose views show tape past the model's end: the
    operator puts the needle on the tape's end; on the estimated end's line (within 4 mm,
    up to 25 mm past the tip) the tip moves there and the grasp is planned and run;
    elsewhere nothing moves (freedrive only)."""
    import numpy as np
    from fakes import FakeRobot, install_fake_rtde

    images, cameras = real_like
    real_estimate = _poor_fit_past_the_end(monkeypatch)
    robot = FakeRobot(np.array(load_cell_config().arm.park_joints))
    install_fake_rtde(monkeypatch, robot, probe=False)
    from tapecell.cli.commands.run import grab_capture
    from tapecell.estimator.capture import load_cameras

    est = real_estimate(grab_capture(load_cell_config(), load_cameras(cameras), images))
    trunk, side = est.tip_rotation[:, 0], est.tip_rotation[:, 2]
    end = est.tip_position + 1e-3 * (along_mm * trunk + side_mm * side)
    _guide_needle_to(robot, end, monkeypatch, end - 0.012 * trunk)
    code = main(["run", "--config", str(default_cell_path()), "--cameras", str(cameras), "--images", str(images),
                 "--execute", "--probe", "--yes"])
    out, err = capsys.readouterr()
    names = [c[0] for c in robot.log]
    assert "teachMode" in names and "endTeachMode" in names
    if measured:
        assert code == 0, err
        assert f"the tape's end measured by the needle: {along_mm:.1f} mm past the model's end" in out
        assert "grasp executed" in out and names.index("endTeachMode") < names.index("moveJ")
    else:
        assert code == 1 and "is not on the estimated end's line" in err.strip().splitlines()[-1]
        assert not any(c[0] in ("moveJ", "moveL", "setStandardDigitalOut") for c in robot.log)


def test_measured_end_lies_on_the_estimated_ends_line():
    """cell.probe.measured_end: a touch on the trunk's line moves the end along it (never
    back), within 4 mm of the line and from 4 mm before the tip to 25 mm past it."""
    import numpy as np

    from tapecell.cell.probe import measured_end

    tip, trunk = np.array([0.1, 0.5, 0.1]), np.array([0.0, 0.0, -1.0])
    assert np.allclose(measured_end(tip, trunk, tip + [0.0, 0.003, -0.012]), tip + [0.0, 0.0, -0.012])
    assert np.allclose(measured_end(tip, trunk, tip + [0.0, 0.0, 0.003]), tip)        # behind: kept
    assert measured_end(tip, trunk, tip + [0.0, 0.005, -0.012]) is None              # beside the line
    assert measured_end(tip, trunk, tip + [0.0, 0.0, -0.030]) is None                # too far past
    assert measured_end(tip, trunk, tip + [0.0, 0.0, 0.005]) is None                 # too far behind
