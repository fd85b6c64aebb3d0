"""URArm against fake ur_rtde modules: the exact calls sent, and the connection guards."""
from __future__ import annotations

import socket
import struct
import sys
import threading
import time

import numpy as np
import pytest

from tapecell.cell.arm import ArmError, ArmNotConnectedError, ProtectiveStopError
from tapecell.cell.kinematics import fk
from tapecell.cell.poses import matrix_to_pose6
from tapecell.cell.safety import SafetyError, SafetyLimits
from tapecell.cell.config import GripperIOSection
from tapecell.cell.ur import ArmConfigError, KinematicsMismatch, URArm, probe_rtde
from fakes import FakeRobot, install_fake_rtde

Q_START = np.array([-1.5708, -1.9, 2.2, -1.87, -1.5708, 0.0])   # flange near (-0.13, 0.34, 0.35)
LIMITS = SafetyLimits(workspace_min=[-0.30, 0.10, 0.05], workspace_max=[0.60, 0.90, 0.70],
                      max_tcp_speed=0.25, max_tcp_accel=1.2, max_joint_speed=1.0,
                      keepout_min=[-0.07, 0.44, 0.0], keepout_max=[0.07, 0.56, 0.095])


# ---------------------------------------------------------------- a fake RTDE server
class RTDEServer:
    """Accepts connections on 127.0.0.1; answers the protocol-version request if ``answer``."""

    def __init__(self, answer: bool) -> None:
        self.answer = answer
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []
        self.stopping = False
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.1)
        while not self.stopping:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.conns.append(conn)
            if self.answer:
                conn.settimeout(1.0)
                request = conn.recv(5)
                size, kind, version = struct.unpack(">HBH", request)
                assert (size, kind, version) == (5, 86, 2)
                conn.sendall(struct.pack(">HBB", 4, 86, 1))

    def close(self) -> None:
        self.stopping = True
        self.thread.join(2)
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.fixture
def rtde_server():
    server = RTDEServer(answer=True)
    yield server
    server.close()


@pytest.fixture
def silent_server():
    server = RTDEServer(answer=False)
    yield server
    server.close()


# ---------------------------------------------------------------- fake ur_rtde modules
@pytest.fixture
def robot(monkeypatch):
    r = FakeRobot(Q_START)
    install_fake_rtde(monkeypatch, r)
    return r


def make_arm(port: int, **kw) -> URArm:
    kw.setdefault("gripper", GripperIOSection(close_wait_s=0.0, open_wait_s=0.0))
    kw.setdefault("retry_delay_s", 0.0)
    return URArm("127.0.0.1", port, LIMITS, **kw)


def motion_calls(robot: FakeRobot) -> list[tuple]:
    keep = {"servoStop", "speedStop", "moveL", "moveJ", "stopL", "stopJ", "isPoseWithinSafetyLimits",
            "isJointsWithinSafetyLimits"}
    return [c for c in robot.log if c[0] in keep]


# ---------------------------------------------------------------- probe
def test_probe_silent_host_fails_quickly_with_host_and_port(silent_server):
    t0 = time.monotonic()
    with pytest.raises(ArmError) as e:
        probe_rtde("127.0.0.1", silent_server.port, timeout=0.3)
    assert time.monotonic() - t0 < 2.0
    msg = str(e.value)
    assert f"127.0.0.1:{silent_server.port}" in msg and "did not answer" in msg


def test_probe_closed_port_is_a_clear_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(ArmError, match=f"127.0.0.1:{port} refused"):
        probe_rtde("127.0.0.1", port, timeout=0.5)


def test_probe_accepts_an_rtde_answer(rtde_server):
    probe_rtde("127.0.0.1", rtde_server.port, timeout=1.0)


def test_connect_to_silent_host_never_constructs(robot, silent_server):
    arm = make_arm(silent_server.port, probe_timeout_s=0.2, connect_attempts=2)
    t0 = time.monotonic()
    with pytest.raises(ArmError, match=f"127.0.0.1:{silent_server.port}.*2 attempt"):
        arm.connect()
    assert time.monotonic() - t0 < 3.0
    assert not any(c[0] == "RTDEControlInterface" for c in robot.log)
    assert not arm.is_connected


def test_connect_retries_a_bounded_number_of_times(robot, rtde_server):
    robot.construct_failures = 2
    arm = make_arm(rtde_server.port, connect_attempts=3)
    arm.connect()
    assert arm.is_connected
    assert ("setTcp", [0.0] * 6) in robot.log   # flange poses in and out
    arm.disconnect()

    robot.construct_failures = 5
    with pytest.raises(ArmError, match="after 3 attempt"):
        make_arm(rtde_server.port, connect_attempts=3).connect()


def test_commands_need_a_connection(robot):
    arm = make_arm(1)
    with pytest.raises(ArmNotConnectedError):
        arm.move_linear([0.1, 0.3, 0.3, 0, 3.14, 0], 0.1, 0.5)
    assert robot.log == []


# ---------------------------------------------------------------- motions: exact calls
def test_move_linear_sends_exact_pose_after_servo_and_speed_stop(robot, rtde_server):
    start = matrix_to_pose6(fk(Q_START))
    target = start + np.array([0.05, 0.02, -0.03, 0.0, 0.0, 0.0])
    with make_arm(rtde_server.port) as arm:
        arm.move_linear(target, 0.1, 0.5)
    calls = motion_calls(robot)
    assert [c[0] for c in calls] == ["isPoseWithinSafetyLimits", "servoStop", "speedStop", "moveL"]
    name, pose, speed, acc = calls[-1]
    assert isinstance(pose, list) and len(pose) == 6 and all(type(v) is float for v in pose)
    np.testing.assert_allclose(pose, target, atol=1e-12)   # [x, y, z, rx, ry, rz], base frame
    assert (speed, acc) == (0.1, 0.5)
    assert speed <= LIMITS.max_tcp_speed and acc <= LIMITS.max_tcp_accel
    assert robot.log[-3:] == [("control.disconnect",), ("receive.disconnect",), ("io.disconnect",)]


def test_move_linear_path_is_one_blended_move_l_after_every_pose_is_checked(robot, rtde_server):
    start = matrix_to_pose6(fk(Q_START))
    path = [start + np.array([0.0, 0.0, 0.01 * k, 0.0, 0.0, 0.0]) for k in (1, 2, 3)]
    with make_arm(rtde_server.port) as arm:
        with pytest.raises(SafetyError, match="blend"):
            arm.move_linear_path(path, 0.05, 0.8, 0.006)       # overlapping blends: nothing sent
        assert motion_calls(robot) == []
        arm.move_linear_path(path, 0.05, 0.8, 0.002)
    calls = motion_calls(robot)
    assert [c[0] for c in calls] == ["isPoseWithinSafetyLimits"] * 3 + ["servoStop", "speedStop", "moveL"]
    for call, pose in zip(calls, path):
        np.testing.assert_allclose(call[1], pose, atol=1e-12)
    # ur_rtde's moveL(path): rows [x, y, z, rx, ry, rz, speed, acceleration, blend], the last unblended.
    (_, rows) = calls[-1]
    assert [r[6:] for r in rows] == [[0.05, 0.8, 0.002], [0.05, 0.8, 0.002], [0.05, 0.8, 0.0]]
    np.testing.assert_allclose([r[:6] for r in rows], path, atol=1e-12)
    # The controller's inverse kinematics of every pose was checked before the move.
    iks = [c[1] for c in robot.log if c[0] == "getInverseKinematics"]
    np.testing.assert_allclose(iks[-3:], path, atol=1e-12)


def test_a_failed_path_is_stopped(robot, rtde_server):
    robot.move_raises = RuntimeError("fake: RTDE link dropped mid-move")
    start = matrix_to_pose6(fk(Q_START))
    path = [start + np.array([0.0, 0.0, 0.01 * k, 0.0, 0.0, 0.0]) for k in (1, 2)]
    arm = make_arm(rtde_server.port, stop_deceleration=3.0)
    arm.connect()
    with pytest.raises(ArmError, match="moveL path of 2 poses to .* failed: fake: RTDE link dropped"):
        arm.move_linear_path(path, 0.05, 0.8, 0.002)
    assert robot.log[-1] == ("stopL", 3.0)


def test_a_path_the_controller_refuses_or_fails_sends_nothing_or_is_stopped(robot, rtde_server):
    start = matrix_to_pose6(fk(Q_START))
    path = [start + np.array([0.0, 0.0, 0.01 * k, 0.0, 0.0, 0.0]) for k in (1, 2, 3)]
    arm = make_arm(rtde_server.port)
    arm.connect()
    robot.pose_ok = False                  # isPoseWithinSafetyLimits says no: nothing moves
    with pytest.raises(SafetyError, match="outside its safety limits"):
        arm.move_linear_path(path, 0.05, 0.8, 0.002)
    assert not any(c[0] == "moveL" for c in robot.log)
    robot.pose_ok, robot.move_result = True, False     # the controller aborts the path
    with pytest.raises(ArmError, match="moveL path of 3 poses .* failed"):
        arm.move_linear_path(path, 0.05, 0.8, 0.002)
    assert robot.log[-2][0] == "stopL" or robot.log[-1][0] == "stopL"


def test_move_joints_exact_call(robot, rtde_server):
    q = Q_START + np.array([0.1, -0.05, 0.05, 0.0, 0.0, 0.2])
    with make_arm(rtde_server.port) as arm:
        arm.move_joints(q, 0.5, 1.0)
    calls = motion_calls(robot)
    assert [c[0] for c in calls] == ["isJointsWithinSafetyLimits", "servoStop", "speedStop", "moveJ"]
    np.testing.assert_allclose(calls[-1][1], q)
    assert calls[-1][2:] == (0.5, 1.0)


def test_stop_l_in_finally_when_move_raises(robot, rtde_server):
    robot.move_raises = RuntimeError("fake: RTDE link dropped mid-move")
    target = matrix_to_pose6(fk(Q_START)) + np.array([0.0, 0.0, 0.02, 0, 0, 0])
    arm = make_arm(rtde_server.port, stop_deceleration=3.0)
    arm.connect()
    with pytest.raises(ArmError, match="moveL to .* failed: fake: RTDE link dropped mid-move") as e:
        arm.move_linear(target, 0.1, 0.5)
    assert e.value.exit_code == 3
    assert [c[0] for c in motion_calls(robot)][-2:] == ["moveL", "stopL"]
    assert robot.log[-1] == ("stopL", 3.0)


def test_failed_move_stops_and_reports_protective_stop(robot, rtde_server):
    target = matrix_to_pose6(fk(Q_START)) + np.array([0.0, 0.0, 0.02, 0, 0, 0])
    arm = make_arm(rtde_server.port)
    arm.connect()
    robot.move_result = False
    with pytest.raises(ArmError, match="failed"):
        arm.move_linear(target, 0.1, 0.5)
    assert robot.log[-1][0] == "stopL"
    robot.protective = True
    with pytest.raises(ProtectiveStopError):
        arm.move_linear(target, 0.1, 0.5)
    assert [c[0] for c in robot.log].count("moveL") == 1   # refused before sending
    assert arm.is_protective_stopped()


def test_exception_in_with_block_stops_then_disconnects(robot, rtde_server):
    with pytest.raises(ValueError):
        with make_arm(rtde_server.port):
            raise ValueError("caller failed")
    names = [c[0] for c in robot.log]
    assert names[-4:] == ["stopL", "control.disconnect", "receive.disconnect", "io.disconnect"]


# ---------------------------------------------------------------- safety: nothing moves
@pytest.mark.parametrize("target_delta, speed, acc, why", [
    ([0.0, 0.0, 0.02, 0, 0, 0], 0.5, 0.5, "speed"),
    ([0.0, 0.0, 0.02, 0, 0, 0], 0.1, 5.0, "acceleration"),
    ([0.0, 0.0, 0.50, 0, 0, 0], 0.1, 0.5, "workspace"),
])
def test_limit_violations_send_nothing(robot, rtde_server, target_delta, speed, acc, why):
    target = matrix_to_pose6(fk(Q_START)) + np.array(target_delta)
    with make_arm(rtde_server.port) as arm:
        with pytest.raises(SafetyError, match=why):
            arm.move_linear(target, speed, acc)
    assert motion_calls(robot) == []


def test_keepout_target_sends_nothing(robot, rtde_server):
    # A flange target inside the box around the part.
    down = [np.pi, 0.0, 0.0]
    with make_arm(rtde_server.port) as arm:
        robot.q = Q_START
        start = arm.tcp_pose()
        with pytest.raises(SafetyError, match="keep-out"):
            arm.move_linear([0.0, 0.50, 0.06, *down], 0.1, 0.5)
    assert start[2] > 0.095 and motion_calls(robot) == []


def test_controller_safety_refusal_sends_nothing(robot, rtde_server):
    robot.pose_ok = False
    target = matrix_to_pose6(fk(Q_START)) + np.array([0.0, 0.0, 0.02, 0, 0, 0])
    with make_arm(rtde_server.port) as arm:
        with pytest.raises(SafetyError, match="controller"):
            arm.move_linear(target, 0.1, 0.5)
    assert [c[0] for c in motion_calls(robot)] == ["isPoseWithinSafetyLimits"]


# ---------------------------------------------------------------- gripper, freedrive, reconnect
def test_gripper_through_configured_digital_output(robot, rtde_server):
    waits = []
    g = GripperIOSection(close_output=3, active_high=False, close_wait_s=0.4, open_wait_s=0.3)
    with make_arm(rtde_server.port, gripper=g, sleep=waits.append) as arm:
        arm.close_gripper()
        arm.open_gripper()
    io = [c for c in robot.log if c[0] == "setStandardDigitalOut"]
    assert io == [("setStandardDigitalOut", 3, False), ("setStandardDigitalOut", 3, True)]
    assert waits == [0.4, 0.3]
    with pytest.raises(ArmConfigError, match="does not exist"):
        make_arm(rtde_server.port, gripper=GripperIOSection(output_kind="tool", close_output=2))


def test_gripper_with_two_outputs_and_a_confirming_input(robot, rtde_server):
    g = GripperIOSection(close_output=0, open_output=1, close_wait_s=0.0, open_wait_s=0.0, closed_input=5,
                         closed_input_timeout_s=0.2)
    robot.close_sets_input = 5       # the jaws' sensor follows output 0
    with make_arm(rtde_server.port, gripper=g) as arm:
        arm.close_gripper()
        arm.open_gripper()
    calls = [c for c in robot.log if c[0] in ("setStandardDigitalOut", "getDigitalInState")]
    assert calls == [("setStandardDigitalOut", 1, False), ("setStandardDigitalOut", 0, True),
                     ("getDigitalInState", 5),
                     ("setStandardDigitalOut", 0, False), ("setStandardDigitalOut", 1, True),
                     ("getDigitalInState", 5)]
    robot.close_sets_input = None    # the sensor never reports closed: a jammed gripper
    robot.digital_in[5] = False
    with make_arm(rtde_server.port, gripper=g) as arm:
        with pytest.raises(ArmError, match="did not confirm it closed.*input 5") as e:
            arm.close_gripper()
    assert e.value.exit_code == 3


def test_freedrive_uses_teach_mode(robot, rtde_server):
    with make_arm(rtde_server.port) as arm:
        arm.freedrive(True)
        arm.freedrive(False)
    names = [c[0] for c in robot.log]
    assert names.index("teachMode") < names.index("endTeachMode")


def test_dropped_link_is_reconnected_boundedly(robot, rtde_server):
    with make_arm(rtde_server.port) as arm:
        robot.connected = False
        arm.tcp_pose()
        assert ("control.reconnect",) in robot.log

        class Dead:
            def reconnect(self):
                robot.log.append(("dead.reconnect",))
                return False
        robot.connected = False
        sys.modules["rtde_control"].RTDEControlInterface.reconnect = lambda self: Dead().reconnect()
        with pytest.raises(ArmError, match="3 reconnection attempt"):
            arm.joints()
        assert [c[0] for c in robot.log].count("dead.reconnect") == 3


# ---------------------------------------------------------------- kinematics vs the controller's
def test_kinematics_are_checked_against_the_controllers_before_each_move(robot, rtde_server):
    q_target = Q_START + np.array([0.1, -0.05, 0.05, 0.0, 0.0, 0.2])
    with make_arm(rtde_server.port) as arm:
        connect_calls = [c for c in robot.log if c[0] == "getForwardKinematics"]
        assert connect_calls == [("getForwardKinematics", Q_START.tolist(), [0.0] * 6)]   # on connecting
        arm.move_joints(q_target, 0.5, 1.0)
        target = matrix_to_pose6(fk(q_target)) + np.array([0.0, 0.0, 0.02, 0, 0, 0])
        arm.move_linear(target, 0.1, 0.5)
    names = [c[0] for c in robot.log]
    j, l = names.index("moveJ"), names.index("moveL")
    second_fk = [i for i, n in enumerate(names) if n == "getForwardKinematics"][1]
    assert robot.log[second_fk] == ("getForwardKinematics", q_target.tolist(), [0.0] * 6)
    assert second_fk < names.index("isJointsWithinSafetyLimits") < j
    ik_call = robot.log[names.index("getInverseKinematics")]
    assert np.allclose(ik_call[1], target) and np.allclose(ik_call[2], q_target)   # near where the arm is
    assert j < names.index("getInverseKinematics") < names.index("isPoseWithinSafetyLimits") < l


def test_a_calibration_within_tolerance_is_accepted_and_beyond_it_refused(robot, rtde_server):
    robot.calibration[:3, 3] = [0.002, 0.0015, -0.001]          # a real UR's 2-3 mm
    with make_arm(rtde_server.port) as arm:
        q = arm.ik(fk(Q_START), Q_START)
        assert np.allclose(robot.world_from_flange(q), fk(Q_START), atol=1e-9)   # the controller's joints
    robot.calibration[:3, 3] = [0.0, 0.012, 0.0]
    log_len = len(robot.log)
    with pytest.raises(KinematicsMismatch, match="12.0 mm") as e:
        make_arm(rtde_server.port).connect()
    assert e.value.exit_code == 3
    assert robot.log[-3:] == [("control.disconnect",), ("receive.disconnect",), ("io.disconnect",)]
    assert not any(c[0] in ("moveJ", "moveL") for c in robot.log[log_len:])
