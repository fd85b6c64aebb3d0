"""UR5e inverse kinematics in closed form, for reachability checks without MuJoCo.

One DH table, one forward kinematics and one analytic inverse for the whole project
(Universal Robots' published DH parameters): the planner, the safety check, the fake arm
and the simulated arm all use these. The MuJoCo model in ``assets/ur5e.xml`` is built from
the same numbers (tests check that the two agree). The
closed-form inverse follows Hawkins, "Analytic Inverse Kinematics for the Universal Robots
UR-5/UR-10 Arms" (2013): up to 8 solutions (shoulder left/right, wrist up/down, elbow
up/down), each checked against the forward model before it is returned.

Frames: ``base`` = world; ``flange`` = DH frame 6, the pose ur_rtde reports with a zero
TCP offset. Joints in rad, lengths in m.
"""
from __future__ import annotations

import numpy as np

__all__ = ["fk", "dh_frames", "dh_frames_many", "ik_solutions", "ik_nearest", "JOINT_NAMES", "JOINT_LOWER", "JOINT_UPPER"]

# Universal Robots' published DH parameters of the UR5e.
DH_D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
DH_A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])

JOINT_NAMES = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
JOINT_LOWER = np.array([-2 * np.pi, -2 * np.pi, -np.pi, -2 * np.pi, -2 * np.pi, -2 * np.pi])
JOINT_UPPER = -JOINT_LOWER

_D1, _D4, _D5, _D6 = DH_D[0], DH_D[3], DH_D[4], DH_D[5]
_A2, _A3 = DH_A[1], DH_A[2]


_COS_ALPHA, _SIN_ALPHA = np.cos(DH_ALPHA), np.sin(DH_ALPHA)


def dh_frames(q: np.ndarray) -> np.ndarray:
    """(7, 4, 4) world_from_frame_i for DH frames 0..6 at joints ``q`` (6,) [rad]: the
    single-sample case of :func:`dh_frames_many` (the same numbers, without the stacking)."""
    joint = _joint_transforms(np.asarray(q, float)[None, :6])[0]
    out = np.empty((7, 4, 4))
    T = np.eye(4)
    out[0] = T
    for i in range(6):
        T = T @ joint[i]
        out[i + 1] = T
    return out


def _joint_transforms(qs: np.ndarray) -> np.ndarray:
    """(n, 6, 4, 4) frame_{i-1}_from_frame_i of each joint at joints ``qs`` (n, 6): the
    products of :func:`_dh`, for all joints and samples at once."""
    n = len(qs)
    ct, st = np.cos(qs), np.sin(qs)
    ca, sa = _COS_ALPHA, _SIN_ALPHA
    joint = np.zeros((n, 6, 4, 4))
    joint[..., 0, 0] = ct
    joint[..., 0, 1] = -st * ca
    joint[..., 0, 2] = st * sa
    joint[..., 0, 3] = DH_A * ct
    joint[..., 1, 0] = st
    joint[..., 1, 1] = ct * ca
    joint[..., 1, 2] = -ct * sa
    joint[..., 1, 3] = DH_A * st
    joint[..., 2, 1] = sa
    joint[..., 2, 2] = ca
    joint[..., 2, 3] = DH_D
    joint[..., 3, 3] = 1.0
    return joint


def dh_frames_many(qs: np.ndarray) -> np.ndarray:
    """(n, 7, 4, 4): :func:`dh_frames` at each of the joint vectors ``qs`` (n, 6) [rad].

    The joint transforms are filled in for all joints and samples at once (the products
    of :func:`_dh`), then chained frame by frame with one stacked matrix product: the
    same numbers, bit for bit, as chaining ``_dh`` matrices one joint at a time (checked on
    200,000 random joint vectors), at a fraction of the cost (the planner's safety checks
    take the frames at hundreds of samples of every candidate motion)."""
    qs = np.asarray(qs, float).reshape(-1, 6)
    n = len(qs)
    joint = _joint_transforms(qs)
    out = np.empty((n, 7, 4, 4))
    T = np.broadcast_to(np.eye(4), (n, 4, 4))
    out[:, 0] = T
    for i in range(6):
        T = T @ joint[:, i]
        out[:, i + 1] = T
    return out


def fk(q: np.ndarray) -> np.ndarray:
    """4x4 world_from_flange at joints ``q`` (6,) [rad]: the UR5e's DH forward kinematics."""
    return dh_frames(np.asarray(q, float))[-1]


def _dh(theta: float, i: int) -> np.ndarray:
    ct, st = np.cos(theta), np.sin(theta)
    ca, sa = _COS_ALPHA[i], _SIN_ALPHA[i]
    return np.array([[ct, -st * ca, st * sa, DH_A[i] * ct],
                     [st, ct * ca, -ct * sa, DH_A[i] * st],
                     [0.0, sa, ca, DH_D[i]],
                     [0.0, 0.0, 0.0, 1.0]])


def _clip_unit(x: float) -> float:
    """``x`` clipped to [-1, 1] (np.clip's value, NaN passes, without its per-call cost)."""
    return min(max(x, -1.0), 1.0)


def _wrap(q: np.ndarray) -> np.ndarray:
    return (q + np.pi) % (2 * np.pi) - np.pi


def ik_solutions(world_from_flange: np.ndarray, tol_m: float = 1e-6, tol_rad: float = 1e-5,
                 verify: bool = True) -> np.ndarray:
    """(k, 6) joint solutions in [-pi, pi) that put the flange at ``world_from_flange``.

    k is 0 when the pose is out of reach. Solutions at a wrist singularity (sin q5 = 0)
    are dropped: there the arm cannot follow a straight line anyway. Every solution is
    verified with the forward model to ``tol_m`` / ``tol_rad`` (unless ``verify`` is False:
    then the caller must verify the one it uses).
    """
    T = np.asarray(world_from_flange, float)
    p05 = T @ np.array([0.0, 0.0, -_D6, 1.0])
    r = np.hypot(p05[0], p05[1])
    if r < abs(_D4):
        return np.zeros((0, 6))
    out = []
    phi = np.arctan2(p05[1], p05[0])
    psi = np.arccos(_clip_unit(_D4 / r))
    for q1 in (phi + psi + np.pi / 2, phi - psi + np.pi / 2):
        s1, c1 = np.sin(q1), np.cos(q1)
        c5 = (T[0, 3] * s1 - T[1, 3] * c1 - _D4) / _D6
        if abs(c5) > 1.0 + 1e-9:
            continue
        T1_inv_T = np.linalg.inv(_dh(q1, 0)) @ T      # the same for both wrists
        for q5 in (np.arccos(_clip_unit(c5)), -np.arccos(_clip_unit(c5))):
            s5 = np.sin(q5)
            if abs(s5) < 1e-7:
                continue
            # Frame 0's x and y axes seen from frame 6 are the rows of R06.
            q6 = np.arctan2((-T[0, 1] * s1 + T[1, 1] * c1) / s5, (T[0, 0] * s1 - T[1, 0] * c1) / s5)
            T14 = T1_inv_T @ np.linalg.inv(_dh(q5, 4) @ _dh(q6, 5))
            p13 = T14 @ np.array([0.0, -_D4, 0.0, 1.0])
            n13 = np.linalg.norm(p13[:3])
            c3 = (n13 ** 2 - _A2 ** 2 - _A3 ** 2) / (2 * _A2 * _A3)
            if abs(c3) > 1.0 + 1e-9:
                continue
            for q3 in (np.arccos(_clip_unit(c3)), -np.arccos(_clip_unit(c3))):
                q2 = -np.arctan2(p13[1], -p13[0]) + np.arcsin(_clip_unit(_A3 * np.sin(q3) / n13))
                T34 = np.linalg.inv(_dh(q2, 1) @ _dh(q3, 2)) @ T14
                q4 = np.arctan2(T34[1, 0], T34[0, 0])
                q = _wrap(np.array([q1, q2, q3, q4, q5, q6]))
                if not verify or _matches(q, T, tol_m, tol_rad):
                    out.append(q)
    return np.array(out).reshape(-1, 6)


def _matches(q: np.ndarray, T: np.ndarray, tol_m: float, tol_rad: float) -> bool:
    F = fk(q)
    if np.linalg.norm(F[:3, 3] - T[:3, 3]) > tol_m:
        return False
    c = np.clip((np.trace(F[:3, :3].T @ T[:3, :3]) - 1) / 2, -1.0, 1.0)
    return bool(np.arccos(c) <= tol_rad)


def ik_nearest(world_from_flange: np.ndarray, q_near: np.ndarray,
               lower: np.ndarray = JOINT_LOWER, upper: np.ndarray = JOINT_UPPER) -> np.ndarray | None:
    """The solution closest to ``q_near`` (6,) within the joint limits, or None.

    Each closed-form solution is shifted by whole turns to sit nearest ``q_near`` (UR joints
    mostly turn +-2 pi), then the one with the smallest largest-joint change wins: that is
    the configuration a controller's ``moveL`` keeps.
    """
    q_near = np.asarray(q_near, float)
    T = np.asarray(world_from_flange, float)
    candidates = []
    for q in ik_solutions(T, verify=False):
        q = q_near + _wrap(q - q_near)
        if np.any(q < lower - 1e-9) or np.any(q > upper + 1e-9):
            q = _wrap(q)  # fall back to the principal values
            if np.any(q < lower - 1e-9) or np.any(q > upper + 1e-9):
                continue
        candidates.append((float(np.max(np.abs(q - q_near))), q))
    # Verify only the winner (forward kinematics is the expensive part), then runners-up.
    for _, q in sorted(candidates, key=lambda c: c[0]):
        if _matches(q, T, 1e-6, 1e-5):
            return q
    return None
