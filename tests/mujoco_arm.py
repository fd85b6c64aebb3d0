"""The UR5e of the MuJoCo scene on its own, for checking kinematics against the model."""
from __future__ import annotations

import numpy as np

from tapecell import sim  # noqa: F401  (headless GL before mujoco)
import mujoco
from tapecell.cell.config import load_cell_config
from tapecell.sim.scene import build_spec
from tapecell.cell.kinematics import JOINT_NAMES


class MujocoArm:
    """The compiled cell model; ``flange(q)`` is world_from_flange (4x4) at joints q [rad]."""

    def __init__(self) -> None:
        self.model = build_spec(load_cell_config(), 2).compile()
        self.data = mujoco.MjData(self.model)
        self.qadr = [self.model.jnt_qposadr[self.model.joint(n).id] for n in JOINT_NAMES]
        self.flange_id = self.model.body("flange").id

    def flange(self, q: np.ndarray) -> np.ndarray:
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self.flange_id].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self.flange_id]
        return T
