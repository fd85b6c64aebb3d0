"""The real UR5e through ur_rtde (``rtde_control``, ``rtde_receive``, ``rtde_io``).

ur_rtde runs behind a :mod:`cell.ur_link` link (a child process by default), so the
simulator and the tests never need a robot or the library. Facts this driver is built on
(see dependencies.md):

* A host that accepts a TCP connection but never answers makes the ur_rtde constructors
  hang for ever while holding the GIL. So before constructing, :func:`probe_rtde` opens
  the RTDE port with a socket timeout and asks for the protocol version (the first packet
  of the RTDE handshake), and the constructors run in the link's child process with a
  deadline.
* Every call has a deadline: connecting ``connect_timeout_s``, every read, check and I/O
  call ``call_timeout_s``, a move its expected duration (distance / speed + speed /
  acceleration) plus ``move_margin_s``. Past a deadline, or when the link dies, the arm
  is sent a stop on channels of its own (:func:`send_stop`: a URScript ``stopj`` on the
  secondary interface and the dashboard server's ``stop``, each with a socket timeout),
  the link is killed (which closes every connection), and one :class:`RobotSilent` is
  raised: ``tapecell`` exits with 3 well within 15 s of the silence.
* An error ur_rtde raises (a dropped RTDE connection) is an :class:`ArmError` (exit 3),
  after the arm was told to stop.
* Connecting or reconnecting after a protective stop often needs a retry or two: both
  are retried a bounded number of times, each preceded by a probe.
* A path (the lift) is one ``moveL(path)`` call, rows ``[x, y, z, rx, ry, rz, speed,
  acceleration, blend]`` with the last blend 0, so the arm does not stop between its
  poses; every pose is checked as a single move's target is. ur_rtde runs a path as a
  script of its own: it stops its control script, uploads one with the path injected and
  waits (without a limit of its own) for it to run before the move starts, so a path's
  deadline has :data:`PATH_SCRIPT_S` more than a move's.
* After ``servoL``/``speedL`` a ``moveL`` is ignored until ``servoStop``/``speedStop``: both
  are sent before every move.
* A motion that raises (or is interrupted, or returns False) is followed by ``stopL`` /
  ``stopJ``.
* Every target is checked against the cell's :class:`~cell.safety.SafetyLimits` and the
  controller's own ``isPoseWithinSafetyLimits`` / ``isJointsWithinSafetyLimits`` before
  it is sent.
* The planner's kinematics (the UR5e's nominal DH model, :mod:`cell.kinematics`) are
  checked against the controller's own before anything is sent: on connecting and before
  each joint move ``getForwardKinematics`` of the target, before each linear move
  ``getInverseKinematics`` of the target. A real UR's factory calibration moves the tool
  2-3 mm from the nominal model; more than :data:`KINEMATICS_TOLERANCE_M` /
  :data:`KINEMATICS_TOLERANCE_RAD` (or another joint configuration) is refused with a
  :class:`KinematicsMismatch`. :meth:`URArm.ik` is the controller's inverse kinematics, for
  planning in the controller's kinematics while connected.
* The controller's TCP offset is set to zero on connect, so poses in and out are flange
  poses, as the :class:`~cell.arm.Arm` convention says.

Gripper: no Robotiq (or other) gripper binding ships with ur_rtde. The gripper is wired to
digital outputs as the cell file's ``[robot.gripper]`` says (:class:`~cell.config.GripperIOSection`):
one output that closes it (and, at the other level, opens it), or one output to close and
another to open (a double-acting valve), ``rtde_io.setStandardDigitalOut`` (control box,
pins 0-7) or ``setToolDigitalOut`` (tool flange, pins 0-1); each action waits the
configured time for the jaws, and an optional digital input confirms that they closed.
"""
from __future__ import annotations

import socket
import struct
import time
from typing import Any, Callable

import numpy as np

from tapecell.estimator.errors import TapecellError

from .arm import Arm, ArmError, ProtectiveStopError
from .kinematics import fk, ik_nearest
from .poses import matrix_to_pose6, pose6_to_matrix, rotation_angle_between
from .safety import (SafetyError, SafetyLimits, ToolShape, check_joint_move, check_linear_move, check_linear_path,
                     check_points_flange)
from .ur_link import LinkCallError, LinkLost, LinkTimeout, ProcessLink

RTDE_PORT = 30004
_RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
_RTDE_PROTOCOL_VERSION = 2

KINEMATICS_TOLERANCE_M = 0.005
"""Largest tool position difference [m] between the planner's nominal UR5e model and the
controller's calibrated kinematics (a real UR's calibration accounts for 2-3 mm)."""
KINEMATICS_TOLERANCE_RAD = np.radians(0.5)
"""Largest tool rotation difference [rad] between the two models."""
SAME_BRANCH_RAD = 0.1
"""The controller's inverse kinematics must land within this of the planner's on every joint."""
TOOL_REACH_M = 0.2
"""Lever arm [m] used to turn a flange rotation into a path length for a move's deadline."""
PATH_SCRIPT_S = 2.0
"""Allowance [s] in a ``moveL(path)``'s deadline for ur_rtde's script upload before the path
starts (module docstring; a few hundred ms on an idle controller)."""

LINK_FACTORY: Callable[[], Any] = ProcessLink
"""Makes the link a URArm talks through (tests with in-process stand-ins use ThreadLink)."""


class RobotSilent(ArmError):
    """The robot did not answer within a deadline, or the link to it died."""


class KinematicsMismatch(ArmError):
    """The controller's kinematics disagree with the planner's beyond the tolerance."""


class ArmConfigError(TapecellError):
    """The arm's driver was given settings that cannot work (bad input: exit 2)."""


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


def send_stop(host: str, dashboard_port: int = 29999, script_port: int = 30002, timeout: float = 1.0) -> str:
    """Best effort, bounded by about ``2 * timeout`` s per channel: tell the controller to
    stop on channels that do not depend on the RTDE link, a URScript ``stopj(2.0)`` on the
    secondary interface (it replaces the running program, which decelerates the arm) and
    the dashboard server's ``stop``. Returns what was done, for the error line."""
    sent, failed = [], []
    try:
        with socket.create_connection((host, script_port), timeout=timeout) as s:
            s.sendall(b"stopj(2.0)\n")
        sent.append("URScript stopj")
    except OSError as e:
        failed.append(f"URScript port {script_port}: {e.strerror or type(e).__name__}")
    try:
        with socket.create_connection((host, dashboard_port), timeout=timeout) as s:
            s.settimeout(timeout)
            try:
                s.recv(256)          # the dashboard's greeting
            except socket.timeout:
                pass
            s.sendall(b"stop\n")
        sent.append("dashboard stop")
    except OSError as e:
        failed.append(f"dashboard port {dashboard_port}: {e.strerror or type(e).__name__}")
    note = f"sent {' and '.join(sent)}" if sent else "could not send a stop"
    return note + (f" (failed: {'; '.join(failed)})" if failed else "")


class URArm(Arm):
    """A UR arm (UR5e here) through ur_rtde.

    host, port: the controller's address and RTDE port (probed before ur_rtde connects;
    ur_rtde itself always uses 30004, so another port only makes sense for a forwarder).
    limits: the cell's safety limits, checked before every motion; flange_from_tool
    (4x4 or pose6) and extra_points_flange (N, 3) add tool points to that check.
    gripper: the cell file's ``[robot.gripper]`` (:class:`~cell.config.GripperIOSection`;
    default: output 0 closes). probe_timeout_s: per probe. connect_timeout_s,
    call_timeout_s, move_margin_s: the deadlines (module docstring). connect_attempts,
    reconnect_attempts, retry_delay_s: bounded retries. stop_deceleration: m/s^2 for
    ``stopL``; stop_joint_deceleration: rad/s^2 for ``stopJ``. dashboard_port, script_port:
    where :func:`send_stop` goes. link: a :mod:`cell.ur_link` link (default
    :data:`LINK_FACTORY`). check_kinematics: compare with the controller's kinematics.
    """

    def __init__(self, host: str, port: int, limits: SafetyLimits, *, flange_from_tool: Any = None,
                 extra_points_flange: Any = None, gripper: Any = None, probe_timeout_s: float = 2.0,
                 connect_timeout_s: float = 10.0, call_timeout_s: float = 2.0, move_margin_s: float = 2.0,
                 connect_attempts: int = 3, reconnect_attempts: int = 3, retry_delay_s: float = 1.0,
                 stop_deceleration: float = 2.0, stop_joint_deceleration: float = 2.0,
                 dashboard_port: int = 29999, script_port: int = 30002, link: Any = None,
                 check_kinematics: bool = True, sleep: Callable[[float], None] = time.sleep,
                 shape: ToolShape | None = None) -> None:
        from .config import GripperIOSection

        if not isinstance(limits, SafetyLimits):
            raise ArmConfigError("the real arm needs the cell's SafetyLimits")
        g = gripper if gripper is not None else GripperIOSection()
        if g.output_kind not in ("standard", "tool"):
            raise ArmConfigError(f"gripper output kind must be 'standard' or 'tool', got '{g.output_kind}'")
        pins = range(8) if g.output_kind == "standard" else range(2)
        for what, pin in (("close", g.close_output), ("open", g.open_output)):
            if not (pin in pins or (what == "open" and pin == -1)):
                raise ArmConfigError(f"gripper {what} output: {g.output_kind} digital output {pin} does not exist "
                                     f"(pins {pins.start}-{pins.stop - 1})")
        if connect_attempts < 1 or reconnect_attempts < 1:
            raise ArmConfigError("connect and reconnect attempts must be at least 1")
        self.host, self.port, self.limits = host, int(port), limits
        self.name = f"UR arm at {host}:{self.port}"
        self.points_flange = check_points_flange(flange_from_tool, extra_points_flange)
        self.shape = shape
        self.gripper = g
        self.probe_timeout_s = probe_timeout_s
        self.connect_timeout_s, self.call_timeout_s = connect_timeout_s, call_timeout_s
        self.move_margin_s = move_margin_s
        self.connect_attempts, self.reconnect_attempts = connect_attempts, reconnect_attempts
        self.retry_delay_s = retry_delay_s
        self.stop_deceleration, self.stop_joint_deceleration = stop_deceleration, stop_joint_deceleration
        self.dashboard_port, self.script_port = dashboard_port, script_port
        self._link_arg = link
        self.check_kinematics = check_kinematics
        self._sleep = sleep
        self._link = None
        self._last_motion = "linear"

    @classmethod
    def from_config(cls, cfg: Any, flange_from_tool: Any, obstacles: bool = True, **kw: Any) -> "URArm":
        """The arm of a cell file: its ``[robot]`` (address, deadlines, gripper I/O), ``[limits]``
        and, with ``obstacles``, its table and part as boxes the tool and the wrist keep the
        clearance from (calibration turns them off: its grid's moves are checked against the
        workspace and the keep-out box only, see README)."""
        r = cfg.robot
        limits = SafetyLimits.from_cell(cfg) if obstacles else SafetyLimits.from_config(cfg.limits)
        return cls(r.host, r.port, limits, flange_from_tool=flange_from_tool,
                   gripper=r.gripper, connect_timeout_s=r.connect_timeout_s, call_timeout_s=r.call_timeout_s,
                   move_margin_s=r.move_margin_s, dashboard_port=r.dashboard_port, script_port=r.script_port, **kw)

    # -- the link ----------------------------------------------------------------------
    @property
    def is_connected(self) -> bool:
        return self._link is not None

    def _call(self, iface: str, method: str, *args: Any, timeout: float | None = None, what: str = "") -> Any:
        """One ur_rtde call with a deadline. A timeout or a dead link stops the arm on other
        channels, kills the link and raises :class:`RobotSilent`; an error ur_rtde raised
        is an :class:`ArmError` (the link still works, the caller stops the arm)."""
        timeout = self.call_timeout_s if timeout is None else timeout
        what = what or method
        if self._link is None:
            raise RobotSilent(f"{self.name}: not connected (the link was closed after an earlier failure)")
        try:
            return self._link.call(iface, method, *args, timeout=timeout)
        except LinkTimeout:
            self._abandon(f"{self.name} did not answer {what} within {timeout:.3g} s")
        except LinkLost as e:
            self._abandon(f"lost the link to the {self.name} during {what} ({e})")
        except LinkCallError as e:
            raise ArmError(f"{self.name}: {what} failed: {e}") from None

    def _abandon(self, why: str) -> None:
        note = send_stop(self.host, self.dashboard_port, self.script_port)
        link, self._link = self._link, None
        if link is not None:
            link.kill()
        raise RobotSilent(f"{why}; {note}; disconnected")

    # -- connection ----------------------------------------------------------------
    def _connect(self) -> None:
        last: Exception | None = None
        for attempt in range(self.connect_attempts):
            if attempt:
                self._sleep(self.retry_delay_s)
            try:
                probe_rtde(self.host, self.port, self.probe_timeout_s)
            except ArmError as e:
                last = e
                continue
            link = self._link_arg if self._link_arg is not None else LINK_FACTORY()
            try:
                link.open(self.host, self.connect_timeout_s)
            except LinkCallError as e:      # the constructors raised: worth another attempt
                link.close()
                last = e
                continue
            except (LinkTimeout, LinkLost) as e:
                link.kill()
                note = send_stop(self.host, self.dashboard_port, self.script_port)
                raise RobotSilent(f"{self.name}: connecting did not finish within {self.connect_timeout_s:g} s "
                                  f"({e}); {note}; disconnected") from None
            self._link = link
            break
        else:
            raise ArmError(f"cannot connect to the {self.name} after {self.connect_attempts} attempt(s): {last}")
        try:
            # Our poses are flange poses: a TCP offset left on the controller would shift them.
            if not self._call("control", "setTcp", [0.0] * 6):
                raise ArmError(f"{self.name} refused to set a zero TCP offset")
            if self.check_kinematics:
                self._check_fk(self._receive("getActualQ"), "the arm's current joints")
        except BaseException:
            self._close_all()
            raise

    def _disconnect(self) -> None:
        self._close_all()

    def _close_all(self) -> None:
        link, self._link = self._link, None
        if link is not None:
            link.close(self.call_timeout_s)

    def _receive(self, method: str, *args: Any) -> Any:
        return self._call("receive", method, *args)

    def _ensure_link(self) -> None:
        """Reconnect a dropped RTDE link, a bounded number of times, probing first."""
        for attempt in range(self.reconnect_attempts + 1):
            if self._call("control", "isConnected") and self._call("receive", "isConnected"):
                return
            if attempt == self.reconnect_attempts:
                break
            if attempt:
                self._sleep(self.retry_delay_s)
            try:
                probe_rtde(self.host, self.port, self.probe_timeout_s)
                if not self._call("receive", "isConnected"):
                    self._call("receive", "reconnect", timeout=self.connect_timeout_s)
                if not self._call("control", "isConnected"):
                    self._call("control", "reconnect", timeout=self.connect_timeout_s)
            except RobotSilent:
                raise
            except ArmError:
                continue
        raise ArmError(f"lost the connection to the {self.name}; {self.reconnect_attempts} "
                       "reconnection attempt(s) failed")

    # -- kinematics --------------------------------------------------------------------
    def controller_fk(self, q: Any) -> np.ndarray:
        """4x4 world_from_flange at joints ``q`` by the controller's (calibrated) kinematics."""
        pose = self._call("control", "getForwardKinematics", [float(v) for v in q], [0.0] * 6,
                          what="getForwardKinematics")
        return pose6_to_matrix(pose)

    def ik(self, world_from_flange: np.ndarray, q_near: Any) -> np.ndarray | None:
        """Joints [rad] that put the flange at ``world_from_flange`` by the controller's own
        inverse kinematics, near ``q_near``; None when it has no solution. The planner's
        ``ik`` argument while connected: plans are then made in the controller's kinematics."""
        pose = [float(v) for v in matrix_to_pose6(world_from_flange)]
        try:
            q = self._call("control", "getInverseKinematics", pose, [float(v) for v in q_near],
                           what="getInverseKinematics")
        except RobotSilent:
            raise
        except ArmError:
            return None
        q = np.asarray(q, float)
        return q if q.shape == (6,) and np.all(np.isfinite(q)) else None

    def _check_fk(self, q: Any, what: str) -> None:
        """Refuse when the controller's forward kinematics at ``q`` differ from the planner's."""
        ours, theirs = fk(np.asarray(q, float)), self.controller_fk(q)
        self._compare(ours, theirs, f"forward kinematics at {what}")

    def _compare(self, ours: np.ndarray, theirs: np.ndarray, what: str) -> None:
        dp = float(np.linalg.norm(ours[:3, 3] - theirs[:3, 3]))
        dr = rotation_angle_between(ours[:3, :3], theirs[:3, :3])
        if dp > KINEMATICS_TOLERANCE_M or dr > KINEMATICS_TOLERANCE_RAD:
            raise KinematicsMismatch(
                f"{self.name}: the controller's {what} differ from the planner's UR5e model by "
                f"{dp * 1e3:.1f} mm and {np.degrees(dr):.2f} deg (tolerance {KINEMATICS_TOLERANCE_M * 1e3:g} mm, "
                f"{np.degrees(KINEMATICS_TOLERANCE_RAD):g} deg): another arm model, or a wrong calibration? "
                "nothing was sent")

    def _check_ik(self, pose: list[float], q_now: np.ndarray) -> np.ndarray:
        """Before a linear move: the controller's inverse kinematics of the target must exist,
        agree with the planner's forward model, and stay on the planner's configuration.
        Returns the planner's joints at the target (``q_now`` where it has none): where the
        next pose of a path is checked from."""
        T = pose6_to_matrix(pose)
        q_ctrl = self.ik(T, q_now)
        if q_ctrl is None:
            raise KinematicsMismatch(f"{self.name}: the controller has no inverse kinematics solution for "
                                     f"{_fmt(pose)}; nothing was sent")
        self._compare(fk(q_ctrl), T, "inverse kinematics of the target")
        q_ours = ik_nearest(T, q_now)
        if q_ours is not None and np.max(np.abs(q_ours - q_ctrl)) > SAME_BRANCH_RAD:
            raise KinematicsMismatch(f"{self.name}: the controller reaches {_fmt(pose)} in another joint "
                                     f"configuration ({_fmt(q_ctrl)} rad) than the planner "
                                     f"({_fmt(q_ours)} rad); nothing was sent")
        return q_now if q_ours is None else q_ours

    # -- state -----------------------------------------------------------------------
    def _tcp_pose(self) -> list[float]:
        self._ensure_link()
        return self._receive("getActualTCPPose")

    def _joints(self) -> list[float]:
        self._ensure_link()
        return self._receive("getActualQ")

    def _is_protective_stopped(self) -> bool:
        self._ensure_link()
        return bool(self._receive("isProtectiveStopped"))

    def _refuse_if_protective_stopped(self) -> None:
        if self._receive("isProtectiveStopped"):
            raise ProtectiveStopError(f"{self.name} is in a protective stop; clear it on the teach "
                                      "pendant before moving")

    # -- motion ----------------------------------------------------------------------
    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        start, q_now = self._linear_start()
        check_linear_move(self.limits, start, pose, speed, acceleration, self.points_flange, self.shape, q_now)
        (target,) = self._checked_targets([pose], q_now)
        self._begin_motion("linear")
        deadline = _linear_length(start, [target]) / speed + speed / acceleration + self.move_margin_s
        self._run("moveL", [target, speed, acceleration], deadline, self._stop_linear, f"moveL to {_fmt(target)}")

    def _move_linear_path(self, poses: np.ndarray, speed: float, acceleration: float, blend: float) -> None:
        """One ``moveL(path)`` through ``poses``: rows ``[x, y, z, rx, ry, rz, speed,
        acceleration, blend]``, the last with blend 0 (the controller stops there). Every
        pose is checked as a single move's target is, before anything is sent."""
        start, q_now = self._linear_start()
        check_linear_path(self.limits, start, poses, speed, acceleration, blend, self.points_flange, self.shape, q_now)
        targets = self._checked_targets(poses, q_now)
        self._begin_motion("linear")
        rows = [target + [float(speed), float(acceleration), float(blend) if i < len(targets) - 1 else 0.0]
                for i, target in enumerate(targets)]
        # Every leg may speed up and slow down (blend 0 stops at each pose), plus the upload.
        deadline = (_linear_length(start, targets) / speed + len(rows) * speed / acceleration + PATH_SCRIPT_S
                    + self.move_margin_s)
        self._run("moveL", [rows], deadline, self._stop_linear,
                  f"moveL path of {len(rows)} poses to {_fmt(targets[-1])}")

    def _linear_start(self) -> tuple[list[float], np.ndarray | None]:
        """Before a linear move: the link up, no protective stop; (the actual TCP pose, the
        actual joints where a check needs them, else None)."""
        self._ensure_link()
        self._refuse_if_protective_stopped()
        start = self._receive("getActualTCPPose")
        q_now = np.asarray(self._receive("getActualQ"), float) if self.check_kinematics or self.limits.obstacles else None
        return start, q_now

    def _checked_targets(self, poses, q_now: np.ndarray | None) -> list[list[float]]:
        """``poses`` as lists of floats, each checked against the controller's inverse
        kinematics (from ``q_now``, pose after pose) and its ``isPoseWithinSafetyLimits``."""
        targets = [[float(v) for v in pose] for pose in poses]
        if self.check_kinematics:
            q = q_now
            for target in targets:
                q = self._check_ik(target, q)
        for target in targets:
            if not self._call("control", "isPoseWithinSafetyLimits", target):
                raise SafetyError(f"{self.name}: the controller says pose {_fmt(target)} is outside its "
                                  "safety limits or unreachable")
        return targets

    def _begin_motion(self, kind: str) -> None:
        """A move is ignored after servoL/speedL until servoStop/speedStop: both, then the
        motion's kind for :meth:`_stop`."""
        self._call("control", "servoStop")
        self._call("control", "speedStop")
        self._last_motion = kind

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        self._ensure_link()
        self._refuse_if_protective_stopped()
        q_now = np.asarray(self._receive("getActualQ"), float)
        check_joint_move(self.limits, q_now, q, speed, acceleration, self.points_flange, shape=self.shape)
        target = [float(v) for v in q]
        if self.check_kinematics:
            self._check_fk(target, "the target joints")
        if not self._call("control", "isJointsWithinSafetyLimits", target):
            raise SafetyError(f"{self.name}: the controller says joints {_fmt(target)} are outside its "
                              "safety limits")
        self._begin_motion("joint")
        deadline = float(np.max(np.abs(np.asarray(q) - q_now))) / speed + speed / acceleration + self.move_margin_s
        self._run("moveJ", [target, speed, acceleration], deadline, self._stop_joint, f"moveJ to {_fmt(target)}")

    def _run(self, method: str, args: list, deadline: float, stop: Callable[[], None], what: str) -> None:
        """Run a blocking move with a deadline; on an error, an interrupt or a failure,
        stop the arm (a silent robot is stopped and abandoned by ``_call`` itself)."""
        try:
            ok = bool(self._call("control", method, *args, timeout=deadline, what=what))
        except RobotSilent:
            raise
        except BaseException as e:
            try:
                stop()
            except TapecellError:
                # The RTDE link is gone too: stop on the controller's other channels.
                note = send_stop(self.host, self.dashboard_port, self.script_port)
                if isinstance(e, ArmError):
                    raise ArmError(f"{e}; {note}") from None
            raise
        if not ok:
            stop()
            if self._receive("isProtectiveStopped"):
                raise ProtectiveStopError(f"{self.name} went into a protective stop during {what}")
            raise ArmError(f"{self.name}: {what} failed (the controller rejected or aborted it)")

    def _stop_linear(self) -> None:
        self._call("control", "stopL", self.stop_deceleration)

    def _stop_joint(self) -> None:
        self._call("control", "stopJ", self.stop_joint_deceleration)

    def _stop(self) -> None:
        (self._stop_joint if self._last_motion == "joint" else self._stop_linear)()

    # -- gripper and freedrive ------------------------------------------------------
    def _open_gripper(self) -> None:
        self._set_gripper(closed=False)

    def _close_gripper(self) -> None:
        self._set_gripper(closed=True)

    def _set_gripper(self, closed: bool) -> None:
        """Switch the gripper's outputs as ``[robot.gripper]`` says, wait for the jaws and,
        with a confirming input, check that they closed (or opened)."""
        self._ensure_link()
        g = self.gripper
        on, off = bool(g.active_high), not g.active_high
        if g.open_output == -1:
            writes = [(g.close_output, on if closed else off)]
        elif closed:
            writes = [(g.open_output, off), (g.close_output, on)]
        else:
            writes = [(g.close_output, off), (g.open_output, on)]
        setter = "setStandardDigitalOut" if g.output_kind == "standard" else "setToolDigitalOut"
        action = "close" if closed else "open"
        for pin, level in writes:
            if not self._call("io", setter, pin, level, what=f"{setter}({pin}, {level})"):
                raise ArmError(f"{self.name} refused to set {g.output_kind} digital output {pin} "
                               f"(gripper {action})")
        self._sleep(g.close_wait_s if closed else g.open_wait_s)
        if g.closed_input >= 0:
            deadline = time.monotonic() + g.closed_input_timeout_s
            while bool(self._receive("getDigitalInState", g.closed_input)) != closed:
                if time.monotonic() >= deadline:
                    raise ArmError(f"{self.name}: the gripper did not confirm it {'closed' if closed else 'opened'} "
                                   f"(digital input {g.closed_input} stayed {'off' if closed else 'on'} for "
                                   f"{g.closed_input_timeout_s:g} s after the outputs switched)")
                self._sleep(0.02)

    def _freedrive(self, enable: bool) -> None:
        self._ensure_link()
        ok = self._call("control", "teachMode" if enable else "endTeachMode")
        if not ok:
            raise ArmError(f"{self.name} refused to {'start' if enable else 'end'} freedrive")


def _linear_length(start, targets) -> float:
    """Path length [m] of straight moves from ``start`` through ``targets`` (pose6), a turn of
    the flange counted at TOOL_REACH_M: for a move's deadline."""
    length, a = 0.0, pose6_to_matrix(start)
    for target in targets:
        b = pose6_to_matrix(target)
        length += float(np.linalg.norm(b[:3, 3] - a[:3, 3])) + TOOL_REACH_M * rotation_angle_between(a[:3, :3],
                                                                                                   b[:3, :3])
        a = b
    return length


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4f}" for x in v) + "]"
