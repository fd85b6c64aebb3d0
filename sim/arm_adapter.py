"""The simulated UR5e (``sim.arm.SimArm``) behind the :class:`~cell.arm.Arm` interface.

Differences from the real arm, and why:

* Poses in and out are flange poses, as for every Arm: ``SimArm`` is driven with its
  ``"flange"`` tool, so the cell file's tool offset is composed by the caller exactly as
  on the real arm.
* The simulated moves run at the commanded speed with the acceleration implicit in its
  position servos; ``acceleration`` is validated (and checked by SafeArm) but not used.
  A linear path with a blend runs its legs back to back, settling only at the last pose:
  the servos' lag rounds the corners, as the blend radius does on a UR (its size is
  checked by SafeArm, not used); with blend 0 it settles at every pose.
* A move whose joints do not arrive (the arm blocked by contact) is what a real arm
  reports as a protective stop: the adapter raises :class:`ProtectiveStopError` and
  reports ``is_protective_stopped()`` True until :meth:`SimArmAdapter.clear_protective_stop`.
* The jaws close at the cell file's ``tools.gripper.close_speed`` (``SimArm.close_gripper``
  ramps them, as a real gripper closes).
* ``teleport=True`` places the arm exactly at each target (``SimArm.set_joints``) instead
  of simulating the motion: for rendering reference images at given joints (a simulated
  move settles within the cell file's ``joint_tolerance``, ~0.1 mm at the plate). Nothing
  collides on the way, so procedures such as calibration use the simulated motion.
* No one can push a simulated arm by hand, so ``freedrive`` raises :class:`ArmError`.
* "Connecting" binds to the simulation, which is always there.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from tapecell.cell.arm import Arm, ArmError, ProtectiveStopError
from tapecell.cell.poses import matrix_to_pose6, pose6_to_matrix


class SimArmAdapter(Arm):
    """``SimArmAdapter(sim_arm, teleport=False)``: teleport: set the joints instead of
    simulating moves (module docstring). ``gripper_opening`` [m] is the pad distance after
    the last gripper action (None before)."""

    def __init__(self, sim_arm: Any, teleport: bool = False) -> None:
        self.sim_arm = sim_arm
        self.teleport = bool(teleport)
        self.name = "simulated arm"
        self._connected = False
        self._protective = False
        self.gripper_opening: float | None = None

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _connect(self) -> None:
        self._connected = True

    def _disconnect(self) -> None:
        self._connected = False

    def _tcp_pose(self) -> np.ndarray:
        return matrix_to_pose6(self.sim_arm.tcp_pose("flange"))

    def _joints(self) -> np.ndarray:
        return self.sim_arm.joints()

    def _is_protective_stopped(self) -> bool:
        return self._protective

    def clear_protective_stop(self) -> None:
        """What the operator does on the pendant: clear the stop and hold where the arm is."""
        self._protective = False
        self._hold()

    def _guarded(self, move, what: str) -> None:
        from .arm import SimArmError, TargetNotReached
        from .ur5e import IKError

        if self._protective:
            raise ProtectiveStopError(f"{self.name} is in a protective stop")
        try:
            move()
        except IKError as e:
            raise ArmError(f"{self.name}: {what}: {e}") from None
        except TargetNotReached as e:
            self._protective = True
            self._hold()
            raise ProtectiveStopError(f"{self.name} stopped during {what}: {e}") from None
        except SimArmError as e:
            raise ArmError(f"{self.name}: {what}: {e}") from None

    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        world_from_flange = pose6_to_matrix(pose)
        if self.teleport:
            self._guarded(lambda: self.sim_arm.set_joints(self.sim_arm.ik(world_from_flange, "flange")),
                          "linear move")
        else:
            self._guarded(lambda: self.sim_arm.move_tcp(world_from_flange, speed=speed, tool="flange"),
                          "linear move")

    def _move_linear_path(self, poses: np.ndarray, speed: float, acceleration: float, blend: float) -> None:
        targets = [pose6_to_matrix(p) for p in poses]
        if self.teleport:
            def place() -> None:
                q = self.sim_arm.joints()
                for target in targets:        # pose by pose: the configuration moveL keeps
                    q = self.sim_arm.ik(target, "flange", q)
                self.sim_arm.set_joints(q)

            self._guarded(place, "linear path")
        else:
            self._guarded(lambda: self.sim_arm.move_tcp_path(targets, speed=speed, tool="flange", blend=blend > 0),
                          "linear path")

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        if self.teleport:
            self._guarded(lambda: self.sim_arm.set_joints(q), "joint move")
        else:
            self._guarded(lambda: self.sim_arm.move_joints(q, speed=speed), "joint move")

    def _hold(self) -> None:
        # Command the measured joints: the position servos then hold the arm still.
        cell = self.sim_arm.cell
        cell.data.ctrl[cell.arm_actuators] = self.sim_arm.joints()

    def _stop(self) -> None:
        self._hold()

    def _open_gripper(self) -> None:
        self.gripper_opening = float(self.sim_arm.open_gripper())

    def _close_gripper(self) -> None:
        self.gripper_opening = float(self.sim_arm.close_gripper())

    def _freedrive(self, enable: bool) -> None:
        raise ArmError(f"{self.name}: freedrive needs a real arm to push by hand")
