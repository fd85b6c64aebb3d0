"""Calibration: DLT + refinement on synthetic points, pose planning, the calibrate command
on the simulated cell against the true cameras, bad input, and the real-cell path."""
import dataclasses

import numpy as np
import pytest

from tapecell.cell.calibration import (CalibrationError, calibrate_camera, camera_errors, decompose_projection,
                              dlt_projection, plan_poses, solve_all)
from tapecell.cli.main import main
from tapecell.cell.cross import CrossDetection
from tapecell.estimator.capture import load_cameras
from tapecell.estimator.geometry import Camera, rot_x, rot_z
from fakes import FakeRobot, install_fake_rtde
from tapecell.cell.config import CellConfigError, load_cell_config

K = np.array([[1371.0, 0, 319.5], [0, 1371.0, 239.5], [0, 0, 1]])


def _true_camera(dist=(0, 0, 0, 0, 0)):
    R = rot_x(np.radians(-95)) @ rot_z(np.radians(70))
    centre = np.array([0.55, 0.3, 0.2])
    return Camera("cam0", 640, 480, K, np.array(dist, float), R, -R @ centre)


def _grid(n=4):
    ax = [np.linspace(-0.06, 0.06, n), np.linspace(0.44, 0.56, n), np.linspace(0.12, 0.24, n)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


def test_dlt_exact_without_noise():
    cam = _true_camera()
    X = _grid(3)
    Kd, R, t = decompose_projection(dlt_projection(X, cam.project(X)))
    assert np.allclose(Kd, K, atol=1e-4 * 1371)
    assert np.allclose(R, cam.R, atol=1e-7) and np.allclose(t, cam.t, atol=1e-7)


def test_refinement_recovers_distortion_without_noise():
    cam = _true_camera((-0.08, 0.0, 0, 0, 0))
    X = _grid(4)
    fit = calibrate_camera("cam0", (640, 480), X, cam.project(X), "k1")
    e = camera_errors(fit.camera, cam)
    assert fit.camera.rms_px < 1e-3
    assert e["focal_pct"] < 1e-3 and e["principal_px"] < 1e-2 and e["rotation_deg"] < 1e-4
    assert abs(fit.camera.dist[0] + 0.08) < 1e-4


def test_refinement_with_noise_and_outliers():
    cam = _true_camera()
    X = _grid(5)
    rng = np.random.default_rng(0)
    x = cam.project(X) + rng.normal(0, 0.03, (len(X), 2))
    x[[5, 40]] += [3.0, -2.0]                   # two mis-detections
    fit = calibrate_camera("cam0", (640, 480), X, x, "k1k2")
    assert set(np.flatnonzero(~fit.inliers)) == {5, 40}
    e = camera_errors(fit.camera, cam)
    assert 0.02 < fit.camera.rms_px < 0.05
    assert e["focal_pct"] < 0.2 and e["principal_px"] < 2.0 and e["centre_m"] < 1e-3 and e["rotation_deg"] < 0.1
    # Without outlier removal the two bad points would drag the residual up.
    assert np.sqrt(np.mean(fit.residuals_px[fit.inliers] ** 2)) == pytest.approx(fit.camera.rms_px)


def test_coplanar_points_are_refused():
    cam = _true_camera()
    X = _grid(3)
    X[:, 0] = 0.0
    with pytest.raises(CalibrationError):
        dlt_projection(X, cam.project(X))


def test_plan_reaches_the_default_grid_and_faces_the_cameras():
    cell = load_cell_config()
    for n in (2, 3):
        poses = plan_poses(cell, n)
        assert len(poses) == int(np.prod(cell.calibration.grid_counts))
        assert all(max(p.view_deg.values()) <= 45.0 for p in poses)
        normals = np.array([p.world_from_tcp[:3, 2] for p in poses])
        assert np.ptp(normals, axis=0).max() > 0.2           # orientations vary


def test_unreachable_grid_is_an_error():
    cell = load_cell_config()
    far = dataclasses.replace(cell.calibration, grid_min=(1.2, 0.4, 0.1), grid_max=(1.3, 0.6, 0.2))
    with pytest.raises(CellConfigError, match="unreachable") as e:   # the cell file's grid: bad input
        plan_poses(dataclasses.replace(cell, calibration=far), 2)
    assert e.value.exit_code == 2


def _dets(pix, ok):
    return [CrossDetection(p, None) if good else CrossDetection(None, "missing") for p, good in zip(pix, ok)]


def test_too_few_poses_and_large_rms_are_errors():
    cell = load_cell_config()
    cam = _true_camera()
    X = _grid(3)
    pix = cam.project(X)
    ok = np.zeros(len(X), bool)
    ok[:cell.calibration.min_poses - 1] = True
    with pytest.raises(CalibrationError, match="min_poses"):
        solve_all(X, {"cam0": _dets(pix, ok)}, {"cam0": (640, 480)}, cell.calibration)
    noisy = pix + np.random.default_rng(1).normal(0, 0.8, pix.shape)
    with pytest.raises(CalibrationError, match="max_rms_px"):
        solve_all(X, {"cam0": _dets(noisy, np.ones(len(X), bool))}, {"cam0": (640, 480)}, cell.calibration)


# ------------------------------------------------------------------ the command, simulated
@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("calib")
    out, rrd = d / "cams.json", d / "cal.rrd"
    rc = main(["calibrate", "--sim", "--seed", "2", "--out", str(out), "--rrd", str(rrd)])
    return rc, out, rrd


def test_calibrate_command_meets_targets_against_true_cameras(sim_run):
    from tapecell.sim.cell import SimCell

    rc, out, _ = sim_run
    assert rc == 0
    cams = load_cameras(out)
    with SimCell(load_cell_config(), seed=2, n_cameras=2) as sim:
        truth = {c.name: c for c in sim.cameras()}
    assert [c.name for c in cams] == ["cam0", "cam1"]
    for c in cams:
        e = camera_errors(c, truth[c.name])
        assert e["focal_pct"] <= 0.2 and e["principal_px"] <= 1.0
        assert e["centre_m"] <= 1e-3 and e["rotation_deg"] <= 0.05
        assert c.rms_px is not None and c.rms_px <= 0.1


def test_calibrate_recording_reads_back(sim_run):
    from tapecell.cell.recording import read_recording

    _, _, rrd = sim_run
    rows = read_recording(rrd)
    assert any(k.startswith("calibration/images/cam0") for k in rows)
    assert "world/calibration/points" in rows
    assert any(k.startswith("calibration/residual_px/") for k in rows)
    assert "world/calibrated/cam1" in rows


def test_bad_cell_file_writes_nothing(tmp_path, capsys):
    src = load_cell_config().source
    text = open(src).read().replace("grid_min = [-0.08, 0.44, 0.13]", "grid_min = [1.20, 0.44, 0.13]") \
                           .replace("grid_max = [0.05, 0.56, 0.22]", "grid_max = [1.30, 0.56, 0.22]")
    bad = tmp_path / "cell.toml"
    bad.write_text(text)
    out = tmp_path / "cams.json"
    assert main(["calibrate", "--config", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tapecell: error:") and "unreachable" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


# --------------------------------------------------------------------- the real cell, mocked
@pytest.fixture
def fake_rtde(monkeypatch):
    robot = FakeRobot(load_cell_config().arm.home_joints)
    install_fake_rtde(monkeypatch, robot, probe=False)
    return robot.log


def test_real_calibrate_without_execute_only_plans(tmp_path, capsys, fake_rtde):
    out = tmp_path / "cams.json"
    cfg = load_cell_config().source
    assert main(["calibrate", "--config", cfg, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "nothing moved" in text and text.count("pose ") >= 36
    assert fake_rtde == [] and not out.exists()


@pytest.fixture
def fake_ur(monkeypatch):
    """Fake ur_rtde: a controller that goes where moveJ sends it, logging every call."""
    robot = FakeRobot(load_cell_config().arm.home_joints)
    install_fake_rtde(monkeypatch, robot, probe=False)
    return robot


def test_real_calibrate_execute_moves_exactly_the_plan(tmp_path, fake_ur, monkeypatch):
    """--execute with a faked controller and the pose images from a folder (rendered here
    at the planned poses, as a real camera would have taken them)."""
    import cv2
    from tapecell.cli.commands.calibrate import SimCameras
    from tapecell.sim.arm_adapter import SimArmAdapter
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell

    cell = load_cell_config()
    n_cams = min(len(cell.robot.camera_devices), len(cell.cameras.camera))
    poses = plan_poses(cell, n_cams)
    images = tmp_path / "images"
    with SimCell(cell, seed=0, n_cameras=n_cams, tool="plate") as sim:
        src, arm = SimCameras(sim), SimArmAdapter(SimArm(sim), teleport=True)
        arm.connect()
        for p in poses:
            arm.move_joints(p.joints, 0.5, 1.0)
            for name, img in src.grab(p.index).items():
                (images / f"{p.index:03d}").mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(images / f"{p.index:03d}" / f"{name}.png"), img[..., ::-1])
        truth = {c.name: c for c in sim.cameras()}
    out = tmp_path / "cams.json"
    argv = ["calibrate", "--config", cell.source, "--out", str(out), "--execute", "--images", str(images)]
    # No terminal, no --yes: refused before any connection.
    monkeypatch.setattr("sys.stdin.isatty", lambda: False)
    assert main(argv) == 2 and fake_ur.log == [] and not out.exists()
    # On a terminal: the confirmation comes before the first connection.
    monkeypatch.setattr("sys.stdin.isatty", lambda: True)
    asked = []
    monkeypatch.setattr("builtins.input", lambda prompt="": asked.append(len(fake_ur.log)) or "yes")
    rc = main(argv)
    assert rc == 0 and asked == [0]
    moves = [c for c in fake_ur.log if c[0] == "moveJ"]
    assert len(moves) == len(poses) + 1           # the approach to the first pose, then every pose
    for call, p in zip(moves[1:], poses):
        assert np.allclose(call[1], p.joints) and call[2:] == (0.3, 0.5)
    assert ("setTcp", [0.0] * 6) in fake_ur.log
    for c in load_cameras(out):
        e = camera_errors(c, truth[c.name])
        assert e["centre_m"] < 1e-3 and e["rotation_deg"] < 0.05
