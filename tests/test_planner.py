"""Grasp planner: geometry of the grasp, refusals with reasons, execution on the fake arm."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tapecell.cell.arm import ProtectiveStopError
from tapecell.cell.fake_arm import FakeArm
from tapecell.cell.kinematics import fk
from tapecell.cell.planner import (LIFT_BLEND_M, REFERENCE_JOINTS, GraspParams, GripperGeometry, PlanRefused, Speeds, Step, TipFrame,
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
        # The lift is one blended path through every lift pose (the arm does not stop).
        assert plan.steps[4:] == (Step("move_linear_path", "lift", ("lift_1", "lift_2", "lift_3", "lift_4"),
                                       LIFT_BLEND_M),)
        assert list(plan.steps[4].targets) == [w.name for w in plan.waypoints[2:]]
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
    # closes across it (along the normal, world z) dips into the keep-out box. (No centre
    # line given: only the cell file's inset is tried, along the tip's trunk; 83 mm back
    # along it would be past the part's edge, in the air, where no tape is known.)
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
    # A sheet 20.5 mm off the tape's face all around the tip, and back past the furthest
    # grasp point: where a finger slides in, whichever way the jaw comes.
    from tapecell.cell import planner

    far = PARAMS.inset + max(planner.EXTRA_INSETS_M) + 0.03
    a, b = np.meshgrid(np.linspace(-far, 0.06, 35), np.linspace(-0.06, 0.06, 25))
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
                                "move_linear_path", "disconnect"]
    _, (poses, speed, acc, blend) = arm.calls[5]
    np.testing.assert_allclose(poses, [plan.waypoint(n).flange_pose for n in ("lift_1", "lift_2", "lift_3",
                                                                            "lift_4", "lift")])
    assert (speed, acc, blend) == (Speeds().lift, Speeds().linear_accel, LIFT_BLEND_M)
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
    assert not any(name.startswith("move") for name in arm.call_names())


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
    # The lift: one path step, its poses listed, its blend in the JSON.
    assert d["steps"][-1] == ["move_linear_path", "lift", ["lift_1", "lift_2", "lift_3", "lift_4"], LIFT_BLEND_M]
    lines = plan.describe().splitlines()
    assert "move_linear_path: 5 poses, corners blended within 2 mm" in lines[-6]
    assert [ln.split()[:2] for ln in lines[-5:]] == [["through", "lift_1"], ["through", "lift_2"],
                                                     ["through", "lift_3"], ["through", "lift_4"], ["to", "lift"]]


def test_a_plan_whose_blend_would_overlap_is_refused_before_the_first_motion():
    tip, nodes = tape(np.zeros(15))
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=REFERENCE_JOINTS)
    steps = plan.steps[:-1] + (dataclasses.replace(plan.steps[-1], blend=0.006),)    # legs of 10 mm
    arm = FakeArm(q0=REFERENCE_JOINTS)
    with arm, pytest.raises(SafetyError, match="blend radius 6 mm"):
        execute_plan(dataclasses.replace(plan, steps=steps), arm, LIMITS, Speeds())
    assert not any(name.startswith("move") or name.endswith("gripper") for name in arm.call_names())


def test_a_low_hanging_tip_is_reached_where_the_gripper_clears_the_table_and_the_part(monkeypatch):
    # The tape runs 90 mm out over the part's side and hangs straight down to 41 mm above
    # the table: the old flat floor (every check point above z 0.05) refused every approach;
    # the collision check of the gripper's and the wrist's shapes against the table and the
    # part, with the cell file's 5 mm clearance, finds one (from the side, pitched, through
    # a pose above the pre-grasp).
    from tapecell.cell import planner
    from tapecell.cell.config import load_cell_config

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
    with monkeypatch.context() as m, pytest.raises(PlanRefused):
        # The flat floor refuses the grasp points near the end (up to 40 mm in; further
        # back, 50 mm and more, the tape runs level 90 mm above the table).
        m.setattr(planner, "EXTRA_INSETS_M", tuple(d for d in planner.EXTRA_INSETS_M if d <= 0.040 + 1e-9))
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=REFERENCE_JOINTS)
    plan = plan_grasp(tip, PARAMS, GRIPPER, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
    assert plan.inset <= PARAMS.inset + 0.040 + 1e-9
    _assert_waypoints_clear(plan, GRIPPER.shape(), limits)
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


def _assert_waypoints_clear(plan, shape, limits):
    """Every waypoint keeps the gripper's shape and the wrist the clearance from every
    obstacle."""
    from tapecell.cell.safety import check_wrist_clear

    for w in plan.waypoints:
        F = pose6_to_matrix(w.flange_pose)
        pts = (F[:3, :3] @ shape.points_flange.T).T + F[:3, 3]
        for ob in limits.obstacles:
            assert np.min(ob.distance(pts) - shape.radii) >= limits.clearance - 1e-9, (w.name, ob.name)
        check_wrist_clear(limits, w.q[None], w.name)


def _distance_to_polyline(p, line):
    d = []
    for a, b in zip(line[:-1], line[1:]):
        t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        d.append(np.linalg.norm(p - (a + t * (b - a))))
    return min(d)


def test_an_end_hanging_beside_the_parts_face_is_taken_further_back_from_above(monkeypatch):
    # The tape curls over the part's +x edge and hangs 16 mm outside its face, the tip 10 mm
    # below the part's top. An open jaw (40 mm, the fingers 8 mm thick) across the tape at
    # the cell file's 8 mm inset would put the near finger inside the part, from whatever
    # side in the tape's plane it comes (seeds 400040, 400075, 400095 of a campaign). Higher
    # up the hanging end, the near finger passes over the part's top, 5 mm clear.
    from tapecell.cell import planner
    from tapecell.cell.config import load_cell_config
    from tapecell.cell.safety import check_linear_move

    cfg = load_cell_config()
    limits = SafetyLimits.from_cell(cfg)
    gripper = GripperGeometry.from_config(cfg.tools.gripper)
    angles = np.zeros((5, 3))
    angles[:, 1] = np.radians([0.0, -60.0, -30.0, -60.0, -20.0])
    tip, nodes = tape(angles)
    assert 0.075 < tip.position[0] < 0.078 and tip.position[2] < 0.095 and tip.trunk[2] < -0.95
    with monkeypatch.context() as m:          # the first set of variants alone: refused
        m.setattr(planner, "EXTRA_INSETS_M", ())
        m.setattr(planner, "BODY_SIDE_TILTS_RAD", ())
        with pytest.raises(PlanRefused) as e:
            plan_grasp(tip, PARAMS, gripper, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
        assert e.value.reason == "collision" and "part" in str(e.value)
    plan = plan_grasp(tip, PARAMS, gripper, limits, tape_points=nodes, q_start=REFERENCE_JOINTS)
    grasp = plan.waypoint("grasp").world_from_tcp
    # On the estimated centre line, a few mm further back than the cell file's inset.
    line = np.vstack([nodes[:-1], tip.position])
    assert _distance_to_polyline(grasp[:3, 3], line) < 1e-9
    inset = np.linalg.norm(grasp[:3, 3] - tip.position)
    assert PARAMS.inset < inset <= PARAMS.inset + max(planner.EXTRA_INSETS_M) + 1e-9
    # The jaw closes across the tape there: along its normal, up to the approach's pitch.
    _, R = planner.grasp_frame(tip, inset, PARAMS.inset, nodes)
    assert abs(R[1, 2]) < 1e-9 and abs(R[:, 0] @ (grasp[:3, 3] - tip.position)) > 0.99 * inset
    assert abs(grasp[:3, 1] @ R[:, 2]) >= np.cos(plan.approach_pitch_rad) - 1e-9
    # Every pose and every straight move keeps the 5 mm clearance from the part and the table.
    shape = gripper.shape()
    points = gripper.check_points_flange()
    _assert_waypoints_clear(plan, shape, limits)
    # ... with planner.PLAN_MARGIN_M to spare: executed, each straight move is checked again
    # from the pose the arm actually reached (fresh 941160: planned at 5.0 mm, stopped at 4.99).
    planned = dataclasses.replace(limits, clearance=limits.clearance + planner.PLAN_MARGIN_M)
    linear = [n for s in plan.steps if s.action.startswith("move_linear") for n in s.targets]
    previous = "pregrasp"
    for name in linear:
        check_linear_move(planned, plan.waypoint(previous).flange_pose, plan.waypoint(name).flange_pose,
                          0.1, 0.8, points, shape, plan.waypoint(previous).q)
        previous = name
    # Executed on the fake arm through the same checks.
    arm = FakeArm(q0=REFERENCE_JOINTS)
    with arm:
        execute_plan(plan, arm, limits, Speeds())


def test_a_pad_is_not_swept_through_the_tape_on_the_joint_move_to_the_pregrasp():
    # A curled tape's body beside the path the open gripper takes to the pre-grasp pose
    # (seeds 400037, 400177: the pad dragged the tape out of the jaw before the approach).
    from tapecell.cell.config import load_cell_config
    from tapecell.cell.planner import TAPE_CLEARANCE_M, check_tape_clear, tape_surface_points
    from tapecell.cell.poses import invert

    cfg = load_cell_config()
    park = np.array(cfg.arm.park_joints)
    tip, nodes = tape(np.zeros(15))
    shape = forward_kinematics(SPEC, np.zeros((5, 3)))
    surface = tape_surface_points(shape.nodes, shape.frames, SPEC.width)
    assert len(surface) > 500 and np.max(np.abs((surface - BASE)[:, 1])) == pytest.approx(0.015)
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=park, tape_surface=surface)
    assert [s.waypoint for s in plan.steps if s.action == "move_joints"] == ["pregrasp"]
    tcp_from_flange = invert(GRIPPER.flange_from_tcp)
    q_pre = plan.waypoint("pregrasp").q
    check_tape_clear(park, q_pre, surface, GRIPPER, tcp_from_flange)
    # A patch of tape where the left finger passes 60 % of the way along that joint move.
    world_from_tcp = fk(park + 0.6 * (q_pre - park)) @ GRIPPER.flange_from_tcp
    a, b = np.meshgrid(np.linspace(-0.004, 0.004, 5), np.linspace(-0.004, 0.004, 5))
    patch_tcp = np.c_[a.ravel(), np.full(a.size, 0.024), b.ravel() - 0.03]
    patch = patch_tcp @ world_from_tcp[:3, :3].T + world_from_tcp[:3, 3]
    with pytest.raises(SafetyError, match="estimated tape"):
        check_tape_clear(park, q_pre, np.vstack([surface, patch]), GRIPPER, tcp_from_flange)
    # Planned with it, the arm goes another way, and every joint move keeps the clearance.
    replanned = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=park,
                           tape_surface=np.vstack([surface, patch]))
    moves = [replanned.waypoint(s.waypoint).q for s in replanned.steps if s.action == "move_joints"]
    assert len(moves) > 1 or np.max(np.abs(moves[0] - q_pre)) > 1e-6
    for qa, qb in zip([park, *moves[:-1]], moves):
        check_tape_clear(qa, qb, np.vstack([surface, patch]), GRIPPER, tcp_from_flange, TAPE_CLEARANCE_M)
    # Without the tape's faces the planner knew nothing of the patch: the first plan.
    again = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, q_start=park)
    np.testing.assert_allclose(again.waypoint("pregrasp").q, q_pre)


def test_a_straight_move_near_a_wrist_singularity_is_refused_at_its_speed():
    # A 50 mm approach past a wrist singularity (joint 5 near -pi): joints 4 and 6 turn
    # 1.5 rad, ~6 rad/s at 0.1 m/s (seed 400120: the simulated arm left the line by 50 mm
    # and a pad pushed the tape out of the jaw). The old guard (0.25 rad per 5 mm) let it
    # through; at the plan's speed it exceeds the 1 rad/s joint limit.
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.planner import _follow_line

    start = np.array([-0.2837, 0.3944, 0.1639, 0.8574, 1.5331, 1.5207])
    end = np.array([-0.2393, 0.4173, 0.1658, 0.8574, 1.5331, 1.5207])
    q0 = ik_nearest(pose6_to_matrix(start), REFERENCE_JOINTS)
    q_end, along = _follow_line(ik_nearest, start, end, q0, "approach")
    assert abs(q_end[3] - q0[3]) > 1.0 and abs(abs(q0[4]) - np.pi) < 0.1
    with pytest.raises(PlanRefused, match="rad/s") as e:
        _follow_line(ik_nearest, start, end, q0, "approach", 0.1, 1.0)
    assert e.value.reason == "unreachable"
    # Slowly enough, the same line is allowed; a line away from the singularity at full speed too.
    _follow_line(ik_nearest, start, end, q0, "approach", 0.01, 1.0)
    tip, nodes = tape(np.zeros(15))
    plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    names = [w.name for w in plan.waypoints]
    speeds = Speeds()
    for a, b in zip(names[names.index("pregrasp"):-1], names[names.index("pregrasp") + 1:]):
        speed = speeds.approach if b == "grasp" else speeds.lift
        _follow_line(ik_nearest, plan.waypoint(a).flange_pose, plan.waypoint(b).flange_pose,
                     plan.waypoint(a).q, b, speed, LIMITS.max_joint_speed)


def test_planned_straight_moves_keep_the_joint_speed_limit():
    from tapecell.cell.kinematics import ik_nearest
    from tapecell.cell.planner import _follow_line

    speeds = Speeds()
    checked = 0
    for tip, nodes in random_tapes(10, seed=11):
        try:
            plan = plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
        except PlanRefused:
            continue
        names = [w.name for w in plan.waypoints]
        i = names.index("pregrasp")
        for a, b in zip(names[i:-1], names[i + 1:]):
            speed = speeds.approach if b == "grasp" else speeds.lift
            _, along = _follow_line(ik_nearest, plan.waypoint(a).flange_pose, plan.waypoint(b).flange_pose,
                                    plan.waypoint(a).q, b)
            path = np.array([plan.waypoint(a).q, *along])
            length = np.linalg.norm(plan.waypoint(b).flange_pose[:3] - plan.waypoint(a).flange_pose[:3])
            rate = np.max(np.abs(np.diff(path, axis=0))) / (length / (len(path) - 1)) * speed
            assert rate <= LIMITS.max_joint_speed + 1e-9, (a, b, rate)
            checked += 1
    assert checked >= 30


def test_the_open_fingers_keep_a_margin_from_the_tape_on_the_approach(monkeypatch):
    """On the straight approach the open fingers keep 3 mm (APPROACH_TAPE_MARGIN_M) from
    the estimated tape: a sheet of tape 2 mm inside the open jaw's pad faces (18 mm from the
    tape's face, the pads 20 mm) is refused; 3.5 mm inside is planned (an estimate a few mm
    off along an arching body let a pad push the tape out of the jaw in episode 670065)."""
    import tapecell.cell.planner as planner

    tip, nodes = tape(np.zeros(15))
    # A sheet 30 mm either side of the tip, 30 mm past the furthest grasp point back along
    # the trunk (every tilt and pitch of the jaw, at every inset, meets it).
    far = PARAMS.inset + max(planner.EXTRA_INSETS_M) + 0.03
    a, b = np.meshgrid(np.linspace(-far, 0.03, 57), np.linspace(-0.03, 0.03, 25))
    w = tip.rotation[:, 1]

    def sheet(offset):
        return tip.position + a.reshape(-1, 1) * tip.trunk + b.reshape(-1, 1) * w + offset * tip.normal
    with pytest.raises(PlanRefused) as e:
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, tape_surface=sheet(0.018))
    assert e.value.reason == "collision" and "finger would hit the tape" in str(e.value)
    plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, tape_surface=sheet(0.0165))
    monkeypatch.setattr(planner, "APPROACH_TAPE_MARGIN_M", 0.0)        # without the margin: planned
    plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes, tape_surface=sheet(0.018))


def test_far_back_grasps_are_only_tried_across_the_tape(monkeypatch):
    """Every variant the planner tries at a grasp point FAR_INSET_M or more in from the tip
    comes across the tape (tilt 90-120 deg either way); closer in, every tilt is tried."""
    from tapecell.cell import planner
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config()
    tried = []

    def refuse(tip, grasp_position, tape_base, tilt, *a, **k):
        tried.append((float(np.linalg.norm(grasp_position - tip.position)), abs(float(tilt))))
        raise PlanRefused("collision", "refused for the test")

    monkeypatch.setattr(planner, "_plan_variant", refuse)
    tip, nodes = tape(np.zeros((5, 3)))
    with pytest.raises(PlanRefused):
        plan_grasp(tip, PARAMS, GripperGeometry.from_config(cfg.tools.gripper), SafetyLimits.from_cell(cfg),
                   tape_points=nodes)
    far = [t for d, t in tried if d >= planner.FAR_INSET_M - 1e-9]
    near = {round(np.degrees(t)) for d, t in tried if d < planner.FAR_INSET_M - 1e-9}
    assert far and all(np.radians(90.0) - 1e-9 <= t <= np.radians(120.0) + 1e-9 for t in far)
    assert {0, 60, 150, 180} <= near


def test_straight_moves_are_planned_with_a_margin_over_the_clearance(monkeypatch):
    """Executed, each straight move is checked again from the pose the arm actually reached,
    a little off the planned one: a plan passed at the bare clearance can be stopped on the
    way (fresh 941160: the left finger planned at 5.0 mm from the part, stopped at 4.99). The
    planner checks every straight move with planner.PLAN_MARGIN_M more."""
    from tapecell.cell import planner

    seen = []
    check = planner.check_linear_move

    def spy(limits, *a, **k):
        seen.append(limits.clearance)
        return check(limits, *a, **k)

    monkeypatch.setattr(planner, "check_linear_move", spy)
    tip, nodes = next(random_tapes(1))
    plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=nodes)
    assert seen and all(c == pytest.approx(LIMITS.clearance + planner.PLAN_MARGIN_M) for c in seen)


def test_an_end_hanging_out_from_the_part_is_taken_far_back_where_nearer_grasps_collide(monkeypatch):
    # The estimate of fresh seed 968000 (3 cameras): the end curls over the part's +x edge
    # and hangs 30 mm outside its face, pointing out and down. Every one of the 288 approach
    # variants up to 40 mm in from the tip put the palm at the table or a finger within the
    # clearance of the part; 58 mm in, higher up where the tape comes over the edge, the jaw
    # takes it from the side (the episode grasped there, the tape following the lift).
    from tapecell.cell import planner
    from tapecell.cell.config import load_cell_config
    from tapecell.cell.planner import estimated_surface

    cfg = load_cell_config()
    limits = SafetyLimits.from_cell(cfg)
    gripper = GripperGeometry.from_config(cfg.tools.gripper)
    angles = np.radians([[-1.91, -2.01, -0.07], [-0.8, -46.25, -0.09], [-3.29, -73.2, 1.13],
                         [-0.86, -13.71, 0.08], [-0.9, -2.04, 0.2]])
    R = np.array([[0.667, -0.0086, -0.745], [-0.0613, -0.9972, -0.0433], [-0.7425, 0.0745, -0.6657]])
    u, _, vt = np.linalg.svd(R)
    tip = TipFrame(np.array([0.0904, 0.4944, 0.0916]), u @ vt, 0.066)
    nodes = forward_kinematics(SPEC, angles).nodes
    kw = dict(tape_points=nodes, tape_surface=estimated_surface(SPEC, angles),
              q_start=np.array([-0.5, -2.0, 2.3, -1.9, -np.pi / 2, 0.0]))
    with monkeypatch.context() as m:          # the grasp points up to 40 mm in: refused
        m.setattr(planner, "EXTRA_INSETS_M", tuple(d for d in planner.EXTRA_INSETS_M if d <= 0.040 + 1e-9))
        with pytest.raises(PlanRefused) as e:
            plan_grasp(tip, PARAMS, gripper, limits, **kw)
        assert e.value.reason == "collision" and "table" in str(e.value)
    plan = plan_grasp(tip, PARAMS, gripper, limits, **kw)
    assert plan.inset > PARAMS.inset + 0.040
    assert planner.SIDE_TILT_MIN_RAD - 1e-9 <= abs(plan.approach_tilt_rad) <= planner.SIDE_TILT_MAX_RAD + 1e-9
    grasp = plan.waypoint("grasp").world_from_tcp
    assert _distance_to_polyline(grasp[:3, 3], nodes) < 1e-9   # on the estimated centre line
    assert grasp[2, 3] > 0.1                                    # above the part's top (z 0.1 m)
    _assert_waypoints_clear(plan, gripper.shape(), limits)



def test_grasp_points_are_tried_only_where_the_tape_is_known(monkeypatch):
    """With a centre line, no grasp point past its base (grasp_frame would stop at the base,
    on the part, and report the inset it was asked for); without one, none further in than
    the cell file's inset (further back along the tip's trunk is a guess)."""
    from tapecell.cell import planner

    tried = []
    real = planner.grasp_frame

    def spy(tip, inset, straight, tape_points=None):
        tried.append(inset)
        return real(tip, inset, straight, tape_points)
    monkeypatch.setattr(planner, "grasp_frame", spy)
    monkeypatch.setattr(planner, "_plan_variant", lambda *a, **k: (_ for _ in ()).throw(
        PlanRefused("collision", "every variant refused (test)")))
    short = TapeSpec(np.full(2, 0.03), 0.03, BASE, BASE_ROTATION)      # a 60 mm tape
    shape = forward_kinematics(short, np.zeros((2, 3)))
    tip = TipFrame(shape.nodes[-1], shape.frames[-1], 0.02)
    with pytest.raises(PlanRefused):
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS, tape_points=shape.nodes)
    assert tried and max(tried) <= 0.060 + 1e-9
    assert sorted(set(tried)) == [i for i in planner.grasp_insets(PARAMS) if i <= 0.060]
    tried.clear()
    with pytest.raises(PlanRefused):
        plan_grasp(tip, PARAMS, GRIPPER, LIMITS)
    assert set(tried) == {PARAMS.inset}
    tried.clear()
    with pytest.raises(PlanRefused, match="unreachable.*5 mm long"):
        tiny = TapeSpec(np.full(1, 0.005), 0.03, BASE, BASE_ROTATION)
        s5 = forward_kinematics(tiny, np.zeros((1, 3)))
        plan_grasp(TipFrame(s5.nodes[-1], s5.frames[-1], 0.02), PARAMS, GRIPPER, LIMITS, tape_points=s5.nodes)
    assert not tried
