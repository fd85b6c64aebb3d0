"""Fake ur_rtde modules shared by the tests of the real-cell paths (driver, calibrate,
probe): one controller whose state and call log the tests inspect.

    robot = FakeRobot(q_start)
    install_fake_rtde(monkeypatch, robot)                 # URArm still probes the RTDE port
    install_fake_rtde(monkeypatch, robot, probe=False)    # ... or skip that socket check
"""
from __future__ import annotations

import sys
import types

import numpy as np

from tapecell.cell.kinematics import fk
from tapecell.cell.poses import matrix_to_pose6


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

        def moveL(self, pose, speed, acceleration):
            robot.log.append(("moveL", pose, speed, acceleration))
            if robot.move_raises:
                raise robot.move_raises
            return robot.move_result

        def moveJ(self, q, speed, acceleration):
            robot.log.append(("moveJ", q, speed, acceleration))
            if robot.move_result:
                robot.q = np.array(q)
            return robot.move_result

    class Receive:
        def __init__(self, host):
            robot.log.append(("RTDEReceiveInterface", host))

        def isConnected(self):
            return True

        def getActualTCPPose(self):
            if robot.log_reads:
                robot.log.append(("getActualTCPPose",))
            return matrix_to_pose6(fk(robot.q)).tolist()

        def getActualQ(self):
            return robot.q.tolist()

        def isProtectiveStopped(self):
            return robot.protective

        disconnect = record("receive.disconnect")

    class IO:
        def __init__(self, host):
            robot.log.append(("RTDEIOInterface", host))

        setStandardDigitalOut = record("setStandardDigitalOut")
        setToolDigitalOut = record("setToolDigitalOut")
        disconnect = record("io.disconnect")

    for name, attr, cls in (("rtde_control", "RTDEControlInterface", Control),
                            ("rtde_receive", "RTDEReceiveInterface", Receive),
                            ("rtde_io", "RTDEIOInterface", IO)):
        module = types.ModuleType(name)
        setattr(module, attr, cls)
        monkeypatch.setitem(sys.modules, name, module)
    if not probe:
        from tapecell.cell import ur as cell_ur

        # No socket to a real controller: the fake answers for it.
        monkeypatch.setattr(cell_ur, "probe_rtde", lambda *a, **k: None)
