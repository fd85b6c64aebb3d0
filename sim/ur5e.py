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
    J = np.zeros((6, 6))
    # z_i x (p - o_i) for all joints at once, written out (np.cross per joint cost more than
    # the physics in a Cartesian move; the same products and differences)
    z = frames[:6, :3, 2]
    d = T[:3, 3] - frames[:6, :3, 3]
    J[0] = z[:, 1] * d[:, 2] - z[:, 2] * d[:, 1]
    J[1] = z[:, 2] * d[:, 0] - z[:, 0] * d[:, 2]
    J[2] = z[:, 0] * d[:, 1] - z[:, 1] * d[:, 0]
    J[3:] = z.T
    return T, J


def pose_error(base_from_target: np.ndarray, base_from_tcp: np.ndarray) -> np.ndarray:
    """(6,) [position error m, rotation error as a rotation vector rad], both in the base frame."""
    dp = base_from_target[:3, 3] - base_from_tcp[:3, 3]
    dR = base_from_target[:3, :3] @ base_from_tcp[:3, :3].T
    return np.concatenate([dp, rotvec(dR)])


def rotvec(R: np.ndarray) -> np.ndarray:
    """(3,) rotation vector of the rotation matrix ``R`` (the angle in [0, pi] times the
    axis), through its unit quaternion (Shepperd's method, stable at every angle). Agrees
    with scipy's ``Rotation.from_matrix(R).as_rotvec()`` to rounding, at a fraction of its
    cost per call (the numerical inverse calls it every iteration)."""
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    tr = r00 + r11 + r22
    k = max(range(4), key=(r00, r11, r22, tr).__getitem__)
    if k == 3:
        w, x, y, z = 1.0 + tr, r21 - r12, r02 - r20, r10 - r01
    elif k == 0:
        w, x, y, z = r21 - r12, 1.0 + 2.0 * r00 - tr, r01 + r10, r02 + r20
    elif k == 1:
        w, x, y, z = r02 - r20, r01 + r10, 1.0 + 2.0 * r11 - tr, r12 + r21
    else:
        w, x, y, z = r10 - r01, r02 + r20, r12 + r21, 1.0 + 2.0 * r22 - tr
    if w < 0:
        w, x, y, z = -w, -x, -y, -z
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    s = np.sqrt(x * x + y * y + z * z)
    angle = 2.0 * np.arctan2(s, w)
    scale = angle / s if s > 1e-12 else 2.0 / w
    return np.array([x * scale, y * scale, z * scale])


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
    rng = None          # the perturbed seeds' generator, made only when the seed fails
    best: IKResult | None = None
    for attempt in range(restarts + 1):
        if attempt == 1:
            rng = np.random.default_rng(rng_seed)
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


_DAMPING = 1e-3 * np.eye(6)   # damped least squares: lambda I

_JACOBIAN_MEMO: dict = {}
"""(joints bytes, tool bytes) -> (T, J): the last few :func:`jacobian` answers of :func:`_dls`."""
_JACOBIAN_MEMO_SIZE = 4
jacobian_memo_stats = [0, 0]
"""[answers from the memo, answers computed]"""


def _jacobian_memo(q: np.ndarray, flange_from_tcp: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`jacobian` at ``q``, an earlier answer again when ``q`` and the tool are the same
    bit for bit: a Cartesian move solves each waypoint from the last one's solution, so
    each solve starts where the one before converged, and its first waypoint from where
    the solve of its goal started (the same numbers, one evaluation fewer per solve). The
    arrays returned are only read."""
    key = (q.tobytes(), None if flange_from_tcp is None else np.asarray(flange_from_tcp, float).tobytes())
    out = _JACOBIAN_MEMO.get(key)
    if out is not None:
        jacobian_memo_stats[0] += 1
        return out
    jacobian_memo_stats[1] += 1
    out = jacobian(q, flange_from_tcp)
    if len(_JACOBIAN_MEMO) >= _JACOBIAN_MEMO_SIZE:
        del _JACOBIAN_MEMO[next(iter(_JACOBIAN_MEMO))]      # the oldest
    _JACOBIAN_MEMO[key] = out
    return out


def _dls(target, q, flange_from_tcp, lower, upper, tol_m, tol_rad, max_iter) -> IKResult:
    q = q.copy()
    for it in range(max_iter):
        T, J = _jacobian_memo(q, flange_from_tcp)
        e = pose_error(target, T)
        ep, er = np.linalg.norm(e[:3]), np.linalg.norm(e[3:])
        if ep <= tol_m and er <= tol_rad:
            return IKResult(q, ep, er, it)
        # Limit the step so the linearisation holds far from the target.
        step = J.T @ np.linalg.solve(J @ J.T + _DAMPING, e)
        n = np.linalg.norm(step)
        if n > 0.5:
            step *= 0.5 / n
        q = np.clip(q + step, lower, upper)
    T = jacobian(q, flange_from_tcp)[0]
    e = pose_error(target, T)
    return IKResult(q, float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:])), max_iter)
