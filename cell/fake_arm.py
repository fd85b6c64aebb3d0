"""A test double of :class:`~cell.arm.Arm`: records every call, reaches poses instantly.

Kinematics are the UR5e's (closed form), so joints and flange pose stay consistent: a joint
move sets the pose by forward kinematics, a linear move sets the joints to the inverse
solution nearest the current ones (the configuration a ``moveL`` keeps). Used by tests and
for dry runs of a plan (``tapecell run`` without ``--execute``).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .arm import Arm, ArmError, ProtectiveStopError
from .kinematics import fk, ik_nearest
from .poses import matrix_to_pose6, pose6_to_matrix

HOME_JOINTS = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])   # the bundled cell file's home


class FakeArm(Arm):
    """calls: list of (method name, args tuple) in order, e.g.
    ``("move_linear", (pose6, speed, acceleration))`` or ``("move_linear_path", (poses (n, 6),
    speed, acceleration, blend))``. Set ``protective_stop_on`` to the
    index of a motion (0-based among moves) to have it end in a protective stop."""

    name = "fake arm"

    def __init__(self, q0: Any = HOME_JOINTS, protective_stop_on: int | None = None) -> None:
        self._q = np.asarray(q0, float).copy()
        self._connected = False
        self._protective = False
        self.gripper_closed = False
        self.freedrive_on = False
        self.protective_stop_on = protective_stop_on
        self.moves = 0
        self.calls: list[tuple[str, tuple]] = []

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _connect(self) -> None:
        self.calls.append(("connect", ()))
        self._connected = True

    def _disconnect(self) -> None:
        self.calls.append(("disconnect", ()))
        self._connected = False

    def _tcp_pose(self) -> np.ndarray:
        return matrix_to_pose6(fk(self._q))

    def _joints(self) -> np.ndarray:
        return self._q.copy()

    def _is_protective_stopped(self) -> bool:
        return self._protective

    def _begin_move(self) -> None:
        if self._protective:
            raise ProtectiveStopError(f"{self.name} is in a protective stop")
        if self.freedrive_on:
            raise ArmError(f"{self.name} is in freedrive; end it before moving")
        index, self.moves = self.moves, self.moves + 1
        if index == self.protective_stop_on:
            self._protective = True
            raise ProtectiveStopError(f"{self.name} went into a protective stop during move {index}")

    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        self.calls.append(("move_linear", (pose.copy(), speed, acceleration)))
        self._begin_move()
        q = ik_nearest(pose6_to_matrix(pose), self._q)
        if q is None:
            raise ArmError(f"{self.name}: pose {np.round(pose, 4).tolist()} is out of reach")
        self._q = q

    def _move_linear_path(self, poses: np.ndarray, speed: float, acceleration: float, blend: float) -> None:
        self.calls.append(("move_linear_path", (poses.copy(), speed, acceleration, blend)))
        self._begin_move()
        q = self._q
        for pose in poses:      # the configuration moveL keeps, pose after pose
            q = ik_nearest(pose6_to_matrix(pose), q)
            if q is None:
                raise ArmError(f"{self.name}: pose {np.round(pose, 4).tolist()} is out of reach")
        self._q = q

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        self.calls.append(("move_joints", (q.copy(), speed, acceleration)))
        self._begin_move()
        self._q = q.copy()

    def _stop(self) -> None:
        self.calls.append(("stop", ()))

    def _open_gripper(self) -> None:
        self.calls.append(("open_gripper", ()))
        self.gripper_closed = False

    def _close_gripper(self) -> None:
        self.calls.append(("close_gripper", ()))
        self.gripper_closed = True

    def _freedrive(self, enable: bool) -> None:
        self.calls.append(("freedrive", (enable,)))
        self.freedrive_on = enable

    def call_names(self) -> list[str]:
        """The names of the recorded calls, in order."""
        return [name for name, _ in self.calls]
