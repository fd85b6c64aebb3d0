"""Camera calibration from robot-held cross-plate points (the paper's sec. 2.2).

The robot carries the cross plate through a 3-D grid of poses; each pose gives one 3-D
point (the flange pose the arm reports composed with the plate's offset, i.e. robot
coordinates) and, per camera, the detected cross centre. Per camera the points are
non-planar, so the solve is: a DLT initial guess (normalised, Hartley), decomposed into
K, R, t; then ``cv2.calibrateCamera`` with ``CALIB_USE_INTRINSIC_GUESS`` on all points as
one view, the distortion terms chosen by the cell file fixed or free; gross outliers
removed and the solve repeated. The result is in the robot's base frame directly.

Here: the solver (:func:`calibrate_camera`), the pose planner (:func:`plan_poses`) and
the procedure (:func:`run_calibration`), which drives any :class:`cell.arm.Arm` and any
camera source (simulated renders, ``cell.cameras_real``) the same way.
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Callable, Mapping, Protocol, Sequence

import cv2
import numpy as np
import scipy.linalg

from tapecell.estimator.errors import TaskFailed
from tapecell.estimator.geometry import Camera, rot_x, rot_y, rot_z

from .config import CellConfigError
from .cross import REASONS, CrossDetection, CrossParams, detect_cross


class CalibrationError(TaskFailed):
    """Calibration cannot give trustworthy cameras (too few poses, large residuals);
    nothing is written (exit 1)."""


DISTORTION_MODELS = {
    # cell file's calibration.distortion_model -> calibrateCamera flags fixing the other terms
    "none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
    "k1k2p1p2": cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
}


# ------------------------------------------------------------------------------ DLT
def dlt_projection(points_world: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3, 4) projection matrix P with pixels ~ P [X; 1], by the normalised DLT.

    points_world: (N, 3) non-coplanar points [m], N >= 6; pixels: (N, 2).
    """
    X = np.asarray(points_world, float)
    x = np.asarray(pixels, float)
    if len(X) < 6:
        raise CalibrationError(f"the DLT needs at least 6 points, got {len(X)}")
    # Hartley normalisation: centroid at 0, mean distance sqrt(2) (2-D) / sqrt(3) (3-D).
    def norm_T(p: np.ndarray) -> np.ndarray:
        c = p.mean(axis=0)
        s = np.sqrt(p.shape[1]) / max(np.mean(np.linalg.norm(p - c, axis=1)), 1e-12)
        T = np.eye(p.shape[1] + 1)
        T[:-1, :-1] *= s
        T[:-1, -1] = -s * c
        return T
    Tx, TX = norm_T(x), norm_T(X)
    xn = (np.c_[x, np.ones(len(x))] @ Tx.T)[:, :2]
    Xn = np.c_[X, np.ones(len(X))] @ TX.T
    A = np.zeros((2 * len(X), 12))
    A[0::2, 0:4] = Xn
    A[0::2, 8:12] = -xn[:, :1] * Xn
    A[1::2, 4:8] = Xn
    A[1::2, 8:12] = -xn[:, 1:] * Xn
    _, sv, vt = np.linalg.svd(A)
    if sv[-2] < 1e-9 * sv[0]:
        raise CalibrationError("the calibration points are degenerate (coplanar or collinear)")
    Pn = vt[-1].reshape(3, 4)
    return np.linalg.inv(Tx) @ Pn @ TX


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P -> (K (3,3) with positive diagonal and K[2,2]=1, R camera_from_world, t [m])."""
    M = P[:, :3]
    K, R = scipy.linalg.rq(M)
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:           # P is defined up to sign
        R, t = -R, -t
    scale = K[2, 2]
    return K / scale, R, t


# ----------------------------------------------------------------------------- solve
@dataclass(frozen=True, eq=False)
class CameraFit:
    """One camera's calibration.

    camera: the calibrated camera, ``rms_px`` set (inliers only).
    initial: the DLT camera the refinement started from (no distortion).
    residuals_px: (N,) reprojection error of every input point [px], outliers included.
    inliers: (N,) bool, the points the final solve used.
    """

    camera: Camera
    initial: Camera
    residuals_px: np.ndarray
    inliers: np.ndarray

    @property
    def n_outliers(self) -> int:
        return int(np.count_nonzero(~self.inliers))


def _refine(name: str, size: tuple[int, int], X: np.ndarray, x: np.ndarray, K0: np.ndarray,
            flags: int) -> tuple[Camera, float]:
    w, h = size
    obj = [X.astype(np.float32).reshape(-1, 1, 3)]
    img = [x.astype(np.float32).reshape(-1, 1, 2)]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            obj, img, (w, h), K0.copy(), np.zeros(5), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
            criteria=crit)
    except cv2.error as e:
        raise CalibrationError(f"camera {name}: OpenCV calibration failed ({str(e).strip().splitlines()[-1]})") from None
    R, _ = cv2.Rodrigues(rvecs[0])
    return Camera(name, w, h, np.asarray(K, float), np.asarray(dist, float).reshape(-1)[:5],
                  R, np.asarray(tvecs[0], float).reshape(3), float(rms)), float(rms)


def _residuals(camera: Camera, X: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(camera.project(X) - x, axis=1)


def calibrate_camera(name: str, size: tuple[int, int], points_world: np.ndarray, pixels: np.ndarray,
                     distortion_model: str = "k1k2", outlier_px: float = 0.5,
                     max_rounds: int = 5) -> CameraFit:
    """Calibrate one camera from (N, 3) world points [m] and their (N, 2) pixels.

    ``size`` is (width, height). Points whose residual exceeds both ``outlier_px`` and
    five times the median residual are dropped and the solve repeated (at most
    ``max_rounds`` times), which removes mis-detections without trimming honest noise.
    """
    if distortion_model not in DISTORTION_MODELS:
        raise CellConfigError(f"unknown distortion model '{distortion_model}' "
                              f"(known: {', '.join(DISTORTION_MODELS)})")
    X = np.asarray(points_world, float).reshape(-1, 3)
    x = np.asarray(pixels, float).reshape(-1, 2)
    flags = DISTORTION_MODELS[distortion_model]
    inliers = np.ones(len(X), bool)
    P = dlt_projection(X, x)
    K0, R0, t0 = decompose_projection(P)
    K0[0, 1] = 0.0                      # OpenCV's model has no skew
    initial = Camera(name, size[0], size[1], K0, np.zeros(5), R0, t0)
    camera = initial
    for _ in range(max_rounds):
        camera, _ = _refine(name, size, X[inliers], x[inliers], camera.K, flags)
        r = _residuals(camera, X, x)
        limit = max(outlier_px, 5.0 * float(np.median(r[inliers])))
        new = r <= limit
        if np.array_equal(new, inliers) or np.count_nonzero(new) < 6:
            break
        inliers = new
    r = _residuals(camera, X, x)
    rms = float(np.sqrt(np.mean(r[inliers] ** 2)))
    camera = Camera(camera.name, camera.width, camera.height, camera.K, camera.dist, camera.R, camera.t, rms)
    return CameraFit(camera, initial, r, inliers)


def camera_errors(calibrated: Camera, true: Camera) -> dict[str, float]:
    """How far ``calibrated`` is from ``true``: focal [%], principal point [px], centre
    [m], rotation [deg]."""
    f_err = max(abs(calibrated.K[0, 0] / true.K[0, 0] - 1), abs(calibrated.K[1, 1] / true.K[1, 1] - 1))
    pp = float(np.linalg.norm(calibrated.K[:2, 2] - true.K[:2, 2]))
    centre = float(np.linalg.norm(calibrated.center - true.center))
    dR = calibrated.R @ true.R.T
    angle = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0))))
    return {"focal_pct": 100.0 * f_err, "principal_px": pp, "centre_m": centre, "rotation_deg": angle}


# ----------------------------------------------------------------------- pose planning
@dataclass(frozen=True)
class PlanParams:
    """Limits of the pose planner.

    max_view_deg: largest angle between the plate normal and the direction to any camera
        [deg]; beyond it the cross is too foreshortened to measure well.
    image_margin_px: the cross and a rim of plate around it must project this far inside
        every nominal image [px].
    rolls_deg: in-plane rotations of the plate cycled through the grid [deg].
    """

    max_view_deg: float = 45.0
    image_margin_px: float = 10.0
    rolls_deg: tuple[float, ...] = (0.0, 25.0, -25.0)


@dataclass(frozen=True, eq=False)
class PlannedPose:
    """One plate pose of the calibration grid.

    index: order of visit. grid_index: (i, j, k) in the grid.
    world_from_tcp: 4x4, the TCP being the cross centre on the plate's face [m].
    flange_pose: (6,) [x, y, z, rx, ry, rz] flange target in the base frame.
    joints: (6,) IK solution [rad] nearest the previous pose's.
    view_deg: per camera name, angle between plate normal and the line to the camera.
    """

    index: int
    grid_index: tuple[int, int, int]
    world_from_tcp: np.ndarray
    flange_pose: np.ndarray
    joints: np.ndarray
    view_deg: dict[str, float] = field(default_factory=dict)

    @property
    def point(self) -> np.ndarray:
        return self.world_from_tcp[:3, 3]


def nominal_cameras(cell, n_cameras: int) -> list[Camera]:
    """The cameras as the cell file places them (look-at, fx, no distortion): used to plan
    before anything is calibrated."""
    from .config import look_at_world_from_cv

    c = cell.cameras
    K = np.array([[c.fx, 0.0, c.width / 2 - 0.5], [0.0, c.fx, c.height / 2 - 0.5], [0.0, 0.0, 1.0]])
    out = []
    for p in cell.camera_placements(n_cameras):
        world_from_cv = look_at_world_from_cv(p.position, p.target, p.up, cell.source, p.name)
        R = world_from_cv.T
        out.append(Camera(p.name, c.width, c.height, K, np.zeros(5), R, -R @ np.asarray(p.position, float)))
    return out


def _orientations(tilts_deg: Sequence[float], rolls_deg: Sequence[float]) -> list[np.ndarray]:
    """Plate rotations relative to the facing orientation: each tilt about the plate's
    +x, +y, -x, -y axes (one orientation for a zero tilt), each with an in-plane roll."""
    tilts = []
    for t in tilts_deg:
        a = np.radians(t)
        tilts += [np.eye(3)] if abs(t) < 1e-9 else [rot_x(a), rot_y(a), rot_x(-a), rot_y(-a)]
    return [rot_z(np.radians(r)) @ T for T in tilts for r in rolls_deg]


def _grid(section) -> list[tuple[tuple[int, int, int], np.ndarray]]:
    """Grid points in serpentine order (short moves between neighbours)."""
    counts = section.grid_counts
    axes = [np.linspace(lo, hi, n) if n > 1 else np.array([(lo + hi) / 2])
            for lo, hi, n in zip(section.grid_min, section.grid_max, counts)]
    out = []
    for i in range(counts[0]):
        js = range(counts[1]) if i % 2 == 0 else reversed(range(counts[1]))
        for jn, j in enumerate(js):
            ks = range(counts[2]) if (i * counts[1] + jn) % 2 == 0 else reversed(range(counts[2]))
            for k in ks:
                out.append(((i, j, k), np.array([axes[0][i], axes[1][j], axes[2][k]])))
    return out


def _inside(p: np.ndarray, lo, hi) -> bool:
    return bool(np.all(p >= np.asarray(lo)) and np.all(p <= np.asarray(hi)))


def _pose_problem(cell, cams: list[Camera], world_from_tcp: np.ndarray, q_seed: np.ndarray,
                  params: PlanParams) -> tuple[str | None, np.ndarray | None, dict[str, float]]:
    """Why the plate cannot be at ``world_from_tcp`` (None if it can), the IK joints and
    the view angles."""
    from .kinematics import ik_nearest
    from .poses import pose6_to_matrix

    p, n = world_from_tcp[:3, 3], world_from_tcp[:3, 2]
    view = {}
    for cam in cams:
        d = cam.center - p
        view[cam.name] = float(np.degrees(np.arccos(np.clip(n @ d / np.linalg.norm(d), -1, 1))))
        if view[cam.name] > params.max_view_deg:
            return f"plate faces away from {cam.name} ({view[cam.name]:.0f} deg)", None, view
    plate = cell.tools.plate
    # The cross and a rim of plate around it must be seen; the plate's corners may not.
    h = min(plate.cross_length / 2 + plate.cross_width, plate.size / 2)
    corners = (world_from_tcp @ np.array([[sx * h, sy * h, 0, 1] for sx in (-1, 1) for sy in (-1, 1)]).T).T[:, :3]
    for cam in cams:
        uv = cam.project(corners)
        m = params.image_margin_px
        if np.any(uv < m) or np.any(uv[:, 0] > cam.width - 1 - m) or np.any(uv[:, 1] > cam.height - 1 - m):
            return f"cross leaves {cam.name}'s image", None, view
    world_from_flange = world_from_tcp @ np.linalg.inv(pose6_to_matrix(plate.flange_from_tcp))
    lim = cell.limits
    for what, pt in (("TCP", p), ("flange", world_from_flange[:3, 3])):
        if not _inside(pt, lim.workspace_min, lim.workspace_max):
            return f"{what} outside the workspace box", None, view
    # The keep-out box is defined for the TCP and the flange (as cell.safety checks them).
    for what, pt in (("TCP", p), ("flange", world_from_flange[:3, 3])):
        if _inside(pt, lim.keepout_min, lim.keepout_max):
            return f"{what} enters the keep-out box", None, view
    q = ik_nearest(world_from_flange, q_seed)
    if q is None:
        return "no IK solution within the joint limits", None, view
    return None, q, view


def plan_poses(cell, n_cameras: int, q_start: Sequence[float] | None = None,
               params: PlanParams = PlanParams()) -> list[PlannedPose]:
    """Plate poses through the cell file's calibration grid, each reachable (IK within the
    joint limits), inside the workspace and out of the keep-out box, and facing every
    nominal camera with the whole plate in its image.

    Grid points cycle through the orientations (tilts x rolls); a point whose orientation
    fails tries the others. Raises :class:`CalibrationError` naming the first grid point
    that no orientation can reach.
    """
    from .poses import matrix_to_pose6, pose6_to_matrix

    section = cell.calibration
    cams = nominal_cameras(cell, n_cameras)
    rotations = _orientations(section.tilts_deg, params.rolls_deg)
    q = np.asarray(cell.arm.home_joints if q_start is None else q_start, float)
    flange_from_tcp = pose6_to_matrix(cell.tools.plate.flange_from_tcp)
    poses, failures = [], []
    for n, (gidx, p) in enumerate(_grid(section)):
        dirs = np.array([(c.center - p) / np.linalg.norm(c.center - p) for c in cams])
        normal = dirs.mean(axis=0)
        normal /= np.linalg.norm(normal)
        x = np.cross([0.0, 0.0, 1.0], normal)
        x /= np.linalg.norm(x)
        facing = np.column_stack([x, np.cross(normal, x), normal])
        reasons = []
        for r in range(len(rotations)):
            world_from_tcp = np.eye(4)
            world_from_tcp[:3, :3] = facing @ rotations[(n + r) % len(rotations)]
            world_from_tcp[:3, 3] = p
            why, q_new, view = _pose_problem(cell, cams, world_from_tcp, q, params)
            if why is None:
                world_from_flange = world_from_tcp @ np.linalg.inv(flange_from_tcp)
                poses.append(PlannedPose(len(poses), gidx, world_from_tcp, matrix_to_pose6(world_from_flange),
                                         q_new, view))
                q = q_new
                break
            reasons.append(why)
        else:
            failures.append((p, collections.Counter(reasons).most_common(1)[0][0]))
    if failures:
        p, why = failures[0]
        # The cell file's [calibration] grid is wrong for this cell: bad input, not a failed task.
        raise CellConfigError(f"{cell.source}: calibration grid unreachable at {len(failures)} of "
                              f"{len(poses) + len(failures)} points, first at "
                              f"[{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}] m: {why}")
    return poses


# ---------------------------------------------------------------------------- running
class CameraSource(Protocol):
    """Where calibration images come from (simulated renders, VideoCapture, a folder)."""

    names: list[str]

    def size(self, name: str) -> tuple[int, int]:
        """(width, height) of camera ``name``'s images [px]."""

    def grab(self, index: int) -> dict[str, np.ndarray]:
        """One (H, W, 3) uint8 RGB image per camera name, taken now (pose ``index``)."""


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Everything a calibration run produced.

    fits: per camera name, its :class:`CameraFit`.
    poses: the planned poses visited.
    points_world: (P, 3) measured cross centres [m], one per pose (arm-reported).
    detections: per camera name, a list of P :class:`CrossDetection`.
    rejections: per camera name, Counter of rejection reasons.
    """

    fits: dict[str, CameraFit]
    poses: list[PlannedPose]
    points_world: np.ndarray
    detections: dict[str, list[CrossDetection]]
    rejections: dict[str, collections.Counter]

    @property
    def cameras(self) -> list[Camera]:
        return [f.camera for f in self.fits.values()]


def solve_all(points_world: np.ndarray, detections: Mapping[str, Sequence[CrossDetection]],
              sizes: Mapping[str, tuple[int, int]], section, outlier_px: float = 0.5) -> dict[str, CameraFit]:
    """Calibrate every camera from its accepted detections; enforces the cell file's
    ``min_poses`` and ``max_rms_px`` (a :class:`CalibrationError` otherwise)."""
    fits = {}
    for name, dets in detections.items():
        ok = np.array([d.ok for d in dets], bool)
        if np.count_nonzero(ok) < max(section.min_poses, 6):
            raise CalibrationError(f"camera {name}: only {np.count_nonzero(ok)} valid poses, the cell file's "
                                   f"calibration.min_poses is {section.min_poses}")
        pix = np.array([d.center_px for d in dets if d.ok])
        fit = calibrate_camera(name, sizes[name], points_world[ok], pix, section.distortion_model, outlier_px)
        if np.count_nonzero(fit.inliers) < section.min_poses:
            raise CalibrationError(f"camera {name}: only {np.count_nonzero(fit.inliers)} poses left after "
                                   f"removing outliers, calibration.min_poses is {section.min_poses}")
        if fit.camera.rms_px > section.max_rms_px:
            raise CalibrationError(f"camera {name}: RMS reprojection error {fit.camera.rms_px:.3f} px exceeds "
                                   f"calibration.max_rms_px = {section.max_rms_px}")
        fits[name] = fit
    return fits


def run_calibration(cell, arm, source: CameraSource, poses: Sequence[PlannedPose], rec=None,
                    log: Callable[[str], None] = print, joint_speed: float = 0.5,
                    joint_accel: float = 1.0, cross_params: CrossParams = CrossParams()) -> CalibrationResult:
    """Visit ``poses`` with ``arm`` (a connected :class:`cell.arm.Arm`, normally a
    :class:`cell.safety.SafeArm`), detect the cross in every camera, and solve.

    The 3-D point of a pose is the flange pose the arm REPORTS after the move composed
    with the plate's offset, so the arm's own positioning error does not enter. ``rec`` is
    an optional rerun ``RecordingStream``.
    """
    from .poses import pose6_to_matrix

    flange_from_tcp = pose6_to_matrix(cell.tools.plate.flange_from_tcp)
    names = list(source.names)
    detections: dict[str, list[CrossDetection]] = {n: [] for n in names}
    points = []
    for pose in poses:
        arm.move_joints(pose.joints, joint_speed, joint_accel)
        world_from_tcp = pose6_to_matrix(arm.tcp_pose()) @ flange_from_tcp
        points.append(world_from_tcp[:3, 3])
        images = source.grab(pose.index)
        for name in names:
            det = detect_cross(images[name], cross_params)
            detections[name].append(det)
        if rec is not None:
            _log_pose(rec, pose, world_from_tcp, images, {n: detections[n][-1] for n in names})
        seen = ", ".join(f"{n}: {'ok' if detections[n][-1].ok else detections[n][-1].reason}" for n in names)
        log(f"pose {pose.index + 1}/{len(poses)} at {np.round(world_from_tcp[:3, 3], 3).tolist()} m: {seen}")
    points_world = np.array(points)
    rejections = {n: collections.Counter(d.reason for d in detections[n] if not d.ok) for n in names}
    for n in names:
        total = sum(rejections[n].values())
        why = ", ".join(f"{k} {v}" for k, v in sorted(rejections[n].items())) or "none"
        log(f"{n}: {len(poses) - total} of {len(poses)} poses detected; rejected: {why}")
    sizes = {n: source.size(n) for n in names}
    fits = solve_all(points_world, detections, sizes, cell.calibration)
    if rec is not None:
        _log_result(rec, fits, points_world, detections)
    return CalibrationResult(fits, list(poses), points_world, detections, rejections)


def _log_pose(rec, pose: PlannedPose, world_from_tcp: np.ndarray, images: Mapping[str, np.ndarray],
              dets: Mapping[str, CrossDetection]) -> None:
    import rerun as rr

    rec.set_time("calib_pose", sequence=pose.index)
    rec.log("world/calibration/plate", rr.Transform3D(translation=world_from_tcp[:3, 3],
                                                     mat3x3=world_from_tcp[:3, :3]))
    rec.log("world/calibration/plate/axes", rr.Arrows3D(vectors=0.03 * np.eye(3),
                                                         colors=[[255, 0, 0], [0, 255, 0], [0, 0, 255]]))
    for name, img in images.items():
        rec.log(f"calibration/images/{name}", rr.Image(img))
        d = dets[name]
        if d.ok:
            rec.log(f"calibration/images/{name}/cross", rr.Points2D([d.center_px + 0.5], radii=3.0,
                                                                    colors=[[255, 0, 0]]))
        else:
            rec.log(f"calibration/images/{name}/cross", rr.Clear(recursive=False))
        rec.log(f"calibration/detections/{name}", rr.TextLog(f"pose {pose.index}: {d.detail}",
                                                             level="INFO" if d.ok else "WARN"))
    rec.disable_timeline("calib_pose")


def _log_result(rec, fits: Mapping[str, CameraFit], points_world: np.ndarray,
                detections: Mapping[str, Sequence[CrossDetection]]) -> None:
    import rerun as rr

    rec.log("world/calibration/points", rr.Points3D(points_world, radii=0.002, colors=[[230, 0, 200]]),
            static=True)
    for name, fit in fits.items():
        cam = fit.camera
        rec.log(f"world/calibrated/{name}", rr.Transform3D(translation=cam.center, mat3x3=cam.R.T), static=True)
        K = cam.K.copy()
        K[:2, 2] += 0.5                 # rerun puts pixel centres at +0.5
        rec.log(f"world/calibrated/{name}", rr.Pinhole(image_from_camera=K, resolution=[cam.width, cam.height],
                                                       image_plane_distance=0.1), static=True)
        ok_idx = [i for i, d in enumerate(detections[name]) if d.ok]
        res = fit.residuals_px
        rec.send_columns(f"calibration/residual_px/{name}",
                         indexes=[rr.TimeColumn("calib_pose", sequence=np.asarray(ok_idx))],
                         columns=rr.Scalars.columns(scalars=res))
        rec.log(f"calibration/rms_px/{name}", rr.Scalars([float(cam.rms_px)]), static=True)
