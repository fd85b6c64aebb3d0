"""Probing the simulated tape with the needle (the paper's sec. 4.1, Fig. 6).

The needle approaches each target point slowly along the tape's normal until MuJoCo
reports contact between needle and tape (``mj_geomDistance`` <= 0); the needle tip then is
the measured point (flange pose the arm reports composed with the needle offset).
"""
from __future__ import annotations

import numpy as np

from tapecell.cell.probe import ProbedPoint, ProbeError, ProbeParams, needle_world_from_tcp


class SimProber:
    """Probes the simulated tape with the needle on a :class:`sim.arm.SimArm`."""

    def __init__(self, sim_cell, sim_arm, params: ProbeParams = ProbeParams()) -> None:
        self.sim, self.arm, self.params = sim_cell, sim_arm, params
        m = sim_cell.model
        self._needle = m.geom("needle").id

    def gap(self) -> float:
        """Smallest distance between the needle and the tape [m] (<= 0: contact)."""
        return self.sim.tape_gap(self._needle)

    def _go_to_standoff(self, label: str, point: np.ndarray, approach: np.ndarray) -> np.ndarray:
        """Joint move (closed-form IK, any roll of the needle about its axis) to the needle
        frame at ``point`` pointing along ``approach``; returns that frame (4x4). Where the
        needle would meet the tape there already (its shaft through the tape's body), a
        ProbeError before any move: from this side nothing can be probed (the move there and
        back cost two turns of the wrist)."""
        from tapecell.cell.kinematics import ik_nearest

        needle_from_flange = np.linalg.inv(self.sim.config.tools.flange_from_tcp("needle"))
        base = needle_world_from_tcp(point, approach)
        for roll in np.radians(np.arange(0.0, 360.0, 30.0)):
            c, s_ = np.cos(roll), np.sin(roll)
            R = np.array([[c, -s_, 0, 0], [s_, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            T = base @ R
            q = ik_nearest(T @ needle_from_flange, self.arm.joints())
            if q is not None:
                if self.sim.tape_gap_at(self._needle, q) <= 0.0:
                    raise ProbeError(f"{label}: the needle meets the tape at its standoff from "
                                     f"{np.round(point, 4).tolist()} along {np.round(approach, 3).tolist()}")
                self.arm.move_joints(q)
                return T
        raise ProbeError(f"{label}: the needle cannot reach {np.round(point, 4).tolist()} along "
                         f"{np.round(approach, 3).tolist()}")

    def probe(self, label: str, target: np.ndarray, normal: np.ndarray) -> ProbedPoint:
        """Approach ``target`` along -``normal`` (from the side ``normal`` points to) until
        the needle touches the tape; the needle tip at contact is the measurement."""
        p = self.params
        approach = -normal / np.linalg.norm(normal)
        start = self._go_to_standoff(label, target - p.standoff * approach, approach)
        travelled, reach = 0.0, 2 * p.standoff + p.coarse_step
        while True:
            gap = self.gap()
            if gap <= 0.0:
                break
            if travelled > 2 * p.standoff:
                raise ProbeError(f"{label}: no contact with the tape within {2000 * p.standoff:.0f} mm "
                                 f"of {np.round(target, 4).tolist()}")
            # Conservative advance: no point of the tape is nearer the needle than the gap, so
            # a move along the approach by the gap cannot pass through it, and the steps
            # converge on the first contact along the approach, where a slow continuous
            # approach meets the tape (as small steps did, at many times the cost). Far from
            # the tape the needle moves faster and stops a coarse step short of the gap.
            far = gap > 2 * p.coarse_step
            step = min(gap - p.coarse_step if far else max(gap, 1e-5), reach - travelled)
            travelled += step
            T = start.copy()
            T[:3, 3] = start[:3, 3] + travelled * approach
            self.arm.move_tcp(T, speed=p.far_speed if far else p.speed, tool="needle", settle_s=0.3)
        measured = self.arm.tcp_pose("needle")[:3, 3]
        # Back off before the next point so the needle never drags along the tape.
        self.arm.move_tcp(start, speed=p.far_speed, tool="needle")
        return ProbedPoint(label, measured.copy(), np.asarray(target, float))
