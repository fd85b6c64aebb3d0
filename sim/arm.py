"""The simulated UR5e: joint and TCP moves, gripper, state, all simulated physically.

Moves stream position targets to the arm's actuators every physics step, so the tape
(and anything the gripper holds) is simulated along the way. Poses are world (= base)
frame 4x4 transforms or UR-style ``[x, y, z, rx, ry, rz]`` vectors; the TCP is the
selected tool's point (``flange``, ``plate``, ``needle``, ``gripper``) from the cell file.
Knows nothing of ur_rtde; ``cell`` puts this behind the same interface as the real arm.
"""
from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from tapecell.estimator.errors import TaskFailed

from .cell import SimCell
from tapecell.cell.config import TOOL_NAMES, matrix_to_pose, pose_to_matrix
from tapecell.cell.kinematics import JOINT_LOWER, JOINT_UPPER, fk as dh_fk
from .ur5e import IKError, ik

_WAYPOINT_STEPS = 10   # a Cartesian move solves IK every this many physics steps
_WAYPOINT_FRACTIONS = (np.arange(1, _WAYPOINT_STEPS + 1) / _WAYPOINT_STEPS)[:, None]


def _ramp(start: np.ndarray, end: np.ndarray, n: int) -> np.ndarray:
    """(n, k): ``start + (end - start) * (i / n)`` for i = 1..n, the targets a move streams
    one per physics step (the same numbers as computing each row on its own)."""
    return start + (end - start) * (np.arange(1, n + 1) / n)[:, None]


class SimArmError(TaskFailed):
    """A simulated move was refused or did not arrive."""


class TargetNotReached(SimArmError):
    """The simulated arm stopped short of its target (as a real arm's protective stop)."""


def _joint_target(q) -> np.ndarray:
    q = np.asarray(q, float)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise SimArmError(f"joint target must be 6 finite angles, got {q.tolist()}")
    if np.any(q < JOINT_LOWER) or np.any(q > JOINT_UPPER):
        raise SimArmError(f"joint target {np.round(q, 4).tolist()} is outside the joint limits")
    return q


def as_matrix(pose) -> np.ndarray:
    """A 4x4 transform from a 4x4 or a ``[x, y, z, rx, ry, rz]`` pose."""
    p = np.asarray(pose, float)
    if p.shape == (4, 4):
        return p
    if p.shape == (6,):
        return pose_to_matrix(p)
    raise SimArmError(f"a pose must be a 4x4 matrix or [x, y, z, rx, ry, rz], got shape {list(p.shape)}")


class SimArm:
    """The UR5e of a :class:`SimCell`. ``tool`` selects the TCP ("flange" or a tool name)."""

    def __init__(self, cell: SimCell, tool: str | None = None):
        self.cell = cell
        self.tool = "flange"
        self._tcp: dict[str, np.ndarray] = {}      # flange_from_tcp per tool, read-only
        self.select_tool(tool or cell.mounted_tool)

    # ------------------------------------------------------------------ state
    def select_tool(self, tool: str) -> None:
        """Use ``tool``'s TCP for poses; a real tool is also mounted (shown) in the cell."""
        if tool != "flange" and tool not in TOOL_NAMES:
            raise SimArmError(f"unknown tool '{tool}' (known: flange, {', '.join(TOOL_NAMES)})")
        if tool != "flange":
            self.cell.mount_tool(tool)
        self.tool = tool

    def flange_from_tcp(self, tool: str | None = None) -> np.ndarray:
        return self._flange_from_tcp(tool).copy()

    def _flange_from_tcp(self, tool: str | None) -> np.ndarray:
        """The cell file's flange_from_tcp of ``tool`` (default the selected one), computed
        once per tool (scipy's rotation per call cost a third of a Cartesian move's IK);
        read-only."""
        tool = tool or self.tool
        T = self._tcp.get(tool)
        if T is None:
            T = self.cell.config.tools.flange_from_tcp(tool)
            T.setflags(write=False)
            self._tcp[tool] = T
        return T

    def joints(self) -> np.ndarray:
        """(6,) measured joint angles [rad]."""
        return self.cell.data.qpos[self.cell.arm_qadr].copy()

    def tcp_pose(self, tool: str | None = None) -> np.ndarray:
        """4x4 world_from_tcp of the simulated arm (from MuJoCo, not from the DH model)."""
        d, m = self.cell.data, self.cell.model
        fid = m.body("flange").id
        world_from_flange = np.eye(4)
        world_from_flange[:3, :3] = d.xmat[fid].reshape(3, 3)
        world_from_flange[:3, 3] = d.xpos[fid]
        return world_from_flange @ self._flange_from_tcp(tool)

    def tcp_pose_vector(self, tool: str | None = None) -> np.ndarray:
        """[x, y, z, rx, ry, rz] of :meth:`tcp_pose` (as ur_rtde's getActualTCPPose)."""
        return matrix_to_pose(self.tcp_pose(tool))

    def gripper_opening(self) -> float:
        """Distance between the pads [m]."""
        return float(self.cell.data.qpos[self.cell.finger_qadr].sum())

    # ---------------------------------------------------------------- kinematics
    def ik(self, pose, tool: str | None = None, q_seed: np.ndarray | None = None) -> np.ndarray:
        """Joints [rad] that put ``tool``'s TCP at ``pose``, nearest ``q_seed`` (default: now).
        Raises :class:`IKError` when unreachable within the joint limits."""
        seed = self.joints() if q_seed is None else np.asarray(q_seed, float)
        return ik(as_matrix(pose), seed, self._flange_from_tcp(tool)).q

    def fk(self, q: np.ndarray, tool: str | None = None) -> np.ndarray:
        """4x4 world_from_tcp at joints ``q`` by the DH model."""
        return dh_fk(np.asarray(q, float)) @ self._flange_from_tcp(tool)

    # -------------------------------------------------------------------- moves
    def move_joints(self, q, speed: float | None = None, settle_s: float = 1.0) -> np.ndarray:
        """Move to joints ``q`` [rad] at ``speed`` rad/s (the fastest joint; default from the
        cell file), simulating every step; returns the joints reached."""
        q = _joint_target(q)
        speed = speed or self.cell.config.arm.max_joint_speed
        q0 = self.cell.arm_ctrl.copy()
        dt = self.cell.model.opt.timestep
        n = max(1, int(np.ceil(np.abs(q - q0).max() / speed / dt)))
        self.cell.step_targets(self.cell.arm_ctrl, _ramp(q0, q, n))
        return self._wait(q, settle_s)

    def move_tcp(self, pose, speed: float = 0.1, tool: str | None = None, settle_s: float = 1.0) -> np.ndarray:
        """Move the TCP along a straight line (position) and a slerp (orientation) to
        ``pose`` at ``speed`` m/s (rotation at most 1 rad/s), as moveL does; IK is solved
        along the way. Returns the joints reached."""
        return self._wait(self._stream_tcp(as_matrix(pose), speed, tool), settle_s)

    def move_tcp_path(self, poses, speed: float = 0.1, tool: str | None = None, settle_s: float = 1.0,
                      blend: bool = True) -> np.ndarray:
        """Move the TCP through ``poses`` in order, each leg as :meth:`move_tcp`. ``blend``:
        without settling between the legs (as a UR's blended ``moveL`` path: the servos' lag
        rounds the corners), settling at the last; else settling at every pose. Every pose's
        IK is solved before the arm moves (as the real arm checks every pose before the
        path is sent). A blocked arm is noticed at the end (the settling fails), not per leg.
        Returns the joints reached."""
        targets = [as_matrix(p) for p in poses]
        if not targets:
            raise SimArmError("a path needs at least one pose")
        goals, q = [], self.cell.arm_ctrl.copy()
        for target in targets:                 # fail before moving
            q = self.ik(target, tool, q)
            goals.append(q)
        for k, (target, q_goal) in enumerate(zip(targets, goals)):
            self._stream_tcp(target, speed, tool, q_goal)
            if not blend or k == len(targets) - 1:
                q = self._wait(q_goal, settle_s)
        return q

    def _stream_tcp(self, target: np.ndarray, speed: float, tool: str | None,
                    q_goal: np.ndarray | None = None) -> np.ndarray:
        """Stream the servo targets of a straight TCP move from the commanded pose to
        ``target`` (4x4), one per physics step; returns the target's joints (not waited for).
        ``q_goal``: those joints when already solved (from the commanded joints, as here)."""
        start = self.fk(self.cell.arm_ctrl.copy(), tool)
        if q_goal is None:
            q_goal = self.ik(target, tool, self.cell.arm_ctrl.copy())  # fail before moving
        dist = np.linalg.norm(target[:3, 3] - start[:3, 3])
        rots = Rotation.from_matrix(np.stack([start[:3, :3], target[:3, :3]]))
        angle = (rots[1] * rots[0].inv()).magnitude()
        dt = self.cell.model.opt.timestep
        duration = max(dist / speed, angle / 1.0, dt)
        n_way = max(1, int(np.ceil(duration / dt / _WAYPOINT_STEPS)))
        # every waypoint's orientation in one call (a call per waypoint cost more than the physics)
        turns = Slerp([0.0, 1.0], rots)(np.arange(1, n_way + 1) / n_way).as_matrix()
        q_prev = self.cell.arm_ctrl.copy()
        for k in range(1, n_way + 1):
            s = k / n_way
            T = np.eye(4)
            T[:3, :3] = turns[k - 1]
            T[:3, 3] = start[:3, 3] + s * (target[:3, 3] - start[:3, 3])
            q_next = q_goal if k == n_way else self.ik(T, tool, q_prev)
            # the waypoint's IK first, then its steps (an unreachable waypoint stops the arm there)
            self.cell.step_targets(self.cell.arm_ctrl, q_prev + (q_next - q_prev) * _WAYPOINT_FRACTIONS)
            q_prev = q_next
        return q_goal

    def set_joints(self, q) -> np.ndarray:
        """Place the arm exactly at joints ``q`` [rad] (servo targets too) without simulating
        the motion: nothing collides on the way and no time passes. For putting the arm at
        given joints exactly (a settled move stops within ``joint_tolerance``), e.g. to
        render reference images; returns the joints."""
        q = _joint_target(q)
        d = self.cell.data
        d.qpos[self.cell.arm_qadr] = q
        d.qvel[self.cell.arm_dofs] = 0.0
        self._command(q)
        mujoco.mj_forward(self.cell.model, d)
        return self.joints()

    def park(self) -> np.ndarray:
        """Move to the cell file's park joints, out of every camera's view."""
        return self.move_joints(self.cell.config.arm.park_joints)

    def home(self) -> np.ndarray:
        return self.move_joints(self.cell.config.arm.home_joints)

    def open_gripper(self, settle_s: float = 0.5) -> float:
        """Open the gripper fully; returns the pad distance [m]."""
        return self._move_fingers(self.cell.config.tools.gripper.max_opening / 2, settle_s)

    def close_gripper(self, settle_s: float = 0.5, speed: float | None = None) -> float:
        """Close the gripper (squeezing whatever is between the pads) with the pad distance
        shrinking at ``speed`` m/s (default the cell file's ``tools.gripper.close_speed``),
        as a real gripper closes; returns the pad distance [m].

        The finger servos alone would slam the pads together at ~0.4 m/s, and a 0.2 mm
        tape then passes through a pad within one timestep (seen with the true tip frame
        on seeds 2, 4 and 7): the finger targets are ramped, then settled."""
        speed = self.cell.config.tools.gripper.close_speed if speed is None else float(speed)
        if not speed > 0:
            raise SimArmError(f"gripper close speed must be positive, got {speed}")
        fingers = self.cell.finger_actuators
        closed = self.cell.model.actuator_ctrlrange[fingers, 0]      # each finger's closed target [m]
        start = self.cell.finger_ctrl.copy()
        dt = self.cell.model.opt.timestep
        # Each finger covers half the pad distance: ramp at speed / 2 per finger.
        n = max(1, int(np.ceil(np.max(start - closed) / (speed / 2) / dt)))
        self.cell.step_targets(self.cell.finger_ctrl, _ramp(start, closed, n))
        return self._move_fingers(closed, settle_s)

    # ----------------------------------------------------------------- helpers
    def _command(self, q: np.ndarray) -> None:
        self.cell.data.ctrl[self.cell.arm_actuators] = q

    def _wait(self, q: np.ndarray, settle_s: float) -> np.ndarray:
        """Step until the joints are within tolerance of ``q`` and nearly still. A load (the
        tape in the gripper) leaves a small steady offset under the position servos: still
        for 0.1 s within 10x the tolerance counts as arrived too."""
        qpos, qvel = self.cell.arm_qpos, self.cell.arm_qvel      # views of the data
        tol = self.cell.config.arm.joint_tolerance
        dt = self.cell.model.opt.timestep
        still_steps = 0
        for _ in range(int(round(settle_s / dt))):
            still = np.abs(qvel).max() < 0.01
            still_steps = still_steps + 1 if still else 0
            if still:      # the joint error matters only then
                err = np.abs(qpos - q).max()
                if err < tol or (err < 10 * tol and still_steps * dt >= 0.1):
                    self.cell.sync()
                    return self.joints()
            self.cell.step(1, sync=False)
        self.cell.sync()
        err = np.abs(qpos - q).max()
        raise TargetNotReached(f"the simulated arm did not reach its target (joint error {err:.4f} rad after {settle_s} s)")

    def _move_fingers(self, target: float, settle_s: float) -> float:
        self.cell.finger_ctrl[:] = target
        n = int(round(settle_s / self.cell.model.opt.timestep))
        fingers = self.cell.finger_qpos          # a view of the data
        prev = fingers.copy()
        for i in range(n):
            self.cell.step(1, sync=False)
            q = fingers.copy()
            if i > 50 and np.abs(q - prev).max() < 1e-7:
                break
            prev = q
        self.cell.sync()
        return self.gripper_opening()


__all__ = ["SimArm", "SimArmError", "IKError", "as_matrix"]
