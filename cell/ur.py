"""The real UR5e through ur_rtde (``rtde_control``, ``rtde_receive``, ``rtde_io``).

ur_rtde is imported inside :meth:`URArm.connect`, so the simulator and the tests never need
a robot or the library. Facts this driver is built on (see dependencies.md):

* A host that accepts a TCP connection but never answers makes the ur_rtde constructors
  hang for ever while holding the GIL. So before constructing, :func:`probe_rtde` opens
  the RTDE port with a socket timeout and asks for the protocol version (the first packet
  of the RTDE handshake); only a controller that answers gets a constructor call.
* Connecting or reconnecting after a protective stop often needs a retry or two: both
  are retried a bounded number of times, each preceded by a probe.
* After ``servoL``/``speedL`` a ``moveL`` is ignored until ``servoStop``/``speedStop``: both
  are sent before every move.
* A motion that raises (or is interrupted, or returns False) is followed by ``stopL`` /
  ``stopJ`` in ``finally``.
* Every target is checked against the cell's :class:`~cell.safety.SafetyLimits` and the
  controller's own ``isPoseWithinSafetyLimits`` / ``isJointsWithinSafetyLimits`` before
  it is sent.
* The controller's TCP offset is set to zero on connect, so poses in and out are flange
  poses, as the :class:`~cell.arm.Arm` convention says.

Gripper: no Robotiq (or other) gripper binding ships with ur_rtde. This driver drives a
gripper wired to one digital output (a pneumatic valve, or an electric gripper's I/O
mode): ``rtde_io.setStandardDigitalOut(pin, level)`` (pins 0-7 in the control box) or
``setToolDigitalOut`` (pins 0-1 at the tool flange). ``gripper_close_level`` is the level
that closes it. A digital output has no feedback, so each action waits
``gripper_settle_s`` for the jaws to move.
"""
from __future__ import annotations

import socket
import struct
import time
from typing import Any, Callable

import numpy as np

from .arm import Arm, ArmError, ProtectiveStopError
from .safety import SafetyError, SafetyLimits, check_joint_move, check_linear_move, check_points_flange

RTDE_PORT = 30004
_RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
_RTDE_PROTOCOL_VERSION = 2


def probe_rtde(host: str, port: int = RTDE_PORT, timeout: float = 2.0) -> None:
    """Return when ``host:port`` answers the RTDE handshake within ``timeout`` s, else raise
    one :class:`ArmError` naming host, port and what went wrong."""
    where = f"robot at {host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except socket.timeout:
        raise ArmError(f"{where} did not accept a connection within {timeout:g} s "
                       "(wrong address, or the controller is off?)") from None
    except ConnectionRefusedError:
        raise ArmError(f"{where} refused the connection: nothing is listening "
                       "(controller off, or RTDE disabled?)") from None
    except OSError as e:
        raise ArmError(f"cannot reach {where}: {e.strerror or e}") from None
    with sock:
        deadline = time.monotonic() + timeout
        try:
            sock.sendall(struct.pack(">HBH", 5, _RTDE_REQUEST_PROTOCOL_VERSION, _RTDE_PROTOCOL_VERSION))
            header = _recv_exactly(sock, 3, deadline)
        except socket.timeout:
            raise ArmError(f"{where} accepted the connection but did not answer the RTDE handshake "
                           f"within {timeout:g} s (not a UR controller, or it is hung)") from None
        except OSError as e:
            raise ArmError(f"{where} failed during the RTDE handshake: {e.strerror or e}") from None
    if header is None:
        raise ArmError(f"{where} closed the connection without answering the RTDE handshake")
    _size, kind = struct.unpack(">HB", header)
    if kind != _RTDE_REQUEST_PROTOCOL_VERSION:
        raise ArmError(f"{where} answered with something other than RTDE (packet type {kind})")


def _recv_exactly(sock: socket.socket, n: int, deadline: float) -> bytes | None:
    data = b""
    while len(data) < n:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise socket.timeout()
        sock.settimeout(remaining)
        chunk = sock.recv(n - len(data))
        if not chunk:
            return None
        data += chunk
    return data


class URArm(Arm):
    """A UR arm (UR5e here) through ur_rtde.

    host, port: the controller's address and RTDE port (probed before ur_rtde connects;
    ur_rtde itself always uses 30004, so another port only makes sense for a forwarder).
    limits: the cell's safety limits, checked before every motion; flange_from_tool
    (4x4 or pose6) and extra_points_flange (N, 3) add tool points to that check.
    gripper_*: see the module docstring. probe_timeout_s: per probe. connect_attempts,
    reconnect_attempts, retry_delay_s: bounded retries. stop_deceleration: m/s^2 for
    ``stopL``; stop_joint_deceleration: rad/s^2 for ``stopJ``.
    """

    def __init__(self, host: str, port: int, limits: SafetyLimits, *, flange_from_tool: Any = None,
                 extra_points_flange: Any = None, gripper_output: int = 0, gripper_output_kind: str = "standard",
                 gripper_close_level: bool = True, gripper_settle_s: float = 0.5, probe_timeout_s: float = 2.0,
                 connect_attempts: int = 3, reconnect_attempts: int = 3, retry_delay_s: float = 1.0,
                 stop_deceleration: float = 2.0, stop_joint_deceleration: float = 2.0,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if not isinstance(limits, SafetyLimits):
            raise ArmError("the real arm needs the cell's SafetyLimits")
        if gripper_output_kind not in ("standard", "tool"):
            raise ArmError(f"gripper output kind must be 'standard' or 'tool', got '{gripper_output_kind}'")
        pins = range(8) if gripper_output_kind == "standard" else range(2)
        if gripper_output not in pins:
            raise ArmError(f"{gripper_output_kind} digital output {gripper_output} does not exist "
                           f"(pins {pins.start}-{pins.stop - 1})")
        if connect_attempts < 1 or reconnect_attempts < 1:
            raise ArmError("connect and reconnect attempts must be at least 1")
        self.host, self.port, self.limits = host, int(port), limits
        self.name = f"UR arm at {host}:{self.port}"
        self.points_flange = check_points_flange(flange_from_tool, extra_points_flange)
        self.gripper_output, self.gripper_output_kind = gripper_output, gripper_output_kind
        self.gripper_close_level, self.gripper_settle_s = bool(gripper_close_level), gripper_settle_s
        self.probe_timeout_s = probe_timeout_s
        self.connect_attempts, self.reconnect_attempts = connect_attempts, reconnect_attempts
        self.retry_delay_s = retry_delay_s
        self.stop_deceleration, self.stop_joint_deceleration = stop_deceleration, stop_joint_deceleration
        self._sleep = sleep
        self._control = self._receive = self._io = None
        self._last_motion = "linear"

    # -- connection ----------------------------------------------------------------
    @property
    def is_connected(self) -> bool:
        return self._control is not None

    def _connect(self) -> None:
        try:
            import rtde_control
            import rtde_io
            import rtde_receive
        except ImportError as e:
            raise ArmError(f"ur_rtde is not installed ({e}); pip install ur-rtde") from None
        last: Exception | None = None
        for attempt in range(self.connect_attempts):
            if attempt:
                self._sleep(self.retry_delay_s)
            try:
                probe_rtde(self.host, self.port, self.probe_timeout_s)
                self._receive = rtde_receive.RTDEReceiveInterface(self.host)
                self._control = rtde_control.RTDEControlInterface(self.host)
                self._io = rtde_io.RTDEIOInterface(self.host)
                break
            except (ArmError, RuntimeError) as e:
                last = e
                self._close_all()
        else:
            raise ArmError(f"cannot connect to the {self.name} after {self.connect_attempts} attempt(s): {last}")
        # Our poses are flange poses: a TCP offset left on the controller would shift them.
        if not self._control.setTcp([0.0] * 6):
            self._close_all()
            raise ArmError(f"{self.name} refused to set a zero TCP offset")

    def _disconnect(self) -> None:
        self._close_all()

    def _close_all(self) -> None:
        for iface in (self._control, self._receive, self._io):
            if iface is not None:
                try:
                    iface.disconnect()
                except RuntimeError:
                    pass  # already gone; nothing else to release
        self._control = self._receive = self._io = None

    def _ensure_link(self) -> None:
        """Reconnect a dropped RTDE link, a bounded number of times, probing first."""
        c, r = self._control, self._receive
        for attempt in range(self.reconnect_attempts + 1):
            if c.isConnected() and r.isConnected():
                return
            if attempt == self.reconnect_attempts:
                break
            if attempt:
                self._sleep(self.retry_delay_s)
            try:
                probe_rtde(self.host, self.port, self.probe_timeout_s)
                if not r.isConnected():
                    r.reconnect()
                if not c.isConnected():
                    c.reconnect()
            except (ArmError, RuntimeError):
                continue
        raise ArmError(f"lost the connection to the {self.name}; {self.reconnect_attempts} "
                       "reconnection attempt(s) failed")

    # -- state -----------------------------------------------------------------------
    def _tcp_pose(self) -> list[float]:
        self._ensure_link()
        return self._receive.getActualTCPPose()

    def _joints(self) -> list[float]:
        self._ensure_link()
        return self._receive.getActualQ()

    def _is_protective_stopped(self) -> bool:
        self._ensure_link()
        return bool(self._receive.isProtectiveStopped())

    def _refuse_if_protective_stopped(self) -> None:
        if self._receive.isProtectiveStopped():
            raise ProtectiveStopError(f"{self.name} is in a protective stop; clear it on the teach "
                                      "pendant before moving")

    # -- motion ----------------------------------------------------------------------
    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        self._ensure_link()
        self._refuse_if_protective_stopped()
        check_linear_move(self.limits, self._receive.getActualTCPPose(), pose, speed, acceleration,
                          self.points_flange)
        target = [float(v) for v in pose]
        c = self._control
        if not c.isPoseWithinSafetyLimits(target):
            raise SafetyError(f"{self.name}: the controller says pose {_fmt(target)} is outside its "
                              "safety limits or unreachable")
        c.servoStop()
        c.speedStop()
        self._last_motion = "linear"
        self._run(lambda: c.moveL(target, speed, acceleration), self._stop_linear, f"moveL to {_fmt(target)}")

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        self._ensure_link()
        self._refuse_if_protective_stopped()
        check_joint_move(self.limits, self._receive.getActualQ(), q, speed, acceleration, self.points_flange)
        target = [float(v) for v in q]
        c = self._control
        if not c.isJointsWithinSafetyLimits(target):
            raise SafetyError(f"{self.name}: the controller says joints {_fmt(target)} are outside its "
                              "safety limits")
        c.servoStop()
        c.speedStop()
        self._last_motion = "joint"
        self._run(lambda: c.moveJ(target, speed, acceleration), self._stop_joint, f"moveJ to {_fmt(target)}")

    def _run(self, move: Callable[[], bool], stop: Callable[[], None], what: str) -> None:
        """Run a blocking move; on any exception, interrupt or failure, stop the arm."""
        try:
            ok = bool(move())
        except BaseException:
            try:
                stop()
            except RuntimeError:
                pass   # the link is gone: the move's own error is what the caller needs
            raise
        if not ok:
            stop()
            if self._receive.isProtectiveStopped():
                raise ProtectiveStopError(f"{self.name} went into a protective stop during {what}")
            raise ArmError(f"{self.name}: {what} failed (the controller rejected or aborted it)")

    def _stop_linear(self) -> None:
        self._control.stopL(self.stop_deceleration)

    def _stop_joint(self) -> None:
        self._control.stopJ(self.stop_joint_deceleration)

    def _stop(self) -> None:
        (self._stop_joint if self._last_motion == "joint" else self._stop_linear)()

    # -- gripper and freedrive ------------------------------------------------------
    def _open_gripper(self) -> None:
        self._set_gripper(closed=False)

    def _close_gripper(self) -> None:
        self._set_gripper(closed=True)

    def _set_gripper(self, closed: bool) -> None:
        self._ensure_link()
        level = self.gripper_close_level if closed else not self.gripper_close_level
        setter = (self._io.setStandardDigitalOut if self.gripper_output_kind == "standard"
                  else self._io.setToolDigitalOut)
        if not setter(self.gripper_output, level):
            raise ArmError(f"{self.name} refused to set {self.gripper_output_kind} digital output "
                           f"{self.gripper_output} (gripper {'close' if closed else 'open'})")
        self._sleep(self.gripper_settle_s)

    def _freedrive(self, enable: bool) -> None:
        self._ensure_link()
        ok = self._control.teachMode() if enable else self._control.endTeachMode()
        if not ok:
            raise ArmError(f"{self.name} refused to {'start' if enable else 'end'} freedrive")


def _fmt(v: list[float]) -> str:
    return "[" + ", ".join(f"{x:.4f}" for x in v) + "]"
