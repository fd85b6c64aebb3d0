"""The simulated arm behind the Arm interface, and a planned grasp executed physically."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell import sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco is imported)

from tapecell.cell.arm import Arm, ArmError
from tapecell.cell.kinematics import fk
from tapecell.cell.planner import GraspParams, GripperGeometry, TipFrame, execute_plan, plan_grasp
from tapecell.cell.poses import matrix_to_pose6, pose_distance
from tapecell.cell.safety import SafeArm, SafetyError, SafetyLimits
from tapecell.sim.arm_adapter import SimArmAdapter


@pytest.fixture(scope="module")
def sim():
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config()
    cell = SimCell(cfg, seed=3, n_cameras=2, tool="gripper")
    yield cfg, cell, SimArm(cell, tool="gripper")
    cell.close()


def test_adapter_is_an_arm_reporting_flange_poses(sim):
    cfg, cell, sim_arm = sim
    cell.reset(3)
    with SimArmAdapter(sim_arm) as arm:
        assert isinstance(arm, Arm)
        pose = arm.tcp_pose()
        assert max(pose_distance(pose, matrix_to_pose6(fk(arm.joints())))) < 1e-9
        target = pose + np.array([0.0, 0.02, -0.02, 0.0, 0.0, 0.0])
        arm.move_linear(target, 0.1, 0.5)
        dist_m, angle = pose_distance(arm.tcp_pose(), target)
        assert dist_m < 0.002 and angle < 0.01
        with pytest.raises(ArmError, match="freedrive"):
            arm.freedrive(True)


def test_a_path_does_not_stop_at_its_intermediate_poses(sim):
    # The same 4 poses 10 mm apart, as one path and as four moves: both end at the last
    # pose; the path takes less simulated time (no settling at the three corners).
    cfg, cell, sim_arm = sim
    elapsed, ends = [], []
    for as_path in (True, False):
        cell.reset(3)
        with SimArmAdapter(sim_arm) as arm:
            start = arm.tcp_pose()
            path = [start + np.array([0.0, 0.0, 0.01 * k, 0.0, 0.0, 0.0]) for k in (1, 2, 3, 4)]
            t0 = cell.data.time
            if as_path:
                arm.move_linear_path(path, 0.05, 0.8, 0.002)
            else:
                for pose in path:
                    arm.move_linear(pose, 0.05, 0.8)
            elapsed.append(cell.data.time - t0)
            ends.append(pose_distance(arm.tcp_pose(), path[-1]))
    assert all(d < 0.001 and a < 0.01 for d, a in ends)
    assert 0.8 <= elapsed[0] < elapsed[1] - 0.1, elapsed      # 40 mm at 50 mm/s, then the last settling


def test_safety_refusal_leaves_the_simulated_arm_still(sim):
    cfg, cell, sim_arm = sim
    cell.reset(3)
    limits = SafetyLimits.from_config(cfg.limits)
    with SafeArm(SimArmAdapter(sim_arm), limits, flange_from_tool=cfg.tools.gripper.flange_from_tcp) as arm:
        q0 = arm.joints()
        t0 = cell.data.time
        with pytest.raises(SafetyError, match="workspace"):
            arm.move_linear(arm.tcp_pose() + [0.0, 0.0, 0.6, 0, 0, 0], 0.1, 0.5)
        assert cell.data.time == t0
        np.testing.assert_allclose(arm.joints(), q0)


def test_planned_grasp_at_the_true_tip_holds_the_tape_through_the_lift(sim):
    cfg, cell, sim_arm = sim
    cell.reset(3)
    limits = SafetyLimits.from_config(cfg.limits)
    world_from_tip = cell.tape_tip_frame()
    nodes, _ = cell.tape_frames()
    plan = plan_grasp(TipFrame(world_from_tip[:3, 3], world_from_tip[:3, :3], 0.0),
                      GraspParams.from_config(cfg.grasp), GripperGeometry.from_config(cfg.tools.gripper), limits,
                      q_start=sim_arm.joints(), tape_points=nodes)
    seen = {}

    def on_step(step, arm):
        if step.action == "close_gripper":
            seen["contacts"] = cell.gripper_pad_contacts_with_tape()
            seen["tip"] = cell.tape_tip_position()
            seen["tcp"] = sim_arm.tcp_pose("gripper")[:3, 3].copy()

    with SimArmAdapter(sim_arm) as arm:
        execute_plan(plan, arm, limits, on_step=on_step)
        assert arm.gripper_opening is not None and arm.gripper_opening < 0.004
    assert seen["contacts"]["left"] > 0 and seen["contacts"]["right"] > 0
    after = cell.gripper_pad_contacts_with_tape()
    assert after["left"] > 0 and after["right"] > 0
    gripper_move = sim_arm.tcp_pose("gripper")[:3, 3] - seen["tcp"]
    tip_move = cell.tape_tip_position() - seen["tip"]
    assert np.linalg.norm(gripper_move) > 0.04
    assert np.linalg.norm(tip_move - gripper_move) < 0.008      # the tip went with the gripper
