"""Plausibility checks that refuse garbage a capture's files can hold although every number
in them is well-formed: a mask that is inverted, a file in millimetres, a camera whose
rotation is transposed or whose pose or intrinsics put the tape somewhere else than where
its mask is.

Each check raises :class:`CaptureError` with one line naming the file and the problem.

The geometric check is sound without knowing the tape's shape: whatever its angles, the
tape lies within ``reach = sum(segment_lengths) + width / 2`` of its base, so its pixels
lie inside the projection of that ball. A mask mostly outside that region cannot be this
tape seen by this camera.
"""
from __future__ import annotations

import cv2
import numpy as np

from .errors import CaptureError
from .geometry import MAX_CAMERA_DISTANCE_M, Camera
from .tape import TapeSpec

MAX_MASK_FRACTION = 0.5
"""A silhouette covering more of the image than this is taken as inverted (tape black on
white): the tape, seen whole by a camera that can frame it, never fills most of the image."""
MAX_DISTANCE_M = MAX_CAMERA_DISTANCE_M
"""No camera or tape base of a cell lies farther than this from the robot's base: a larger
number is a file in millimetres."""
MAX_SEGMENT_M = 1.0
"""No plate of a tape model is longer (or wider) than this: a larger one is in millimetres."""
MIN_MASK_IN_REACH = 0.5
"""At least this fraction of a view's visible mask must lie where the tape can project."""


def check_distance(position: np.ndarray, what: str, source: str) -> None:
    """Refuse a position [m] too far from the world origin to be in metres."""
    d = float(np.linalg.norm(position))
    if d > MAX_DISTANCE_M:
        raise CaptureError(f"{source}: {what} is {d:.4g} m from the world origin; the file looks like it is "
                           f"in millimetres (metres expected, no cell is larger than {MAX_DISTANCE_M:g} m)")


def check_tape_units(tape: TapeSpec, source: str) -> None:
    """Refuse tape dimensions that are millimetres written as metres."""
    longest = float(np.max(tape.segment_lengths))
    if longest > MAX_SEGMENT_M or tape.width > MAX_SEGMENT_M:
        raise CaptureError(f"{source}: tape plates of {longest:.4g} m and width {tape.width:.4g} m; the file looks "
                           "like it is in millimetres (metres expected)")
    check_distance(tape.base_position, "the tape base", source)


def check_mask_coverage(mask: np.ndarray, camera_name: str, source: str) -> None:
    """Refuse a mask whose tape covers most of the image (an inverted mask)."""
    fraction = float(np.count_nonzero(mask)) / max(mask.size, 1)
    if fraction > MAX_MASK_FRACTION:
        raise CaptureError(f"{source}: the mask of camera {camera_name} marks {100 * fraction:.0f} % of the image as "
                           "tape; it looks inverted (the tape must be white, 255, on black, 0)")


def _rays(camera: Camera, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(N, 3) unit viewing rays in the camera frame of pixels (xs, ys), lens distortion removed."""
    pts = np.column_stack([xs, ys]).astype(np.float64).reshape(-1, 1, 2)
    if len(pts) == 0:
        return np.zeros((0, 3))
    if camera.has_distortion:
        xy = cv2.undistortPoints(pts, camera.K, camera.dist).reshape(-1, 2)
    else:
        K = camera.K
        y = (pts[:, 0, 1] - K[1, 2]) / K[1, 1]
        x = (pts[:, 0, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
        xy = np.column_stack([x, y])
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def reach_cone(camera: Camera, tape: TapeSpec) -> tuple[np.ndarray, float] | None:
    """The rays along which ``camera`` can see the tape: (unit axis in the camera frame,
    cos of the half-angle), the cone of rays through the ball of radius ``reach`` (a little
    enlarged) around the tape's base. None when the camera is inside that ball (no bound)."""
    reach = 1.05 * (tape.length + 0.5 * tape.width)
    centre = camera.to_camera(np.asarray(tape.base_position, float)[None])[0]
    d = float(np.linalg.norm(centre))
    if d <= reach:
        return None
    return centre / d, float(np.sqrt(1.0 - (reach / d) ** 2))


def _fraction_in_reach(camera: Camera, tape: TapeSpec, xs: np.ndarray, ys: np.ndarray) -> float | None:
    cone = reach_cone(camera, tape)
    if cone is None:
        return None
    if len(xs) == 0:
        return 1.0
    axis, cos_half = cone
    return float(np.mean(_rays(camera, xs, ys) @ axis >= cos_half))


def check_view_geometry(camera: Camera, tape: TapeSpec, visible: np.ndarray, source: str) -> None:
    """Refuse a camera whose calibration puts the tape away from where its mask is.

    visible: (H, W) bool, the mask pixels that count (outside the ignore mask). A camera
    that explains the mask with its rotation transposed, or with its pose inverted
    (world_from_camera written for camera_from_world), is named as such."""
    ys, xs = np.nonzero(visible)
    frac = _fraction_in_reach(camera, tape, xs, ys)
    if frac is None or frac >= MIN_MASK_IN_REACH:
        return
    where = f"{source}: camera {camera.name}"
    transposed = camera.with_pose(camera.R.T, camera.t)
    inverted = camera.with_pose(camera.R.T, -camera.R.T @ camera.t)
    for alt, what in ((inverted, "its R and t look like the camera's pose (world_from_camera), "
                                 "but tape-cameras/1 wants camera_from_world (x_cam = R X + t)"),
                      (transposed, "its rotation R looks transposed (x_cam = R X + t expected)")):
        alt_frac = _fraction_in_reach(alt, tape, xs, ys)
        if alt_frac is not None and alt_frac >= MIN_MASK_IN_REACH:
            raise CaptureError(f"{where}: the tape cannot be where its mask is; {what}")
    axis, cos_half = reach_cone(camera, tape)
    w, h = camera.width, camera.height
    if axis[2] < -np.sqrt(1.0 - cos_half ** 2):
        raise CaptureError(f"{where}: the tape (base at {np.round(tape.base_position, 3).tolist()} m) is behind "
                           "the camera; check its R and t")
    gx, gy = np.meshgrid(np.linspace(0, w - 1, 33), np.linspace(0, h - 1, 25))
    if not np.any(_rays(camera, gx.ravel(), gy.ravel()) @ axis >= cos_half):
        raise CaptureError(f"{where}: the tape (base at {np.round(tape.base_position, 3).tolist()} m) is outside "
                           f"the {w}x{h} image; check its intrinsics K and its pose")
    raise CaptureError(f"{where}: {100 * (1 - frac):.0f} % of its mask lies where the tape cannot be (farther "
                       f"than {tape.length + 0.5 * tape.width:.3f} m from its base); check its intrinsics K and "
                       "its pose, or the mask")
