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

Collisions with the cell's solid boxes (``obstacles``: the table and the part, from the
cell file's ``[table]`` and ``[part]``): the tool's shape (a :class:`ToolShape`, points
with radii in the flange frame: the gripper's fingers, palm and mount, or the needle) and
the wrist's three links (cylinders of :data:`WRIST_RADIUS_M` between the UR5e's wrist
centres and the flange) must stay ``clearance`` metres away from every box along the whole
motion. This replaces a flat floor under the workspace: a tip hanging low is reached as
long as the gripper itself clears the table.

:class:`SafeArm` wraps any :class:`~cell.arm.Arm` so no caller can bypass the check.
"""
from __future__ import annotations

import functools

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy.spatial.transform import Rotation

from tapecell.estimator.errors import TaskFailed

from .arm import Arm
from .poses import interpolate_pose6, interpolate_pose6_at, pose6_to_matrix, rotation_angle_between


class SafetyError(TaskFailed):
    """A target or a motion violates the cell's safety limits; nothing was sent (exit 1:
    the task cannot be done within the limits)."""


class KeepOutError(SafetyError):
    """A motion would take a check point into the keep-out box around the part."""


class CollisionError(KeepOutError):
    """A motion would bring the tool or the wrist closer than the clearance to the table
    or the part."""


WRIST_RADIUS_M = 0.040
"""Radius of the UR5e's wrist housings (about 80 mm across; the simulated arm's wrist
cylinders, assets/ur5e.xml), as cylinders from each wrist centre to the next and to the
flange."""
SHAPE_STEP_M = 0.003
"""Tool shapes are sampled this finely: a surface between samples is at most ~2 mm from
one, so the clearance actually kept is at least ``clearance`` - 2 mm."""


_PREFILTER_SLACK_M = 1e-9
"""A vectorised bounding-sphere test skips a part or a wrist link only when it is clear by
this much more than the clearance, so rounding in the vectorised arithmetic cannot skip one
that the exact test would find too close."""


@dataclass(frozen=True)
class Obstacle:
    """A solid axis-aligned box of the cell [m] (world = base frame)."""

    name: str
    lo: np.ndarray
    hi: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(...,) distance of points (..., 3) from the box (0 inside)."""
        d = np.maximum(np.maximum(self.lo - points, points - self.hi), 0.0)
        # np.linalg.norm(d, axis=-1) written out as it computes it (the same numbers,
        # without its checks: this runs tens of thousands of times per refused plan)
        return np.sqrt(np.add.reduce(d * d, axis=-1))


@dataclass(frozen=True, eq=False)
class ToolShape:
    """A tool's solid shape as spheres: centres (N, 3) in the flange frame [m], radii (N,)
    [m] (0 for points sampled on a surface) and, for messages, which named part (index
    into ``parts``) each belongs to."""

    points_flange: np.ndarray
    radii: np.ndarray
    parts: tuple = ("tool",)
    part_index: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.part_index is None:
            object.__setattr__(self, "part_index", np.zeros(len(self.points_flange), int))

    @functools.cached_property
    def part_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """(centres (P, 3) in the flange frame [m], radii (P,) [m]): per part, a sphere
        around its points' spheres (a coarse test before the points' own)."""
        centres, reaches = [], []
        for k in range(len(self.parts)):
            pts, rad = self.points_flange[self.part_index == k], self.radii[self.part_index == k]
            if len(pts) == 0:
                continue
            c = pts.mean(axis=0)
            centres.append(c)
            reaches.append(float(np.max(np.linalg.norm(pts - c, axis=1) + rad)))
        return np.array(centres).reshape(-1, 3), np.array(reaches)

    @functools.cached_property
    def part_points(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """Per part that has points, in the order of :attr:`part_spheres`: (its points
        (N_k, 3) in the flange frame [m], their radii (N_k,) [m])."""
        return tuple((self.points_flange[self.part_index == k], self.radii[self.part_index == k])
                     for k in range(len(self.parts)) if np.any(self.part_index == k))

    @classmethod
    def join(cls, *shapes: "ToolShape") -> "ToolShape":
        parts: list[str] = []
        index = []
        for sh in shapes:
            index.append(sh.part_index + len(parts))
            parts += list(sh.parts)
        return cls(np.vstack([sh.points_flange for sh in shapes]), np.concatenate([sh.radii for sh in shapes]),
                   tuple(parts), np.concatenate(index))

    @classmethod
    def points(cls, points_flange: Any, name: str = "tool") -> "ToolShape":
        """Bare points (radius 0), e.g. the check points of a tool known only by them."""
        p = np.asarray(points_flange, float).reshape(-1, 3)
        return cls(p, np.zeros(len(p)), (name,))

    @classmethod
    def box(cls, name: str, flange_from_box: np.ndarray, lo: Any, hi: Any, step: float = SHAPE_STEP_M) -> "ToolShape":
        """A box (lo, hi) in its own frame, placed by ``flange_from_box`` (4x4), sampled
        on its surface."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        axes = [np.linspace(lo[k], hi[k], max(int(np.ceil((hi[k] - lo[k]) / step)), 1) + 1) for k in range(3)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        p = grid[np.any(np.isclose(grid, lo) | np.isclose(grid, hi), axis=1)]
        p = (np.asarray(flange_from_box, float)[:3, :3] @ p.T).T + np.asarray(flange_from_box, float)[:3, 3]
        return cls(p, np.zeros(len(p)), (name,))

    @classmethod
    def capsule(cls, name: str, a: Any, b: Any, radius: float, step: float = SHAPE_STEP_M) -> "ToolShape":
        """A capsule from a to b (flange frame) of ``radius`` [m]."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1) + 1
        p = a + (b - a) * np.linspace(0.0, 1.0, n)[:, None]
        return cls(p, np.full(n, float(radius)), (name,))


@dataclass(frozen=True, eq=False)
class SafetyLimits:
    """The cell's limits. Boxes are axis-aligned in the base frame (= world) [m].

    workspace_min, workspace_max: (3,) box every check point's target must lie in.
    keepout_min, keepout_max: (3,) box around the part no check point may enter.
    obstacles: :class:`Obstacle` boxes (the table, the part) the tool's shape and the wrist
    keep ``clearance`` [m] from.
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
    obstacles: tuple = ()
    clearance: float = 0.005

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
        if not np.isfinite(self.clearance) or self.clearance < 0:
            raise SafetyError("limits.clearance must be a number >= 0 [m]")
        object.__setattr__(self, "clearance", float(self.clearance))
        object.__setattr__(self, "obstacles", tuple(self.obstacles))

    @classmethod
    def from_config(cls, section: Any, obstacles: Any = ()) -> "SafetyLimits":
        """From the cell file's ``limits`` section (``sim.config.LimitsSection``) or any
        object with the same attributes; ``max_joint_accel`` defaults to UR's 1.4 rad/s^2,
        ``clearance`` to 5 mm. ``obstacles``: :class:`Obstacle` boxes (see
        :meth:`from_cell`)."""
        return cls(
            workspace_min=section.workspace_min, workspace_max=section.workspace_max,
            max_tcp_speed=section.max_tcp_speed, max_tcp_accel=section.max_tcp_accel,
            max_joint_speed=section.max_joint_speed,
            keepout_min=section.keepout_min, keepout_max=section.keepout_max,
            max_joint_accel=getattr(section, "max_joint_accel", 1.4),
            obstacles=tuple(obstacles), clearance=getattr(section, "clearance", 0.005),
        )

    @classmethod
    def from_cell(cls, cfg: Any) -> "SafetyLimits":
        """The whole cell's limits: ``[limits]`` with the table and the part of the cell
        file as obstacles."""
        from .config import scene_boxes

        obstacles = [Obstacle(b.name, b.center - b.size / 2, b.center + b.size / 2) for b in scene_boxes(cfg)]
        return cls.from_config(cfg.limits, obstacles)


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
    n, k = paths.shape[:2]
    hits = segments_hit_box(paths[:-1].reshape(-1, 3), paths[1:].reshape(-1, 3), limits.keepout_min,
                            limits.keepout_max).reshape(n - 1, k) if n > 1 else np.zeros((0, k), bool)
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


def _check_clear(limits: SafetyLimits, points: np.ndarray, radii: np.ndarray, names: list[str],
                 motion: str) -> None:
    """points (n_samples, k, 3) world, radii (k,), names (k,): raise :class:`CollisionError`
    where a sphere comes closer than the clearance to an obstacle."""
    for ob in limits.obstacles:
        gap = ob.distance(points) - radii           # (n_samples, k)
        bad = gap < limits.clearance
        if np.any(bad):
            i, j = np.unravel_index(np.argmin(np.where(bad, gap, np.inf)), gap.shape)
            raise CollisionError(f"{motion}: the {names[j]} would come {max(gap[i, j], 0.0) * 1e3:.1f} mm from "
                                 f"the {ob.name} (clearance {limits.clearance * 1e3:.0f} mm) near "
                                 f"{_fmt(points[i, j])} m")


def _check_tool_clear(limits: SafetyLimits, world_from_flange: np.ndarray, shape: ToolShape, motion: str) -> None:
    """world_from_flange (n, 4, 4) along a motion: the tool's shape against the obstacles."""
    if not limits.obstacles:
        return
    # Only the samples where the shape's bounding sphere comes within the clearance of a
    # box need the shape's every point (the same answer, a fraction of the work).
    centre = shape.points_flange.mean(axis=0)
    reach = float(np.max(np.linalg.norm(shape.points_flange - centre, axis=1) + shape.radii))
    centres = np.einsum("nij,j->ni", world_from_flange[:, :3, :3], centre) + world_from_flange[:, :3, 3]
    near = np.zeros(len(centres), bool)
    for ob in limits.obstacles:
        near |= ob.distance(centres) < reach + limits.clearance
    if not np.any(near):
        return
    # Of those, only the samples where some part's own bounding sphere comes that close
    # (with _PREFILTER_SLACK_M to spare): a sample dropped here has no point within the
    # clearance, so the points' test below sees the same offending points, if any.
    part_centres, part_reach = shape.part_spheres
    if len(part_centres) > 1:
        R, t = world_from_flange[near, :3, :3], world_from_flange[near, None, :3, 3]
        parts_world = np.einsum("nij,pj->npi", R, part_centres) + t               # (n_near, P, 3)
        near_part = np.zeros(parts_world.shape[:2], bool)
        for ob in limits.obstacles:
            near_part |= ob.distance(parts_world) < part_reach + limits.clearance + _PREFILTER_SLACK_M
        keep = near_part.any(axis=1)
        near[np.flatnonzero(near)[~keep]] = False
        if not np.any(near):
            return
        near_part = near_part[keep]
    else:
        near_part = np.ones((int(near.sum()), 1), bool)
    T = world_from_flange[near]
    # Of those, only the samples where some point of a part found near comes within the
    # clearance (with _PREFILTER_SLACK_M to spare) by a matrix product (a tenth of einsum's
    # time; its rounding differs by ~1e-16 m) are computed again by einsum and tested as
    # before: a sample dropped here has no point within the clearance (a part not near has
    # none either), so the same point is named.
    close = np.zeros(len(T), bool)
    for k, (pts_k, radii_k) in enumerate(shape.part_points if near_part.shape[1] > 1 else
                                         ((shape.points_flange, shape.radii),)):
        rows = np.flatnonzero(near_part[:, k] & ~close)
        if len(rows) == 0:
            continue
        Tk = T[rows]
        approx = pts_k @ Tk[:, :3, :3].transpose(0, 2, 1) + Tk[:, None, :3, 3]      # (rows, points of k, 3)
        hit = np.zeros(len(rows), bool)
        for ob in limits.obstacles:
            hit |= np.any(ob.distance(approx) - radii_k < limits.clearance + _PREFILTER_SLACK_M, axis=1)
        close[rows[hit]] = True
    if not np.any(close):
        return
    T = T[close]
    pts = np.einsum("nij,kj->nki", T[:, :3, :3], shape.points_flange) + T[:, None, :3, 3]
    _check_clear(limits, pts, shape.radii, [shape.parts[i] for i in shape.part_index], motion)


WRIST_LINKS = (("wrist 1", 3, 4, 0.0), ("wrist 2", 4, 5, 0.045), ("wrist 3", 5, 6, 0.045))
"""The wrist's links as (name, from DH frame, to DH frame, back [m]): cylinders of
WRIST_RADIUS_M around the line between the two frames' origins, started ``back`` metres
behind the first (a wrist joint's housing is centred on its joint, 90 mm long); the last
ends at the flange's face."""
_RING = np.linspace(0.0, 2 * np.pi, 32, endpoint=False)


def _cylinder_surface(a: np.ndarray, b: np.ndarray, radius: float, step: float = 0.005) -> np.ndarray:
    """Points on the surface of the cylinder from a to b (its side every ``step`` along
    the axis and every 1/32 turn, ~8 mm apart at 40 mm; its two end discs)."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    z = axis / length
    e1 = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(z, e1)
    ring = np.cos(_RING)[:, None] * e1 + np.sin(_RING)[:, None] * e2          # (32, 3)
    t = np.linspace(0.0, 1.0, max(int(np.ceil(length / step)), 1) + 1)
    side = a + t[:, None, None] * axis + radius * ring[None]                     # (nt, 32, 3)
    discs = [c + f * radius * ring for c in (a, b) for f in (0.0, 0.5)]
    return np.vstack([side.reshape(-1, 3), *discs])


def check_wrist_clear(limits: SafetyLimits, joint_path: Any, motion: str,
                      frames: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
    """Raise :class:`CollisionError` unless the wrist's links keep the clearance from the
    obstacles at every joint vector of ``joint_path`` (n, 6) [rad] (samples of a motion).
    Compared with the simulated arm's wrist geometry (MuJoCo's distances to the part) at
    600 random flange poses near it: never clear by 5 mm where MuJoCo's wrist touches the
    part; a few mm more cautious where both are clear."""
    if not limits.obstacles:
        return
    qs = np.asarray(joint_path, float).reshape(-1, 6)
    if frames is None:
        from .kinematics import dh_frames_many
        all_frames = dh_frames_many(qs)
    else:
        all_frames = np.array([frames(q) for q in qs]).reshape(-1, 7, 4, 4)
    _check_wrist_frames(limits, all_frames, motion)


def _check_wrist_frames(limits: SafetyLimits, all_frames: np.ndarray, motion: str) -> None:
    """:func:`check_wrist_clear` on the DH frames (n, 7, 4, 4) of the samples. A link whose
    bounding sphere is clear of every box is clear: that is tested for all samples at once
    first, and the rest (usually none) in order with the link's cylinder surface, exactly as
    one sample at a time, so the same sample raises the same error."""
    r = WRIST_RADIUS_M
    origins = all_frames[:, :, :3, 3]                                  # (n, 7, 3)
    candidate = np.zeros((len(all_frames), len(WRIST_LINKS)), bool)
    for k, (_, i, j, back) in enumerate(WRIST_LINKS):
        a, b = origins[:, i], origins[:, j]
        length = np.linalg.norm(b - a, axis=-1)
        a = a - (back / length)[:, None] * (b - a)
        centre, reach = 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=-1) + r
        for ob in limits.obstacles:
            candidate[:, k] |= ob.distance(centre) < reach + limits.clearance + _PREFILTER_SLACK_M
    _drop_clear_axes(limits, origins, candidate)
    for n, k in zip(*np.nonzero(candidate)):                         # sample-major, as before
        name, i, j, back = WRIST_LINKS[k]
        F = all_frames[n]
        a, b = F[i, :3, 3], F[j, :3, 3]
        a = a - back * (b - a) / np.linalg.norm(b - a)
        centre, reach = 0.5 * (a + b), 0.5 * float(np.linalg.norm(b - a)) + r
        if all(ob.distance(centre) >= reach + limits.clearance for ob in limits.obstacles):
            continue      # the link's bounding sphere is clear: so is the link
        if _axis_clear(limits, a, b, r):
            continue      # clear by the axis' samples: so is every point of its surface
        pts = _cylinder_surface(a, b, r)
        _check_clear(limits, pts[None], np.zeros(len(pts)), [name] * len(pts), motion)


def _drop_clear_axes(limits: SafetyLimits, origins: np.ndarray, candidate: np.ndarray, step: float = 0.01) -> None:
    """Unmark in ``candidate`` (n, links) each sample's wrist link that :func:`_axis_clear`'s
    test shows clear with _PREFILTER_SLACK_M more to spare, for all candidates at once
    (stacked arithmetic, rounding ~1e-16 m apart from the one-at-a-time test's): each
    surface point lies within the radius of the axis and each axis point within half a
    sample spacing of a sample, so such a link is clear by the clearance and cannot raise;
    the rest are tested one at a time as before, in the same order."""
    r = WRIST_RADIUS_M
    for k, (_, i, j, back) in enumerate(WRIST_LINKS):
        rows = np.flatnonzero(candidate[:, k])
        if len(rows) == 0:
            continue
        a, b = origins[rows, i], origins[rows, j]
        a = a - (back / np.linalg.norm(b - a, axis=-1))[:, None] * (b - a)
        length = np.linalg.norm(b - a, axis=-1)
        m = np.maximum(np.ceil(length / step), 1).astype(int) + 1
        for mm in np.unique(m):
            g = np.flatnonzero(m == mm)
            samples = a[g, None] + np.linspace(0.0, 1.0, mm)[None, :, None] * (b - a)[g, None]     # (g, mm, 3)
            margin = r + 0.5 * length[g] / (mm - 1) + limits.clearance + 2 * _PREFILTER_SLACK_M
            clear = np.ones(len(g), bool)
            for ob in limits.obstacles:
                clear &= np.min(ob.distance(samples), axis=1) >= margin
            candidate[rows[g[clear]], k] = False


def _axis_clear(limits: SafetyLimits, a: np.ndarray, b: np.ndarray, radius: float, step: float = 0.01) -> bool:
    """True when the cylinder of ``radius`` around a-b is surely clear of every obstacle by
    the clearance (and _PREFILTER_SLACK_M): each of its surface points lies within
    ``radius`` of the axis, and each axis point within half a sample spacing of a sample,
    so a sample's distance less both bounds every surface point's (a lower bound; False
    says only "test the surface")."""
    length = float(np.linalg.norm(b - a))
    m = max(int(np.ceil(length / step)), 1) + 1
    samples = a + np.linspace(0.0, 1.0, m)[:, None] * (b - a)
    margin = radius + 0.5 * length / (m - 1) + limits.clearance + _PREFILTER_SLACK_M
    return all(float(np.min(ob.distance(samples))) >= margin for ob in limits.obstacles)


def check_linear_move(limits: SafetyLimits, start_pose: Any, target_pose: Any, speed: float,
                      acceleration: float, points_flange: np.ndarray | None = None,
                      shape: ToolShape | None = None, q_start: Any = None) -> None:
    """Raise :class:`SafetyError` unless a ``moveL`` of the flange from ``start_pose`` to
    ``target_pose`` (pose6) at ``speed`` m/s / ``acceleration`` m/s^2 keeps every check
    point (``points_flange`` (k, 3), default the flange origin) inside the workspace and
    out of the keep-out box, and the tool's ``shape`` (default: the check points) clear of
    the obstacles. With ``q_start`` (6,) [rad], where the arm starts, the wrist is checked
    too, in the configuration ``moveL`` keeps (inverse kinematics along the line)."""
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
    if limits.obstacles:
        T = np.zeros((len(poses), 4, 4))
        T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R, poses[:, :3], 1.0
        _check_tool_clear(limits, T, shape if shape is not None else ToolShape.points(pts), "linear move")
        if q_start is not None:
            check_wrist_clear(limits, line_joints(T[::max(len(T) // 20, 1)], q_start), "linear move")


def check_linear_path(limits: SafetyLimits, start_pose: Any, poses: Any, speed: float, acceleration: float,
                      blend: float, points_flange: np.ndarray | None = None, shape: ToolShape | None = None,
                      q_start: Any = None) -> None:
    """Raise :class:`SafetyError` unless a blended ``moveL`` path of the flange from
    ``start_pose`` through ``poses`` (n, 6) keeps to the limits: every leg as
    :func:`check_linear_move` checks a single move, and the blends (:func:`check_blends`).
    A refusal names the leg."""
    from .kinematics import ik_nearest

    rows = np.asarray(poses, float).reshape(-1, 6)
    previous = np.asarray(start_pose, float)
    q = None if q_start is None else np.asarray(q_start, float)
    for i, target in enumerate(rows):
        try:
            check_linear_move(limits, previous, target, speed, acceleration, points_flange, shape, q)
        except SafetyError as e:
            raise type(e)(f"linear path, leg {i + 1} of {len(rows)}: {e}") from None
        if q is not None:
            q_next = ik_nearest(pose6_to_matrix(target), q)
            q = q if q_next is None else q_next
        previous = target
    check_blends(limits, start_pose, rows, speed, acceleration, blend, points_flange, shape)


def check_blends(limits: SafetyLimits, start_pose: Any, poses: Any, speed: float, acceleration: float,
                 blend: float, points_flange: np.ndarray | None = None, shape: ToolShape | None = None) -> None:
    """Raise :class:`SafetyError` unless the blends of a ``moveL`` path from ``start_pose``
    through ``poses`` (n, 6), ``blend`` [m] at each intermediate pose (the last is reached
    exactly), are sound: ``blend`` finite and not negative, less than half of each leg it
    joins (a UR refuses overlapping blends), and the chord across each blended corner, from
    where the blend leaves one leg to where it joins the next, kept to the limits as a
    straight move (:func:`check_linear_move`). A blend's curve lies in the triangle of that
    chord and the two legs' ends (each within ``blend`` of the corner), whose three sides
    are then checked. The legs themselves are :func:`check_linear_path`'s."""
    blend = float(blend)
    if not np.isfinite(blend) or blend < 0:
        raise SafetyError(f"linear path: blend radius {blend} m is not a distance")
    rows = np.asarray(poses, float).reshape(-1, 6)
    if blend == 0 or len(rows) < 2:
        return
    ends = np.vstack([np.asarray(start_pose, float)[None], rows])
    for i in range(1, len(rows)):
        before, corner, after = ends[i - 1], ends[i], ends[i + 1]
        legs = np.linalg.norm(corner[:3] - before[:3]), np.linalg.norm(after[:3] - corner[:3])
        if not blend < 0.5 * min(legs):
            raise SafetyError(f"linear path: blend radius {blend * 1e3:g} mm at pose {i} of {len(rows)} is not "
                              f"less than half of its shorter leg ({min(legs) * 1e3:.1f} mm)")
        leave = interpolate_pose6_at(before, corner, 1.0 - blend / legs[0])
        join = interpolate_pose6_at(corner, after, blend / legs[1])
        try:
            check_linear_move(limits, leave, join, speed, acceleration, points_flange, shape)
        except SafetyError as e:
            raise type(e)(f"linear path, the blend at pose {i} of {len(rows)}: {e}") from None


def line_joints(world_from_flange: np.ndarray, q_start: Any) -> np.ndarray:
    """(n, 6) joints along flange poses (n, 4, 4), each the IK solution nearest the last
    (the configuration ``moveL`` keeps); poses without a solution are left out (the arm's
    own reach check refuses those)."""
    from .kinematics import ik_nearest

    q = np.asarray(q_start, float)
    out = [q]
    for T in world_from_flange:
        q_next = ik_nearest(T, q)
        if q_next is not None:
            q = q_next
            out.append(q)
    return np.array(out)


def check_joint_move(limits: SafetyLimits, q_start: Any, q_target: Any, speed: float, acceleration: float,
                     points_flange: np.ndarray | None = None,
                     frames: Callable[[np.ndarray], np.ndarray] | None = None,
                     shape: ToolShape | None = None) -> None:
    """Raise :class:`SafetyError` unless a joint move from ``q_start`` to ``q_target`` [rad]
    at ``speed`` rad/s / ``acceleration`` rad/s^2 keeps the check points inside the
    workspace, every check point and wrist centre out of the keep-out box, and the tool's
    ``shape`` (default: the check points) and the wrist clear of the obstacles.
    ``frames(q) -> (7, 4, 4)`` are the DH frames (default the UR5e's)."""
    if not 0 < speed <= limits.max_joint_speed:
        raise SafetyError(f"joint move: speed {speed:g} rad/s exceeds the limit {limits.max_joint_speed:g} rad/s")
    if not 0 < acceleration <= limits.max_joint_accel:
        raise SafetyError(f"joint move: acceleration {acceleration:g} rad/s^2 exceeds the limit "
                          f"{limits.max_joint_accel:g} rad/s^2")
    pts = check_points_flange() if points_flange is None else np.asarray(points_flange, float)
    qa, qb = np.asarray(q_start, float), np.asarray(q_target, float)
    n = int(np.ceil(np.max(np.abs(qb - qa)) / 0.01)) + 2
    qs = qa + np.linspace(0.0, 1.0, n)[:, None] * (qb - qa)
    if frames is None:
        from .kinematics import dh_frames_many
        all_frames = dh_frames_many(qs)
    else:
        all_frames = np.array([frames(q) for q in qs]).reshape(-1, 7, 4, 4)
    pts_h = np.c_[pts, np.ones(len(pts))].T
    # All samples' products at once: a stacked matmul multiplies each sample's matrices as
    # the one-sample product does (the same numbers, checked on 20 million values), as
    # contiguous arrays like the per-sample lists they replace.
    flanges = np.ascontiguousarray(all_frames[:, -1])
    tool_paths = np.ascontiguousarray((flanges @ pts_h).transpose(0, 2, 1)[:, :, :3])
    _check_box_path(limits, tool_paths, _point_labels(len(pts)), "joint move")
    wrist = np.ascontiguousarray(all_frames[:, 4:6, :3, 3])
    for j, label in enumerate(("wrist 2 centre", "wrist 3 centre")):
        if np.any(segments_hit_box(wrist[:-1, j], wrist[1:, j], limits.keepout_min, limits.keepout_max)):
            raise KeepOutError(f"joint move: the {label} would enter the keep-out box around the part")
    if limits.obstacles:
        # Samples 0.01 rad apart: a tool point ~1 m from the base moves ~10 mm between
        # two, on a path that is nearly straight there, so against the boxes' faces the
        # samples are the nearest points (near a box's edge the path may pass a few mm
        # closer than the samples say; joint moves here go to a pre-grasp pose away from
        # everything).
        _check_tool_clear(limits, flanges, shape if shape is not None else ToolShape.points(pts), "joint move")
        _check_wrist_frames(limits, all_frames, "joint move")


class SafeArm(Arm):
    """An :class:`Arm` whose every motion is checked against ``limits`` first.

    ``flange_from_tool`` (4x4 or pose6) is the mounted tool, whose TCP is checked along with
    the flange; ``extra_points_flange`` (N, 3) adds points such as finger tips;
    ``points_flange`` (k, 3) replaces the whole list (flange origin first); ``shape`` is the
    tool's :class:`ToolShape` kept clear of the cell's obstacles (default: the check
    points). Motions start from the arm's reported pose and joints, so the checks cover the
    real path.
    """

    def __init__(self, arm: Arm, limits: SafetyLimits, flange_from_tool: Any = None,
                 extra_points_flange: Any = None, points_flange: Any = None, shape: ToolShape | None = None) -> None:
        self.arm = arm
        self.limits = limits
        self.shape = shape
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
        q_now = self.arm.joints() if self.limits.obstacles else None
        check_linear_move(self.limits, self.arm.tcp_pose(), pose, speed, acceleration, self.points_flange,
                          self.shape, q_now)
        self.arm.move_linear(pose, speed, acceleration)

    def _move_linear_path(self, poses: np.ndarray, speed: float, acceleration: float, blend: float) -> None:
        q_now = self.arm.joints() if self.limits.obstacles else None
        check_linear_path(self.limits, self.arm.tcp_pose(), poses, speed, acceleration, blend, self.points_flange,
                          self.shape, q_now)
        self.arm.move_linear_path(poses, speed, acceleration, blend)

    def _move_joints(self, q: np.ndarray, speed: float, acceleration: float) -> None:
        check_joint_move(self.limits, self.arm.joints(), q, speed, acceleration, self.points_flange,
                         shape=self.shape)
        self.arm.move_joints(q, speed, acceleration)

    def _stop(self) -> None:
        self.arm.stop()

    def _open_gripper(self) -> None:
        self.arm.open_gripper()

    def _close_gripper(self) -> None:
        self.arm.close_gripper()

    def _freedrive(self, enable: bool) -> None:
        self.arm.freedrive(enable)
