"""One small interface for every arm: the real UR5e, the simulated one and a test double.

Convention: every pose the interface takes or reports is the FLANGE pose
``[x, y, z, rx, ry, rz]`` (m, rotation vector rad) in the robot's base frame (= world),
i.e. what ur_rtde reports with a zero TCP offset. Tool offsets (``flange_from_tool`` in
the cell file) are composed by callers with :mod:`cell.poses`. Joints are (6,) rad.

The public methods validate their arguments and check the connection, then call the
implementation's ``_method``; so no implementation can skip either. Motions block until
the arm is there (or raise).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from tapecell.estimator.errors import HardwareError, TapecellError


class ArmError(HardwareError):
    """The arm cannot be reached, refused a command, or failed during a motion (exit 3)."""


class ArmNotConnectedError(ArmError):
    """A command was given to an arm that is not connected."""


class ProtectiveStopError(ArmError):
    """The arm is (or went) into a protective stop; it must be cleared on the pendant."""


def _vector6(value: Any, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ArmError(f"{what} is not numeric") from None
    if arr.shape != (6,):
        raise ArmError(f"{what} has shape {list(arr.shape)}, expected 6 numbers")
    if not np.all(np.isfinite(arr)):
        raise ArmError(f"{what} holds NaN or infinite numbers")
    return arr


def _positive(value: Any, what: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ArmError(f"{what} must be a positive number, got {value}")
    return v


class Arm(ABC):
    """An arm with a gripper. Use as a context manager::

        with URArm(host, limits=...) as arm:
            arm.move_linear(pose6, speed=0.1, acceleration=0.5)

    Leaving the block stops the arm if an exception escaped, then disconnects.
    """

    name: str = "arm"

    # -- connection ----------------------------------------------------------------
    @property
    @abstractmethod
    def is_connected(self) -> bool:
        """True while commands can be sent."""

    def connect(self) -> None:
        """Connect (idempotent). Raises :class:`ArmError` when the arm cannot be reached."""
        if not self.is_connected:
            self._connect()

    def disconnect(self) -> None:
        """Disconnect (idempotent; safe to call when never connected)."""
        if self.is_connected:
            self._disconnect()

    def __enter__(self) -> "Arm":
        self.connect()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is not None and self.is_connected:
                try:
                    self._stop()
                except (TapecellError, RuntimeError):
                    pass   # keep the error that ended the block; it says more
        finally:
            self.disconnect()

    # -- state -----------------------------------------------------------------------
    def tcp_pose(self) -> np.ndarray:
        """(6,) flange pose [x, y, z, rx, ry, rz] in the base frame [m, rad]."""
        self._require_connected()
        return _vector6(self._tcp_pose(), f"{self.name} reported TCP pose")

    def joints(self) -> np.ndarray:
        """(6,) joint angles [rad]."""
        self._require_connected()
        return _vector6(self._joints(), f"{self.name} reported joints")

    def is_protective_stopped(self) -> bool:
        self._require_connected()
        return bool(self._is_protective_stopped())

    # -- motion ----------------------------------------------------------------------
    def move_linear(self, pose: Any, speed: float, acceleration: float) -> None:
        """Straight line of the flange to ``pose`` (6,) at ``speed`` m/s, ``acceleration`` m/s^2."""
        target = _vector6(pose, "target pose")
        speed = _positive(speed, "speed")
        acceleration = _positive(acceleration, "acceleration")
        self._require_connected()
        self._move_linear(target, speed, acceleration)

    def move_linear_path(self, poses: Any, speed: float, acceleration: float, blend: float) -> None:
        """Straight lines of the flange through ``poses`` (n, 6) in order, without stopping at
        the intermediate ones: each corner is rounded within ``blend`` m of its pose (a UR's
        blend radius; 0 stops at every pose), the last pose is reached exactly. A blend of
        half a leg or more would overlap the next: :class:`~cell.safety.SafeArm` and the real
        arm refuse it (:func:`~cell.safety.check_blends`)."""
        try:
            rows = np.asarray(poses, dtype=float)
        except (TypeError, ValueError):
            raise ArmError("path poses are not numeric") from None
        if rows.ndim != 2 or rows.shape[1] != 6 or len(rows) == 0:
            raise ArmError(f"path poses have shape {list(rows.shape)}, expected (n, 6) with n >= 1")
        targets = np.stack([_vector6(r, f"path pose {i + 1}") for i, r in enumerate(rows)])
        speed = _positive(speed, "speed")
        acceleration = _positive(acceleration, "acceleration")
        blend = float(blend)
        if not np.isfinite(blend) or blend < 0:
            raise ArmError(f"blend radius must be zero or positive, got {blend}")
        self._require_connected()
        self._move_linear_path(targets, speed, acceleration, blend)

    def move_joints(self, q: Any, speed: float, acceleration: float) -> None:
        """Joint-space move to ``q`` (6,) rad at ``speed`` rad/s, ``acceleration`` rad/s^2."""
        target = _vector6(q, "target joints")
        speed = _positive(speed, "joint speed")
        acceleration = _positive(acceleration, "joint acceleration")
        self._require_connected()
        self._move_joints(target, speed, acceleration)

    def stop(self) -> None:
        """Decelerate to rest."""
        self._require_connected()
        self._stop()

    def open_gripper(self) -> None:
        self._require_connected()
        self._open_gripper()

    def close_gripper(self) -> None:
        self._require_connected()
        self._close_gripper()

    def freedrive(self, enable: bool) -> None:
        """Let the arm be moved by hand (probing) or end it."""
        self._require_connected()
        self._freedrive(bool(enable))

    def _require_connected(self) -> None:
        if not self.is_connected:
            raise ArmNotConnectedError(f"{self.name} is not connected (call connect() or use 'with')")

    # -- what an implementation provides ---------------------------------------------
    @abstractmethod
    def _connect(self) -> None: ...

    @abstractmethod
    def _disconnect(self) -> None: ...

    @abstractmethod
    def _tcp_pose(self) -> Any: ...

    @abstractmethod
    def _joints(self) -> Any: ...

    @abstractmethod
    def _is_protective_stopped(self) -> bool: ...

    @abstractmethod
    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None: ...

    def _move_linear_path(self, poses: np.ndarray, speed: float, acceleration: float, blend: float) -> None:
        """Without blending: a linear move to each pose in turn (``blend`` unused). Every arm
        here overrides it; an arm added later that cannot blend still runs a path safely."""
        for pose in poses:
            self._move_linear(pose, speed, acceleration)

    @abstractmethod
    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None: ...

    @abstractmethod
    def _stop(self) -> None: ...

    @abstractmethod
    def _open_gripper(self) -> None: ...

    @abstractmethod
    def _close_gripper(self) -> None: ...

    @abstractmethod
    def _freedrive(self, enable: bool) -> None: ...
