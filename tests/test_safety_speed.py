"""Speed changes of the planner's safety checks that must give the same answers: each new
path against the code it replaced (kept here as the reference), on random motions near
the cell's boxes and the tape, errors and their messages included."""
from __future__ import annotations

import numpy as np

from tapecell.cell.config import load_cell_config
from tapecell.cell.kinematics import fk, ik_nearest
from tapecell.cell.planner import REFERENCE_JOINTS, TAPE_CLEARANCE_M, GripperGeometry, _mm, check_tape_clear
from tapecell.cell.poses import invert
from tapecell.cell.safety import (CollisionError, Obstacle, SafetyLimits, _check_clear, _check_tool_clear)


def _answer(fn, *a) -> str:
    try:
        fn(*a)
        return "ok"
    except CollisionError as e:
        return str(e)


def _reference_tool_clear(limits, world_from_flange, shape, motion):
    """_check_tool_clear before the per-part matrix-product prefilter: every point of every
    sample whose tool sphere nears a box, by einsum."""
    centre = shape.points_flange.mean(axis=0)
    reach = float(np.max(np.linalg.norm(shape.points_flange - centre, axis=1) + shape.radii))
    centres = np.einsum("nij,j->ni", world_from_flange[:, :3, :3], centre) + world_from_flange[:, :3, 3]
    near = np.zeros(len(centres), bool)
    for ob in limits.obstacles:
        near |= ob.distance(centres) < reach + limits.clearance
    if not np.any(near):
        return
    T = world_from_flange[near]
    pts = np.einsum("nij,kj->nki", T[:, :3, :3], shape.points_flange) + T[:, None, :3, 3]
    _check_clear(limits, pts, shape.radii, [shape.parts[i] for i in shape.part_index], motion)


def _reference_tape_clear(q_start, q_target, tape_surface, gripper, tcp_from_flange, margin=TAPE_CLEARANCE_M):
    """check_tape_clear before the stacked prefilter: every sample one at a time."""
    qa, qb = np.asarray(q_start, float), np.asarray(q_target, float)
    n = int(np.ceil(np.max(np.abs(qb - qa)) / 0.01)) + 2
    boxes = gripper.finger_boxes_tcp()
    flange_from_tcp = invert(tcp_from_flange)
    centre = tape_surface.mean(axis=0)
    reach = float(np.max(np.linalg.norm(tape_surface - centre, axis=1)))
    near_at_start = None
    for s in np.linspace(0.0, 1.0, n):
        world_from_tcp = fk(qa + s * (qb - qa)) @ flange_from_tcp
        if near_at_start is not None and \
                np.linalg.norm(world_from_tcp[:3, 3] - centre) > reach + gripper.finger_length + 0.1:
            continue
        local = (tape_surface - world_from_tcp[:3, 3]) @ world_from_tcp[:3, :3]
        near = np.zeros((len(boxes), len(tape_surface)), bool)
        for i, (lo, hi) in enumerate(boxes):
            near[i] = np.all((local > lo - margin) & (local < hi + margin), axis=1)
        if near_at_start is None:
            near_at_start = near.any(axis=0)
            if np.any(near_at_start):
                return
            continue
        for i in range(len(boxes)):
            inside = near[i]
            if np.any(inside):
                part = "palm" if i == 2 else "finger"
                raise CollisionError(f"joint move: the open gripper's {part} would pass within "
                                     f"{margin * 1e3:.0f} mm of the estimated tape near "
                                     f"{_mm(tape_surface[np.argmax(inside)])} mm")


def test_box_distance_is_numpys_norm_bit_for_bit():
    rng = np.random.default_rng(0)
    ob = Obstacle("box", np.array([-0.1, 0.2, 0.0]), np.array([0.3, 0.5, 0.05]))
    for shape in ((7, 3), (5, 11, 3), (3,)):
        p = rng.uniform(-1, 1, shape)
        d = np.maximum(np.maximum(ob.lo - p, p - ob.hi), 0.0)
        assert np.array_equal(ob.distance(p), np.linalg.norm(d, axis=-1))


def test_tool_clear_answers_as_before_near_the_boxes():
    cfg = load_cell_config()
    limits = SafetyLimits.from_cell(cfg)
    shape = GripperGeometry.from_config(cfg.tools.gripper).shape()
    rng = np.random.default_rng(3)
    base = fk(REFERENCE_JOINTS)
    answers = []
    for trial in range(150):
        n = int(rng.integers(2, 40))
        T = np.repeat(base[None], n, axis=0)
        # down towards the part and the table, tilted a little: some pass, some come too near
        T[:, :3, 3] += np.linspace(0, 1, n)[:, None] * rng.uniform([-0.15, -0.15, -0.45], [0.15, 0.15, -0.1])
        angle = rng.uniform(-0.4, 0.4)
        c, s = np.cos(angle), np.sin(angle)
        T[:, :3, :3] = T[:, :3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        new = _answer(_check_tool_clear, limits, T, shape, "m")
        assert new == _answer(_reference_tool_clear, limits, T, shape, "m"), trial
        answers.append(new)
    assert 10 < sum(a != "ok" for a in answers) < 140       # both answers were exercised


def test_tape_clear_answers_as_before():
    cfg = load_cell_config()
    gripper = GripperGeometry.from_config(cfg.tools.gripper)
    tcp_from_flange = invert(gripper.flange_from_tcp)
    rng = np.random.default_rng(5)
    outcomes = []
    for trial in range(80):
        # a strip of tape below the reference pose's gripper, a joint move down to near it
        T = fk(REFERENCE_JOINTS) @ gripper.flange_from_tcp
        centre = T[:3, 3] + np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), -rng.uniform(0.02, 0.2)])
        u, v = np.meshgrid(np.linspace(-0.02, 0.02, 9), np.linspace(-0.01, 0.01, 5))
        tape = centre + np.c_[u.ravel(), v.ravel(), 0.2 * u.ravel() * rng.uniform(-1, 1)]
        goal = T.copy()
        goal[:3, 3] = centre + np.array([0.0, 0.0, rng.uniform(0.0, 0.08)]) + rng.uniform(-0.03, 0.03, 3)
        q_goal = ik_nearest(goal @ tcp_from_flange, REFERENCE_JOINTS)
        if q_goal is None:
            continue
        args = (REFERENCE_JOINTS, q_goal, tape, gripper, tcp_from_flange)
        new = _answer(check_tape_clear, *args)
        assert new == _answer(_reference_tape_clear, *args), trial
        outcomes.append(new == "ok")
    assert 5 < sum(outcomes) < len(outcomes) - 5     # clear and not clear both exercised


def test_joint_move_tool_paths_stacked_are_the_per_sample_products():
    """check_joint_move multiplies all samples' flange frames with the check points at once:
    the same numbers as one sample at a time, as it did."""
    from tapecell.cell.kinematics import dh_frames_many

    rng = np.random.default_rng(7)
    for _ in range(200):
        frames = dh_frames_many(rng.uniform(-6, 6, (int(rng.integers(1, 200)), 6)))
        pts = rng.normal(size=(int(rng.integers(1, 30)), 3)) * 0.1
        pts_h = np.c_[pts, np.ones(len(pts))].T
        per_sample = np.array([(F[-1] @ pts_h).T[:, :3] for F in frames])
        stacked = (frames[:, -1] @ pts_h).transpose(0, 2, 1)[:, :, :3]
        assert np.array_equal(per_sample, stacked)


def test_wrist_check_answers_as_without_the_stacked_axis_prefilter(monkeypatch):
    """The wrist's links near the part and the table: the same answer (and message) with
    the stacked axis test in front as with every candidate tested one at a time."""
    import tapecell.cell.safety as safety

    cfg = load_cell_config()
    limits = SafetyLimits.from_cell(cfg)
    rng = np.random.default_rng(11)
    paths = []
    for _ in range(120):
        a = REFERENCE_JOINTS + rng.uniform(-0.6, 0.6, 6)
        b = a + rng.uniform(-1.2, 1.2, 6)
        paths.append(a + np.linspace(0, 1, 25)[:, None] * (b - a))
    new = [_answer(safety.check_wrist_clear, limits, p, "m") for p in paths]
    monkeypatch.setattr(safety, "_drop_clear_axes", lambda *a, **k: None)
    old = [_answer(safety.check_wrist_clear, limits, p, "m") for p in paths]
    assert new == old
    assert 5 < sum(a != "ok" for a in new) < 115
