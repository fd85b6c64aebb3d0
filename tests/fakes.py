"""Fake ur_rtde modules shared by the tests of the real-cell paths (driver, calibrate,
probe): one controller whose state and call log the tests inspect.

    robot = FakeRobot(q_start)
    install_fake_rtde(monkeypatch, robot)                 # URArm still probes the RTDE port
    install_fake_rtde(monkeypatch, robot, probe=False)    # ... or skip that socket check

The fakes live in this process, so URArm talks to them through a ThreadLink (the real
driver's ProcessLink would import the real ur_rtde in its child).

The controller's kinematics are the nominal UR5e model composed with ``robot.calibration``
(a flange-frame 4x4, identity by default): a real UR's calibrated kinematics put the tool
a few mm from the nominal model. ``getActualTCPPose``, ``getForwardKinematics`` and
``getInverseKinematics`` all use it, as a real controller does.
"""
from __future__ import annotations

import sys
import threading
import types

import numpy as np

from tapecell.cell.kinematics import fk, ik_nearest
from tapecell.cell.poses import invert, matrix_to_pose6, pose6_to_matrix


class FakeRobot:
    """Shared state of the fake controller and a log of every call across the interfaces.

    q (6,) [rad]: the joints, which a successful moveJ updates; ``log_reads`` also logs
    ``getActualTCPPose`` calls (for tests that check when the pose was read)."""

    def __init__(self, q, log_reads: bool = False) -> None:
        self.log: list[tuple] = []
        self.q = np.array(q, float)
        self.log_reads = log_reads
        self.protective = False
        self.connected = True
        self.move_result = True
        self.move_raises: Exception | None = None
        self.pose_ok = True
        self.construct_failures = 0
        self.calibration = np.eye(4)
        self.digital_in = [False] * 8
        self.close_sets_input: int | None = None   # a gripper input wired to the close output
        self.move_blocks: threading.Event | None = None   # moves wait on it (a silent robot)

    def world_from_flange(self, q) -> np.ndarray:
        """The controller's own forward kinematics."""
        return fk(np.asarray(q, float)) @ self.calibration


def install_fake_rtde(monkeypatch, robot: FakeRobot, probe: bool = True) -> None:
    """Put fake ``rtde_control``, ``rtde_receive`` and ``rtde_io`` modules driving ``robot``
    into ``sys.modules``; with ``probe=False`` also skip URArm's RTDE port probe."""

    def record(name):
        def method(self, *args):
            robot.log.append((name, *args))
            return True
        return method

    class Control:
        def __init__(self, host):
            if robot.construct_failures > 0:
                robot.construct_failures -= 1
                raise RuntimeError("fake: connection failed")
            robot.log.append(("RTDEControlInterface", host))

        setTcp = record("setTcp")
        servoStop = record("servoStop")
        speedStop = record("speedStop")
        stopL = record("stopL")
        stopJ = record("stopJ")
        teachMode = record("teachMode")
        endTeachMode = record("endTeachMode")
        disconnect = record("control.disconnect")

        def isConnected(self):
            return robot.connected

        def reconnect(self):
            robot.log.append(("control.reconnect",))
            robot.connected = True
            return True

        def isPoseWithinSafetyLimits(self, pose):
            robot.log.append(("isPoseWithinSafetyLimits", pose))
            return robot.pose_ok

        def isJointsWithinSafetyLimits(self, q):
            robot.log.append(("isJointsWithinSafetyLimits", q))
            return True

        def moveL(self, *args):
            # ur_rtde's two overloads: moveL(pose, speed, acceleration) and moveL(path), the
            # path's rows [x, y, z, rx, ry, rz, speed, acceleration, blend], the last blend 0.
            if len(args) == 1:
                (path,) = args
                assert isinstance(path, list) and path and all(
                    isinstance(r, list) and len(r) == 9 and all(type(v) is float for v in r) for r in path), path
                assert path[-1][8] == 0.0 and all(r[8] >= 0.0 for r in path), "the last pose of a path is not blended"
                robot.log.append(("moveL", path))
                poses = [r[:6] for r in path]
            else:
                pose, speed, acceleration = args
                robot.log.append(("moveL", pose, speed, acceleration))
                poses = [pose]
            if robot.move_blocks is not None:
                robot.move_blocks.wait()
            if robot.move_raises:
                raise robot.move_raises
            if robot.move_result:
                for pose in poses:
                    q = ik_nearest(pose6_to_matrix(pose) @ invert(robot.calibration), robot.q)
                    if q is not None:
                        robot.q = q
            return robot.move_result

        def moveJ(self, q, speed, acceleration):
            robot.log.append(("moveJ", q, speed, acceleration))
            if robot.move_blocks is not None:
                robot.move_blocks.wait()
            if robot.move_result:
                robot.q = np.array(q)
            return robot.move_result

        def getForwardKinematics(self, q=(), tcp_offset=()):
            robot.log.append(("getForwardKinematics", q, tcp_offset))
            assert list(tcp_offset) == [0.0] * 6, "URArm works in flange poses"
            return matrix_to_pose6(robot.world_from_flange(q if len(q) else robot.q)).tolist()

        def getInverseKinematics(self, x, qnear=(), max_position_error=1e-10, max_orientation_error=1e-10):
            robot.log.append(("getInverseKinematics", x, qnear))
            q = ik_nearest(pose6_to_matrix(x) @ invert(robot.calibration), np.asarray(qnear, float))
            if q is None:
                raise RuntimeError("fake: no inverse kinematics solution")
            return q.tolist()

    class Receive:
        def __init__(self, host):
            robot.log.append(("RTDEReceiveInterface", host))

        def isConnected(self):
            return True

        def getActualTCPPose(self):
            if robot.log_reads:
                robot.log.append(("getActualTCPPose",))
            return matrix_to_pose6(robot.world_from_flange(robot.q)).tolist()

        def getDigitalInState(self, pin):
            robot.log.append(("getDigitalInState", pin))
            return robot.digital_in[pin]

        def getActualQ(self):
            return robot.q.tolist()

        def isProtectiveStopped(self):
            return robot.protective

        disconnect = record("receive.disconnect")

    class IO:
        def __init__(self, host):
            robot.log.append(("RTDEIOInterface", host))

        def setStandardDigitalOut(self, pin, level):
            robot.log.append(("setStandardDigitalOut", pin, level))
            if robot.close_sets_input is not None and pin == 0:
                robot.digital_in[robot.close_sets_input] = bool(level)
            return True

        setToolDigitalOut = record("setToolDigitalOut")
        disconnect = record("io.disconnect")

    for name, attr, cls in (("rtde_control", "RTDEControlInterface", Control),
                            ("rtde_receive", "RTDEReceiveInterface", Receive),
                            ("rtde_io", "RTDEIOInterface", IO)):
        module = types.ModuleType(name)
        setattr(module, attr, cls)
        monkeypatch.setitem(sys.modules, name, module)
    from tapecell.cell import ur as cell_ur
    from tapecell.cell.ur_link import ThreadLink

    monkeypatch.setattr(cell_ur, "LINK_FACTORY", ThreadLink)
    if not probe:
        # No socket to a real controller: the fake answers for it.
        monkeypatch.setattr(cell_ur, "probe_rtde", lambda *a, **k: None)
