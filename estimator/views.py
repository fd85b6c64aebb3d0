"""Views and masks: each camera's view prepared for the boundary fit (stage 1 of
:mod:`estimator.fit`): the mask cleaned (speckles dropped, pinholes filled), a region of
interest boxed around the tape, the signed distance field of the observed silhouette and
its gradient, the observed outline's points and the silhouette target for eq. 7."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import _kernels_beam, _kernels_boxes
from .capture import View
from .config import DEFAULT, FitConfig
from .geometry import Camera
from .silhouette import ViewTarget


@dataclass(frozen=True, eq=False)
class Field:
    """One view prepared for the boundary fit.

    camera: its calibration; x0, y0: ROI origin [px]; field: (h, w, 4) float32 of the
    signed distance to the observed boundary [px] (negative inside), its x/y gradient and,
    only with an ignore mask, 1 where the pixel is ignored (else (h, w, 3)); has_ignore: whether the view has an ignore mask;
    target: the cleaned mask as a :class:`ViewTarget` for the silhouette cost;
    outline: (P, 2) points on the observed outline [px, full image];
    weight: factor on this view's robust terms (see :func:`_view_weight`).
    """

    camera: Camera
    x0: int
    y0: int
    field: np.ndarray
    has_ignore: bool
    target: ViewTarget
    outline: np.ndarray
    weight: float = 1.0
    planes: tuple = ()
    """(sdf (h, w), ignore flag (h, w) or (1, 1) zeros) float32: the field's channels 0
    and 3 on their own, for the beam's score (no gradient needed: half the memory read)."""
    boxes: tuple = ()
    """The capture's scene boxes: model points behind them from this camera count nothing."""
    box_arrays: tuple = ()
    """``boxes`` in the kernels' form (see :func:`_kernels_boxes.box_arrays`)."""
    outline_px: float = 1.0
    """Length of the observed silhouette's outer outline [px]."""


def _drop_small(m: np.ndarray, connectivity: int, cfg: FitConfig) -> np.ndarray:
    """uint8 0/1 ``m`` without its connected regions smaller than cfg.speckle_px (the largest
    is always kept). Labels without stats: OpenCV's statistics pass costs ten times more."""
    count, labels = cv2.connectedComponents(m, connectivity=connectivity)
    if count <= 2:
        return m
    areas = _kernels_beam.label_areas(labels, count) if cfg.compiled else np.bincount(labels.ravel(), minlength=count)
    keep = np.zeros(count, np.uint8)
    keep[1:] = areas[1:] >= min(cfg.speckle_px, areas[1:].max())
    return _kernels_beam.map_labels(labels, keep, np.zeros(m.shape, np.uint8)) if cfg.compiled else keep[labels]


def clean_mask(mask: np.ndarray, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """The mask without speckles (small isolated regions); uint8 0/1."""
    return _drop_small(mask.view(np.uint8), 8, cfg)


def fill_pinholes(m: np.ndarray, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """``m`` with small holes (background regions not touching much else) filled."""
    inv = (1 - m).astype(np.uint8)
    count, labels = cv2.connectedComponents(inv, connectivity=4)
    if count <= 2:
        return m
    areas = _kernels_beam.label_areas(labels, count) if cfg.compiled else np.bincount(labels.ravel(), minlength=count)
    small = np.zeros(count, bool)
    small[1:] = areas[1:] < cfg.speckle_px
    if cfg.compiled:
        return _kernels_beam.map_labels(labels, small.view(np.uint8), np.ascontiguousarray(m))
    out = m.copy()
    out[small[labels]] = 1
    return out


def _crop_box(mask: np.ndarray, cfg: FitConfig) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of the tape in a mask: :func:`_tape_box`, and where at
    least cfg.speckle_px tape pixels lie outside it, grown to every region of that many
    pixels. A thin line (the tape seen edge-on, one pixel per row) has too few pixels per
    row for :func:`_tape_box`, which alone would crop it off."""
    box = _tape_box(mask)
    m = mask.view(np.uint8)
    x0, y0, x1, y1 = box
    if cv2.countNonZero(m) - cv2.countNonZero(m[y0:y1, x0:x1]) < cfg.speckle_px:
        return box
    count, _, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    for sx, sy, sw, sh, area in stats[1:]:
        if area >= cfg.speckle_px:
            x0, y0, x1, y1 = min(x0, sx), min(y0, sy), max(x1, sx + sw), max(y1, sy + sh)
    return int(x0), int(y0), int(x1), int(y1)


def _tape_box(mask: np.ndarray) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of the tape, ignoring isolated speckles: only rows and
    columns holding at least 3 tape pixels count."""
    m = mask.view(np.uint8)
    cols = np.flatnonzero(cv2.reduce(m, 0, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[0] >= 3)
    rows = np.flatnonzero(cv2.reduce(m, 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S)[:, 0] >= 3)
    if cols.size == 0 or rows.size == 0:
        x, y, w, h = cv2.boundingRect(m)
        return x, y, x + w, y + h
    return int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1


def prepare(view: View, boxes: tuple = (), cfg: FitConfig = DEFAULT) -> Field:
    """``view`` ready for the boundary fit: its cleaned mask's signed distance field, outline
    and silhouette target in a region of interest (see :class:`Field`)."""
    cam = view.camera
    bx0, by0, bx1, by1 = _crop_box(view.mask, cfg)
    margin = cfg.occluded_margin_px if view.ignore is not None else cfg.margin_px
    x0, y0 = max(0, bx0 - margin), max(0, by0 - margin)
    x1, y1 = min(cam.width, bx1 + margin), min(cam.height, by1 + margin)
    roi = clean_mask(view.mask[y0:y1, x0:x1], cfg)
    # Speckles of a noisy mask stretch the first box over most of the image; without them
    # the box is the tape's, and every step below works on far fewer pixels.
    cx0, cy0, cx1, cy1 = _crop_box(roi, cfg)
    cx0, cy0 = max(0, cx0 - margin), max(0, cy0 - margin)
    cx1, cy1 = min(x1 - x0, cx1 + margin), min(y1 - y0, cy1 + margin)
    roi = fill_pinholes(np.ascontiguousarray(roi[cy0:cy1, cx0:cx1]), cfg)
    x0, y0, x1, y1 = x0 + cx0, y0 + cy0, x0 + cx1, y0 + cy1
    ignore = None if view.ignore is None else view.ignore[y0:y1, x0:x1]
    # Unknown pixels get the benefit of the doubt: no boundary is drawn through them.
    solid = roi if ignore is None else (roi | ignore).astype(np.uint8)
    inside = cv2.distanceTransform(solid, cv2.DIST_L2, cv2.DIST_MASK_5)
    outside = cv2.distanceTransform(1 - solid, cv2.DIST_L2, cv2.DIST_MASK_5)
    # 0.5 - inside on tape pixels, outside - 0.5 elsewhere: the boundary between pixels.
    sdf = outside - inside
    sdf += solid
    sdf -= 0.5
    gx = cv2.Sobel(sdf, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(sdf, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    flag = np.zeros((1, 1), np.float32) if ignore is None else ignore.astype(np.float32)
    field = cv2.merge([sdf, gx, gy] if ignore is None else [sdf, gx, gy, flag])
    valid = None if ignore is None else (~ignore).astype(np.uint8)
    observed = roi if valid is None else roi & valid
    target = ViewTarget(cam, x0, y0, np.ascontiguousarray(observed), valid,
                        max(1.0, float(cv2.countNonZero(observed))))
    contours, _ = cv2.findContours(roi, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outline = _outline(contours, ignore, x0, y0, cfg)
    if boxes and len(outline):
        outline = outline[~_on_box_outline(cam, boxes, outline, cfg)]
    perimeter = max(1.0, sum(cv2.arcLength(c, True) for c in contours))
    return Field(cam, x0, y0, field, ignore is not None, target, outline,
                  _view_weight(roi, perimeter, cfg), (sdf, flag), tuple(boxes), _kernels_boxes.box_arrays(boxes) if boxes else (),
                  perimeter)


def _on_box_outline(camera: Camera, boxes, points: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """(P,) which outline points (P, 2) [px] lie on the projected outline of a box."""
    return box_outline_px(camera, boxes, points) < cfg.box_edge_px


_BOX_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)


def box_hulls(camera: Camera, boxes):
    """Each scene box's projected outline in ``camera``: the convex hull (c, 1, 2) float32 of
    its projected corners [px]; a box with a corner behind the camera is left out."""
    for box in boxes:
        corners = box.center + (_BOX_SIGNS * box.half) @ box.rotation.T
        if np.all(camera.to_camera(corners)[:, 2] > 0):
            yield cv2.convexHull(camera.project(corners).astype(np.float32))


def box_outline_px(camera: Camera, boxes, points: np.ndarray) -> np.ndarray:
    """(P,) distance [px] from each image point (P, 2) to the nearest scene box's projected
    outline (the convex hull of its projected corners; inf without boxes, or for a box with
    a corner behind the camera, or for a point that is not finite)."""
    out = np.full(len(points), np.inf)
    for hull in box_hulls(camera, boxes):
        for k, (u, v) in enumerate(points):
            if np.isfinite(u) and np.isfinite(v):
                out[k] = min(out[k], abs(cv2.pointPolygonTest(hull, (float(u), float(v)), True)))
    return out


def box_outline_mask(camera: Camera, boxes, shape: tuple[int, int], origin: tuple[int, int],
                     px: float) -> np.ndarray:
    """uint8 0/1 (h, w) crop (top-left pixel ``origin``) of the pixels within ``px`` (to
    half a pixel) of a scene box's projected outline, as :func:`box_outline_px` measures it:
    the convex hull of the box's projected corners, a box with a corner behind the camera
    left out. (The outline drawn one pixel wide, then each pixel's Euclidean distance to
    it: a thick line of OpenCV's reaches a pixel or two farther at its round ends.)"""
    line = np.zeros(shape, np.uint8)
    for hull in box_hulls(camera, boxes):
        hull = hull[:, 0] - np.asarray(origin, np.float32)
        if np.all(np.isfinite(hull)) and np.all(np.abs(hull) < 1e6):
            cv2.polylines(line, [np.rint(hull).astype(np.int32)], True, 1)
    if not line.any():
        return line
    return (cv2.distanceTransform(1 - line, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) <= px).astype(np.uint8)


def _view_weight(roi: np.ndarray, perimeter: float, cfg: FitConfig) -> float:
    """Factor on a view's robust terms: 1, less for a very thin silhouette (the tape seen
    nearly edge-on). There a pixel of segmentation or calibration error moves the boundary
    across the whole band, so the edge terms of the right shape land outside and that one
    view would outvote the others (measured: sim edge-on captures)."""
    if cfg.thin_px <= 0:
        return 1.0
    thickness = 2.0 * float(cv2.countNonZero(roi)) / max(perimeter, 1.0)   # mean width [px]
    return min(1.0, thickness / cfg.thin_px) ** 2


def _outline(contours, ignore: np.ndarray | None, x0: int, y0: int, cfg: FitConfig) -> np.ndarray:
    """About cfg.outline_points points spread evenly along the observed silhouette's outer
    boundary (``contours``: its outer contours in the ROI), in full-image pixels; none next
    to ignored pixels (not a real boundary)."""
    if not contours:
        return np.zeros((0, 2))
    pts = np.concatenate([c.reshape(-1, 2) for c in contours])
    if ignore is not None:
        near = cv2.dilate(ignore.astype(np.uint8), np.ones((5, 5), np.uint8))
        pts = pts[near[pts[:, 1], pts[:, 0]] == 0]
    step = max(1, len(pts) // cfg.outline_points)
    return pts[::step].astype(float) + np.array([x0, y0], float)
