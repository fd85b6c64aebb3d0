"""The simulated UR5e respects the real arm's joint torque limits (150 N m for the three
large joints, 28 N m for the wrist), gravity compensation included: it holds its rated
payload stretched out, and sags, failing the move, under four times that."""
from __future__ import annotations

import numpy as np
import pytest

from tapecell.cell.config import load_cell_config
from tapecell.cell.kinematics import JOINT_NAMES
from tapecell.sim.arm import SimArm, SimArmError
from tapecell.sim.cell import SimCell

LIMITS_NM = np.array([150.0, 150.0, 150.0, 28.0, 28.0, 28.0])
STRETCHED = [0.0, 0.0, 0.0, -1.5708, 0.0, 0.0]      # the arm horizontal, fully out (~0.9 m)


def test_the_model_has_the_ur5e_torque_limits():
    with SimCell(load_cell_config(), 0) as cell:
        m = cell.model
        ids = [m.joint(n).id for n in JOINT_NAMES]
        assert np.allclose(m.jnt_actfrcrange[ids], np.c_[-LIMITS_NM, LIMITS_NM])
        assert m.jnt_actfrclimited[ids].all() and m.jnt_actgravcomp[ids].all()


def _stretch_out(payload_kg: float) -> tuple[np.ndarray, str | None]:
    """Peak joint torques [N m] moving to STRETCHED with ``payload_kg`` at the flange, and
    the error when the move failed."""
    with SimCell(load_cell_config(), 0, tool="gripper") as cell:
        m, d = cell.model, cell.data
        m.body_mass[m.body("flange").id] += payload_kg
        arm = SimArm(cell, tool="gripper")
        peak = np.zeros(6)
        step = cell.step

        def recording_step(n: int = 1, sync: bool = True) -> None:
            for _ in range(n):
                step(1, sync=sync)
                np.maximum(peak, np.abs(d.qfrc_actuator[cell.arm_dofs]), out=peak)
        cell.step = recording_step
        try:
            arm.move_joints(STRETCHED, settle_s=2.0)
        except SimArmError as e:
            return peak, str(e)
    return peak, None


@pytest.mark.parametrize("payload_kg, reaches", [(4.0, True), (20.0, False)])
def test_payload_within_the_limits_is_held_and_beyond_them_is_not(payload_kg, reaches):
    peak, error = _stretch_out(payload_kg)
    assert np.all(peak <= LIMITS_NM + 1e-6), peak                # never more torque than the real arm has
    if reaches:
        assert error is None and peak[1] > 50.0                  # the shoulder really carries the load
    else:
        assert error is not None and "did not reach" in error
        assert peak[1] == pytest.approx(150.0)                   # the shoulder saturated
