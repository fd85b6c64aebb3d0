"""The test double: the Arm contract (connection, validation, context manager)."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.cell.arm import Arm, ArmError, ArmNotConnectedError, ProtectiveStopError
from tapecell.cell.fake_arm import FakeArm
from tapecell.cell.kinematics import fk
from tapecell.cell.poses import matrix_to_pose6, pose_distance

Q0 = np.array([-1.5708, -1.9, 2.2, -1.87, -1.5708, 0.0])


def test_is_an_arm_and_needs_a_connection():
    arm = FakeArm(q0=Q0)
    assert isinstance(arm, Arm) and not arm.is_connected
    for call in (arm.tcp_pose, arm.joints, arm.stop, arm.open_gripper, arm.close_gripper,
                 arm.is_protective_stopped, lambda: arm.freedrive(True),
                 lambda: arm.move_joints(Q0, 0.5, 1.0), lambda: arm.move_linear(np.zeros(6), 0.1, 0.5)):
        with pytest.raises(ArmNotConnectedError, match="not connected"):
            call()
    assert arm.calls == []


def test_arguments_are_validated_before_anything_is_sent():
    with FakeArm(q0=Q0) as arm:
        with pytest.raises(ArmError, match="shape"):
            arm.move_linear([0.1, 0.2, 0.3], 0.1, 0.5)
        with pytest.raises(ArmError, match="NaN"):
            arm.move_joints([0, 0, np.nan, 0, 0, 0], 0.5, 1.0)
        with pytest.raises(ArmError, match="speed must be a positive"):
            arm.move_linear(arm.tcp_pose(), 0.0, 0.5)
        assert [n for n in arm.call_names() if n.startswith("move")] == []


def test_kinematics_stay_consistent():
    with FakeArm(q0=Q0) as arm:
        start = arm.tcp_pose()
        np.testing.assert_allclose(start, matrix_to_pose6(fk(Q0)))
        target = start + np.array([0.03, -0.02, 0.01, 0, 0, 0])
        arm.move_linear(target, 0.1, 0.5)
        assert max(pose_distance(arm.tcp_pose(), target)) < 1e-9
        assert np.max(np.abs(arm.joints() - Q0)) < 0.2          # same configuration
        arm.move_joints(Q0, 0.5, 1.0)
        np.testing.assert_allclose(arm.joints(), Q0)
        with pytest.raises(ArmError, match="out of reach"):
            arm.move_linear([2.0, 0.0, 0.3, 0, 0, 0], 0.1, 0.5)
        assert arm.calls[1] == ("move_linear", (arm.calls[1][1][0], 0.1, 0.5))


def test_gripper_freedrive_and_protective_stop():
    arm = FakeArm(q0=Q0, protective_stop_on=1)
    with arm:
        arm.close_gripper()
        assert arm.gripper_closed
        arm.freedrive(True)
        with pytest.raises(ArmError, match="freedrive"):
            arm.move_joints(Q0, 0.5, 1.0)
        arm.freedrive(False)
        arm.move_joints(Q0, 0.5, 1.0)                   # move 0
        with pytest.raises(ProtectiveStopError):
            arm.move_joints(Q0, 0.5, 1.0)               # move 1 stops
        assert arm.is_protective_stopped()
        with pytest.raises(ProtectiveStopError):
            arm.move_joints(Q0, 0.5, 1.0)
    assert not arm.is_connected


def test_context_manager_stops_only_on_error():
    arm = FakeArm(q0=Q0)
    with arm:
        pass
    assert arm.call_names() == ["connect", "disconnect"]
    with pytest.raises(KeyError):
        with arm:
            raise KeyError("x")
    assert arm.call_names()[-3:] == ["connect", "stop", "disconnect"]
