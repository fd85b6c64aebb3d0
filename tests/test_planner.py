"""Grasp planner: geometry of the grasp, refusals with reasons, execution on the fake arm."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.cell.arm import ProtectiveStopError
from tapecell.cell.fake_arm import FakeArm
from tapecell.cell.kinematics import fk
from tapecell.cell.planner import (REFERENCE_JOINTS, GraspParams, GripperGeometry, PlanRefused, Speeds, Step, TipFrame,
                          execute_plan, plan_grasp)
from tapecell.cell.poses import pose6_to_matrix, pose_distance
from tapecell.cell.safety import SafetyError, SafetyLimits
from tapecell.estimator.tape import TapeSpec, forward_kinematics

LIMITS = SafetyLimits(workspace_min=[-0.30, 0.10, 0.05], workspace_max=[0.60, 0.90, 0.70],
                      max_tcp_speed=0.25, max_tcp_accel=1.2, max_joint_speed=1.0,
                      keepout_min=[-0.07, 0.44, 0.0], keepout_max=[0.07, 0.56, 0.095])
PARAMS = GraspParams(inset=0.008, pregrasp_distance=0.05, lift=0.05)
GRIPPER = GripperGeometry(pose6_to_matrix([0, 0, 0.16, 0, 0, 0]), 0.04, np.array([0.012, 0.002, 0.012]))
BASE = np.array([0.0, 0.50, 0.1005])
# Tape standing up from the part's top, face towards +x (the cell file's layout).
BASE_ROTATION = np.column_stack([[0.0, 0.0, 1.0], np.cross([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]), [1.0, 0.0, 0.0]])
SPEC = TapeSpec(np.full(5, 0.03), 0.03, BASE, BASE_ROTATION)


def tape(angles) -> tuple[TipFrame, np.ndarray]:
    shape = forward_kinematics(SPEC, np.asarray(angles, float).reshape(5, 3))
    return TipFrame(shape.nodes[-1], shape.frames[-1], 0.02), shape.nodes


def random_tapes(n: int, seed: int = 3):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        angles = np.zeros((5, 3))
        angles[:, 0] = rng.uniform(-0.3, 0.3, 5)     # twist
        angles[:, 1] = rng.uniform(-0.35, 0.35, 5)   # flat bend
        angles[:, 2] = rng.uniform(-0.03, 0.03, 5)   # edge bend
        yield tape(angles)


def test_grasp_geometry_pads_straddle_the_normal_inset_from_the_tip():
    planned = 0
    for tip, nodes in random_tapes(25):
        try:
            plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
        except PlanRefused as e:
            assert e.reason in {"unreachable", "collision", "limits"}
            continue
        planned += 1
        grasp = plan.waypoint("grasp").world_from_tcp
        y, z = grasp[:3, 1], grasp[:3, 2]
        # Closing axis along the tape normal: the pads sit on either face of the tape.
        assert abs(abs(y @ tip.normal) - 1.0) < 1e-9
        pads = [grasp[:3, 3] + s * GRIPPER.max_opening / 2 * y for s in (-1, 1)]
        sides = [(p - grasp[:3, 3]) @ tip.normal for p in pads]
        assert sides[0] * sides[1] < 0
        # TCP on the tape's centre line, `inset` in from the tip.
        np.testing.assert_allclose(grasp[:3, 3], tip.position - PARAMS.inset * tip.trunk, atol=1e-12)
        # Approaching within the tilt range (up to 90 deg about the normal), never along the normal.
        assert z @ -tip.trunk >= -1e-9      # from beyond the tip or from the side, never from the base
        assert abs(z @ tip.normal) < 1e-9
        # The flange pose is the TCP pose composed with the tool offset.
        w = plan.waypoint("grasp")
        np.testing.assert_allclose(pose6_to_matrix(w.flange_pose) @ GRIPPER.flange_from_tcp, grasp, atol=1e-9)
        np.testing.assert_allclose(fk(w.q), pose6_to_matrix(w.flange_pose), atol=1e-6)
        # Pre-grasp back along the approach, clear of the tape's end; lift raises the TCP.
        pre = plan.waypoint("pregrasp").world_from_tcp[:3, 3]
        np.testing.assert_allclose(grasp[:3, 3] - pre, PARAMS.pregrasp_distance * z, atol=1e-12)
        # Lift: an arc of length `lift` about the tape's base, in steps of <= 10 mm, that
        # never stretches the free length and raises the tip unless it is already on top.
        lifts = [w.world_from_tcp[:3, 3] for w in plan.waypoints[1:]]
        steps = np.linalg.norm(np.diff(lifts, axis=0), axis=1)
        assert np.all(steps <= 0.0101) and abs(steps.sum() - PARAMS.lift) < 0.001
        radius = np.linalg.norm(grasp[:3, 3] - BASE)
        assert np.allclose(np.linalg.norm(np.array(lifts) - BASE, axis=1), radius, atol=1e-9)
        chord = (grasp[:3, 3] - BASE) / radius
        if chord[2] < np.cos(PARAMS.lift / radius):
            assert lifts[-1][2] > grasp[2, 3] + 0.005
        assert [s.action for s in plan.steps][:4] == ["open_gripper", "move_joints", "move_linear", "close_gripper"]
        assert [s.waypoint for s in plan.steps[4:]] == [w.name for w in plan.waypoints[2:]]
        assert plan.steps[-1].waypoint == "lift"
    assert planned >= 20


def test_a_hanging_tip_is_taken_from_the_side_not_from_below():
    angles = np.zeros((5, 3))
    angles[1:3, 1] = -np.pi / 4      # over to horizontal (towards +x) ...
    angles[4, 1] = -np.pi / 2        # ... and hanging down at the end
    tip, nodes = tape(angles)
    assert tip.trunk[2] < -0.99
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    approach = plan.waypoint("grasp").world_from_tcp[:3, 2]
    assert abs(np.degrees(plan.approach_tilt_rad)) > 45 and approach[2] < 0.5
    assert abs(abs(plan.waypoint("grasp").world_from_tcp[:3, 1] @ tip.normal) - 1) < 1e-9


def test_peel_mode_pulls_straight_up_and_away():
    tip, nodes = tape(np.zeros(15))
    params = GraspParams(0.008, 0.05, 0.05, lift_mode="peel")
    plan = plan_grasp(tip, params, GRIPPER, LIMITS, tape_points=nodes)
    grasp = plan.waypoint("grasp").world_from_tcp
    lift = plan.waypoint("lift").world_from_tcp
    np.testing.assert_allclose(lift[:3, :3], grasp[:3, :3])      # a pull, no turn
    np.testing.assert_allclose(lift[:3, 3] - grasp[:3, 3], [0.0, 0.0, 0.05], atol=1e-9)
    with pytest.raises(PlanRefused, match="lift mode"):
        GraspParams(0.008, 0.05, 0.05, lift_mode="yank")


def test_refuses_a_bad_estimate():
    tip, nodes = tape(np.zeros(15))
    bad = TipFrame(tip.position, tip.rotation, cost=0.05, verdict="ambiguous", reason="two shapes 0.5 apart")
    with pytest.raises(PlanRefused) as e:
        plan_grasp(bad, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    assert e.value.reason == "estimate rejected" and "0.5" in str(e.value)


def test_refuses_an_unreachable_tip():
    tip, nodes = tape(np.zeros(15))
    far = TipFrame(tip.position + np.array([0.0, 0.4, 0.8]), tip.rotation, tip.cost)
    roomy = SafetyLimits(LIMITS.workspace_min, [0.6, 1.5, 1.5], 0.25, 1.2, 1.0, LIMITS.keepout_min,
                         LIMITS.keepout_max)
    with pytest.raises(PlanRefused) as e:
        plan_grasp(far, PARAMS, GRIPPER, roomy)
    assert e.value.reason == "unreachable"
    # An injected IK that reaches nothing refuses the same way.
    with pytest.raises(PlanRefused) as e:
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, ik=lambda T, q: None)
    assert e.value.reason == "unreachable"


def test_refuses_outside_the_workspace():
    tip, nodes = tape(np.zeros(15))
    low = SafetyLimits(LIMITS.workspace_min, [0.6, 0.9, 0.20], 0.25, 1.2, 1.0, LIMITS.keepout_min,
                       LIMITS.keepout_max)
    with pytest.raises(PlanRefused) as e:
        plan_grasp(tip, PARAMS, GRIPPER, low)
    assert e.value.reason == "limits" and "workspace" in str(e.value)


def test_refuses_an_approach_through_the_part():
    # Tip lying flat just above the part's top, face up: the lower finger of any jaw that
    # closes across it (along the normal, world z) dips into the keep-out box.
    rotation = np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    tip = TipFrame(np.array([0.0, 0.50, 0.115]), rotation, 0.02)
    with pytest.raises(PlanRefused) as e:
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS)
    assert e.value.reason == "collision" and "keep-out" in str(e.value)
    # The same tip 30 mm higher is fine.
    plan_grasp(TipFrame(tip.position + [0.0, 0.0, 0.03], rotation, 0.02), PARAMS, GRIPPER, LIMITS)


def test_refuses_when_the_fingers_would_hit_the_tape():
    # A tape curled back on itself: a layer lies right where the open jaw comes in.
    tip, nodes = tape(np.zeros(15))
    # A sheet 20.5 mm off the tape's face all around the tip: where a finger slides in,
    # whichever way the jaw comes.
    a, b = np.meshgrid(np.linspace(-0.06, 0.06, 25), np.linspace(-0.06, 0.06, 25))
    w = tip.rotation[:, 1]
    sheet = (tip.position + a.reshape(-1, 1) * tip.trunk + b.reshape(-1, 1) * w + 0.0205 * tip.normal)
    with pytest.raises(PlanRefused) as e:
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, tape_surface=sheet)
    assert e.value.reason == "collision" and "finger" in str(e.value)
    plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)  # the straight tape is fine


def test_execute_plan_on_the_fake_arm_reaches_every_waypoint():
    tip, nodes = tape(np.zeros(15))
    arm = FakeArm(q0=REFERENCE_JOINTS)
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=REFERENCE_JOINTS)
    seen = []
    with arm:
        done = execute_plan(plan, arm, LIMITS, Speeds(), on_step=lambda s, a: seen.append(a.tcp_pose()))
        assert max(pose_distance(arm.tcp_pose(), plan.waypoint("lift").flange_pose)) < 1e-6
    assert done == list(plan.steps) and len(seen) == len(plan.steps)
    assert arm.call_names() == ["connect", "open_gripper", "move_joints", "move_linear", "close_gripper",
                                *["move_linear"] * (len(plan.steps) - 4), "disconnect"]
    _, (pose, speed, acc) = arm.calls[3]
    np.testing.assert_allclose(pose, plan.waypoint("grasp").flange_pose)
    assert speed <= LIMITS.max_tcp_speed and acc <= LIMITS.max_tcp_accel
    assert max(pose_distance(seen[2], plan.waypoint("grasp").flange_pose)) < 1e-6
    assert arm.gripper_closed


def test_execute_plan_checks_before_the_first_motion():
    tip, nodes = tape(np.zeros(15))
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    arm = FakeArm(q0=REFERENCE_JOINTS)
    tight = SafetyLimits(LIMITS.workspace_min, [0.6, 0.9, 0.42], 0.25, 1.2, 1.0, LIMITS.keepout_min,
                         LIMITS.keepout_max)
    with arm:
        with pytest.raises(SafetyError):
            execute_plan(plan, arm, tight)
        with pytest.raises(SafetyError, match="speed"):
            execute_plan(plan, arm, LIMITS, Speeds(approach=1.0))
    assert "move_joints" not in arm.call_names() and "move_linear" not in arm.call_names()


def test_execute_plan_stops_the_arm_on_a_protective_stop():
    tip, nodes = tape(np.zeros(15))
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    arm = FakeArm(q0=REFERENCE_JOINTS, protective_stop_on=1)   # during the approach
    with arm:
        with pytest.raises(ProtectiveStopError):
            execute_plan(plan, arm, LIMITS)
    names = arm.call_names()
    assert names[-2:] == ["stop", "disconnect"] and "close_gripper" not in names


def test_plan_to_json_and_describe():
    tip, nodes = tape(np.zeros(15))
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    d = plan.to_json()
    names = ["pregrasp", "grasp", "lift_1", "lift_2", "lift_3", "lift_4", "lift"]
    assert [w["name"] for w in d["waypoints"]] == names
    assert list(plan.tool_waypoints()) == names
    assert "grasp" in plan.describe() and "close_gripper" in plan.describe()


def test_a_low_hanging_tip_is_reached_where_the_gripper_clears_the_table_and_the_part():
    # The tape runs 90 mm out over the part's side and hangs straight down to 41 mm above
    # the table: the old flat floor (every check point above z 0.05) refused every approach;
    # the collision check of the gripper's and the wrist's shapes against the table and the
    # part, with the cell file's 5 mm clearance, finds one (from the side, pitched, through
    # a pose above the pre-grasp).
    from tapecell.cell.config import load_cell_config
    from tapecell.cell.safety import check_wrist_clear

    limits = SafetyLimits.from_cell(load_cell_config())
    angles = np.zeros((5, 3))
    angles[0, 1] = angles[3, 1] = -np.pi / 2
    tip, nodes = tape(angles)
    assert tip.position[2] == pytest.approx(0.0405, abs=1e-3) and tip.trunk[2] < -0.99
    # 30 mm from the part's face, the jaw's near finger (its pad and 6 mm of finger behind
    # it, 28 mm from the jaw's centre) would come 2 mm from the part: refused.
    with pytest.raises(PlanRefused, match="part"):
        plan_grasp(tip, PARAMS, GRIPPER, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
    angles[3, 1] = -np.radians(80.0)                # hanging 10 deg outwards: 40 mm from the face
    tip, nodes = tape(angles)
    assert tip.position[2] == pytest.approx(0.0414, abs=1e-3) and tip.trunk[2] < -0.98
    with pytest.raises(PlanRefused):
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=REFERENCE_JOINTS)
    plan = plan_grasp(tip, PARAMS, GRIPPER, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
    shape = GRIPPER.shape()
    for w in plan.waypoints:
        F = pose6_to_matrix(w.flange_pose)
        pts = (F[:3, :3] @ shape.points_flange.T).T + F[:3, 3]
        for ob in limits.obstacles:
            assert np.min(ob.distance(pts) - shape.radii) >= limits.clearance - 1e-9, (w.name, ob.name)
        check_wrist_clear(limits, w.q[None], w.name)
    assert plan.steps[1] == Step("move_joints", "above") and plan.steps[2] == Step("move_joints", "pregrasp")
    # Executed on the fake arm through the same checks.
    arm = FakeArm(q0=REFERENCE_JOINTS)
    with arm:
        execute_plan(plan, arm, limits, Speeds())
        np.testing.assert_allclose(arm.joints(), plan.waypoint("lift").q, atol=1e-6)


def test_a_tip_on_the_tables_surface_is_refused_as_a_collision():
    from tapecell.cell.config import load_cell_config

    limits = SafetyLimits.from_cell(load_cell_config())
    angles = np.zeros((5, 3))
    angles[0, 1] = angles[2, 1] = -np.pi / 2
    tip, nodes = tape(angles)                       # hangs down the part's face to 11 mm
    with pytest.raises(PlanRefused):
        plan_grasp(tip, PARAMS, GRIPPER, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
