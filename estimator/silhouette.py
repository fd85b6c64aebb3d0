"""Model silhouettes and the paper's silhouette cost (eq. 5-7, 11).

The model's silhouette in a camera is the union of its plates' projected quads, filled
with sub-pixel vertices (``cv2.fillPoly`` with ``shift``). The cost of one view is the
number of pixels where model and observed masks differ (exclusive-OR, eq. 5-6) divided by
the observed object's area (eq. 7); views combine as the root of the sum of squares
(eq. 11). Pixels marked in a view's ``ignore`` mask count in neither term.

With known scene boxes (the part, the table), a model plate behind a box from a camera is
not drawn in that view: the opaque box, not tape, is what the camera sees there, so that
pixel is no mismatch where the observed mask shows no tape. Plates are cut into
``OCCLUSION_CELLS`` x ``OCCLUSION_CELLS`` cells for this test, each hidden or not by its
centre.

Rendering works in a region of interest (ROI) of each image. Model area that falls
outside the ROI is charged analytically (quad area minus its part inside the ROI), so a
cropped cost equals the full-image cost as long as the observed tape lies inside the ROI.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .capture import View
from .geometry import Camera
from . import _kernels_boxes
from .scene import Box
from .tape import TapeShape

OCCLUSION_CELLS = 3
"""Cells along and across a plate for the occlusion test (the cut along a box's edge is
then within a third of a plate of the truth, and only where a plate straddles it)."""

SHIFT = 4
"""Fixed-point bits of polygon vertices: vertices land on a 1/16 px grid."""
_ONE = 1 << SHIFT


@dataclass(frozen=True, eq=False)
class ViewTarget:
    """One camera's observed silhouette, cropped and ready for repeated cost evaluation.

    camera: the camera.
    x0, y0: top-left pixel of the ROI in the full image [px].
    observed: (h, w) uint8 ROI of the observed mask (1 tape, 0 background), ignored pixels 0.
    valid: (h, w) uint8, 1 where a pixel counts (not ignored), or None when all count.
    area: observed object's area r_d in counted pixels (eq. 7), at least 1.
    """

    camera: Camera
    x0: int
    y0: int
    observed: np.ndarray
    valid: np.ndarray | None
    area: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.observed.shape  # type: ignore[return-value]


def roi_of(mask: np.ndarray, margin: int) -> tuple[int, int, int, int]:
    """Bounding box (x0, y0, x1, y1) of ``mask``'s pixels grown by ``margin``, clipped."""
    ys, xs = np.nonzero(mask)
    h, w = mask.shape
    if xs.size == 0:
        return 0, 0, w, h
    return (max(0, int(xs.min()) - margin), max(0, int(ys.min()) - margin),
            min(w, int(xs.max()) + margin + 1), min(h, int(ys.max()) + margin + 1))


def make_target(view: View, mask: np.ndarray | None = None,
                roi: tuple[int, int, int, int] | None = None) -> ViewTarget:
    """Prepare ``view`` (or ``mask`` in its place) for cost evaluation in ``roi``.

    ``roi`` defaults to the whole image (the paper's setting).
    """
    mask = view.mask if mask is None else mask
    h, w = mask.shape
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, w, h)
    observed = mask[y0:y1, x0:x1].astype(np.uint8)
    valid = None
    if view.ignore is not None:
        valid = (~view.ignore[y0:y1, x0:x1]).astype(np.uint8)
        observed &= valid
    area = max(1.0, float(cv2.countNonZero(observed)))
    return ViewTarget(view.camera, x0, y0, np.ascontiguousarray(observed), valid, area)


def project_quads(camera: Camera, quads: np.ndarray) -> np.ndarray:
    """(m, 4, 3) world quads -> (m, 4, 2) pixel coordinates (lens distortion applied)."""
    return camera.project(quads.reshape(-1, 3)).reshape(-1, 4, 2)


def render(quads_px: np.ndarray, shape: tuple[int, int], x0: int = 0, y0: int = 0,
           out: np.ndarray | None = None) -> np.ndarray:
    """Fill (m, 4, 2) pixel quads into a (h, w) uint8 image whose top-left pixel is (x0, y0).

    Each quad is filled on its own: one ``fillPoly`` call with several polygons would
    cancel their overlaps (even-odd rule), while the silhouette is their union.
    """
    img = np.zeros(shape, np.uint8) if out is None else out
    if out is not None:
        img[:] = 0
    pts = quads_px - np.array([x0, y0], float)
    if not np.all(np.isfinite(pts)):
        return img
    _fill(img, _fixed_point(pts))
    return img


def _fixed_point(pts: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) as fillPoly's fixed-point int32 vertices, kept inside
    int32 even for points far outside the image."""
    return np.rint(np.clip(pts, -1e5, 1e5) * _ONE).astype(np.int32)


def _fill(img: np.ndarray, fixed: np.ndarray) -> None:
    """Fill each of the fixed-point quads (m, 4, 2) into ``img`` with 1, one by one."""
    for q in fixed:
        cv2.fillPoly(img, [q], 1, cv2.LINE_8, SHIFT)


def _polygon_area(p: np.ndarray) -> float:
    return abs(signed_area(p))


def outside_area(quads_px: np.ndarray, x0: int, y0: int, w: int, h: int) -> float:
    """Approximate model area [px] of ``quads_px`` lying outside the ROI rectangle.

    Zero when every vertex is inside. Quads are treated as convex polygons; overlaps
    between quads outside the ROI are counted twice, which only matters far from the
    optimum where it makes the cost a little steeper.
    """
    lo = np.array([x0 - 0.5, y0 - 0.5])
    hi = np.array([x0 + w - 0.5, y0 + h - 0.5])
    if np.all((quads_px >= lo) & (quads_px <= hi)):
        return 0.0
    rect = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]], np.float32)
    total = 0.0
    for q in quads_px:
        if np.all((q >= lo) & (q <= hi)):
            continue
        if not np.all(np.isfinite(q)):
            return float(w * h)  # behind the camera: as bad as filling the whole ROI
        qf = np.ascontiguousarray(q, np.float32)
        if signed_area(qf) < 0:
            qf = qf[::-1].copy()
        inside, _ = cv2.intersectConvexConvex(qf, rect)
        total += max(0.0, _polygon_area(q) - max(0.0, float(inside)))
    return total


def signed_area(p: np.ndarray) -> float:
    """The area of the polygon ``p`` (k, 2) [px^2] (shoelace), positive where its vertices
    turn from the x axis towards the y axis."""
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def subdivide(quads: np.ndarray, k: int) -> np.ndarray:
    """(..., 4, 3) quads (P_L[i-1], P_L[i], P_R[i], P_R[i-1]) -> (..., k k, 4, 3) bilinear
    cells, k along the tape and k across."""
    a, b, c, d = (quads[..., i, None, None, :] for i in range(4))
    t = np.linspace(0.0, 1.0, k + 1)
    u, v = t[:, None, None], t[None, :, None]
    g = (1 - u) * (1 - v) * a + u * (1 - v) * b + u * v * c + (1 - u) * v * d   # (..., k+1, k+1, 3)
    cells = np.stack([g[..., :-1, :-1, :], g[..., 1:, :-1, :], g[..., 1:, 1:, :], g[..., :-1, 1:, :]], axis=-2)
    return cells.reshape(*quads.shape[:-2], k * k, 4, 3)


def visible_quads(camera: Camera, quads_world: np.ndarray, boxes: Sequence[Box],
                  cells: int = OCCLUSION_CELLS) -> np.ndarray:
    """What no box hides from ``camera`` of (m, 4, 3) world quads, as quads (c, 4, 3): a
    plate whose corners and centre are all seen whole, one they all hide not at all, and
    the cells (``cells`` x ``cells`` a plate) of the others that are seen."""
    return visible_quads_batch(camera, np.asarray(quads_world, float).reshape(1, -1, 4, 3), boxes, cells)[0]


def visible_quads_batch(camera: Camera, quads_world: np.ndarray, boxes: Sequence[Box],
                        cells_per_side: int = OCCLUSION_CELLS) -> list[np.ndarray]:
    """:func:`visible_quads` of B chains' quads (B, m, 4, 3) at once: a list of B (c, 4, 3)."""
    B, m = quads_world.shape[:2]
    probes = np.concatenate([quads_world, quads_world.mean(axis=2, keepdims=True)], axis=2)   # (B, m, 5, 3)
    arrays = _box_arrays(boxes)
    center = np.ascontiguousarray(camera.center, float)
    behind = _kernels_boxes.segments_hit_boxes(center, probes.reshape(-1, 3), *arrays).reshape(B, m, 5)
    whole, mixed = ~behind.any(axis=2), behind.any(axis=2) & ~behind.all(axis=2)
    if not mixed.any():
        return [quads_world[b][whole[b]] for b in range(B)]
    k = cells_per_side * cells_per_side
    cells = subdivide(quads_world[mixed], cells_per_side)                                  # (M, k, 4, 3)
    seen = ~_kernels_boxes.segments_hit_boxes(center, cells.reshape(-1, 4, 3).mean(axis=1), *arrays).reshape(-1, k)
    owner = np.nonzero(mixed)[0]
    return [np.concatenate([quads_world[b][whole[b]], cells[owner == b][seen[owner == b]]]) for b in range(B)]


def _box_arrays(boxes: Sequence[Box]) -> tuple:
    key = tuple(id(b) for b in boxes)
    arrays = _BOX_ARRAYS.get(key)
    if arrays is None or arrays[0] is not boxes[0]:
        if len(_BOX_ARRAYS) > 64:
            _BOX_ARRAYS.clear()
        arrays = _BOX_ARRAYS[key] = (boxes[0], _kernels_boxes.box_arrays(boxes))
    return arrays[1]


_BOX_ARRAYS: dict = {}


class CostEvaluator:
    """Evaluates eq. 7 per view and eq. 11 overall for plate quads, reusing buffers;
    with scene ``boxes``, plates a box hides from a camera are not drawn in its view."""

    def __init__(self, targets: Sequence[ViewTarget], boxes: Sequence[Box] = ()):
        self.targets = list(targets)
        self.boxes = tuple(boxes)
        self._model = [np.zeros(t.shape, np.uint8) for t in self.targets]
        self._diff = [np.zeros(t.shape, np.uint8) for t in self.targets]
        self.evaluations = 0

    def _seen(self, t: ViewTarget, quads_world: np.ndarray, cells: int = OCCLUSION_CELLS) -> np.ndarray:
        return visible_quads(t.camera, quads_world, self.boxes, cells) if self.boxes else quads_world

    def view_costs(self, quads_world: np.ndarray) -> np.ndarray:
        """(m, 4, 3) world quads -> (views,) normalised XOR costs s/r_d (eq. 5-7)."""
        self.evaluations += 1
        out = np.empty(len(self.targets))
        for k, t in enumerate(self.targets):
            px = project_quads(t.camera, self._seen(t, quads_world))
            out[k] = self._view_xors(k, px[None])[0] / t.area
        return out

    def _view_xors(self, k: int, quads_px: np.ndarray) -> np.ndarray:
        """(B,) XOR pixel counts in view ``k`` of B chains' pixel quads (B, m, 4, 2), each as
        :func:`render` draws it, plus its area outside the ROI (:func:`outside_area`); the
        vertices are converted for all chains at once. Leaves the last chain's images in the
        view's buffers."""
        t = self.targets[k]
        h, w = t.shape
        pts = quads_px - np.array([t.x0, t.y0], float)
        finite = np.isfinite(pts).all(axis=(1, 2, 3))
        fixed = _fixed_point(np.where(finite[:, None, None, None], pts, 0.0))
        lo = np.array([t.x0 - 0.5, t.y0 - 0.5])
        hi = np.array([t.x0 + w - 0.5, t.y0 + h - 0.5])
        inside = ((quads_px >= lo) & (quads_px <= hi)).all(axis=(1, 2, 3))
        model, diff = self._model[k], self._diff[k]
        out = np.empty(len(quads_px))
        for b in range(len(quads_px)):
            model[:] = 0
            if finite[b]:
                _fill(model, fixed[b])
            if t.valid is not None:
                cv2.bitwise_and(model, t.valid, dst=model)
            cv2.bitwise_xor(model, t.observed, dst=diff)
            out[b] = float(cv2.countNonZero(diff)) + (0.0 if inside[b] else
                                                       outside_area(quads_px[b], t.x0, t.y0, w, h))
        return out

    def cost(self, quads_world: np.ndarray) -> float:
        """Combined cost over cameras (eq. 11)."""
        return combine(self.view_costs(quads_world))

    def costs(self, quads_world: np.ndarray) -> np.ndarray:
        """(B, m, 4, 3) world quads of B chains -> (B,) eq.-11 costs (each view projects
        all chains at once)."""
        B, m = quads_world.shape[:2]
        if self.boxes:
            self.evaluations += B
            out = np.zeros((B, len(self.targets)))
            for k, t in enumerate(self.targets if B else ()):
                for b, q in enumerate(visible_quads_batch(t.camera, quads_world, self.boxes)):
                    out[b, k] = self._view_xors(k, project_quads(t.camera, q)[None])[0] / t.area
            return np.array([combine(row) for row in out])
        self.evaluations += B
        out = np.zeros((B, len(self.targets)))
        for k, t in enumerate(self.targets if B else ()):
            px = project_quads(t.camera, quads_world.reshape(-1, 4, 3)).reshape(B, m, 4, 2)
            out[:, k] = self._view_xors(k, px) / t.area
        return np.array([combine(row) for row in out])

    def last_diffs(self) -> list[np.ndarray]:
        """Each view's disagreement image (ROI-sized uint8: the model on counted pixels XOR
        the observed silhouette) of the last chain evaluated: the buffers the last
        :meth:`view_costs` (or the last chain of :meth:`costs`) wrote, not copies."""
        return self._diff

    def model_masks(self, quads_world: np.ndarray, occluded: bool = True,
                    cells: int = OCCLUSION_CELLS) -> list[np.ndarray]:
        """The model silhouettes (ROI-sized uint8 images) for the given quads: behind the
        scene boxes hidden (a plate a box's edge crosses cut into ``cells`` x ``cells``
        cells, each hidden or not by its centre), or, ``occluded`` False, as if no box hid
        them."""
        return [render(project_quads(t.camera, self._seen(t, quads_world, cells) if occluded else quads_world),
                       t.shape, t.x0, t.y0)
                for t in self.targets]


def combine(view_costs: np.ndarray) -> float:
    """Eq. 11: root of the sum of squared per-view costs."""
    return float(np.sqrt(np.sum(np.square(view_costs))))


def shape_quads(shape: TapeShape) -> np.ndarray:
    """(n, 4, 3) plate quads of a tape shape."""
    return shape.quads()


def render_view(camera: Camera, shape: TapeShape, boxes: Sequence[Box] = ()) -> np.ndarray:
    """Full-image bool silhouette of ``shape`` in ``camera`` (behind ``boxes`` hidden)."""
    quads = shape.quads()
    px = project_quads(camera, visible_quads(camera, quads, boxes) if boxes else quads)
    return render(px, (camera.height, camera.width)).astype(bool)
