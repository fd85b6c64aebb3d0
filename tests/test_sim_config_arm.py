"""The cell file's checks, the UR5e's kinematics and the simulated arm, and the sim CLI."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.cli.main import main
from tapecell.cell.config import CellConfigError, default_cell_path, load_cell_config
from tapecell.cell.kinematics import fk as dh_fk
from tapecell.sim.ur5e import IKError, ik

TEXT = default_cell_path().read_text()


def _write(tmp_path, text):
    p = tmp_path / "cell.toml"
    p.write_text(text)
    return p


def test_bundled_cell_file_loads():
    cfg = load_cell_config()
    assert cfg.tape.plates == 30 and cfg.tape.estimator_plates == 5
    assert len(cfg.cameras.camera) == 3
    assert cfg.cameras.fovy_deg == pytest.approx(19.86, abs=0.01)
    np.testing.assert_allclose(cfg.tools.flange_from_tcp("needle")[:3, 3], [0, 0, 0.12])


def test_unknown_key_is_named(tmp_path):
    p = _write(tmp_path, TEXT.replace("[tools.needle]\n", "[tools.needle]\nlenght = 0.1\n"))
    with pytest.raises(CellConfigError, match=r"cell.toml: unknown key 'tools.needle.lenght'"):
        load_cell_config(p)


def test_unknown_section_is_named(tmp_path):
    with pytest.raises(CellConfigError, match=r"unknown key 'gripperz'"):
        load_cell_config(_write(tmp_path, TEXT + "\n[gripperz]\nx = 1\n"))


def test_missing_tool_offset_is_named(tmp_path):
    text = TEXT.replace("flange_from_tcp = [0.0, 0.0, 0.12, 0.0, 0.0, 0.0]\n", "")
    with pytest.raises(CellConfigError, match=r"missing key 'tools.needle.flange_from_tcp'"):
        load_cell_config(_write(tmp_path, text))


def test_camera_that_does_not_see_the_tape(tmp_path):
    text = TEXT.replace("target = [0.0, 0.50, 0.175]", "target = [0.0, 0.0, 0.175]", 1)
    with pytest.raises(CellConfigError, match=r"camera 'cam0' does not see the tape"):
        load_cell_config(_write(tmp_path, text))


def test_wrong_type_and_bad_toml(tmp_path):
    with pytest.raises(CellConfigError, match=r"'tape.plates' must be an integer"):
        load_cell_config(_write(tmp_path, TEXT.replace("plates = 30 ", 'plates = "30" ')))
    with pytest.raises(CellConfigError, match="not valid TOML"):
        load_cell_config(_write(tmp_path, TEXT + "\n[[["))
    with pytest.raises(CellConfigError, match="not found"):
        load_cell_config(tmp_path / "nope.toml")


def test_camera_devices_are_indices_or_urls(tmp_path):
    devices = 'camera_devices = [0, "rtsp://192.168.1.20/stream1", "/dev/video4"]'
    cfg = load_cell_config(_write(tmp_path, TEXT.replace("camera_devices = [0, 1, 2]", devices)))
    assert cfg.robot.camera_devices == (0, "rtsp://192.168.1.20/stream1", "/dev/video4")
    assert load_cell_config().robot.camera_devices == (0, 1, 2)
    with pytest.raises(CellConfigError, match=r"'robot.camera_devices\[1\]' must be an integer or a string"):
        load_cell_config(_write(tmp_path, TEXT.replace("camera_devices = [0, 1, 2]", "camera_devices = [0, 1.5]")))


def test_home_is_inside_the_limits_with_every_tool():
    from tapecell.cell.fake_arm import FakeArm
    from tapecell.cell.planner import REFERENCE_JOINTS
    from tapecell.cell.safety import SafeArm, SafetyLimits

    cfg = load_cell_config()
    limits = SafetyLimits.from_config(cfg.limits)
    for tool in ("plate", "needle", "gripper"):
        fake = FakeArm(q0=REFERENCE_JOINTS)
        with SafeArm(fake, limits, getattr(cfg.tools, tool).flange_from_tcp) as arm:
            arm.move_joints(cfg.arm.home_joints, 0.5, 1.0)
            np.testing.assert_allclose(arm.joints(), cfg.arm.home_joints)


def test_grasp_lift_mode_and_joint_accel_reach_the_planner_and_limits(tmp_path):
    from tapecell.cell.planner import GraspParams
    from tapecell.cell.safety import SafetyLimits

    text = TEXT.replace('lift_mode = "arc"', 'lift_mode = "peel"').replace("max_joint_accel = 1.4 ", "max_joint_accel = 1.1 ")
    cfg = load_cell_config(_write(tmp_path, text))
    assert GraspParams.from_config(cfg.grasp).lift_mode == "peel"
    assert SafetyLimits.from_config(cfg.limits).max_joint_accel == 1.1
    with pytest.raises(CellConfigError, match=r"'grasp.lift_mode' must be \"arc\" or \"peel\""):
        load_cell_config(_write(tmp_path, TEXT.replace('lift_mode = "arc"', 'lift_mode = "yank"')))


def test_cli_bad_cell_file_is_one_line(tmp_path, capsys):
    p = _write(tmp_path, TEXT.replace("[arm]\n", "[arm]\nspeed = 1\n"))
    assert main(["sim", "cameras", "--config", str(p), "--out", str(tmp_path / "c.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key 'arm.speed'" in err[0]
    assert not (tmp_path / "c.json").exists()


def test_mujoco_arm_matches_dh_at_random_joints():
    from mujoco_arm import MujocoArm

    arm = MujocoArm()
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.uniform(-np.pi, np.pi, 6)
        T = dh_fk(q)
        F = arm.flange(q)
        np.testing.assert_allclose(F[:3, 3], T[:3, 3], atol=1e-12)
        np.testing.assert_allclose(F[:3, :3], T[:3, :3], atol=1e-12)


def test_dh_zero_pose_is_the_published_one():
    # UR5e at zero joints: flange at x = a2 + a3, y = -(d4 + d6), z = d1 - d5.
    np.testing.assert_allclose(dh_fk(np.zeros(6))[:3, 3], [-0.8172, -0.2329, 0.0628], atol=1e-12)


def test_ik_round_trip_and_unreachable():
    rng = np.random.default_rng(2)
    for _ in range(5):
        q = rng.uniform(-2, 2, 6)
        T = dh_fk(q)
        sol = ik(T, q + rng.uniform(-0.2, 0.2, 6)).q
        np.testing.assert_allclose(dh_fk(sol), T, atol=1e-5)
    far = np.eye(4)
    far[:3, 3] = [1.5, 0.0, 0.3]
    with pytest.raises(IKError, match="unreachable"):
        ik(far, np.zeros(6), restarts=2)


@pytest.fixture(scope="module")
def arm():
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell

    with SimCell(load_cell_config(), 0, n_cameras=2) as cell:
        yield SimArm(cell)


def test_arm_moves_and_reports_tcp(arm):
    q = np.array([1.4, -1.4, 1.6, -1.8, -1.5708, 0.1])
    arm.move_joints(q)
    np.testing.assert_allclose(arm.joints(), q, atol=arm.cell.config.arm.joint_tolerance)
    np.testing.assert_allclose(arm.tcp_pose(), arm.fk(arm.joints()), atol=1e-9)
    target = arm.tcp_pose().copy()
    target[:3, 3] += [0.03, -0.02, 0.04]
    arm.move_tcp(target, speed=0.2)
    assert np.linalg.norm(arm.tcp_pose()[:3, 3] - target[:3, 3]) < 2e-4
    np.testing.assert_allclose(arm.tcp_pose()[:3, :3], target[:3, :3], atol=1e-3)
    for tool in ("flange", "plate", "needle", "gripper"):
        off = arm.cell.config.tools.flange_from_tcp(tool)
        np.testing.assert_allclose(arm.tcp_pose(tool), arm.tcp_pose("flange") @ off, atol=1e-12)


def test_gripper_pinches_and_lifts_the_tape(arm):
    cell = arm.cell
    cell.reset(0)
    arm.select_tool("gripper")
    arm.open_gripper()
    tip = cell.tape_tip_frame()
    F = tip[:3, :3]
    grasp = np.eye(4)   # pads close along the tape normal, approaching back along the tape
    z, y = -F[:, 0], F[:, 2]
    grasp[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    grasp[:3, 3] = tip[:3, 3] - 0.008 * F[:, 0]
    pre = grasp.copy()
    pre[:3, 3] -= 0.04 * z
    arm.move_tcp(pre, speed=0.25)
    arm.move_tcp(grasp, speed=0.05)
    opening = arm.close_gripper()
    assert opening < 0.002
    contacts = cell.gripper_pad_contacts_with_tape()
    assert contacts["left"] > 0 and contacts["right"] > 0
    lift = grasp.copy()
    lift[2, 3] += 0.02
    before = cell.tape_tip_position()
    arm.move_tcp(lift, speed=0.05)
    assert cell.tape_tip_position()[2] - before[2] > 0.015   # the tip came along
    arm.open_gripper()
    arm.park()


def test_cli_capture_and_cameras(tmp_path, capsys):
    from tapecell.estimator.capture import load_cameras, load_capture

    assert main(["sim", "capture", "--seed", "4", "--cameras", "3", "--rgb", "--out", str(tmp_path / "cap")]) == 0
    cap = load_capture(tmp_path / "cap")
    assert len(cap.views) == 3 and cap.truth is not None
    assert (tmp_path / "cap" / "cam2_rgb.png").exists()
    assert main(["sim", "cameras", "--out", str(tmp_path / "cams.json")]) == 0
    cams = load_cameras(tmp_path / "cams.json")
    np.testing.assert_allclose(cams[0].K, cap.views[0].camera.K)
    assert main(["sim", "snapshot", "--seed", "1", "--out", str(tmp_path / "snap")]) == 0
    assert {p.name for p in (tmp_path / "snap").iterdir()} == {"cam0.png", "cam1.png", "overview.png"}
