"""Safety limits, checked before any target is sent to an arm.

The cell file's ``[limits]`` section gives a workspace box the tool must stay in, the
largest TCP speed and acceleration (and joint speed), and a keep-out box around the part
that no tool point may enter, not even on the way to a target. A violation raises
:class:`SafetyError` naming the rule and the numbers, before anything moves.

What is checked ("check points"): the flange origin, the tool's TCP and any extra points
given in the flange frame (e.g. the gripper's finger tips). Linear moves follow the
flange's straight line with slerped orientation (what UR ``moveL`` does), sampled finely
and tested piecewise against the keep-out box exactly (segment/box slab test). Joint moves
are sampled in joint space through the UR5e forward kinematics, the wrist centres
included, because a joint move's tool path is not a straight line.

:class:`SafeArm` wraps any :class:`~cell.arm.Arm` so no caller can bypass the check.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from tapecell.estimator.errors import TaskFailed

from .arm import Arm
from .poses import interpolate_pose6, pose6_to_matrix, rotation_angle_between


class SafetyError(TaskFailed):
    """A target or a motion violates the cell's safety limits; nothing was sent (exit 1:
    the task cannot be done within the limits)."""


class KeepOutError(SafetyError):
    """A motion would take a check point into the keep-out box around the part."""


@dataclass(frozen=True, eq=False)
class SafetyLimits:
    """The cell's limits. Boxes are axis-aligned in the base frame (= world) [m].

    workspace_min, workspace_max: (3,) box every check point's target must lie in.
    keepout_min, keepout_max: (3,) box around the part no check point may enter.
    max_tcp_speed [m/s], max_tcp_accel [m/s^2]: bounds of linear moves.
    max_joint_speed [rad/s], max_joint_accel [rad/s^2]: bounds of joint moves.
    """

    workspace_min: np.ndarray
    workspace_max: np.ndarray
    max_tcp_speed: float
    max_tcp_accel: float
    max_joint_speed: float
    keepout_min: np.ndarray
    keepout_max: np.ndarray
    max_joint_accel: float = 1.4

    def __post_init__(self) -> None:
        for name in ("workspace_min", "workspace_max", "keepout_min", "keepout_max"):
            v = np.asarray(getattr(self, name), float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise SafetyError(f"limits.{name} must be 3 finite numbers [m]")
            object.__setattr__(self, name, v)
        if np.any(self.workspace_min >= self.workspace_max):
            raise SafetyError("limits.workspace_min must be below limits.workspace_max on every axis")
        if np.any(self.keepout_min >= self.keepout_max):
            raise SafetyError("limits.keepout_min must be below limits.keepout_max on every axis")
        for name in ("max_tcp_speed", "max_tcp_accel", "max_joint_speed", "max_joint_accel"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v <= 0:
                raise SafetyError(f"limits.{name} must be a positive number")
            object.__setattr__(self, name, v)

    @classmethod
    def from_config(cls, section: Any) -> "SafetyLimits":
        """From the cell file's ``limits`` section (``sim.config.LimitsSection``) or any
        object with the same attributes; ``max_joint_accel`` defaults to UR's 1.4 rad/s^2."""
        return cls(
            workspace_min=section.workspace_min, workspace_max=section.workspace_max,
            max_tcp_speed=section.max_tcp_speed, max_tcp_accel=section.max_tcp_accel,
            max_joint_speed=section.max_joint_speed,
            keepout_min=section.keepout_min, keepout_max=section.keepout_max,
            max_joint_accel=getattr(section, "max_joint_accel", 1.4),
        )


def check_points_flange(flange_from_tool: Any = None, extra_points_flange: Any = None) -> np.ndarray:
    """(k, 3) points in the flange frame that are checked: the flange origin, the tool's
    TCP (``flange_from_tool`` 4x4 or pose6) and ``extra_points_flange`` (N, 3)."""
    points = [np.zeros(3)]
    if flange_from_tool is not None:
        F = np.asarray(flange_from_tool, float)
        F = pose6_to_matrix(F) if F.shape == (6,) else F
        points.append(F[:3, 3])
    if extra_points_flange is not None:
        points.extend(np.asarray(extra_points_flange, float).reshape(-1, 3))
    return np.array(points)


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.4f}" for x in v) + "]"


def segment_hits_box(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """True when the closed segment a-b meets the open box (lo, hi) (slab test)."""
    return bool(segments_hit_box(np.asarray(a, float)[None], np.asarray(b, float)[None], lo, hi)[0])


def segments_hit_box(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n,) bool: which segments a[i]-b[i] ((n, 3) each) meet the open box (lo, hi)."""
    d = b - a
    t0 = np.zeros(len(a))
    t1 = np.ones(len(a))
    ok = np.ones(len(a), bool)
    for k in range(3):
        flat = np.abs(d[:, k]) < 1e-15
        ok &= ~flat | ((lo[k] < a[:, k]) & (a[:, k] < hi[k]))
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (lo[k] - a[:, k]) / d[:, k]
            tb = (hi[k] - a[:, k]) / d[:, k]
        near, far = np.minimum(ta, tb), np.maximum(ta, tb)
        t0 = np.where(flat, t0, np.maximum(t0, near))
        t1 = np.where(flat, t1, np.minimum(t1, far))
    return ok & (t0 < t1)


def _inside(p: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Which points (..., 3) lie in the closed box (lo, hi)."""
    return np.all((p >= lo - tol) & (p <= hi + tol), axis=-1)


def _check_box_path(limits: SafetyLimits, paths: np.ndarray, labels: list[str], motion: str) -> None:
    """paths: (n_samples, k, 3) world positions of k points along a motion."""
    lo, hi = limits.workspace_min, limits.workspace_max
    inside = _inside(paths, lo, hi)
    hits = np.stack([segments_hit_box(paths[:-1, j], paths[1:, j], limits.keepout_min, limits.keepout_max)
                     for j in range(paths.shape[1])], axis=1) if len(paths) > 1 else np.zeros((0, paths.shape[1]), bool)
    for j, label in enumerate(labels):
        if not inside[-1, j]:
            raise SafetyError(f"{motion}: the {label} target {_fmt(paths[-1, j])} m is outside the workspace box "
                              f"{_fmt(lo)}..{_fmt(hi)}")
        # The box is convex: a path from inside stays inside unless the orientation sweeps
        # the point out, which the samples catch. A start outside (recovery) is allowed.
        if inside[0, j] and not np.all(inside[:, j]):
            p = paths[np.argmin(inside[:, j]), j]
            raise SafetyError(f"{motion}: the {label} passes {_fmt(p)} m, outside the workspace box")
        if np.any(hits[:, j]):
            p = paths[np.argmax(hits[:, j]) + 1, j]
            raise KeepOutError(f"{motion}: the {label} would enter the keep-out box around the part "
                              f"{_fmt(limits.keepout_min)}..{_fmt(limits.keepout_max)} near {_fmt(p)} m")


def _point_labels(k: int) -> list[str]:
    return ["flange", "TCP"][:k] + [f"check point {i}" for i in range(2, k)]


def check_linear_move(limits: SafetyLimits, start_pose: Any, target_pose: Any, speed: float,
                      acceleration: float, points_flange: np.ndarray | None = None) -> None:
    """Raise :class:`SafetyError` unless a ``moveL`` of the flange from ``start_pose`` to
    ``target_pose`` (pose6) at ``speed`` m/s / ``acceleration`` m/s^2 keeps every check
    point (``points_flange`` (k, 3), default the flange origin) inside the workspace and
    out of the keep-out box."""
    if not 0 < speed <= limits.max_tcp_speed:
        raise SafetyError(f"linear move: speed {speed:g} m/s exceeds the limit {limits.max_tcp_speed:g} m/s")
    if not 0 < acceleration <= limits.max_tcp_accel:
        raise SafetyError(f"linear move: acceleration {acceleration:g} m/s^2 exceeds the limit "
                          f"{limits.max_tcp_accel:g} m/s^2")
    pts = check_points_flange() if points_flange is None else np.asarray(points_flange, float)
    a, b = np.asarray(start_pose, float), np.asarray(target_pose, float)
    reach = float(np.max(np.linalg.norm(pts, axis=1)))
    angle = rotation_angle_between(pose6_to_matrix(a)[:3, :3], pose6_to_matrix(b)[:3, :3])
    # Fine enough that no sample step moves any point more than ~2 mm.
    n = int(np.ceil((np.linalg.norm(b[:3] - a[:3]) + reach * angle) / 0.002)) + 2
    poses = interpolate_pose6(a, b, min(n, 2000))
    R = Rotation.from_rotvec(poses[:, 3:]).as_matrix()                # (n, 3, 3)
    paths = np.einsum("nij,kj->nki", R, pts) + poses[:, None, :3]    # (n, k, 3)
    _check_box_path(limits, paths, _point_labels(len(pts)), "linear move")


def check_joint_move(limits: SafetyLimits, q_start: Any, q_target: Any, speed: float, acceleration: float,
                     points_flange: np.ndarray | None = None,
                     frames: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
    """Raise :class:`SafetyError` unless a joint move from ``q_start`` to ``q_target`` [rad]
    at ``speed`` rad/s / ``acceleration`` rad/s^2 keeps the check points inside the
    workspace and every check point and wrist centre out of the keep-out box.
    ``frames(q) -> (7, 4, 4)`` are the DH frames (default the UR5e's)."""
    if not 0 < speed <= limits.max_joint_speed:
        raise SafetyError(f"joint move: speed {speed:g} rad/s exceeds the limit {limits.max_joint_speed:g} rad/s")
    if not 0 < acceleration <= limits.max_joint_accel:
        raise SafetyError(f"joint move: acceleration {acceleration:g} rad/s^2 exceeds the limit "
                          f"{limits.max_joint_accel:g} rad/s^2")
    if frames is None:
        from .kinematics import dh_frames as frames
    pts = check_points_flange() if points_flange is None else np.asarray(points_flange, float)
    qa, qb = np.asarray(q_start, float), np.asarray(q_target, float)
    n = int(np.ceil(np.max(np.abs(qb - qa)) / 0.01)) + 2
    tool_paths, wrist_paths = [], []
    for s in np.linspace(0.0, 1.0, n):
        F = frames(qa + s * (qb - qa))
        tool_paths.append((F[-1] @ np.c_[pts, np.ones(len(pts))].T).T[:, :3])
        wrist_paths.append(F[4:6, :3, 3])
    _check_box_path(limits, np.array(tool_paths), _point_labels(len(pts)), "joint move")
    wrist = np.array(wrist_paths)
    for j, label in enumerate(("wrist 2 centre", "wrist 3 centre")):
        if np.any(segments_hit_box(wrist[:-1, j], wrist[1:, j], limits.keepout_min, limits.keepout_max)):
            raise KeepOutError(f"joint move: the {label} would enter the keep-out box around the part")


class SafeArm(Arm):
    """An :class:`Arm` whose every motion is checked against ``limits`` first.

    ``flange_from_tool`` (4x4 or pose6) is the mounted tool, whose TCP is checked along with
    the flange; ``extra_points_flange`` (N, 3) adds points such as finger tips;
    ``points_flange`` (k, 3) replaces the whole list (flange origin first). Motions
    start from the arm's reported pose, so the straight-line check covers the real path.
    """

    def __init__(self, arm: Arm, limits: SafetyLimits, flange_from_tool: Any = None,
                 extra_points_flange: Any = None, points_flange: Any = None) -> None:
        self.arm = arm
        self.limits = limits
        if points_flange is not None:   # a full list, e.g. GripperGeometry.check_points_flange()
            self.points_flange = np.asarray(points_flange, float).reshape(-1, 3)
        else:
            self.points_flange = check_points_flange(flange_from_tool, extra_points_flange)
        self.name = f"safe {arm.name}"

    @property
    def is_connected(self) -> bool:
        return self.arm.is_connected

    def _connect(self) -> None:
        self.arm.connect()

    def _disconnect(self) -> None:
        self.arm.disconnect()

    def _tcp_pose(self) -> np.ndarray:
        return self.arm.tcp_pose()

    def _joints(self) -> np.ndarray:
        return self.arm.joints()

    def _is_protective_stopped(self) -> bool:
        return self.arm.is_protective_stopped()

    def _move_linear(self, pose: np.ndarray, speed: float, acceleration: float) -> None:
        check_linear_move(self.limits, self.arm.tcp_pose(), pose, speed, acceleration, self.points_flange)
        self.arm.move_linear(pose, speed, acceleration)

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        check_joint_move(self.limits, self.arm.joints(), q, speed, acceleration, self.points_flange)
        self.arm.move_joints(q, speed, acceleration)

    def _stop(self) -> None:
        self.arm.stop()

    def _open_gripper(self) -> None:
        self.arm.open_gripper()

    def _close_gripper(self) -> None:
        self.arm.close_gripper()

    def _freedrive(self, enable: bool) -> None:
        self.arm.freedrive(enable)
