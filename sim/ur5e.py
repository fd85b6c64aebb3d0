"""The simulated controller's numerical inverse: damped least squares on the DH model of
``tapecell.cell.kinematics`` (the one forward kinematics), seeded from the current joints
the way a controller's Cartesian move follows its path.

Frames: ``base`` is the robot's base frame (= the world in this project), ``flange`` is
DH frame 6, the pose ur_rtde's ``getActualTCPPose`` reports with a zero TCP offset.
Joint angles in rad, lengths in m. The MuJoCo model in ``assets/ur5e.xml`` is built from
the same numbers (tests check that the two agree).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tapecell.cell.kinematics import JOINT_LOWER, JOINT_UPPER, dh_frames, fk as dh_fk
from tapecell.estimator.errors import TaskFailed


class IKError(TaskFailed):
    """No joint solution within the joint limits reaches the requested pose."""


def jacobian(q: np.ndarray, flange_from_tcp: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(base_from_tcp 4x4, geometric Jacobian (6, 6)): rows are linear then angular velocity
    of the TCP in the base frame per joint rate."""
    frames = dh_frames(np.asarray(q, float))
    T = frames[-1] if flange_from_tcp is None else frames[-1] @ flange_from_tcp
    p = T[:3, 3]
    J = np.zeros((6, 6))
    for i in range(6):
        z = frames[i][:3, 2]
        J[:3, i] = np.cross(z, p - frames[i][:3, 3])
        J[3:, i] = z
    return T, J


def pose_error(base_from_target: np.ndarray, base_from_tcp: np.ndarray) -> np.ndarray:
    """(6,) [position error m, rotation error as a rotation vector rad], both in the base frame."""
    from scipy.spatial.transform import Rotation

    dp = base_from_target[:3, 3] - base_from_tcp[:3, 3]
    dR = base_from_target[:3, :3] @ base_from_tcp[:3, :3].T
    return np.concatenate([dp, Rotation.from_matrix(dR).as_rotvec()])


@dataclass(frozen=True)
class IKResult:
    """q: (6,) joints [rad]; position_error_m, rotation_error_rad: residual; iterations."""
    q: np.ndarray
    position_error_m: float
    rotation_error_rad: float
    iterations: int


def ik(base_from_target: np.ndarray, q_seed: np.ndarray, flange_from_tcp: np.ndarray | None = None,
       lower: np.ndarray = JOINT_LOWER, upper: np.ndarray = JOINT_UPPER,
       tol_m: float = 1e-6, tol_rad: float = 1e-6, max_iter: int = 200, restarts: int = 8,
       rng_seed: int = 0) -> IKResult:
    """Joints that put the TCP at ``base_from_target`` (4x4), nearest the seed first.

    Damped least squares from ``q_seed``, clamped to the joint limits; if that does not
    converge, from seeds perturbed deterministically. Raises :class:`IKError` with the
    residual when no start converges.
    """
    q_seed = np.asarray(q_seed, float)
    rng = np.random.default_rng(rng_seed)
    best: IKResult | None = None
    for attempt in range(restarts + 1):
        q0 = q_seed if attempt == 0 else np.clip(q_seed + rng.uniform(-1.5, 1.5, 6), lower, upper)
        res = _dls(base_from_target, q0, flange_from_tcp, lower, upper, tol_m, tol_rad, max_iter)
        if best is None or res.position_error_m + 0.1 * res.rotation_error_rad < \
                best.position_error_m + 0.1 * best.rotation_error_rad:
            best = res
        if res.position_error_m <= tol_m * 10 and res.rotation_error_rad <= tol_rad * 10:
            return res
    assert best is not None
    p = base_from_target[:3, 3]
    raise IKError(f"pose at [{p[0]:.4f}, {p[1]:.4f}, {p[2]:.4f}] m is unreachable within the joint limits "
                  f"(best residual {best.position_error_m * 1000:.2f} mm, "
                  f"{np.degrees(best.rotation_error_rad):.2f} deg)")


def _dls(target, q, flange_from_tcp, lower, upper, tol_m, tol_rad, max_iter) -> IKResult:
    q = q.copy()
    lam = 1e-3
    for it in range(max_iter):
        T, J = jacobian(q, flange_from_tcp)
        e = pose_error(target, T)
        ep, er = np.linalg.norm(e[:3]), np.linalg.norm(e[3:])
        if ep <= tol_m and er <= tol_rad:
            return IKResult(q, ep, er, it)
        # Limit the step so the linearisation holds far from the target.
        step = J.T @ np.linalg.solve(J @ J.T + lam * np.eye(6), e)
        n = np.linalg.norm(step)
        if n > 0.5:
            step *= 0.5 / n
        q = np.clip(q + step, lower, upper)
    T = jacobian(q, flange_from_tcp)[0]
    e = pose_error(target, T)
    return IKResult(q, float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:])), max_iter)
