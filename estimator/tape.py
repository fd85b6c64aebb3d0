"""The paper's tape model: a chain of rigid plates joined by three rotation angles.

Frame of node 0 is the fixed base frame F0. For node i = 1..n (formats.md, eq. 1-4):

    F_i = F_{i-1} @ Rz(θz_i) @ Ry(θy_i) @ Rx(θx_i)
    P_C[i] = P_C[i-1] + L_i * F_i[:, 0]
    P_L[i] = P_C[i] + (W/2) * F_i[:, 1],   P_R[i] = P_C[i] - (W/2) * F_i[:, 1]

A frame's columns are the trunk direction, the direction across the width (towards the
left stem) and the surface normal.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class TapeSpec:
    """Known dimensions and fixed base of the tape model.

    segment_lengths: (n,) trunk lengths L_1..L_n [m].
    width: tape width W [m].
    base_position: (3,) P_C[0] in the world frame [m].
    base_rotation: (3, 3) world_from_base, the frame F0 (columns trunk, left, normal).
    """

    segment_lengths: np.ndarray
    width: float
    base_position: np.ndarray
    base_rotation: np.ndarray

    @property
    def n(self) -> int:
        return int(len(self.segment_lengths))

    @property
    def length(self) -> float:
        return float(np.sum(self.segment_lengths))

    def to_json(self) -> dict:
        return {
            "segment_lengths": np.asarray(self.segment_lengths).tolist(),
            "width": float(self.width),
            "base": {"position": np.asarray(self.base_position).tolist(),
                     "rotation": np.asarray(self.base_rotation).tolist()},
        }


@dataclass(frozen=True, eq=False)
class TapeShape:
    """The model's geometry in the world frame for one set of angles.

    nodes: (n+1, 3) trunk nodes P_C[0..n] [m].
    frames: (n+1, 3, 3) node frames F_0..F_n (world_from_node rotations).
    left, right: (n+1, 3) stem tips P_L, P_R [m].
    """

    nodes: np.ndarray
    frames: np.ndarray
    left: np.ndarray
    right: np.ndarray

    def quads(self) -> np.ndarray:
        """(n, 4, 3) plate corners P_L[i-1], P_L[i], P_R[i], P_R[i-1]."""
        return np.stack([self.left[:-1], self.left[1:], self.right[1:], self.right[:-1]], axis=1)


def joint_rotations(angles: np.ndarray) -> np.ndarray:
    """(n, 3) angles (θx, θy, θz) -> (n, 3, 3) Rz(θz) @ Ry(θy) @ Rx(θx), vectorised."""
    a = np.asarray(angles, float).reshape(-1, 3)
    cx, sx = np.cos(a[:, 0]), np.sin(a[:, 0])
    cy, sy = np.cos(a[:, 1]), np.sin(a[:, 1])
    cz, sz = np.cos(a[:, 2]), np.sin(a[:, 2])
    R = np.empty((len(a), 3, 3))
    R[:, 0, 0] = cz * cy
    R[:, 0, 1] = cz * sy * sx - sz * cx
    R[:, 0, 2] = cz * sy * cx + sz * sx
    R[:, 1, 0] = sz * cy
    R[:, 1, 1] = sz * sy * sx + cz * cx
    R[:, 1, 2] = sz * sy * cx - cz * sx
    R[:, 2, 0] = -sy
    R[:, 2, 1] = cy * sx
    R[:, 2, 2] = cy * cx
    return R


def forward_kinematics(spec: TapeSpec, angles: np.ndarray) -> TapeShape:
    """Nodes, frames and stem tips of the chain for (n, 3) angles [rad]."""
    angles = np.asarray(angles, float).reshape(spec.n, 3)
    Rj = joint_rotations(angles)
    frames = np.empty((spec.n + 1, 3, 3))
    nodes = np.empty((spec.n + 1, 3))
    frames[0] = spec.base_rotation
    nodes[0] = spec.base_position
    for i in range(spec.n):
        frames[i + 1] = frames[i] @ Rj[i]
        nodes[i + 1] = nodes[i] + spec.segment_lengths[i] * frames[i + 1][:, 0]
    half = 0.5 * spec.width * frames[:, :, 1]
    return TapeShape(nodes, frames, nodes + half, nodes - half)


def angles_from_frames(frames: np.ndarray) -> np.ndarray:
    """Inverse of the chain's rotations: (n+1, 3, 3) frames -> (n, 3) angles (θx, θy, θz)."""
    out = np.empty((len(frames) - 1, 3))
    for i in range(1, len(frames)):
        R = frames[i - 1].T @ frames[i]
        out[i - 1, 1] = np.arcsin(np.clip(-R[2, 0], -1.0, 1.0))
        out[i - 1, 0] = np.arctan2(R[2, 1], R[2, 2])
        out[i - 1, 2] = np.arctan2(R[1, 0], R[0, 0])
    return out
