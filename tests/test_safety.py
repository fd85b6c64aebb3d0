"""Safety limits: every rule refuses with a clear reason, and nothing moves."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tapecell.cell.arm import ArmError
from tapecell.cell.fake_arm import FakeArm
from tapecell.cell.kinematics import fk
from tapecell.cell.poses import pose6_to_matrix
from tapecell.cell.safety import (KeepOutError, SafeArm, SafetyError, SafetyLimits, check_blends, check_joint_move,
                         check_linear_move, check_linear_path, check_points_flange, segment_hits_box)

Q0 = np.array([-1.5708, -1.9, 2.2, -1.87, -1.5708, 0.0])    # flange about (-0.13, 0.34, 0.35), down
LIMITS = SafetyLimits(workspace_min=[-0.30, 0.10, 0.05], workspace_max=[0.60, 0.90, 0.70],
                      max_tcp_speed=0.25, max_tcp_accel=1.2, max_joint_speed=1.0,
                      keepout_min=[-0.07, 0.44, 0.0], keepout_max=[0.07, 0.56, 0.095])
DOWN = [np.pi, 0.0, 0.0]   # flange z pointing at the table
GRIPPER = [0.0, 0.0, 0.16, 0.0, 0.0, 0.0]


def moves(arm: FakeArm) -> list[str]:
    return [n for n in arm.call_names() if n.startswith("move")]


def test_from_config_reads_the_cell_files_section():
    section = SimpleNamespace(workspace_min=(-0.3, 0.1, 0.05), workspace_max=(0.6, 0.9, 0.7), max_tcp_speed=0.25,
                              max_tcp_accel=1.2, max_joint_speed=1.0, keepout_min=(-0.07, 0.44, 0.0),
                              keepout_max=(0.07, 0.56, 0.095))
    limits = SafetyLimits.from_config(section)
    assert limits.max_tcp_speed == 0.25 and limits.max_joint_accel == 1.4
    np.testing.assert_allclose(limits.keepout_max, [0.07, 0.56, 0.095])
    with pytest.raises(SafetyError, match="workspace_min must be below"):
        SafetyLimits.from_config(SimpleNamespace(**{**vars(section), "workspace_max": (0.6, 0.0, 0.7)}))
    with pytest.raises(SafetyError, match="max_tcp_speed must be a positive"):
        SafetyLimits.from_config(SimpleNamespace(**{**vars(section), "max_tcp_speed": -1.0}))


def test_the_cell_file_limits_load():
    config = pytest.importorskip("tapecell.cell.config")
    limits = SafetyLimits.from_config(config.load_cell_config().limits)
    assert np.all(limits.workspace_min < limits.workspace_max)


def test_segment_box_property_against_dense_sampling():
    rng = np.random.default_rng(7)
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.5, 0.2])
    for _ in range(500):
        a, b = rng.uniform(-1, 2, 3), rng.uniform(-1, 2, 3)
        pts = a + np.linspace(0, 1, 5001)[:, None] * (b - a)
        dense = bool(np.any(np.all((pts > lo) & (pts < hi), axis=1)))
        assert segment_hits_box(a, b, lo, hi) == dense


def test_straight_line_through_the_keepout_is_refused_though_both_ends_are_clear():
    # Both ends outside the box around the part, the line between them through it.
    a = [-0.15, 0.50, 0.06, *DOWN]
    b = [0.15, 0.50, 0.06, *DOWN]
    with pytest.raises(SafetyError, match="keep-out box around the part"):
        check_linear_move(LIMITS, a, b, 0.1, 0.5)
    check_linear_move(LIMITS, a, [-0.15, 0.30, 0.06, *DOWN], 0.1, 0.5)   # alongside: fine


def test_tool_points_are_checked_not_just_the_flange():
    # Flange 150 mm above the part's top; the gripper's TCP 160 mm below the flange is inside.
    target = [0.0, 0.50, 0.245, *DOWN]
    start = [0.0, 0.30, 0.40, *DOWN]
    check_linear_move(LIMITS, start, target, 0.1, 0.5)   # flange alone: clear
    with pytest.raises(SafetyError, match="TCP would enter the keep-out"):
        check_linear_move(LIMITS, start, target, 0.1, 0.5, check_points_flange(GRIPPER))


@pytest.mark.parametrize("speed, acc, match", [(0.3, 0.5, "speed 0.3 m/s exceeds the limit 0.25"),
                                               (0.1, 2.0, "acceleration 2 m/s\\^2 exceeds the limit 1.2")])
def test_speed_and_acceleration_limits(speed, acc, match):
    pose = [0.0, 0.3, 0.4, *DOWN]
    with pytest.raises(SafetyError, match=match):
        check_linear_move(LIMITS, pose, pose, speed, acc)


def test_workspace_target_and_path():
    start = [0.0, 0.30, 0.40, *DOWN]
    with pytest.raises(SafetyError, match="outside the workspace box"):
        check_linear_move(LIMITS, start, [0.0, 0.30, 0.80, *DOWN], 0.1, 0.5)
    # From outside back in is allowed (recovery); the target must be inside.
    check_linear_move(LIMITS, [0.0, 0.0, 0.40, *DOWN], start, 0.1, 0.5)


def test_joint_moves_checked_along_the_joint_path():
    with pytest.raises(SafetyError, match="joint move: speed 2 rad/s"):
        check_joint_move(LIMITS, Q0, Q0, 2.0, 1.0)
    with pytest.raises(SafetyError, match="joint move: acceleration"):
        check_joint_move(LIMITS, Q0, Q0, 0.5, 3.0)
    # Home faces -y, outside the workspace box: a joint move there is refused.
    home = np.array([1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
    with pytest.raises(SafetyError, match="outside the workspace box"):
        check_joint_move(LIMITS, Q0, home, 0.5, 1.0)
    check_joint_move(LIMITS, Q0, Q0 + [0.1, 0.0, 0.0, 0.0, 0.0, 0.5], 0.5, 1.0, check_points_flange(GRIPPER))


def test_joint_move_sweeping_through_the_part_is_refused():
    # Swing the base joint with the tool low over the table: the TCP passes through the part.
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.poses import pose6_to_matrix

    flange_from_tcp = pose6_to_matrix(GRIPPER)
    a = ik_nearest(pose6_to_matrix([-0.20, 0.50, 0.22, *DOWN]), Q0)
    b = ik_nearest(pose6_to_matrix([0.20, 0.50, 0.22, *DOWN]), a)
    assert a is not None and b is not None
    for q in (a, b):
        tcp = (fk(q) @ flange_from_tcp)[:3, 3]
        assert not np.all((tcp > LIMITS.keepout_min) & (tcp < LIMITS.keepout_max))
    with pytest.raises(SafetyError, match="keep-out"):
        check_joint_move(LIMITS, a, b, 0.5, 1.0, check_points_flange(GRIPPER))


def test_safe_arm_sends_nothing_on_a_violation():
    arm = FakeArm(q0=Q0)
    safe = SafeArm(arm, LIMITS, flange_from_tool=GRIPPER)
    with safe:
        start = safe.tcp_pose()
        with pytest.raises(SafetyError):
            safe.move_linear(start + [0, 0, 0.5, 0, 0, 0], 0.1, 0.5)
        with pytest.raises(SafetyError):
            safe.move_linear(start + [0, 0, 0.01, 0, 0, 0], 1.0, 0.5)
        with pytest.raises(SafetyError):
            safe.move_joints(Q0, 5.0, 1.0)
        assert moves(arm) == []
        np.testing.assert_allclose(safe.tcp_pose(), start)
        safe.move_linear(start + [0.02, 0.0, -0.01, 0, 0, 0], 0.1, 0.5)
        assert moves(arm) == ["move_linear"]
        np.testing.assert_allclose(arm.calls[-1][1][0], start + [0.02, 0.0, -0.01, 0, 0, 0])
    assert arm.call_names()[-1] == "disconnect"


def test_safe_arm_checks_every_segment_and_the_blend_of_a_path():
    arm = FakeArm(q0=Q0)
    safe = SafeArm(arm, LIMITS, flange_from_tool=GRIPPER)
    with safe:
        start = safe.tcp_pose()
        up = np.array([0, 0, 0.01, 0, 0, 0])
        path = [start + up, start + 2 * up, start + 3 * up]
        # A middle pose out of the workspace: the straight legs either side of it leave it.
        with pytest.raises(SafetyError, match="workspace"):
            safe.move_linear_path([path[0], start + [0, 0, 0.5, 0, 0, 0], path[2]], 0.05, 0.5, 0.002)
        # Blends that would overlap (a UR refuses them): 6 mm against 10 mm segments.
        with pytest.raises(SafetyError, match="blend radius 6 mm at pose 1"):
            safe.move_linear_path(path, 0.05, 0.5, 0.006)
        with pytest.raises(SafetyError, match="speed"):
            safe.move_linear_path(path, 1.0, 0.5, 0.002)
        with pytest.raises(ArmError, match="blend"):
            safe.move_linear_path(path, 0.05, 0.5, -0.001)
        assert moves(arm) == []
        safe.move_linear_path(path, 0.05, 0.5, 0.002)
        assert moves(arm) == ["move_linear_path"]
        poses, speed, acc, blend = arm.calls[-1][1]
        np.testing.assert_allclose(poses, path)
        assert (speed, acc, blend) == (0.05, 0.5, 0.002)
        np.testing.assert_allclose(safe.tcp_pose(), path[-1], atol=1e-9)


def test_a_blend_that_cuts_a_corner_into_the_keep_out_box_is_refused():
    # Two 25 mm legs round the keep-out box's corner, 5 mm outside both of its faces: each
    # leg is clear, and so is a 2 mm blend; a 12 mm blend's chord cuts into the box.
    origin = np.zeros((1, 3))
    start, corner, end = ([0.075, 0.54, 0.05, *DOWN], [0.075, 0.565, 0.05, *DOWN], [0.05, 0.565, 0.05, *DOWN])
    check_linear_path(LIMITS, start, [corner, end], 0.05, 0.5, 0.002, origin)
    with pytest.raises(KeepOutError, match="the blend at pose 1 of 2"):
        check_linear_path(LIMITS, start, [corner, end], 0.05, 0.5, 0.012, origin)
    with pytest.raises(SafetyError, match="not a distance"):
        check_blends(LIMITS, start, [corner, end], 0.05, 0.5, float("nan"), origin)
    # A leg's refusal names the leg.
    with pytest.raises(SafetyError, match="leg 2 of 2: .*keep-out"):
        check_linear_path(LIMITS, start, [corner, [0.0, 0.50, 0.05, *DOWN]], 0.05, 0.5, 0.002, origin)


def test_safe_arm_stops_the_inner_arm_when_the_block_fails():
    arm = FakeArm(q0=Q0)
    with pytest.raises(RuntimeError):
        with SafeArm(arm, LIMITS):
            raise RuntimeError("boom")
    assert arm.call_names()[-2:] == ["stop", "disconnect"]


def test_checks_start_from_where_the_arm_really_is():
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.poses import pose6_to_matrix

    q_beside = ik_nearest(pose6_to_matrix([-0.15, 0.50, 0.10, *DOWN]), Q0)
    arm = FakeArm(q0=q_beside)
    with SafeArm(arm, LIMITS) as safe:
        np.testing.assert_allclose(safe.tcp_pose()[:3], [-0.15, 0.50, 0.10], atol=1e-9)
        # The target is clear of the part, but the line from where the arm is is not.
        with pytest.raises(SafetyError, match="keep-out"):
            safe.move_linear([0.15, 0.50, 0.06, *DOWN], 0.1, 0.5)
    assert moves(arm) == []


# ------------------------------------------------------------------ the table and the part as obstacles
def _with_boxes(clearance: float = 0.005) -> SafetyLimits:
    from tapecell.cell.safety import Obstacle

    return SafetyLimits(workspace_min=[-0.30, 0.10, 0.0], workspace_max=[0.60, 0.90, 0.70],
                        max_tcp_speed=0.25, max_tcp_accel=1.2, max_joint_speed=1.0,
                        keepout_min=[-0.07, 0.44, 0.0], keepout_max=[0.07, 0.56, 0.095],
                        obstacles=(Obstacle("table", np.array([-0.4, -0.5, -0.04]), np.array([1.0, 0.9, 0.0])),
                                   Obstacle("part", np.array([-0.06, 0.45, 0.0]), np.array([0.06, 0.55, 0.10]))),
                        clearance=clearance)


def test_from_cell_takes_the_table_and_the_part_as_obstacles():
    from tapecell.cell.config import load_cell_config

    limits = SafetyLimits.from_cell(load_cell_config())
    names = {o.name: o for o in limits.obstacles}
    assert set(names) == {"table", "part"} and limits.clearance == pytest.approx(0.005)
    assert names["table"].hi[2] == pytest.approx(0.0) and names["part"].hi[2] == pytest.approx(0.10)


def test_the_tool_shape_keeps_the_clearance_from_the_table_not_a_flat_floor():
    from tapecell.cell.safety import CollisionError, ToolShape

    limits = _with_boxes()
    # A gripper finger is a box 12 mm across, down to the TCP; the TCP goes down to the table.
    shape = ToolShape.box("finger", pose6_to_matrix(GRIPPER), [-0.006, -0.023, -0.13], [0.006, -0.02, 0.006])
    above = [0.25, 0.30, 0.16 + 0.006 + 0.012, *DOWN]     # the finger's end 12 mm above the table
    check_linear_move(limits, above, above, 0.1, 0.5, check_points_flange(GRIPPER), shape)
    low = [0.25, 0.30, 0.16 + 0.006 + 0.003, *DOWN]       # 3 mm: closer than the 5 mm clearance
    with pytest.raises(CollisionError, match="finger would come 3.0 mm from the table"):
        check_linear_move(limits, above, low, 0.1, 0.5, check_points_flange(GRIPPER), shape)
    # The same move is fine for the old rule's check points alone with the floor at the table.
    check_linear_move(SafetyLimits(**{**vars(limits), "obstacles": ()}), above, low, 0.1, 0.5,
                      check_points_flange(GRIPPER))


def test_the_wrist_is_checked_against_the_part_along_a_joint_move():
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.safety import CollisionError, check_wrist_clear

    limits = _with_boxes()
    # Flange 20 mm above the part's top, pointing down: the wrist's housings clear it.
    q = ik_nearest(pose6_to_matrix([0.0, 0.50, 0.10 + 0.02, *DOWN]), Q0)
    check_wrist_clear(limits, q[None], "pose")
    q_low = ik_nearest(pose6_to_matrix([0.0, 0.50, 0.10 + 0.003, *DOWN]), Q0)
    with pytest.raises(CollisionError, match="wrist 3 would come .* from the part"):
        check_wrist_clear(limits, q_low[None], "pose")
    with pytest.raises(CollisionError, match="joint move: the .* from the part"):
        check_joint_move(limits, q, q_low, 0.5, 1.0)


def test_safe_arm_checks_its_tool_shape_and_wrist_against_the_boxes():
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.safety import CollisionError, ToolShape

    limits = _with_boxes()
    start = [0.25, 0.30, 0.30, *DOWN]
    arm = FakeArm(q0=ik_nearest(pose6_to_matrix(start), Q0))
    shape = ToolShape.capsule("gripper mount", np.zeros(3), [0.0, 0.0, 0.16], 0.03)
    safe = SafeArm(arm, limits, flange_from_tool=GRIPPER, shape=shape)
    with safe:
        with pytest.raises(CollisionError, match="gripper mount would come"):
            safe.move_linear(np.array([0.25, 0.30, 0.16 + 0.03 + 0.002, *DOWN]), 0.1, 0.5)
        assert moves(arm) == []
        safe.move_linear(np.array([0.25, 0.30, 0.16 + 0.03 + 0.01, *DOWN]), 0.1, 0.5)
        assert moves(arm) == ["move_linear"]
