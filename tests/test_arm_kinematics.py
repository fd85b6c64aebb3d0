"""Closed-form UR5e inverse kinematics and the pose helpers (seeded property tests)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tapecell.cell.kinematics import fk, ik_nearest, ik_solutions
from tapecell.cell.poses import (PoseError, as_pose6, flange_target_for_tool, interpolate_pose6, invert, matrix_to_pose6,
                        pose6_to_matrix, pose_distance, tool_from_flange_pose)


def random_q(rng) -> np.ndarray:
    q = rng.uniform(-np.pi, np.pi, 6)
    q[2] = rng.uniform(-2.8, 2.8)
    return q


def test_every_solution_reaches_the_pose_and_one_is_the_original():
    rng = np.random.default_rng(11)
    for _ in range(200):
        q = random_q(rng)
        T = fk(q)
        sols = ik_solutions(T)
        assert 1 <= len(sols) <= 8
        for s in sols:
            F = fk(s)
            assert np.linalg.norm(F[:3, 3] - T[:3, 3]) < 1e-6
            assert pose_distance(matrix_to_pose6(F), matrix_to_pose6(T))[1] < 1e-5
        diffs = np.abs(np.angle(np.exp(1j * (sols - q))))
        assert diffs.max(axis=1).min() < 1e-6


def test_nearest_solution_keeps_the_configuration_and_out_of_reach_is_none():
    rng = np.random.default_rng(5)
    checked = 0
    while checked < 50:
        q = random_q(rng)
        if abs(np.sin(q[4])) < 0.3 or abs(np.sin(q[2])) < 0.3:
            continue    # near the wrist or elbow singularity a small step may need large joint moves
        checked += 1
        step = fk(q)
        step[:3, 3] += rng.normal(0, 0.002, 3)      # a 2-3 mm step, as along a line
        near = ik_nearest(step, q)
        if near is not None:
            assert np.max(np.abs(near - q)) < 0.2
    far = np.eye(4)
    far[:3, 3] = [1.5, 0.0, 0.3]   # beyond the UR5e's ~0.85 m reach
    assert len(ik_solutions(far)) == 0 and ik_nearest(far, np.zeros(6)) is None


def test_ik_solutions_put_the_mujoco_arm_at_the_target():
    """Closed-form IK checked against the independent MuJoCo model (not against the DH
    forward kinematics it is derived from)."""
    from mujoco_arm import MujocoArm

    arm = MujocoArm()
    rng = np.random.default_rng(2)
    for _ in range(10):
        target = fk(random_q(rng))
        for q in ik_solutions(target):
            T = arm.flange(q)
            np.testing.assert_allclose(T[:3, 3], target[:3, 3], atol=1e-6)
            np.testing.assert_allclose(T[:3, :3], target[:3, :3], atol=1e-6)


def test_pose_round_trip_near_a_half_turn():
    rng = np.random.default_rng(3)
    for _ in range(200):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = np.pi - rng.uniform(0, 1e-6)          # where rotation vectors flip sign
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(axis * angle).as_matrix()
        T[:3, 3] = rng.uniform(-1, 1, 3)
        p = matrix_to_pose6(T)
        assert np.linalg.norm(p[3:]) <= np.pi + 1e-9
        np.testing.assert_allclose(pose6_to_matrix(p), T, atol=1e-9)
    # r and -r of length pi are the same rotation: equal by pose_distance, not element-wise.
    a = np.array([0.1, 0.2, 0.3, np.pi, 0.0, 0.0])
    b = np.array([0.1, 0.2, 0.3, -np.pi, 0.0, 0.0])
    assert max(pose_distance(a, b)) < 1e-12


def test_flange_target_for_tool_composes_the_offset():
    rng = np.random.default_rng(4)
    flange_from_tool = pose6_to_matrix([0.01, -0.02, 0.16, 0.1, -0.2, 0.3])
    for _ in range(50):
        world_from_tool = pose6_to_matrix(np.r_[rng.uniform(-0.5, 0.5, 3), Rotation.random(random_state=rng).as_rotvec()])
        flange = flange_target_for_tool(world_from_tool, flange_from_tool)
        np.testing.assert_allclose(pose6_to_matrix(flange) @ flange_from_tool, world_from_tool, atol=1e-12)
        np.testing.assert_allclose(tool_from_flange_pose(flange, flange_from_tool), world_from_tool, atol=1e-12)
        np.testing.assert_allclose(invert(world_from_tool) @ world_from_tool, np.eye(4), atol=1e-12)
    # pose6 form of the offset, as in the cell file
    f2 = flange_target_for_tool(np.eye(4), [0, 0, 0.16, 0, 0, 0])
    np.testing.assert_allclose(f2, [0, 0, -0.16, 0, 0, 0], atol=1e-12)


def test_interpolation_is_straight_and_slerped():
    a = np.array([0.0, 0.3, 0.4, np.pi, 0.0, 0.0])
    b = np.array([0.1, 0.3, 0.2, 0.0, np.pi / 2, 0.0])
    path = interpolate_pose6(a, b, 11)
    assert max(pose_distance(path[0], a)) < 1e-12 and max(pose_distance(path[-1], b)) < 1e-12
    np.testing.assert_allclose(np.diff(path[:, :3], axis=0), np.tile((b[:3] - a[:3]) / 10, (10, 1)), atol=1e-12)
    angles = [pose_distance(path[i], path[i + 1])[1] for i in range(10)]
    np.testing.assert_allclose(angles, angles[0], atol=1e-9)


@pytest.mark.parametrize("bad, match", [([1, 2, 3], "shape"), ([0, 0, 0, 0, 0, np.nan], "NaN"),
                                        ("abc", "not a numeric")])
def test_bad_poses_are_clear_errors(bad, match):
    with pytest.raises(PoseError, match=match):
        as_pose6(bad)
