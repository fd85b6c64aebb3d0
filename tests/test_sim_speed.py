"""Speed changes of the simulated arm that must not change a number: the streamed targets
of a move, the stepping loop, the numerical IK's memo of its last Jacobians."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell import sim  # noqa: F401  (sets MUJOCO_GL=egl before mujoco is imported)

from tapecell.cell.kinematics import fk


@pytest.fixture(scope="module")
def cell():
    from tapecell.cell.config import load_cell_config
    from tapecell.sim.cell import SimCell

    c = SimCell(load_cell_config(), seed=3, n_cameras=2, tool="gripper")
    yield c
    c.close()


def test_ramp_is_the_per_step_formula_bit_for_bit():
    from tapecell.sim.arm import _WAYPOINT_FRACTIONS, _WAYPOINT_STEPS, _ramp

    rng = np.random.default_rng(1)
    for n in (1, 2, 7, 10, 333, 2500):
        a, b = rng.uniform(-3, 3, 6), rng.uniform(-3, 3, 6)
        rows = _ramp(a, b, n)
        assert rows.shape == (n, 6)
        for i in range(1, n + 1):
            assert np.array_equal(rows[i - 1], a + (b - a) * (i / n))
    a, b = rng.uniform(-3, 3, 6), rng.uniform(-3, 3, 6)
    rows = a + (b - a) * _WAYPOINT_FRACTIONS
    for i in range(1, _WAYPOINT_STEPS + 1):
        assert np.array_equal(rows[i - 1], a + (b - a) * (i / _WAYPOINT_STEPS))


def test_views_are_the_indexed_entries(cell):
    d = cell.data
    assert np.shares_memory(cell.arm_ctrl, d.ctrl) and np.shares_memory(cell.arm_qpos, d.qpos)
    assert np.array_equal(cell.arm_qpos, d.qpos[cell.arm_qadr])
    assert np.array_equal(cell.arm_qvel, d.qvel[cell.arm_dofs])
    assert np.array_equal(cell.arm_ctrl, d.ctrl[cell.arm_actuators])
    assert np.array_equal(cell.finger_qpos, d.qpos[cell.finger_qadr])
    assert np.array_equal(cell.finger_ctrl, d.ctrl[cell.finger_actuators])


def test_step_targets_is_stepping_row_by_row(cell):
    """The same state, bit for bit, as writing the targets and stepping one at a time; the
    step hook runs after every step."""
    from tapecell.sim.arm import _ramp

    cell.reset(3)
    cell.set_tape_sleep(True)
    q0 = cell.arm_ctrl.copy()
    targets = _ramp(q0, q0 + np.array([0.2, -0.1, 0.1, 0.05, 0.1, -0.2]), 400)
    calls = []
    cell.step_hook = lambda: calls.append(float(cell.data.time))
    try:
        cell.step_targets(cell.arm_ctrl, targets)
        fast = (cell.data.qpos.copy(), cell.data.qvel.copy(), cell.data.qacc_warmstart.copy(), cell.data.time)
        cell.reset(3)
        for row in targets:
            cell.data.ctrl[cell.arm_actuators] = row
            cell.step(1, sync=False)
        slow = (cell.data.qpos.copy(), cell.data.qvel.copy(), cell.data.qacc_warmstart.copy(), cell.data.time)
    finally:
        cell.step_hook = None
        cell.set_tape_sleep(False)
    assert len(calls) == 2 * len(targets)
    for f, s in zip(fast, slow):
        assert np.array_equal(f, s)


def test_step_targets_reports_a_warning(cell):
    from tapecell.sim.cell import SimError

    cell.reset(3)
    try:
        cell.data.warning[0].number = 1        # as MuJoCo counts one
        with pytest.raises(SimError, match="warned"):
            cell.step_targets(cell.arm_ctrl, cell.arm_ctrl.copy()[None])
    finally:
        cell.data.warning[0].number = 0


def test_ik_memo_gives_the_same_solutions():
    """Solving along a line from the last solution, with and without the memo of the last
    Jacobians: the same joints bit for bit, and the memo answers some evaluations."""
    from tapecell.sim import ur5e

    q = np.array([0.1, -1.2, 1.3, -1.6, -1.5, 0.2])
    tool = np.eye(4)
    tool[2, 3] = 0.15
    start = fk(q) @ tool

    def solve_line(memo: bool) -> list[np.ndarray]:
        saved = ur5e._jacobian_memo
        if not memo:
            ur5e._jacobian_memo = ur5e.jacobian
        ur5e._JACOBIAN_MEMO.clear()
        try:
            out, qk = [], q
            for k in range(1, 40):
                T = start.copy()
                T[:3, 3] += k * np.array([0.0005, -0.0003, 0.0004])
                qk = ur5e.ik(T, qk, tool).q
                out.append(qk)
            return out
        finally:
            ur5e._jacobian_memo = saved

    ur5e.jacobian_memo_stats[:] = [0, 0]
    with_memo = solve_line(True)
    assert ur5e.jacobian_memo_stats[0] >= 30
    for a, b in zip(with_memo, solve_line(False)):
        assert np.array_equal(a, b)


def test_tool_offsets_are_the_cell_files_and_read_only(cell):
    from tapecell.sim.arm import SimArm

    arm = SimArm(cell, tool="gripper")
    for tool in ("flange", "gripper", "needle", "plate"):
        T = arm.flange_from_tcp(tool)
        assert np.array_equal(T, cell.config.tools.flange_from_tcp(tool))
        T[0, 3] += 1.0                               # a caller's copy: the cache is untouched
        assert np.array_equal(arm.flange_from_tcp(tool), cell.config.tools.flange_from_tcp(tool))
        with pytest.raises(ValueError):
            arm._flange_from_tcp(tool)[0, 3] = 1.0


def test_an_open_gripper_adds_no_constraint_while_the_tape_sleeps(cell):
    """The fingers' stops lie past the open command (``scene.FINGER_STOP_M``): an open finger
    rests on its servo, so a step of the arm's moves with the tape asleep has no constraint
    row at all (a joint-limit row there doubled such a step's cost). The plate tape's
    model solves its constraints with dense Jacobians (faster with the pads on the tape)."""
    import mujoco

    from tapecell.sim.arm import SimArm, _ramp
    from tapecell.sim.scene import FINGER_STOP_M

    m = cell.model
    assert m.opt.jacobian == mujoco.mjtJacobian.mjJAC_DENSE
    open_half = cell.config.tools.gripper.max_opening / 2
    for j in cell.finger_qadr:
        assert m.jnt_range[list(m.jnt_qposadr).index(j), 1] == pytest.approx(open_half + FINGER_STOP_M)
    cell.reset(3)
    SimArm(cell).open_gripper()
    cell.set_tape_sleep(True)
    rows = []
    cell.step_hook = lambda: rows.append((cell.data.nefc, cell.data.ntree_awake < m.ntree))
    try:
        q0 = cell.arm_ctrl.copy()
        cell.step_targets(cell.arm_ctrl, _ramp(q0, q0 + np.array([0.1, -0.05, 0.05, 0.0, 0.05, -0.1]), 300))
    finally:
        cell.step_hook = None
        cell.set_tape_sleep(False)
    asleep = [n for n, sleeping in rows if sleeping]
    assert len(asleep) > 200                 # the tape did fall asleep
    assert max(asleep) == 0
    assert np.allclose(cell.finger_qpos, open_half, atol=2e-4)
