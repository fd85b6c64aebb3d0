"""Grasp planning at the tape's tip, and running a plan on any :class:`~cell.arm.Arm`.

The gripper (cell file ``[tools.gripper]``) is a parallel two-finger gripper: its TCP sits
midway between the pads, the pads close along the TCP's y axis and the fingers point along
its z axis (out of the flange). The tape is 0.2 mm thick and 30 mm wide, so the only grip a
parallel gripper can make is across the thickness: the closing axis (TCP y) lies along the
tape's normal and the fingers straddle the tape, one pad on each face.

Approach: along -trunk, i.e. the open jaw slides onto the tape's end from beyond the tip,
like a fork. This is what a real parallel gripper can do with a curled, floppy tape: the
tape is inside the jaw's 40 mm gap the whole way, so errors along the normal (the
estimator's weakest direction) are absorbed by the gap, and the pads (12 mm along the
tape's width, centred on its centre line) end up a few mm in from the end. A side approach
(along the width) would reach only the 12 mm pad depth into a 30 mm wide tape; an approach
along the normal is impossible, a finger would have to pass through the tape. When the
straight approach is blocked (the tip points down, the part is in the way, or the arm
cannot reach it) the approach is tilted about the normal, up to 90 deg (from the side,
across the width), and the jaw may be turned half a turn about its own axis (the gripper
is symmetric); the least tilted feasible variant wins. Only where all of these fail (an
end hanging a little outside the part's face, where the open jaw's near finger would be
inside the part) does the jaw come from the tape's body side (tilts past 90 deg), and then
take the tape further back along the estimated end (:data:`EXTRA_INSETS_M`).

Plan: open; joint move to ``pregrasp`` (``pregrasp_distance`` back along the approach, clear
of the tape; through ``above``, 150 mm over it, when the direct joint move would sweep the
wrist or the gripper into the table or the part); linear ``approach`` to ``grasp`` (TCP ``inset`` in from the tip along the
trunk); close; lift by ``lift`` metres (TCP path length) through poses at most 10 mm apart
(``lift_1`` ... ``lift``), one blended linear path (:data:`LIFT_BLEND_M`: the arm does not
stop between them). Two lift modes:

* "arc" (default): the gripper carries the grasped point on an arc about the line where
  the tape is stuck (its base), turning the base-to-grasp chord towards the vertical; the
  jaw keeps its orientation (the floppy tape bends at the grasp, and the wrist stays
  still). The free length never has to stretch, so the tape follows the gripper as long
  as its base holds: the first phase of every peel, and all a simulated tape with a
  welded base allows.
* "peel": a straight pull between the part's top normal (world z) and the chord from the
  base to the grasp, which drives the peel front along the adhesive line (real cell).

Refusals raise :class:`PlanRefused` with ``reason`` one of "estimate rejected" (fit cost
above the threshold), "unreachable" (no inverse kinematics, or a straight segment crosses a
singularity / changes configuration), "limits" (workspace box or speeds), "collision"
(keep-out box around the part, the gripper or the wrist closer than the clearance to the
table or the part, or the open fingers through the tape).
"""
from __future__ import annotations

import dataclasses

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from tapecell.estimator.errors import TaskFailed
from tapecell.estimator.geometry import is_rotation

from .arm import Arm, ArmError, ProtectiveStopError
from .kinematics import fk, ik_nearest
from .poses import interpolate_pose6, invert, matrix_to_pose6, pose6_to_matrix
from .safety import (KeepOutError, SafeArm, SafetyError, SafetyLimits, ToolShape, check_joint_move,
                     check_blends, check_linear_move, check_linear_path, check_points_flange,
                     check_wrist_clear)

IK = Callable[[np.ndarray, np.ndarray], "np.ndarray | None"]
"""ik(world_from_flange 4x4, q_near (6,)) -> joints (6,) nearest q_near, or None."""

# Joints of the UR5e reaching over the part from above (elbow up, wrist down): the branch
# the planner prefers when the caller does not say where the arm is.
REFERENCE_JOINTS = np.array([-1.5708, -1.9, 2.2, -1.87, -1.5708, 0.0])
# Tilts of the approach about the tape normal, least first: 0 slides the jaw onto the end
# along -trunk; +-90 deg comes in from the side, across the width (the pads still grip a
# 12 x 12 mm patch on the centre line; the near half of the width passes between the
# fingers), which is how a tip that hangs down is reached without coming from below.
APPROACH_TILTS_RAD = tuple(np.radians(a) for a in (0.0, 20.0, -20.0, 40.0, -40.0, 60.0, -60.0, 90.0, -90.0))
# Pitches of the approach out of the tape's plane (about its width axis), tried after every
# tilt at the pitch before failed: the jaw then closes at this angle to the tape's faces
# (the 40 mm gap still straddles a 0.2 mm tape; the floppy tape turns into the pads).
APPROACH_PITCHES_RAD = tuple(np.radians(a) for a in (0.0, 25.0, -25.0))
# Tilts past the side, tried after all of the above: the jaw comes from the tape's body
# side, fingers first along the tape towards its end (from above an end that hangs down
# beside the part, where a jaw from the side or from beyond the tip would put a finger
# between the tape and the part's face). The tape's body then lies between the open
# fingers, which the check against the estimated tape covers.
BODY_SIDE_TILTS_RAD = tuple(np.radians(a) for a in (120.0, -120.0, 150.0, -150.0, 180.0))
# Where every approach at the cell file's inset is refused, the grasp point moves further
# back along the estimated end by these amounts [m] (the jaw then holds the tape higher
# up a hanging end, away from the part's face or the table below it). 30 and 40 mm: ends
# hanging low beside the part or near the table, where every closer grasp put a finger
# within the clearance (8 of 9 such simulated episodes grasped, the tip following the
# lift within 0.3-6.1 mm of the 8 allowed). 50, 60 and 75 mm (2026-11-27): ends hanging
# beside the part's face or low over the table, where every grasp up to 40 mm in put the
# palm, the mount or a finger within the clearance of the table or the part: of 17
# simulated episodes of earlier sessions' ranges (45, 930055-968045) once refused for that,
# re-run, 15 grasped here (9 at 58 mm in, one at 68 mm, 5 at 83 mm), none failed; 941160
# grasps 38 mm in without them, 958102 stays refused (no tape beside its grasp point).
EXTRA_INSETS_M = (0.006, 0.012, 0.017, 0.022, 0.030, 0.040, 0.050, 0.060, 0.075)
FAR_INSET_M = 0.020
SIDE_TILT_MIN_RAD, SIDE_TILT_MAX_RAD = np.radians(90.0), np.radians(120.0)
"""At a grasp point FAR_INSET_M or more in from the tip, only approaches across the tape are
tried (tilts of SIDE_TILT_MIN_RAD to SIDE_TILT_MAX_RAD either way): the jaw meets the tape at
the grasp point. From beyond the tip (0-60 deg) or from along the body (150-180 deg) the
fingers slide along the tape's faces over that length, where a free end or a body a few
millimetres off the estimate is swept out of the jaw or flips over the pads (846135, 20 mm in
at 150 deg: a pad struck the body, the pads closed on air; 847002, 25 mm in at 180 deg: the
tip lagged 48 mm). Of 401 simulated episodes that planned through fallbacks (830000-847000),
31 grasped 20 mm or more in: at 90-120 deg 24 of 24 took the tape, at 150-180 deg 5 of 7.
Those 7 again with only 90-120 deg: 846135 and 847002 grasped (25 and 48 mm in at 120 deg),
4 refused (collision), 832172 (an "ok" 23 mm off) slipped; with 60-120 deg, 5 of them
failed at 60 deg, 30 mm in."""
APPROACH_TAPE_MARGIN_M = 0.003
"""On the straight approach the open fingers and the palm keep this far [m] from the
estimated tape (its centre line and faces): the estimate is a few millimetres off along an
arching body (2.5 mm in episode 670065, whose pad touched the body 50 mm from the end on
the approach and pushed the end out of the jaw; 530040 alike). Measured on fresh episodes
710000-710099: the same outcomes with and without it."""
TAPE_CLEARANCE_M = 0.005
"""The open gripper's fingers and palm keep this far [m] from the estimated tape's surface
on the joint moves to the pre-grasp pose (a pad swept through a curled tape's body drags
it out of the jaw: the "missed" grasps of seeds 400037 and 400177)."""
MAX_JOINT_STEP_RAD = 0.25      # per ~5 mm of a straight segment: more means a singularity or a flip
PATH_STEP_M = 0.005
PLAN_MARGIN_M = 0.001
"""The tool and the wrist keep this much more than the clearance along the planned straight
moves [m]: executed, the arm's joints differ slightly from the planned IK samples, and each
straight move is checked again from the pose the arm actually reached (a fresh campaign's
plan passed the wrist at 5.0 mm and was stopped at 4.9; fresh 941160's left finger, planned
at 5.0 mm from the part, was stopped at 4.99 on the approach)."""
LIFT_BLEND_M = 0.002
"""Blend radius [m] of the lift's path at its intermediate poses (5-10 mm apart): the arm
peels in one motion instead of stopping every 10 mm. Less than half the shortest leg, as a
UR requires; each blended corner's chord is checked as a straight move
(:func:`~cell.safety.check_blends`)."""


class PlanRefused(TaskFailed):
    """The planner will not grasp (exit 1). ``reason`` is a short tag (see the module docstring)."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"grasp refused ({reason}): {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, eq=False)
class TipFrame:
    """The estimated tape tip. position (3,) [m] world; rotation (3, 3) world_from_tip with
    columns trunk (outward along the tape), left (across the width), normal; cost: the
    estimate's silhouette cost; verdict: the estimator's ("ok" is the only one a grasp is
    planned for); reason: its one-line why."""

    position: np.ndarray
    rotation: np.ndarray
    cost: float
    verdict: str = "ok"
    reason: str = ""

    @property
    def trunk(self) -> np.ndarray:
        return self.rotation[:, 0]

    @property
    def normal(self) -> np.ndarray:
        return self.rotation[:, 2]

    @classmethod
    def from_estimate(cls, estimate: Any) -> "TipFrame":
        """From an ``estimator.Estimate`` (its tip frame, cost and verdict)."""
        verdict = getattr(estimate, "verdict", "ok")
        return cls(np.asarray(estimate.tip_position, float), np.asarray(estimate.tip_rotation, float),
                   float(estimate.cost), str(getattr(verdict, "value", verdict)), getattr(estimate, "verdict_reason", ""))


@dataclass(frozen=True)
class GraspParams:
    """inset [m]: TCP this far in from the tip; pregrasp_distance [m]: start of the
    approach, back along it; lift [m]: length of the peel."""

    inset: float
    pregrasp_distance: float
    lift: float
    lift_mode: str = "arc"

    def __post_init__(self) -> None:
        if self.lift_mode not in ("arc", "peel"):
            raise PlanRefused("limits", f"unknown lift mode '{self.lift_mode}' (arc or peel)")

    @classmethod
    def from_config(cls, section: Any) -> "GraspParams":
        """From the cell file's ``[grasp]`` section (``sim.config.GraspSection``); its
        optional ``lift_mode`` ("arc" or "peel") defaults to "arc"."""
        return cls(float(section.inset), float(section.pregrasp_distance),
                   float(section.lift), str(getattr(section, "lift_mode", "arc")))


@dataclass(frozen=True, eq=False)
class GripperGeometry:
    """flange_from_tcp: 4x4; max_opening [m] between the pads; pad_size (3,) [m] full
    extents (x along the jaw, y thickness, z depth); finger_length [m] from the pad centre
    back towards the flange, where the palm starts (from the cell file: the flange-to-TCP
    depth less 30 mm of palm and mount)."""

    flange_from_tcp: np.ndarray
    max_opening: float
    pad_size: np.ndarray
    finger_length: float = 0.05
    finger_thickness: float = 0.006

    @classmethod
    def from_config(cls, tool: Any) -> "GripperGeometry":
        """From the cell file's ``[tools.gripper]`` (``sim.config.GripperTool``)."""
        flange_from_tcp = pose6_to_matrix(tool.flange_from_tcp)
        depth = float(np.linalg.norm(flange_from_tcp[:3, 3]))
        return cls(flange_from_tcp, float(tool.max_opening), np.asarray(tool.pad_size, float),
                   finger_length=max(depth - 0.03, float(tool.pad_size[2]) / 2),
                   finger_thickness=float(getattr(tool, "finger_thickness", 0.006)))

    def finger_boxes_tcp(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(lo, hi) boxes in the TCP frame of the two open fingers (each its pad and the
        finger behind it, ``finger_thickness`` thick) and the palm."""
        hx, ty, hz = self.pad_size[0] / 2, self.pad_size[1] + self.finger_thickness, self.pad_size[2] / 2
        g = self.max_opening / 2
        boxes = [(np.array([-hx, s0, -self.finger_length]), np.array([hx, s1, hz]))
                 for s0, s1 in ((g, g + ty), (-g - ty, -g))]
        w = g + self.pad_size[1] + 0.02     # the palm, as :meth:`shape` has it
        boxes.append((np.array([-0.02, -w, -self.finger_length - 0.024]), np.array([0.02, w, -self.finger_length])))
        return boxes

    def shape(self) -> ToolShape:
        """The open gripper's solid shape in the flange frame, as the collision check sees
        it: the two open fingers (with their pads), the palm (40 mm along the jaw, 20 mm
        beyond each finger, 24 mm thick) and the mount, a 25 mm radius column from the
        flange to the palm (the simulated gripper's geometry, sim/scene.py)."""
        F = self.flange_from_tcp
        fingers = self.finger_boxes_tcp()[:2]
        g, ty = self.max_opening / 2, self.pad_size[1]
        palm_z = -self.finger_length
        parts = [ToolShape.box(name, F, lo, hi) for name, (lo, hi) in zip(("left finger", "right finger"), fingers)]
        parts.append(ToolShape.box("palm", F, [-0.02, -g - ty - 0.02, palm_z - 0.024], [0.02, g + ty + 0.02, palm_z]))
        palm_flange = (F @ np.array([0.0, 0.0, palm_z - 0.024, 1.0]))[:3]
        parts.append(ToolShape.capsule("gripper mount", np.zeros(3), palm_flange, 0.025))
        return ToolShape.join(*parts)

    def check_points_flange(self) -> np.ndarray:
        """(k, 3) points in the flange frame for the safety check: the flange origin, the
        TCP, then the corners of the open fingers' boxes (as :class:`SafeArm` labels them)."""
        corners = []
        for lo, hi in self.finger_boxes_tcp()[:2]:
            corners += [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        corners = np.array(corners)
        corners_flange = (self.flange_from_tcp @ np.c_[corners, np.ones(len(corners))].T).T[:, :3]
        return check_points_flange(self.flange_from_tcp, corners_flange)


@dataclass(frozen=True, eq=False)
class Waypoint:
    """name; world_from_tcp 4x4 (the gripper's TCP); flange_pose (6,) [x, y, z, rx, ry, rz]
    base frame, what the arm is sent; q (6,) [rad] the inverse-kinematics solution."""

    name: str
    world_from_tcp: np.ndarray
    flange_pose: np.ndarray
    q: np.ndarray


@dataclass(frozen=True)
class Step:
    """action: "open_gripper", "close_gripper", "move_joints", "move_linear" or
    "move_linear_path"; waypoint: the target's name for moves; a path's ``through``: the
    waypoints it passes first, in order, each corner blended within ``blend`` [m]."""

    action: str
    waypoint: str | None = None
    through: tuple[str, ...] = ()
    blend: float = 0.0

    @property
    def targets(self) -> tuple[str, ...]:
        """The waypoints the step moves to, in order (empty for gripper steps)."""
        return () if self.waypoint is None else (*self.through, self.waypoint)

    def to_json(self) -> list:
        """``[action, waypoint]``; a path adds the waypoints it passes and its blend [m]."""
        if self.action == "move_linear_path":
            return [self.action, self.waypoint, list(self.through), self.blend]
        return [self.action, self.waypoint]


@dataclass(frozen=True, eq=False)
class GraspPlan:
    """Waypoints (in visiting order), the steps that run them, the tip it was planned for,
    the approach variant chosen (tilt in the tape's plane, jaw turned, pitch out of it),
    the flange-frame check points of the gripper, the overall lift direction (unit, grasp
    to final lift pose) and the gripper's shape the collision check used."""

    waypoints: tuple[Waypoint, ...]
    steps: tuple[Step, ...]
    tip: TipFrame
    approach_tilt_rad: float
    flipped: bool
    points_flange: np.ndarray
    lift_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    shape: ToolShape | None = None
    approach_pitch_rad: float = 0.0
    inset: float = 0.0
    """The grasp point's distance in from the tip along the estimated end [m]: the cell
    file's ``inset``, or further back (:data:`EXTRA_INSETS_M`) where no closer grasp passed."""

    def waypoint(self, name: str) -> Waypoint:
        for w in self.waypoints:
            if w.name == name:
                return w
        raise KeyError(name)

    def tool_waypoints(self) -> dict[str, np.ndarray]:
        """name -> world_from_tcp 4x4, in visiting order (for ``cell.recording.log_plan``)."""
        return {w.name: w.world_from_tcp for w in self.waypoints}

    def to_json(self) -> dict[str, Any]:
        return {
            "waypoints": [{"name": w.name, "tcp_position": w.world_from_tcp[:3, 3].tolist(),
                           "tcp_rotation": w.world_from_tcp[:3, :3].tolist(),
                           "flange_pose": w.flange_pose.tolist(), "joints": w.q.tolist()}
                          for w in self.waypoints],
            "steps": [s.to_json() for s in self.steps],
            "approach_tilt_deg": float(np.degrees(self.approach_tilt_rad)),
            "approach_pitch_deg": float(np.degrees(self.approach_pitch_rad)),
            "flipped": self.flipped,
            "inset_m": self.inset,
            "lift_direction": self.lift_direction.tolist(),
        }

    def describe(self) -> str:
        """Human-readable plan, one line a step and a path's poses a line each (what ``tapecell
        run`` shows before moving)."""
        pitch = f", pitch {np.degrees(self.approach_pitch_rad):+.0f} deg" if self.approach_pitch_rad else ""
        lines = [f"grasp plan (approach tilt {np.degrees(self.approach_tilt_rad):+.0f} deg{pitch}"
                 f"{', jaw turned' if self.flipped else ''}):"]
        for s in self.steps:
            if s.waypoint is None:
                lines.append(f"  {s.action}")
            if s.through:
                lines.append(f"  {s.action}: {len(s.targets)} poses, corners blended within {s.blend * 1e3:g} mm")
            for name in s.targets:
                w = self.waypoint(name)
                p = w.world_from_tcp[:3, 3] * 1000
                f = ", ".join(f"{v:.4f}" for v in w.flange_pose)
                action = s.action if not s.through else "  to" if name == s.waypoint else "  through"
                lines.append(f"  {action:<12} {w.name:<9} TCP [{p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}] mm"
                             f"  flange [{f}]")
        return "\n".join(lines)


# ------------------------------------------------------------------------------ planning
def plan_grasp(tip: TipFrame, params: GraspParams, gripper: GripperGeometry, limits: SafetyLimits, *,
               ik: IK = ik_nearest, q_start: Any = None, tape_points: Any = None,
               tape_base: Any = None, tape_surface: Any = None, speeds: "Speeds | None" = None,
               insets: Any = None) -> GraspPlan:
    """Plan a grasp of the tape at ``tip`` or raise :class:`PlanRefused`.

    ik: inverse kinematics (default the UR5e's closed form). q_start (6,): where the arm is
    (the joint move to pre-grasp is checked from there, and the nearest configuration is
    chosen); default :data:`REFERENCE_JOINTS`. tape_points (N, 3): the estimated centre line
    (e.g. ``Estimate.nodes``), checked against the open fingers. tape_base (3,): where the
    tape is stuck on the part (default ``tape_points[0]``), for the peel direction.
    tape_surface (M, 3): points on the estimated tape's faces (:func:`tape_surface_points`),
    checked against the open fingers on the approach and, with :data:`TAPE_CLEARANCE_M`,
    on the joint moves to the pre-grasp pose. speeds: the approach and lift speeds the plan
    will run at (default :class:`Speeds`), at which no joint may turn faster than
    ``limits.max_joint_speed`` on a straight segment. insets: the grasp points' distances in
    from the tip to try [m], in order (default the cell file's inset, then the fallbacks of
    :data:`EXTRA_INSETS_M`).

    Variants, in order: at the cell file's inset, every tilt of
    :data:`APPROACH_TILTS_RAD` and pitch, the jaw either way round; then the body-side
    tilts (:data:`BODY_SIDE_TILTS_RAD`); then the same at the insets of
    :data:`EXTRA_INSETS_M` (the grasp point further back along the estimated end), from
    :data:`FAR_INSET_M` on only from the side. The first that passes every check is the plan.
    Grasp points are tried only where the tape is known: short of the base of
    ``tape_points``; without them, no further in than the cell file's inset.
    """
    if tip.verdict != "ok":
        # A robot acts only on an estimate the estimator vouches for (estimator/verdict.py).
        raise PlanRefused("estimate rejected", f"verdict {tip.verdict}: {tip.reason}")
    R_tip = np.asarray(tip.rotation, float)
    if not is_rotation(R_tip, tol=1e-4):
        raise PlanRefused("estimate rejected", "the tip rotation is not a rotation matrix")
    q_ref = REFERENCE_JOINTS if q_start is None else np.asarray(q_start, float)
    tape = None if tape_points is None else _densify(np.asarray(tape_points, float), 0.002)
    if tape_base is None and tape_points is not None:
        tape_base = np.asarray(tape_points, float)[0]
    surface = None if tape_surface is None else np.asarray(tape_surface, float).reshape(-1, 3)
    speeds = Speeds() if speeds is None else speeds
    solid = (gripper.check_points_flange(), gripper.shape())     # the same for every variant
    refusals: list[PlanRefused] = []
    primary = 0        # how many refusals are of the first set (the cell file's inset, up to the side)
    if insets is None:
        insets = grasp_insets(params)
    # Grasp points only where the tape is known: without a centre line, along the tip's own
    # trunk up to the cell file's inset (further back along the trunk would be a guess);
    # with one, short of its base (beyond it grasp_frame stops at the base, on the part).
    reach = (float(params.inset) if tape_points is None
             else float(np.linalg.norm(np.diff(_centre_line(tip, tape_points), axis=0), axis=1).sum()))
    insets = [i for i in insets if i <= reach + 1e-9]
    if not insets:
        raise PlanRefused("unreachable", f"no grasp point: the estimated tape is {1e3 * reach:.0f} mm long, the "
                          f"cell file's inset {1e3 * float(params.inset):.0f} mm")
    for inset in insets:
        grasp_position, grasp_rotation = grasp_frame(tip, inset, params.inset, tape_points)
        for tilts in (APPROACH_TILTS_RAD, BODY_SIDE_TILTS_RAD):
            primary = primary or len(refusals)
            if inset >= FAR_INSET_M - 1e-9:
                tilts = tuple(t for t in tilts if SIDE_TILT_MIN_RAD - 1e-9 <= abs(t) <= SIDE_TILT_MAX_RAD + 1e-9)
            for pitch in APPROACH_PITCHES_RAD:
                for tilt in tilts:
                    for flipped in (False, True):
                        try:
                            plan = _plan_variant(tip, grasp_position, tape_base, tilt, flipped, params, gripper,
                                                 limits, ik, q_ref, q_start is not None, tape, pitch,
                                                 grasp_rotation=grasp_rotation, surface=surface, speeds=speeds,
                                                 precheck=primary > 0, solid=solid)
                        except PlanRefused as e:
                            refusals.append(e)
                        else:
                            return dataclasses.replace(plan, inset=float(inset))
    # The most telling refusal of the first set of variants (the fallbacks are for the odd
    # tip beside the part): a collision (the tip is near the part or the table) over an
    # unreachable pose over a limit (most straight approaches to a low tip start below the
    # table), with the count of each over all variants.
    counts = {r: sum(e.reason == r for e in refusals) for r in ("collision", "unreachable", "limits")}
    first = refusals[:primary] or refusals
    shown = next(e for r in ("collision", "unreachable", "limits", None) for e in first if r is None or e.reason == r)
    tally = ", ".join(f"{n} {r}" for r, n in counts.items() if n)
    raise PlanRefused(shown.reason, f"{shown.detail} (all {len(refusals)} approach variants refused: {tally})")


def plan_for_estimate(est: Any, spec: Any, cfg: Any, limits: SafetyLimits, *, shift: Any = None,
                      **kw: Any) -> GraspPlan:
    """:func:`plan_grasp` for an ``estimator.Estimate`` ``est`` of the tape ``spec``
    (``Capture.tape``) in the cell file ``cfg``: its tip frame, its centre line and faces
    checked against the open fingers, its base for the peel direction. ``shift`` (3,) [m]:
    the estimated tape (tip, centre line and faces; not its base) moved by this first (onto
    the needle's touch at a grasp point). ``kw``: :func:`plan_grasp`'s other keywords."""
    tip = TipFrame.from_estimate(est)
    nodes = np.asarray(est.nodes, float)
    surface = estimated_surface(spec, est.angles)
    if shift is not None:
        tip = dataclasses.replace(tip, position=tip.position + shift)
        nodes, surface = nodes + shift, surface + shift
    return plan_grasp(tip, GraspParams.from_config(cfg.grasp), GripperGeometry.from_config(cfg.tools.gripper), limits,
                      tape_points=nodes, tape_base=np.asarray(est.nodes, float)[0], tape_surface=surface, **kw)


def grasp_insets(params: Any) -> tuple[float, ...]:
    """The grasp points' distances in from the tip [m] :func:`plan_grasp` tries, in order: the
    cell file's ``inset`` (``params.inset``), then the fallbacks of :data:`EXTRA_INSETS_M`."""
    return (float(params.inset), *(float(params.inset) + d for d in EXTRA_INSETS_M))


def grasp_frame(tip: TipFrame, inset: float, straight: float, tape_points: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), world_from_grasp rotation (3, 3)) of the grasp point ``inset`` [m] in
    from the tip. Up to ``straight`` [m] (the cell file's inset) along the tip's trunk, with
    the tip's frame; further in, along the estimated centre line (``tape_points``, base
    first, ending at the tip's plate), the tip's frame turned by the least rotation that
    lays its trunk along the line there (without ``tape_points``: along the trunk)."""
    R_tip = np.asarray(tip.rotation, float)
    if inset <= straight + 1e-12 or tape_points is None:
        return tip.position - inset * tip.trunk, R_tip
    line = list(_centre_line(tip, tape_points))
    left = inset
    for a, b in zip(line[:-1], line[1:]):
        length = float(np.linalg.norm(b - a))
        if length < 1e-9:
            continue
        if left <= length or b is line[-1]:
            trunk = (a - b) / length                 # outwards, towards the tip
            position = a + (b - a) * min(left / length, 1.0)
            break
        left -= length
    else:
        return tip.position - inset * tip.trunk, R_tip
    axis = np.cross(tip.trunk, trunk)
    s, c = float(np.linalg.norm(axis)), float(tip.trunk @ trunk)
    turn = _axis_angle(axis / s, np.arctan2(s, c)) if s > 1e-9 else np.eye(3)
    return position, turn @ R_tip


def _centre_line(tip: TipFrame, tape_points: Any) -> np.ndarray:
    """(k, 3) the estimated centre line :func:`grasp_frame` walks: from the tip back through
    ``tape_points`` (base first, ending at the tip's plate) to the base."""
    return np.vstack([np.asarray(tip.position, float)[None], np.asarray(tape_points, float)[-2::-1]])


def tape_surface_points(nodes: Any, frames: Any, width: float, step: float = 0.002) -> np.ndarray:
    """(M, 3) points on a plate chain's faces: along each plate (``nodes`` (n+1, 3), base
    first) every ``step`` [m] and across its ``width`` [m] every ~2.5 mm, the plate's width
    axis the second column of ``frames[i + 1]`` ((n+1, 3, 3), as ``forward_kinematics``
    gives them)."""
    nodes, frames = np.asarray(nodes, float), np.asarray(frames, float)
    across = np.linspace(-0.5, 0.5, max(int(np.ceil(width / 0.0025)), 1) + 1) * width
    out = []
    for i in range(len(nodes) - 1):
        a, b = nodes[i], nodes[i + 1]
        k = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        line = a + (b - a) * np.linspace(0.0, 1.0, k + 1)[:, None]
        out.append((line[:, None, :] + across[None, :, None] * frames[i + 1][:, 1]).reshape(-1, 3))
    return np.concatenate(out) if out else np.zeros((0, 3))


def estimated_surface(spec: Any, angles: Any) -> np.ndarray:
    """:func:`tape_surface_points` of the plate chain ``angles`` (n, 3) [rad] of the tape
    model ``spec`` (an ``estimator.TapeSpec``, e.g. ``Capture.tape``): what the planner keeps
    the open gripper clear of."""
    from tapecell.estimator.tape import forward_kinematics

    shape = forward_kinematics(spec, np.asarray(angles, float))
    return tape_surface_points(shape.nodes, shape.frames, float(spec.width))


def lift_path(world_from_grasp: np.ndarray, tape_base: Any, lift: float, mode: str) -> list[np.ndarray]:
    """world_from_tcp poses after the grasp, each within 10 mm of the previous, covering a
    TCP path of ``lift`` metres (see the module docstring for the modes)."""
    up = np.array([0.0, 0.0, 1.0])
    p = world_from_grasp[:3, 3]
    chord = None if tape_base is None else p - np.asarray(tape_base, float)
    k = max(int(np.ceil(lift / 0.01)), 1)
    if mode == "arc" and chord is not None and np.linalg.norm(chord) > 1e-3:
        radius = np.linalg.norm(chord)
        axis = np.cross(chord, up)
        if np.linalg.norm(axis) < 1e-6 * radius:
            axis = np.cross(chord, world_from_grasp[:3, 1])   # vertical chord: swing across the jaw
        axis /= np.linalg.norm(axis)
        out = []
        for i in range(1, k + 1):
            R = _axis_angle(axis, (lift / radius) * i / k)
            T = world_from_grasp.copy()    # the jaw keeps its orientation: a floppy tape
            T[:3, 3] = np.asarray(tape_base, float) + R @ chord   # bends at the grasp instead
            out.append(T)
        return out
    d = up if chord is None or np.linalg.norm(chord) < 1e-6 else up + chord / np.linalg.norm(chord)
    d /= np.linalg.norm(d)
    out = []
    for i in range(1, k + 1):
        T = world_from_grasp.copy()
        T[:3, 3] = p + lift * d * i / k
        out.append(T)
    return out


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(axis * angle).as_matrix()


def tcp_rotation(tip: TipFrame, tilt: float, flipped: bool, pitch: float = 0.0) -> np.ndarray:
    """world_from_tcp rotation: y (closing axis) along the tape normal, z (approach) along
    -trunk tilted by ``tilt`` rad about the normal, then pitched by ``pitch`` rad out of
    the tape's plane (towards the normal); ``flipped`` turns the jaw half a turn."""
    t, w, n = tip.rotation[:, 0], tip.rotation[:, 1], tip.rotation[:, 2]
    y = -n if flipped else n
    z = np.cos(tilt) * (-t) + np.sin(tilt) * w   # rotating -t about n stays in the tape's plane
    z = np.cos(pitch) * z + np.sin(pitch) * n
    z /= np.linalg.norm(z)
    y = y - z * (y @ z)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def _plan_variant(tip, grasp_position, tape_base, tilt, flipped, params, gripper, limits, ik, q_ref,
                  check_joint_path, tape, pitch=0.0, grasp_rotation=None, surface=None, speeds=None,
                  precheck=False, solid=None) -> GraspPlan:
    """The plan of one approach variant, or :class:`PlanRefused` with the first check it
    fails. ``precheck``: first the cheap checks (each waypoint's pose where it stands, the
    arm's reach at the grasp), then the motions: the same answer, sooner for the many
    fallback variants that fail (a refusal's reason may then be another of its failures)."""
    speeds = Speeds() if speeds is None else speeds
    at_grasp = tip if grasp_rotation is None else TipFrame(grasp_position, grasp_rotation, tip.cost)
    R = tcp_rotation(at_grasp, tilt, flipped, pitch)
    approach = R[:, 2]
    world_from_tcp = {"pregrasp": _T(R, grasp_position - params.pregrasp_distance * approach),
                      "grasp": _T(R, grasp_position)}
    lifts = lift_path(world_from_tcp["grasp"], tape_base, params.lift, params.lift_mode)
    lift_names = [f"lift_{i}" for i in range(1, len(lifts))] + ["lift"]
    world_from_tcp.update(zip(lift_names, lifts))
    names = list(world_from_tcp)
    tcp_from_flange = invert(gripper.flange_from_tcp)
    flange = {k: matrix_to_pose6(T @ tcp_from_flange) for k, T in world_from_tcp.items()}
    points, shape = solid if solid is not None else (gripper.check_points_flange(), gripper.shape())
    planned = dataclasses.replace(limits, clearance=limits.clearance + PLAN_MARGIN_M)
    if precheck:
        try:
            for name in ("grasp", "pregrasp", names[-1]):
                check_linear_move(planned, flange[name], flange[name], limits.max_tcp_speed, limits.max_tcp_accel,
                                  points, shape)
        except SafetyError as e:
            raise PlanRefused("collision" if isinstance(e, KeepOutError) else "limits", str(e)) from None
        if ik is ik_nearest and ik(pose6_to_matrix(flange["grasp"]), q_ref) is None:   # None: no solution at all
            raise PlanRefused("unreachable", f"no joint solution puts the gripper at the grasp pose "
                                             f"(TCP at {_mm(grasp_position)} mm)")
    try:
        check_linear_move(planned, flange["pregrasp"], flange["pregrasp"], limits.max_tcp_speed,
                          limits.max_tcp_accel, points, shape)
        for a, b in zip(names[:-1], names[1:]):
            check_linear_move(planned, flange[a], flange[b], limits.max_tcp_speed, limits.max_tcp_accel, points,
                              shape)
    except SafetyError as e:
        raise PlanRefused("collision" if isinstance(e, KeepOutError) else "limits", str(e)) from None
    for points_on_tape in (tape, surface):
        if points_on_tape is not None:
            _check_fingers_clear(points_on_tape, world_from_tcp["pregrasp"], world_from_tcp["grasp"], gripper)
    q_pre, via = _reach_pregrasp(world_from_tcp["pregrasp"], flange["pregrasp"], tcp_from_flange, q_ref, ik,
                                 limits, points, shape, check_joint_path,
                                 tape_clear=None if surface is None else (surface, gripper))
    q = {"pregrasp": q_pre}
    path = [q_pre]
    for a, b in zip(names[:-1], names[1:]):
        q[b], along = _follow_line(ik, flange[a], flange[b], q[a], "approach" if b == "grasp" else "lift",
                                   speeds.approach if b == "grasp" else speeds.lift, limits.max_joint_speed)
        path += along
    try:
        # With PLAN_MARGIN_M more than the clearance: the arm's joints on the way differ a
        # little from these IK samples, and the same check runs again on them as it moves.
        check_wrist_clear(planned, np.array(path), "approach and lift")
    except SafetyError as e:
        raise PlanRefused("collision", str(e)) from None
    waypoints = tuple(Waypoint(k, world_from_tcp[k], flange[k], q[k]) for k in names)
    first = (Step("move_joints", "pregrasp"),)
    for name in reversed(list(via)):
        w = via[name]
        waypoints = (Waypoint(name, w["world_from_tcp"], w["flange"], w["q"]),) + waypoints
        first = (Step("move_joints", name),) + first
    if len(lift_names) > 1:
        try:
            # The lift's legs were checked above; its blends (each corner's chord) too.
            check_blends(planned, flange["grasp"], [flange[k] for k in lift_names], limits.max_tcp_speed,
                         limits.max_tcp_accel, LIFT_BLEND_M, points, shape)
        except SafetyError as e:
            raise PlanRefused("collision" if isinstance(e, KeepOutError) else "limits", str(e)) from None
    lift_step = (Step("move_linear_path", lift_names[-1], tuple(lift_names[:-1]), LIFT_BLEND_M)
                 if len(lift_names) > 1 else Step("move_linear", lift_names[-1]))
    steps = (Step("open_gripper"), *first, Step("move_linear", "grasp"), Step("close_gripper"), lift_step)
    lift_vector = lifts[-1][:3, 3] - grasp_position
    return GraspPlan(waypoints, steps, tip, float(tilt), bool(flipped), points,
                     lift_vector / max(np.linalg.norm(lift_vector), 1e-12), shape, float(pitch))


def _reach_pregrasp(world_from_pre: np.ndarray, flange_pre: np.ndarray, tcp_from_flange: np.ndarray,
                    q_ref: np.ndarray, ik: IK, limits: SafetyLimits, points: np.ndarray, shape: ToolShape,
                    check_joint_path: bool, tape_clear: tuple | None = None) -> tuple[np.ndarray, dict]:
    """(joints at the pre-grasp pose, the "above" waypoint or {}): the arm configuration
    nearest ``q_ref`` whose joint move there (straight, or through "above") keeps the wrist
    and the gripper clear (and, with ``tape_clear`` = (tape surface points (M, 3), the
    gripper's geometry), the open fingers and palm :data:`TAPE_CLEARANCE_M` from the
    estimated tape); with the UR5e's own kinematics the other configurations (elbow,
    wrist, shoulder flipped) are tried when the nearest one is blocked."""
    T = pose6_to_matrix(flange_pre)
    q_near = ik(T, q_ref)
    if q_near is None:
        raise PlanRefused("unreachable", f"no joint solution puts the gripper at the pre-grasp pose "
                                         f"(TCP at {_mm(world_from_pre[:3, 3])} mm)")
    if not check_joint_path:
        return q_near, {}
    candidates = [q_near]
    if ik is ik_nearest:
        from .kinematics import JOINT_LOWER, JOINT_UPPER, ik_solutions

        others = [q_ref + (q - q_ref + np.pi) % (2 * np.pi) - np.pi for q in ik_solutions(T)]
        others = [q for q in others if np.all(q >= JOINT_LOWER) and np.all(q <= JOINT_UPPER)
                  and np.max(np.abs(q - q_near)) > 1e-6]
        candidates += sorted(others, key=lambda q: float(np.max(np.abs(q - q_ref))))
    first: SafetyError | None = None
    for q_pre in candidates:
        try:
            check_joint_move(limits, q_ref, q_pre, limits.max_joint_speed, limits.max_joint_accel, points,
                             shape=shape)
            if tape_clear is not None:
                check_tape_clear(q_ref, q_pre, *tape_clear, tcp_from_flange)
            return q_pre, {}
        except SafetyError as e:
            first = first or e
            # A straight joint move would sweep the wrist or the gripper through the table
            # or the part (or the open gripper through the tape): go through a pose above
            # the pre-grasp, or high over the part.
            for via in (_via_above(world_from_pre, tcp_from_flange, q_ref, q_pre, ik, limits, points, shape,
                                   tape_clear),
                        _via_clear(tcp_from_flange, q_ref, q_pre, limits, points, shape, tape_clear)):
                if via:
                    return q_pre, via
    raise PlanRefused("collision" if isinstance(first, KeepOutError) else "limits",
                      f"joint move to the pre-grasp pose: {first}")


def check_tape_clear(q_start: np.ndarray, q_target: np.ndarray, tape_surface: np.ndarray, gripper: GripperGeometry,
                     tcp_from_flange: np.ndarray, margin: float = TAPE_CLEARANCE_M) -> None:
    """Raise :class:`~cell.safety.CollisionError` where a joint move from ``q_start`` to
    ``q_target`` [rad] (sampled as :func:`~cell.safety.check_joint_move` samples it) brings
    the open gripper's fingers or palm within ``margin`` [m] of a point of ``tape_surface``
    (M, 3) [m, world]: the tape is not an obstacle of the cell, but a pad swept through it
    drags the floppy tape out of the jaw before the approach starts. A move that starts
    with the gripper already that close (an arm an operator left at the tape, after probing
    it in freedrive) is not judged: where it goes from there is the operator's setup, not
    the planner's choice."""
    from .safety import CollisionError

    if len(tape_surface) == 0:
        return
    qa, qb = np.asarray(q_start, float), np.asarray(q_target, float)
    n = int(np.ceil(np.max(np.abs(qb - qa)) / 0.01)) + 2
    boxes = gripper.finger_boxes_tcp()
    flange_from_tcp = invert(tcp_from_flange)
    centre = tape_surface.mean(axis=0)
    reach = float(np.max(np.linalg.norm(tape_surface - centre, axis=1)))
    steps = np.linspace(0.0, 1.0, n)
    far = reach + gripper.finger_length + 0.1
    near_at_start = None
    maybe = np.ones(0, bool)
    for k, s in enumerate(steps):
        if k % _TAPE_NEAR_CHUNK == 0:      # the next samples' prefilter, all at once
            maybe = _tape_maybe_near(qa, qb, steps[k:k + _TAPE_NEAR_CHUNK], tape_surface, boxes, flange_from_tcp,
                                     centre, far, margin)
        if k > 0 and not maybe[k % _TAPE_NEAR_CHUNK]:
            continue          # surely no tape point near the gripper here: the test below would pass it
        world_from_tcp = fk(qa + s * (qb - qa)) @ flange_from_tcp
        if near_at_start is not None and np.linalg.norm(world_from_tcp[:3, 3] - centre) > far:
            continue          # the whole gripper is far from the whole tape
        near = _in_boxes((tape_surface - world_from_tcp[:3, 3]) @ world_from_tcp[:3, :3], boxes, margin)
        if near_at_start is None:
            near_at_start = near.any(axis=0)
            if np.any(near_at_start):
                return
            continue
        for i in range(len(boxes)):
            inside = near[i]
            if np.any(inside):
                part = "palm" if i == 2 else "finger"
                raise CollisionError(f"joint move: the open gripper's {part} would pass within "
                                     f"{margin * 1e3:.0f} mm of the estimated tape near "
                                     f"{_mm(tape_surface[np.argmax(inside)])} mm")


_TAPE_NEAR_SLACK_M = 1e-9
""":func:`_tape_maybe_near` passes a sample unless it is clear by this much more than the
exact test needs, so that its stacked arithmetic (rounding ~1e-16 m apart from the exact
test's) cannot drop a sample the exact test would stop at."""


def _tape_maybe_near(qa: np.ndarray, qb: np.ndarray, steps: np.ndarray, tape_surface: np.ndarray, boxes: list,
                     flange_from_tcp: np.ndarray, centre: np.ndarray, far: float, margin: float) -> np.ndarray:
    """(n,) bool, per sample of the joint move of :func:`check_tape_clear`: False where that
    sample surely has no tape point within ``margin`` of a finger or the palm (the TCP more
    than ``far`` from the tape's ``centre``, or every point outside every widened box), by
    slack :data:`_TAPE_NEAR_SLACK_M`; all samples at once with stacked arithmetic, so only
    the others need the exact test one at a time."""
    from .kinematics import dh_frames_many

    world_from_tcp = dh_frames_many(qa + steps[:, None] * (qb - qa))[:, -1] @ flange_from_tcp      # (n, 4, 4)
    p = world_from_tcp[:, :3, 3]
    maybe = np.linalg.norm(p - centre, axis=1) <= far + _TAPE_NEAR_SLACK_M
    # A sphere around the widened boxes (TCP frame) against a sphere around the tape
    # (about its centre): where they are apart, no tape point is in a widened box.
    corners_lo = np.min([lo for lo, _ in boxes], axis=0) - margin
    corners_hi = np.max([hi for _, hi in boxes], axis=0) + margin
    mid = 0.5 * (corners_lo + corners_hi)
    radius = max(float(np.linalg.norm(np.maximum(np.abs(lo - margin - mid), np.abs(hi + margin - mid))))
                 for lo, hi in boxes)
    tape_reach = float(np.max(np.linalg.norm(tape_surface - centre, axis=1)))
    mid_world = np.einsum("nij,j->ni", world_from_tcp[:, :3, :3], mid) + p
    maybe &= np.linalg.norm(mid_world - centre, axis=1) <= tape_reach + radius + _TAPE_NEAR_SLACK_M
    idx = np.flatnonzero(maybe)
    if len(idx):
        local = (tape_surface[None] - p[idx, None]) @ world_from_tcp[idx, :3, :3]      # (m, M, 3)
        maybe[idx] = _in_boxes(local, boxes, margin + _TAPE_NEAR_SLACK_M).any(axis=(0, 2))
    return maybe


_TAPE_NEAR_CHUNK = 32
"""Samples per call of :func:`_tape_maybe_near` (a move that stops early computes little more)."""


VIA_RISE_M = 0.15
"""When the joint move to the pre-grasp pose would hit the table or the part, the arm
first goes to the pre-grasp pose raised by this much [m] (same orientation and arm
configuration), then down to it; failing that, through :data:`REFERENCE_JOINTS` (high
over the part, wrist down)."""


def _waypoint_at(q: np.ndarray, tcp_from_flange: np.ndarray) -> dict:
    world_from_flange = fk(q)
    return {"world_from_tcp": world_from_flange @ invert(tcp_from_flange), "flange": matrix_to_pose6(world_from_flange),
            "q": np.asarray(q, float)}


def _clear_moves(limits, points, shape, *qs, tape_clear=None, tcp_from_flange=None) -> bool:
    """Are the joint moves through ``qs`` in turn clear of every limit and obstacle (and of
    the estimated tape, with ``tape_clear``)?"""
    try:
        for a, b in zip(qs[:-1], qs[1:]):
            check_joint_move(limits, a, b, limits.max_joint_speed, limits.max_joint_accel, points, shape=shape)
            if tape_clear is not None:
                check_tape_clear(a, b, *tape_clear, tcp_from_flange)
    except SafetyError:
        return False
    return True


def _via_above(world_from_pre: np.ndarray, tcp_from_flange: np.ndarray, q_ref: np.ndarray, q_pre: np.ndarray,
               ik: IK, limits: SafetyLimits, points: np.ndarray, shape: ToolShape, tape_clear=None) -> dict:
    """{"above": waypoint} through which both joint moves are clear, or {}."""
    T = world_from_pre.copy()
    T[2, 3] += VIA_RISE_M
    flange = matrix_to_pose6(T @ tcp_from_flange)
    q_via = ik(pose6_to_matrix(flange), q_pre)
    if q_via is None or not _clear_moves(limits, points, shape, q_ref, q_via, q_pre, tape_clear=tape_clear,
                                         tcp_from_flange=tcp_from_flange):
        return {}
    return {"above": {"world_from_tcp": T, "flange": flange, "q": q_via}}


def _via_clear(tcp_from_flange: np.ndarray, q_ref: np.ndarray, q_pre: np.ndarray, limits: SafetyLimits,
               points: np.ndarray, shape: ToolShape, tape_clear=None) -> dict:
    """{"clear": REFERENCE_JOINTS} through which both joint moves are clear, or {}."""
    if np.allclose(q_ref, REFERENCE_JOINTS) or not _clear_moves(limits, points, shape, q_ref, REFERENCE_JOINTS, q_pre,
                                                                tape_clear=tape_clear,
                                                                tcp_from_flange=tcp_from_flange):
        return {}
    return {"clear": _waypoint_at(REFERENCE_JOINTS, tcp_from_flange)}


def _follow_line(ik: IK, start: np.ndarray, end: np.ndarray, q0: np.ndarray, what: str,
                 speed: float | None = None, max_joint_speed: float | None = None) -> tuple:
    """(joints at ``end``, the joints at every sample on the way) after following the
    straight flange line from ``start``, keeping one configuration (as ``moveL`` does);
    refuse where the line leaves the reachable set or passes a singularity (a large joint
    step between nearby samples), or, given the line's ``speed`` [m/s], where a joint would
    have to turn faster than ``max_joint_speed`` [rad/s] to keep the tool on the line (near
    a wrist singularity: the simulated arm then leaves the line by centimetres, seed 400120,
    and a real controller stops)."""
    length = float(np.linalg.norm(end[:3] - start[:3]))
    n = int(np.ceil(length / PATH_STEP_M)) + 1
    q = q0
    along = []
    fastest = np.inf if not (speed and max_joint_speed) else max_joint_speed * (length / n) / speed
    for pose in interpolate_pose6(start, end, n + 1)[1:]:
        q_next = ik(pose6_to_matrix(pose), q)
        if q_next is None:
            raise PlanRefused("unreachable", f"the {what} leaves the arm's reach near flange {_mm(pose[:3])} mm")
        step = float(np.max(np.abs(q_next - q)))
        if step > MAX_JOINT_STEP_RAD:
            raise PlanRefused("unreachable", f"the {what} passes a singularity near flange {_mm(pose[:3])} mm")
        if step > fastest:
            raise PlanRefused("unreachable", f"the {what} at {speed:g} m/s would turn a joint at "
                                             f"{step / fastest * max_joint_speed:.1f} rad/s (limit "
                                             f"{max_joint_speed:g}) near flange {_mm(pose[:3])} mm: near a singularity")
        q = q_next
        along.append(q)
    return q, along


def _check_fingers_clear(tape: np.ndarray, start: np.ndarray, end: np.ndarray, gripper: GripperGeometry) -> None:
    """Refuse when a tape point lies inside an open finger or the palm, or within
    APPROACH_TAPE_MARGIN_M of one, anywhere on the approach from ``start`` to ``end``
    (world_from_tcp)."""
    boxes = gripper.finger_boxes_tcp()
    n = int(np.ceil(np.linalg.norm(end[:3, 3] - start[:3, 3]) / 0.002)) + 1
    # The approach only translates: the tape in the TCP frame at every sample at once.
    local0 = (tape - start[:3, 3]) @ start[:3, :3]                             # (M, 3)
    shift = np.linspace(0.0, 1.0, n + 1)[:, None] * ((end[:3, 3] - start[:3, 3]) @ start[:3, :3])
    local = local0[None] - shift[:, None]                                     # (n + 1, M, 3)
    inside = _in_boxes(local, boxes, APPROACH_TAPE_MARGIN_M)                    # (boxes, n + 1, M)
    if np.any(inside):
        hit = inside.any(axis=2)                                              # (boxes, n + 1)
        first = int(np.argmax(hit.any(axis=0)))                               # the earliest sample
        i = int(np.argmax(hit[:, first]))
        part = "palm" if i == 2 else "finger"
        raise PlanRefused("collision", f"the open gripper's {part} would hit the tape near "
                                       f"{_mm(tape[np.argmax(inside[i, first])])} mm on the approach")


def _in_boxes(local: np.ndarray, boxes: list, margin: float) -> np.ndarray:
    """(boxes, ...) bool: which points ``local`` (..., 3), in the boxes' frame, lie inside
    each (lo, hi) box grown by ``margin`` [m]."""
    return np.stack([np.all((local > lo - margin) & (local < hi + margin), axis=-1) for lo, hi in boxes])


def _densify(points: np.ndarray, step: float) -> np.ndarray:
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        k = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out.append(a + (b - a) * np.linspace(0, 1, k + 1)[1:, None])
    return np.concatenate(out)


def _T(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


def _mm(p: np.ndarray) -> str:
    return "[" + ", ".join(f"{v * 1000:.1f}" for v in p) + "]"


# ------------------------------------------------------------------------------ execution
@dataclass(frozen=True)
class Speeds:
    """joint [rad/s], joint_accel [rad/s^2] for the move to pre-grasp; linear [m/s] and
    linear_accel [m/s^2] for the approach and the lift (slow: contact and peeling)."""

    joint: float = 1.0
    joint_accel: float = 1.2
    approach: float = 0.1
    lift: float = 0.05
    linear_accel: float = 0.8


def execute_plan(plan: GraspPlan, arm: Arm, limits: SafetyLimits, speeds: Speeds = Speeds(),
                 on_step: Callable[[Step, Arm], None] | None = None) -> list[Step]:
    """Run ``plan`` on a connected ``arm``; every motion is checked against ``limits``
    (through :class:`~cell.safety.SafeArm`, with the gripper's check points) before it is
    sent. The whole plan and the speeds are checked before the first motion, so a plan that
    would violate a limit halfway never starts. On any error the arm is stopped and the
    error re-raised. ``on_step(step, arm)`` is called after each step (logging). Returns
    the steps done."""
    safe = SafeArm(arm, limits, points_flange=plan.points_flange, shape=plan.shape)
    _precheck(plan, limits, speeds)
    done: list[Step] = []
    try:
        for step in plan.steps:
            _run_step(safe, plan, step, speeds)
            if safe.is_protective_stopped():
                raise ProtectiveStopError(f"{arm.name} is in a protective stop after {step.action}")
            done.append(step)
            if on_step is not None:
                on_step(step, arm)
    except BaseException:
        if arm.is_connected:
            try:
                arm.stop()
            except ArmError:
                pass  # the original error says more
        raise
    return done


def _precheck(plan: GraspPlan, limits: SafetyLimits, speeds: Speeds) -> None:
    if speeds.joint > limits.max_joint_speed or speeds.joint_accel > limits.max_joint_accel:
        raise SafetyError(f"plan joint speed {speeds.joint:g} rad/s / acceleration {speeds.joint_accel:g} "
                          f"rad/s^2 exceeds the limits {limits.max_joint_speed:g} / {limits.max_joint_accel:g}")
    for v in (speeds.approach, speeds.lift):
        if v > limits.max_tcp_speed:
            raise SafetyError(f"plan speed {v:g} m/s exceeds the limit {limits.max_tcp_speed:g} m/s")
    if speeds.linear_accel > limits.max_tcp_accel:
        raise SafetyError(f"plan acceleration {speeds.linear_accel:g} m/s^2 exceeds the limit "
                          f"{limits.max_tcp_accel:g} m/s^2")
    previous = None
    for step in plan.steps:
        if step.waypoint is None:
            continue
        targets = [plan.waypoint(name).flange_pose for name in step.targets]
        start = targets[0] if previous is None or step.action == "move_joints" else previous
        check_linear_path(limits, start, targets, speeds.approach, speeds.linear_accel, step.blend,
                          plan.points_flange, plan.shape)
        previous = targets[-1]


def _run_step(arm: Arm, plan: GraspPlan, step: Step, speeds: Speeds) -> None:
    if step.action == "open_gripper":
        arm.open_gripper()
    elif step.action == "close_gripper":
        arm.close_gripper()
    elif step.action == "move_joints":
        arm.move_joints(plan.waypoint(step.waypoint).q, speeds.joint, speeds.joint_accel)
    elif step.action in ("move_linear", "move_linear_path"):
        speed = speeds.lift if step.waypoint.startswith("lift") else speeds.approach
        poses = [plan.waypoint(name).flange_pose for name in step.targets]
        if step.action == "move_linear":
            arm.move_linear(poses[0], speed, speeds.linear_accel)
        else:
            arm.move_linear_path(poses, speed, speeds.linear_accel, step.blend)
    else:
        raise ArmError(f"unknown plan step '{step.action}'")
