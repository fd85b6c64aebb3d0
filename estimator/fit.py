"""The project's estimator (method="default") and the public :func:`estimate`.

Where the paper searches the XOR cost with a simplex, node by node, we fit the plate
chain's silhouette *boundary* to the observed one, which gives a smooth cost with an
analytic Jacobian:

1. Per view, clean the mask (drop speckles, fill pinholes), crop a region of interest and
   build the signed distance field (SDF) of the observed silhouette, negative inside.
2. Global stage, a beam search node by node: every kept partial chain is extended by a
   grid of joint angles (twist, out-of-plane and in-plane bend); a candidate's score
   asks that its plate edges lie on the observed boundary and its centre line inside the
   silhouette in every view (robust losses: Huber outside, Cauchy inside, so an edge
   hidden behind another part of the tape costs little). Keeping several chains escapes
   the wrong branches a greedy pass falls into (twist sign, a tape curled back).
3. Local stage: Levenberg-Marquardt on all 3n angles jointly, with the same residuals
   (re-weighted each iteration) and their exact Jacobian through the chain's kinematics
   and the camera projection.
4. The refined candidates are ranked by the paper's own silhouette cost (eq. 11); the
   best one is returned with its per-view costs on the full observed masks.
5. Only when that cost is high (a poor fit) a wide stage runs: a finer, larger beam plus
   the other branches next to the winner (mirrored bends, flipped or quarter-turned
   twists); its result replaces the first only when its eq.-11 cost is clearly lower.
6. Strip stage: a 30 mm plate cannot follow a tape that curls within its length, so its
   last plate is a chord and the tip lands mm off. From the winner, a continuous strip
   (a fine chain whose twist and bend rates vary linearly between knots at the model's
   nodes, in-plane bending held near zero as a tape's is) is fitted on the same
   residuals; the output plate chain is the one closest to the strip in 3-D at the
   model's nodes, tip first. A chain that explains the views far worse than the plate
   fit (the strip gone astray) is dropped for the plate fit.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from . import _kernels, _kernels_beam, _kernels_boxes
from .capture import Capture, View
from .errors import EstimateError
from .geometry import Camera, _distort
from .result import Alternative, Estimate, Verdict
from .silhouette import CostEvaluator, ViewTarget, combine, make_target, project_quads
from .tape import TapeSpec, forward_kinematics, joint_rotations
from .verdict import DISTINCT_TIP_M, FOLD_DEG, assess, is_close_alternative, mask_fault

Callback = Callable[[int, float, np.ndarray], None]

MARGIN_PX = 12
"""ROI margin around the observed tape [px]."""
OCCLUDED_MARGIN_PX = 60
"""ROI margin when an ignore mask may hide part of the tape [px]."""
SPECKLE_PX = 25
"""Connected regions (of tape or of background inside it) smaller than this are noise."""
DELTA_OUT_PX = 3.0
"""Huber scale for points outside the silhouette [px]."""
DELTA_IN_PX = 1.5
"""Cauchy scale for edge points inside the silhouette (possibly hidden edges) [px]."""
OUTLINE_POINTS = 48
"""Observed outline points per view in the coverage term."""
BEAM = 8
DIVERSE_M = 0.006
"""Plate ends of two kept partial chains differ by at least this [m] (beam diversity)."""
DIVERSE_POOL = 2
"""The diverse beam picks from this many times its width of best candidates."""
"""Partial chains kept per node in the global stage."""
REFINE = 3
"""Candidates refined to convergence after screening."""
REFINE_EQ11 = 1
"""Further screened candidates, the best by the silhouette cost (eq. 11), refined too..."""
EQ11_RANGE = 2.0
"""... chosen among those whose robust cost is below this multiple of the best one's."""
LM_SCREEN = 4
"""Levenberg-Marquardt iterations every beam candidate gets before screening."""
LM_ITERATIONS = 6
TIP_WEIGHT = 1.0
"""Weight of the residuals on the last plate's edges and the tip edge (others 1)."""
LM_RTOL = 3e-3
"""A local-stage step that lowers the robust cost by less than this fraction ends it."""
ANGLE_PRIOR = 0.05
"""Weight of a weak preference for small joint angles in the global stage."""
WIDE_COST = 0.15
"""Eq.-11 cost above which a fit is poor enough to pay for the wide search."""
WIDE_OFFSET_PX = 1.5
"""... or when a view's mean boundary distance (its XOR over its outline length) is above
this [px]: a view the first search's winner does not explain (about 1 in 10 good fits)."""
WIDE_BEAM = 8
THOROUGH_BEAM = 24

"""Partial chains kept per node in the second look an estimate that is not "ok" gets (see
:func:`estimate`)."""
"""Partial chains kept per node in the wide search."""
WIDE_VARIANTS = True
WIDE_GAIN = 0.85
"""The wide search's result replaces the first when its eq.-11 cost is below this
fraction of the first's (only a clear difference counts)."""
ANGLE_PRIOR_PX = 1.0
"""Residual [px] per radian of every joint angle in the local stage (a weak prior)."""
PENETRATION_PX_PER_M = 5000.0
"""Residual [px] per metre a chain point lies inside a scene box (1 mm inside costs like a
boundary 5 px off): the tape cannot pass through the part or the table."""
BEAM_PENETRATION = 50.0
"""Beam-score penalty per millimetre a candidate's sample point lies inside a scene box."""
ALTERNATIVES = 2
"""Distinct screened candidates (tips more than DISTINCT_TIP_M from the refined ones)
refined as well, so that another shape explaining the views is found and weighed."""
THIN_PX = 15.0
"""A view whose silhouette is on average thinner than this [px] (2 area / perimeter) has
its robust terms weighted by (thickness / THIN_PX)^2 (0: off)."""
COMPILED = True
"""Evaluate the hot loops with the compiled kernels of estimator/_kernels.py (numba); off:
the NumPy reference code here (same numbers to float rounding, ~10x slower per call)."""

_EDGE_T = np.array([0.25, 0.5, 0.75, 1.0])
_TIP_T = np.array([0.1, 0.3, 0.5, 0.7, 0.9])
_CENTRE_T = np.array([0.5, 1.0])
_BEAM_EDGE_T = np.array([0.25, 0.5, 0.75, 1.0])
BEAM_OUTLINE_STEP = 2
"""Every how many observed outline points rank the beam's complete chains."""


def _angle_grid(tx, ty, tz) -> np.ndarray:
    """Candidate joint angles (θx, θy, θz) of the global stage [rad]."""
    return np.stack(np.meshgrid(tx, ty, tz, indexing="ij"), axis=-1).reshape(-1, 3)


_GRID = _angle_grid([-0.8, -0.4, 0.0, 0.4, 0.8], np.linspace(-1.2, 1.2, 9), [0.0])
_WIDE_GRID = _angle_grid(np.linspace(-1.2, 1.2, 7), np.linspace(-1.5, 1.5, 11), [-0.4, 0.0, 0.4])


# --------------------------------------------------------------------------- views

@dataclass(frozen=True, eq=False)
class _Field:
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


def _drop_small(m: np.ndarray, connectivity: int) -> np.ndarray:
    """uint8 0/1 ``m`` without its connected regions smaller than SPECKLE_PX (the largest
    is always kept). Labels without stats: OpenCV's statistics pass costs ten times more."""
    count, labels = cv2.connectedComponents(m, connectivity=connectivity)
    if count <= 2:
        return m
    areas = _kernels_beam.label_areas(labels, count) if COMPILED else np.bincount(labels.ravel(), minlength=count)
    keep = np.zeros(count, np.uint8)
    keep[1:] = areas[1:] >= min(SPECKLE_PX, areas[1:].max())
    return _kernels_beam.map_labels(labels, keep, np.zeros(m.shape, np.uint8)) if COMPILED else keep[labels]


def _clean_mask(mask: np.ndarray) -> np.ndarray:
    """The mask without speckles (small isolated regions); uint8 0/1."""
    return _drop_small(mask.view(np.uint8), 8)


def _fill_pinholes(m: np.ndarray) -> np.ndarray:
    """``m`` with small holes (background regions not touching much else) filled."""
    inv = (1 - m).astype(np.uint8)
    count, labels = cv2.connectedComponents(inv, connectivity=4)
    if count <= 2:
        return m
    areas = _kernels_beam.label_areas(labels, count) if COMPILED else np.bincount(labels.ravel(), minlength=count)
    small = np.zeros(count, bool)
    small[1:] = areas[1:] < SPECKLE_PX
    if COMPILED:
        return _kernels_beam.map_labels(labels, small.view(np.uint8), np.ascontiguousarray(m))
    out = m.copy()
    out[small[labels]] = 1
    return out


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


def _prepare(view: View, boxes: tuple = ()) -> _Field:
    cam = view.camera
    bx0, by0, bx1, by1 = _tape_box(view.mask)
    margin = OCCLUDED_MARGIN_PX if view.ignore is not None else MARGIN_PX
    x0, y0 = max(0, bx0 - margin), max(0, by0 - margin)
    x1, y1 = min(cam.width, bx1 + margin), min(cam.height, by1 + margin)
    roi = _clean_mask(view.mask[y0:y1, x0:x1])
    # Speckles of a noisy mask stretch the first box over most of the image; without them
    # the box is the tape's, and every step below works on far fewer pixels.
    cx0, cy0, cx1, cy1 = _tape_box(roi)
    cx0, cy0 = max(0, cx0 - margin), max(0, cy0 - margin)
    cx1, cy1 = min(x1 - x0, cx1 + margin), min(y1 - y0, cy1 + margin)
    roi = _fill_pinholes(np.ascontiguousarray(roi[cy0:cy1, cx0:cx1]))
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
    outline = _outline(contours, ignore, x0, y0)
    if boxes and len(outline):
        outline = outline[~_on_box_outline(cam, boxes, outline)]
    perimeter = max(1.0, sum(cv2.arcLength(c, True) for c in contours))
    return _Field(cam, x0, y0, field, ignore is not None, target, outline,
                  _view_weight(roi, perimeter), (sdf, flag), tuple(boxes), _kernels_boxes.box_arrays(boxes) if boxes else (),
                  perimeter)


BOX_EDGE_PX = 3.0
"""Observed outline points this close [px] to a scene box's projected outline are where the
tape goes behind the box, not the tape's own edge: the coverage term leaves them out."""


def _on_box_outline(camera: Camera, boxes, points: np.ndarray) -> np.ndarray:
    """(P,) which outline points (P, 2) [px] lie on the projected outline of a box."""
    out = np.zeros(len(points), bool)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    for box in boxes:
        corners = box.center + (signs * box.half) @ box.rotation.T
        if np.any(camera.to_camera(corners)[:, 2] <= 0):
            continue
        hull = cv2.convexHull(camera.project(corners).astype(np.float32))
        d = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), True) for x, y in points])
        out |= np.abs(d) < BOX_EDGE_PX
    return out


def _view_weight(roi: np.ndarray, perimeter: float) -> float:
    """Factor on a view's robust terms: 1, less for a very thin silhouette (the tape seen
    nearly edge-on). There a pixel of segmentation or calibration error moves the boundary
    across the whole band, so the edge terms of the right shape land outside and that one
    view would outvote the others (measured: sim edge-on captures)."""
    if THIN_PX <= 0:
        return 1.0
    thickness = 2.0 * float(cv2.countNonZero(roi)) / max(perimeter, 1.0)   # mean width [px]
    return min(1.0, thickness / THIN_PX) ** 2


def _outline(contours, ignore: np.ndarray | None, x0: int, y0: int) -> np.ndarray:
    """About OUTLINE_POINTS points spread evenly along the observed silhouette's outer
    boundary (``contours``: its outer contours in the ROI), in full-image pixels; none next
    to ignored pixels (not a real boundary)."""
    if not contours:
        return np.zeros((0, 2))
    pts = np.concatenate([c.reshape(-1, 2) for c in contours])
    if ignore is not None:
        near = cv2.dilate(ignore.astype(np.uint8), np.ones((5, 5), np.uint8))
        pts = pts[near[pts[:, 1], pts[:, 0]] == 0]
    step = max(1, len(pts) // OUTLINE_POINTS)
    return pts[::step].astype(float) + np.array([x0, y0], float)


# --------------------------------------------------------------------------- sampling

def _lookup(field: _Field, u: np.ndarray, v: np.ndarray):
    """Bilinear look-up (one ``cv2.remap`` call) of the SDF, its gradient and the ignore
    flag at pixel coordinates (u, v) of any shape.

    Outside the ROI the SDF continues as the value at the ROI's edge plus the distance to
    it, and its gradient points back towards the ROI. Returns (sdf, gx, gy, ignored|None).
    """
    h, w = field.field.shape[:2]
    shape = u.shape
    x = (u - field.x0).reshape(-1)
    y = (v - field.y0).reshape(-1)
    xc = np.clip(x, 0.0, w - 1.0)
    yc = np.clip(y, 0.0, h - 1.0)
    ox = x - xc
    oy = y - yc
    n = x.size
    cols = 8192
    rows = -(-n // cols) if n > cols else 1
    width = cols if n > cols else n
    mx = np.zeros(rows * width, np.float32)
    my = np.zeros(rows * width, np.float32)
    mx[:n] = xc
    my[:n] = yc
    val = cv2.remap(field.field, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE).reshape(-1, field.field.shape[2])[:n]
    extra = np.abs(ox) + np.abs(oy)
    outside = extra > 0
    sdf = val[:, 0] + extra
    gx = np.where(ox != 0, np.sign(ox), val[:, 1])
    gy = np.where(oy != 0, np.sign(oy), val[:, 2])
    ignored = ((val[:, 3] > 0.5) & ~outside).reshape(shape) if field.has_ignore else None
    return sdf.reshape(shape), gx.reshape(shape), gy.reshape(shape), ignored


def _project(camera: Camera, pts: np.ndarray):
    """Pixels (u, v) of world points (..., 3) and their camera-frame x/z, y/z and z."""
    pc = pts @ camera.R.T + camera.t
    z = np.maximum(pc[..., 2], 1e-6)
    x = pc[..., 0] / z
    y = pc[..., 1] / z
    if camera.has_distortion:
        xd, yd = _distort(x, y, camera.dist)
    else:
        xd, yd = x, y
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    return u, v, x, y, z


def _pixel_jacobian(camera: Camera, x, y, z, J: np.ndarray) -> np.ndarray:
    """(..., 2, N) d(u, v)/d(angles) of points with world Jacobian J (..., 3, N), pinhole
    part (lens distortion is a small correction the iterations absorb)."""
    K = camera.K
    inv_z = 1.0 / z
    duv = np.zeros(z.shape + (2, 3))
    duv[..., 0, 0] = K[0, 0] * inv_z
    duv[..., 0, 1] = K[0, 1] * inv_z
    duv[..., 0, 2] = -(K[0, 0] * x + K[0, 1] * y) * inv_z
    duv[..., 1, 1] = K[1, 1] * inv_z
    duv[..., 1, 2] = -K[1, 1] * y * inv_z
    return (duv @ camera.R) @ J


def _robust(r: np.ndarray, inside_edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss ρ(r) and IRLS weight: Cauchy for edge points inside the silhouette,
    Huber otherwise."""
    a = np.abs(r)
    small = a <= DELTA_OUT_PX
    huber_rho = np.where(small, 0.5 * r * r, DELTA_OUT_PX * (a - 0.5 * DELTA_OUT_PX))
    huber_w = np.where(small, 1.0, DELTA_OUT_PX / np.maximum(a, 1e-12))
    q = (r / DELTA_IN_PX) ** 2
    cauchy_rho = 0.5 * DELTA_IN_PX ** 2 * np.log1p(q)
    cauchy_w = 1.0 / (1.0 + q)
    return np.where(inside_edge, cauchy_rho, huber_rho), np.where(inside_edge, cauchy_w, huber_w)


def _huber(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Huber loss and IRLS weight of non-negative distances [px]."""
    small = d <= DELTA_OUT_PX
    rho = np.where(small, 0.5 * d * d, DELTA_OUT_PX * (d - 0.5 * DELTA_OUT_PX))
    return rho, np.where(small, 1.0, DELTA_OUT_PX / np.maximum(d, 1e-12))


# --------------------------------------------------------------------------- the chain

@functools.lru_cache(maxsize=16)
def _chain_layout(n: int, tip_weight: float, edge_t: tuple, centre_t: tuple):
    """The sample-point layout of an n-plate chain (see :class:`_Chain`), built once per n:
    (M, edge, weight, segments, moves), shared: not to be written."""
    m = n + 1
    rows, edge = [], []
    # corners: index k -> P_C[k], m + k -> P_L[k], 2m + k -> P_R[k]
    for side in (1, 2):
        for i in range(1, m):
            for t in edge_t:
                w = np.zeros(3 * m)
                w[side * m + i - 1] = 1 - t
                w[side * m + i] = t
                rows.append(w)
                edge.append(True)
    for t in _TIP_T:
        w = np.zeros(3 * m)
        w[m + n] = 1 - t
        w[2 * m + n] = t
        rows.append(w)
        edge.append(True)
    for i in range(1, m):
        for t in centre_t:
            w = np.zeros(3 * m)
            w[i - 1] = 1 - t
            w[i] = t
            rows.append(w)
            edge.append(False)
    M = np.array(rows)
    edge = np.array(edge)
    # The tip is what the robot grasps: its plate's edges and the tip edge count more.
    tip = M[:, [m + n, 2 * m + n]].sum(axis=1) > 0
    weight = np.where(tip & edge, tip_weight, 1.0)
    # silhouette outline segments as corner index pairs: left, right, tip and base edges
    left = [(m + k, m + k + 1) for k in range(n)]
    right = [(2 * m + k, 2 * m + k + 1) for k in range(n)]
    segments = np.array(left + right + [(m + n, 2 * m + n), (m, 2 * m)])
    # corner c belongs to the frame of node c % m: it moves with joints 1..c % m
    node_of = np.tile(np.arange(m), 3)
    moves = (node_of[:, None] >= np.arange(1, m)[None, :]).astype(float)  # (3m, n)
    return M, edge, weight, segments, moves


class _Chain:
    """Sample points on the chain's silhouette-relevant parts and their Jacobian, for a
    batch of B angle sets at once."""

    def __init__(self, spec: TapeSpec, edge_t=_EDGE_T, centre_t=_CENTRE_T):
        """edge_t, centre_t: where on each plate (fractions of its length) the edge and
        centre-line sample points lie."""
        self.spec = spec
        self.n = spec.n
        self.M, self.edge, self.weight, self.segments, self.moves = _chain_layout(
            spec.n, float(TIP_WEIGHT), tuple(float(t) for t in edge_t), tuple(float(t) for t in centre_t))
        self.samples = len(self.M)

    def corners(self, angles: np.ndarray):
        """(n, 3) angles -> the corners P_C, P_L, P_R (3m, 3) and their Jacobian (3m, 3, 3n)."""
        a = np.asarray(angles, float).reshape(1, self.n, 3)
        pts, J = _kernels.points(self, a, True) if COMPILED else self.points(a, True)
        return pts[0, self.samples:], J[0, self.samples:]

    def tips(self, angles: np.ndarray) -> np.ndarray:
        """(B, n, 3) angles -> the chains' tips P_C[n] (B, 3)."""
        a = np.asarray(angles, float).reshape(-1, self.n, 3)
        pts, _ = _kernels.points(self, a, False) if COMPILED else self.points(a, False)
        return pts[:, self.samples + self.n]

    def quads(self, angles: np.ndarray) -> np.ndarray:
        """(B, n, 3) angles -> the plates' quads (B, n, 4, 3), as ``TapeShape.quads``."""
        a = np.asarray(angles, float).reshape(-1, self.n, 3)
        pts, _ = _kernels.points(self, a, False) if COMPILED else self.points(a, False)
        c = pts[:, self.samples:]
        m, i = self.n + 1, np.arange(self.n)
        return np.stack([c[:, m + i], c[:, m + i + 1], c[:, 2 * m + i + 1], c[:, 2 * m + i]], axis=2)

    def points(self, angles: np.ndarray, jacobian: bool):
        """(B, n, 3) angles -> (B, s + 3m, 3) sample points then corners and, if asked,
        their (B, s + 3m, 3, 3n) Jacobian."""
        spec = self.spec
        B, n, m = len(angles), self.n, self.n + 1
        Rj = joint_rotations(angles.reshape(-1, 3)).reshape(B, n, 3, 3)
        frames = np.empty((B, m, 3, 3))
        nodes = np.empty((B, m, 3))
        frames[:, 0] = spec.base_rotation
        nodes[:, 0] = spec.base_position
        for i in range(n):
            frames[:, i + 1] = frames[:, i] @ Rj[:, i]
            nodes[:, i + 1] = nodes[:, i] + spec.segment_lengths[i] * frames[:, i + 1, :, 0]
        half = 0.5 * spec.width * frames[:, :, :, 1]
        corners = np.concatenate([nodes, nodes + half, nodes - half], axis=1)      # (B, 3m, 3)
        pts = np.concatenate([self.M @ corners, corners], axis=1)
        if not jacobian:
            return pts, None
        cz, sz = np.cos(angles[:, :, 2])[..., None], np.sin(angles[:, :, 2])[..., None]
        axes = np.stack([frames[:, 1:, :, 0],                                      # θx: F_j e_x
                         cz * frames[:, :-1, :, 1] - sz * frames[:, :-1, :, 0],     # θy: F_{j-1} Rz e_y
                         frames[:, :-1, :, 2]], axis=2)                             # θz: F_{j-1} e_z
        a = axes[:, None]                                                          # (B, 1, n, 3, 3)
        r = (corners[:, :, None, :] - nodes[:, None, :-1, :])[:, :, :, None, :]   # (B, 3m, n, 1, 3)
        Jc = np.stack([a[..., 1] * r[..., 2] - a[..., 2] * r[..., 1],
                       a[..., 2] * r[..., 0] - a[..., 0] * r[..., 2],
                       a[..., 0] * r[..., 1] - a[..., 1] * r[..., 0]], axis=2)   # (B, 3m, 3, n, 3)
        Jc *= self.moves[None, :, None, :, None]
        Jc = Jc.reshape(B, 3 * m, 3 * 3 * n)
        Js = (self.M @ Jc)
        J = np.concatenate([Js, Jc], axis=1).reshape(B, -1, 3, 3 * n)
        return pts, J


def _coverage(chain: _Chain, f: _Field, u, v, Juv):
    """Observed outline points' distance to the model's outline: every part of the observed
    silhouette must be explained (the reverse of the edge term). u, v: (B, 3m) corner
    pixels; Juv: their (B, 3m, 2, N) Jacobian or None. Returns (robust cost (B,),
    weighted residuals (B, P), Jacobian (B, P, N) or None)."""
    obs = f.outline
    B = u.shape[0]
    if len(obs) == 0:
        return np.zeros(B), np.zeros((B, 0)), (None if Juv is None else np.zeros((B, 0, Juv.shape[-1])))
    s0, s1 = chain.segments[:, 0], chain.segments[:, 1]
    ax, ay = u[:, s0], v[:, s0]                                         # (B, K)
    bx, by = u[:, s1] - ax, v[:, s1] - ay
    inv_den = 1.0 / np.maximum(bx * bx + by * by, 1e-9)
    bx3, by3 = bx[:, None], by[:, None]
    rx = obs[None, :, 0, None] - ax[:, None, :]                         # (B, P, K)
    ry = obs[None, :, 1, None] - ay[:, None, :]
    t = rx * bx3
    t += ry * by3
    t *= inv_den[:, None]
    np.minimum(t, 1.0, out=t)
    np.maximum(t, 0.0, out=t)
    rx -= t * bx3
    ry -= t * by3
    d2 = rx * rx
    d2 += ry * ry
    k = np.argmin(d2, axis=2)[..., None]                                # (B, P, 1)
    d = np.sqrt(np.take_along_axis(d2, k, 2)[..., 0]) + 1e-9            # (B, P)
    rho, w = _huber(d)
    sw = np.sqrt(w)
    if Juv is None:
        return rho.sum(axis=1), sw * d, None
    k = k[..., 0]
    tk = np.take_along_axis(t, k[..., None], 2)
    nx = np.take_along_axis(rx, k[..., None], 2) / d[..., None]         # (B, P, 1)
    ny = np.take_along_axis(ry, k[..., None], 2) / d[..., None]
    b = np.arange(B)[:, None]
    j0, j1 = Juv[b, s0[k]], Juv[b, s1[k]]                                # (B, P, 2, N)
    g = (nx * j0[..., 0, :] + ny * j0[..., 1, :]) * (tk - 1.0)
    g -= tk * (nx * j1[..., 0, :] + ny * j1[..., 1, :])
    return rho.sum(axis=1), sw * d, sw[..., None] * g


def _residuals(chain: _Chain, fields: list[_Field], params: np.ndarray, jacobian: bool):
    """Weighted residuals (B, R), Jacobian (B, R, P) or None, and robust cost (B,) of a
    batch of parameter vectors (B, P = 3n joint angles)."""
    B = len(params)
    angles = params.reshape(B, chain.n, 3)
    ns = chain.samples
    rs, js = [], []
    cost = np.zeros(B)
    centre = ~chain.edge
    # Compiled per-view terms (estimator/_kernels.py); the NumPy loop below is their
    # reference (tests/test_estimator_kernels.py).
    compiled = COMPILED
    if compiled:
        rs, js, cost, pts, J = _compiled_view_terms(chain, fields, angles, jacobian)
    else:
        pts, J = chain.points(angles, jacobian)
    for k, f in enumerate(() if compiled else fields):
        u, v, x, y, z = _project(f.camera, pts)
        Juv = _pixel_jacobian(f.camera, x, y, z, J) if jacobian else None
        c_cost, c_r, c_j = _coverage(chain, f, u[:, ns:], v[:, ns:], None if Juv is None else Juv[:, ns:])
        vw = np.sqrt(f.weight)
        cost += f.weight * c_cost
        rs.append(vw * c_r)
        if c_j is not None:
            c_j = vw * c_j
        sdf, gx, gy, ignored = _lookup(f, u[:, :ns], v[:, :ns])
        if f.boxes:
            behind = _kernels_boxes.hidden_points(f, pts[:, :ns])
            ignored = behind if ignored is None else ignored | behind
        r = np.where(centre, np.maximum(sdf, 0.0), sdf)
        rho, w = _robust(r, chain.edge & (sdf < 0))
        if ignored is not None:
            rho = np.where(ignored, 0.0, rho)
            w = np.where(ignored, 0.0, w)
        cost += f.weight * (rho * chain.weight ** 2).sum(axis=1)
        sw = np.sqrt(w) * chain.weight * vw
        rs.append(sw * r)
        if jacobian:
            sw = np.where(centre & (sdf <= 0), 0.0, sw)
            g = gx[..., None] * Juv[:, :ns, 0] + gy[..., None] * Juv[:, :ns, 1]     # (B, s, 3n)
            js += [c_j, sw[..., None] * g]
    # A weak preference for small angles keeps the chain from drifting to extreme twists
    # (self-crossing plates) where the silhouette barely constrains it. (Measured and
    # dropped: per-view 2-D image shifts against miscalibration, worse on occluded views;
    # a bend-smoothness term, no help: the wrong branches are chosen in the beam.)
    prior_J = np.diag(np.full(params.shape[1], ANGLE_PRIOR_PX))
    prior = params * ANGLE_PRIOR_PX          # = params @ prior_J.T (diagonal), exactly
    rs.append(prior)
    cost += 0.5 * np.sum(prior * prior, axis=1)
    boxes = fields[0].boxes if fields else ()
    if boxes:
        # The tape cannot pass through a scene box: its corners inside one are charged.
        corners = pts[:, ns:]
        depth, grad = _kernels_boxes.box_penetration(np.ascontiguousarray(corners.reshape(-1, 3)), *fields[0].box_arrays)
        pen = PENETRATION_PX_PER_M * depth.reshape(B, -1)
        rs.append(pen)
        cost += 0.5 * np.sum(pen * pen, axis=1)
        if jacobian:
            g = PENETRATION_PX_PER_M * grad.reshape(B, -1, 3)
            js_pen = np.einsum("bpk,bpkn->bpn", g, J[:, ns:])
    r = np.concatenate(rs, axis=1)
    if not jacobian:
        return r, None, cost
    js.append(np.broadcast_to(prior_J, (B,) + prior_J.shape))
    if boxes:
        js.append(js_pen)
    return r, np.concatenate(js, axis=1), cost


def _compiled_view_terms(chain: _Chain, fields: list[_Field], angles: np.ndarray, jacobian: bool):
    """:func:`_kernels.view_terms` with each view's terms scaled by its weight (one call per
    view only when a view is down-weighted)."""
    if all(f.weight == 1.0 for f in fields):
        return _kernels.view_terms(chain, fields, angles, jacobian, DELTA_OUT_PX, DELTA_IN_PX)
    rs, js, cost = [], [], np.zeros(len(angles))
    for f in fields:
        (r,), j, c, pts, J = _kernels.view_terms(chain, [f], angles, jacobian, DELTA_OUT_PX, DELTA_IN_PX)
        w = np.sqrt(f.weight)
        rs.append(w * r)
        js += [w * jj for jj in j]
        cost += f.weight * c
    return rs, js, cost, pts, J


def _levenberg_marquardt(chain: _Chain, fields: list[_Field], params: np.ndarray, iterations: int,
                         traces: list[list[np.ndarray]] | None = None, state=None):
    """Robust (IRLS) Levenberg-Marquardt on a batch of (B, P) parameter vectors (see
    :func:`_residuals`) at once. ``state``: (residuals, Jacobian, cost) at ``params`` when
    already known. Returns (params (B, P), robust cost (B,), final state); appends every
    candidate's iterated angles (n, 3) to ``traces[b]``."""
    params = np.array(params, float)
    B, N = params.shape
    na = 3 * chain.n
    diag = np.arange(N)
    r, J, cost = _residuals(chain, fields, params, True) if state is None else (s.copy() for s in state)
    mu = np.full(B, 1e-3)
    active = np.arange(B)
    for _ in range(iterations):
        # Whole-batch iterations (the common case) take the arrays as they are: no copies.
        whole = active.size == B
        Ja, ra = (J, r) if whole else (J[active], r[active])
        JT = Ja.transpose(0, 2, 1)
        A = JT @ Ja
        g = (JT @ ra[..., None])[..., 0]
        damp = mu[active, None] * (A[:, diag, diag] + 1e-6)
        A[:, diag, diag] += damp
        step = np.linalg.solve(A, -g[..., None])[..., 0]
        trial = params[active] + step
        r2, J2, c2 = _residuals(chain, fields, trial, True)
        ok = c2 < cost[active]
        # Converged when a step gains less than RTOL of the cost (its noise floor).
        flat = ok & (cost[active] - c2 < LM_RTOL * cost[active])
        acc = active[ok]
        params[acc], cost[acc] = trial[ok], c2[ok]
        if whole and acc.size == B:
            r, J = r2, J2
        else:
            r[acc], J[acc] = r2[ok], J2[ok]
        mu[acc] = np.maximum(mu[acc] * 0.3, 1e-7)
        mu[active[~ok]] *= 10.0
        if traces is not None:
            for b in active:
                traces[b].append(params[b, :na].reshape(chain.n, 3).copy())
        small = np.max(np.abs(step[:, :na]), axis=1) < 1e-4
        done = (ok & small) | flat | (mu[active] > 1e4)
        active = active[~done]
        if active.size == 0:
            break
    return params, cost, (r, J, cost)


# --------------------------------------------------------------------------- global stage

def _diverse(order: np.ndarray, ends: np.ndarray, count: int) -> np.ndarray:
    """Up to ``count`` of the candidates ``order`` (best first) whose new plate ends
    (``ends[k]``: centre, left and right corner (3, 3) [m]) lie at least DIVERSE_M from
    every better kept one's: without this the beam fills with near copies of one chain
    (twist variants of the same bends) and the other bend branch is lost."""
    if DIVERSE_M <= 0 or len(order) <= count:
        return order[:count]
    if COMPILED:
        return _kernels_beam.diverse(order, ends, count, DIVERSE_M)
    e = ends[order].reshape(len(order), -1, 3)
    diff = e[:, None] - e[None, :]
    d2 = np.einsum("abpk,abpk->abp", diff, diff).max(axis=-1)
    # Greedy pick over bitsets of the "too close" relation (rows as Python ints): far
    # cheaper than a NumPy reduction per candidate.
    close = np.packbits(d2 < DIVERSE_M * DIVERSE_M, axis=1, bitorder="little")
    kept_bits, picked = 0, []
    for k in range(len(order)):
        if not int.from_bytes(close[k].tobytes(), "little") & kept_bits:
            kept_bits |= 1 << k
            picked.append(k)
            if len(picked) == count:
                break
    kept = np.zeros(len(order), bool)
    kept[picked] = True
    chosen = order[kept]
    if len(chosen) < count:
        # Fill up with the best of the suppressed ones.
        chosen = np.concatenate([chosen, order[~kept][:count - len(chosen)]])
    return chosen


def _beam_candidates(frames: np.ndarray, nodes: np.ndarray, grid_r: np.ndarray, length: float, h: float,
                     last: bool):
    """Kept partial chains (frames (b, 3, 3), end nodes (b, 3)) extended by every joint
    rotation of ``grid_r`` (g, 3, 3) by a plate of ``length`` and half-width ``h`` [m]:
    (frames (b, g, 3, 3), ends (b, g, 3, 3): the plate's end node, left and right corner,
    sample points (b, g, s, 3): edges, on the last plate the tip edge, centre line).
    The NumPy reference of :func:`_kernels_beam.beam_candidates`."""
    F = np.einsum("bij,gjk->bgik", frames, grid_r)               # (b, g, 3, 3)
    P = nodes[:, None, :] + length * F[..., :, 0]
    L0 = (nodes + h * frames[:, :, 1])[:, None, None, :]
    R0 = (nodes - h * frames[:, :, 1])[:, None, None, :]
    L1 = (P + h * F[..., :, 1])[:, :, None, :]
    R1 = (P - h * F[..., :, 1])[:, :, None, :]
    t = _BEAM_EDGE_T[None, None, :, None]
    parts = [L0 + (L1 - L0) * t, R0 + (R1 - R0) * t]
    if last:
        parts.append(L1 + (R1 - L1) * _TIP_T[None, None, :, None])
    tc = _CENTRE_T[None, None, :, None]
    parts.append(nodes[:, None, None, :] + (P[:, :, None, :] - nodes[:, None, None, :]) * tc)
    ends = np.stack([P, L1[:, :, 0], R1[:, :, 0]], axis=2)
    return F, ends, np.concatenate(parts, axis=2)


def _beam_search(spec: TapeSpec, fields: list[_Field], grid: np.ndarray = _GRID,
                 beam: int = BEAM) -> list[np.ndarray]:
    """Candidate chains (n, 3) from a node-by-node beam search over joint angles ``grid``
    (g, 3) keeping ``beam`` partial chains, best first."""
    grid_r = joint_rotations(grid)
    n = spec.n
    h = 0.5 * spec.width
    frames = spec.base_rotation[None]
    nodes = spec.base_position[None]
    scores = np.zeros(1)
    history = np.zeros((1, 0, 3))
    lefts = (nodes + h * frames[:, :, 1])[:, None, :]
    rights = (nodes - h * frames[:, :, 1])[:, None, :]
    no_tip = np.zeros(0)
    for i in range(n):
        last = i == n - 1
        edge_count = 2 * len(_BEAM_EDGE_T) + (len(_TIP_T) if last else 0)
        if COMPILED:
            F, ends, pts = _kernels_beam.beam_candidates(np.ascontiguousarray(frames), np.ascontiguousarray(nodes), grid_r, float(spec.segment_lengths[i]), h,
                                                    _BEAM_EDGE_T, _TIP_T if last else no_tip, _CENTRE_T)
            F = F.reshape(len(nodes), len(grid), 3, 3)
            pts = pts.reshape(len(nodes), len(grid), -1, 3)
        else:
            F, ends, pts = _beam_candidates(frames, nodes, grid_r, spec.segment_lengths[i], h, last)
        is_edge = np.arange(pts.shape[2]) < edge_count
        plate = np.zeros(pts.shape[:2])
        for f in fields:
            if COMPILED:
                plate += f.weight * _kernels_beam.beam_edge_cost(f, pts, edge_count, DELTA_OUT_PX, DELTA_IN_PX)
                continue
            u, v, *_ = _project(f.camera, pts)
            sdf, _, _, ignored = _lookup(f, u, v)
            r = np.where(is_edge, sdf, np.maximum(sdf, 0.0))
            rho, _ = _robust(r, is_edge & (sdf < 0))
            if ignored is not None:
                rho = np.where(ignored, 0.0, rho)
            plate += f.weight * rho.sum(axis=2)
        boxes = fields[0].boxes if fields else ()
        if boxes:
            depth, _ = _kernels_boxes.box_penetration(np.ascontiguousarray(ends.reshape(-1, 3), float),
                                                *fields[0].box_arrays)   # the plates' end corners
            plate += 1e3 * BEAM_PENETRATION * depth.reshape(plate.shape + (-1,)).sum(axis=-1)
        prior = ANGLE_PRIOR * np.sum(grid ** 2, axis=1)
        total = (scores[:, None] + plate + prior[None, :]).reshape(-1)
        count = beam * (4 if last else 1)
        ends = ends.reshape(-1, 3, 3)
        keep = _diverse(np.argsort(total)[:DIVERSE_POOL * count], ends, count)
        b, gi = np.divmod(keep, len(grid))
        frames = F[b, gi]
        nodes = ends[keep, 0]
        scores = total[keep]
        history = np.concatenate([history[b], grid[gi][:, None, :]], axis=1)
        lefts = np.concatenate([lefts[b], ends[keep, 1][:, None]], axis=1)
        rights = np.concatenate([rights[b], ends[keep, 2][:, None]], axis=1)
    # Complete chains: add the coverage of the observed outline, keep the best.
    corners = np.concatenate([lefts, rights], axis=1)               # (c, 2(n+1), 3)
    m = n + 1
    seg = np.array([(k, k + 1) for k in range(n)] + [(m + k, m + k + 1) for k in range(n)]
                   + [(n, m + n), (0, m)])
    for f in fields:
        if len(f.outline) == 0:
            continue
        obs = f.outline[::BEAM_OUTLINE_STEP]
        if COMPILED:
            scores = scores + f.weight * BEAM_OUTLINE_STEP * _kernels_beam.beam_outline_cost(f, corners, seg, obs,
                                                                                     DELTA_OUT_PX)
            continue
        u, v, *_ = _project(f.camera, corners)                          # (c, 2m)
        ax, ay = u[:, seg[:, 0]], v[:, seg[:, 0]]                       # (c, S)
        bx, by = u[:, seg[:, 1]] - ax, v[:, seg[:, 1]] - ay
        den = np.maximum(bx * bx + by * by, 1e-9)[:, None]
        rx = obs[None, :, 0, None] - ax[:, None]                        # (c, P, S)
        ry = obs[None, :, 1, None] - ay[:, None]
        t = np.clip((rx * bx[:, None] + ry * by[:, None]) / den, 0.0, 1.0)
        rx -= t * bx[:, None]
        ry -= t * by[:, None]
        d = np.sqrt(np.min(rx * rx + ry * ry, axis=2))
        rho, _ = _huber(d)
        scores = scores + f.weight * BEAM_OUTLINE_STEP * rho.sum(axis=1)
    order = np.argsort(scores)[:beam]
    return [history[k] for k in order]


# --------------------------------------------------------------------------- strip stage

STRIP = True
"""After the plate chain's fit, refine a continuous strip (see :class:`_Strip`) on the same
residuals and take the output chain from it (off: the plate chain's fit is the output)."""
STRIP_PLATES = 4
"""Fine plates per model plate in the strip."""
STRIP_EDGE_T = (1 / 3, 2 / 3, 1.0)
STRIP_CENTRE_T = (1.0,)
"""Sample points on each fine plate's edges and centre line (fractions of its length)."""
STRIP_IN_PLANE_PX = 100.0
"""Residual [px] per radian (per model-plate length) of in-plane bending in the strip: a
tape barely bends within its own plane, so this stays near zero unless the views insist."""
STRIP_ITERATIONS = 15
STRIP_RTOL = 3e-3
"""The strip's fit ends when a step lowers its robust cost by less than this fraction."""
STRIP_TIP_WEIGHT = 10.0
"""Weight of the tip's corners when the output chain is fitted to the strip in 3-D."""
STRIP_FRAME_WEIGHT = 1.0
"""Weight of the strip's tip frame (its direction and width axis) on the output chain's
tip frame F_n, relative to a corner's position. The grasp is planned on F_n; on a tape
curled within the last plate, F_n along the chord tilts from the tape's frame at the tip by
half the curl, so the chain's last plate is pulled part of the way towards the strip's
tip frame (measured: tip normal median 6.4 -> 4.8 deg on the samples, 5.2 -> 4.3 on
sample_like, tip error unchanged, the worst node error ~0.3 mm larger; more weight makes
the chain's silhouette cost trip the guard)."""
STRIP_GUARD = 2.0
"""The chain taken from the strip is dropped when its silhouette cost (eq. 11) exceeds this
multiple of the plate chain's own fit (a strip fit gone astray; fitted to the strip rather
than to the images, the chain's cost is up to ~1.5x the plate fit's on good fits)."""


class _Strip:
    """A continuous strip as a fine chain (STRIP_PLATES plates per model plate) whose
    joint angles (twist, out-of-plane and in-plane bend per length) vary linearly along
    the arc length between knots at the model's nodes, after a free first joint: 3 + 3(n+1)
    parameters. The plate chain cannot follow a tape that bends within one plate's length
    (a curl at the tip), so its last plate is a chord: the strip follows it."""

    def __init__(self, spec: TapeSpec):
        k = STRIP_PLATES
        self.fine = TapeSpec(np.repeat(spec.segment_lengths / k, k), spec.width, spec.base_position,
                             spec.base_rotation)
        self.chain = _Chain(self.fine, STRIP_EDGE_T, STRIP_CENTRE_T)
        self.T, self.prior = _strip_layout(spec.n, k, float(STRIP_IN_PLANE_PX))

    def angles(self, x: np.ndarray) -> np.ndarray:
        return (self.T @ x).reshape(-1, 3)

    def corners(self, x: np.ndarray):
        """The fine chain's corners (3 m_fine, 3) and their Jacobian (3 m_fine, 3, P)."""
        c, J = self.chain.corners(self.angles(x))
        return c, J @ self.T

    def residuals(self, fields: list[_Field], x: np.ndarray):
        r, J, cost = _residuals(self.chain, fields, (self.T @ x)[None], True)
        p = self.prior @ x
        return np.concatenate([r[0], p]), np.vstack([J[0] @ self.T, self.prior]), cost[0] + 0.5 * p @ p


@functools.lru_cache(maxsize=8)
def _strip_layout(n: int, k: int, in_plane_px: float):
    """:class:`_Strip`'s parameter map T (3 n k, 3(n+2)) from knot rates to the fine
    chain's angles, and its in-plane prior (3(n+2), 3(n+2)); built once per n, shared: not
    to be written."""
    nf = n * k
    basis = np.zeros((nf, n + 2))
    basis[0, 0] = 1.0
    s = np.arange(1, nf) / k                      # fine joints' arc length [model plates]
    knot = np.minimum(s.astype(int), n - 1)
    t = s - knot
    basis[np.arange(1, nf), 1 + knot] = (1 - t) / k
    basis[np.arange(1, nf), 2 + knot] = t / k
    T = np.kron(basis, np.eye(3))                 # (3 nf, P): parameters -> fine angles
    prior = np.zeros(3 * (n + 2))
    prior[5::3] = in_plane_px                     # in-plane rates of every knot
    prior = np.diag(prior)
    return T, prior


def _gauss_newton(fun, x: np.ndarray, iterations: int, rtol: float) -> np.ndarray:
    """Levenberg-Marquardt on one parameter vector: fun(x) -> (residuals, Jacobian, cost)."""
    r, J, cost = fun(x)
    mu = 1e-3
    for _ in range(iterations):
        A = J.T @ J
        d = np.arange(len(x))
        A[d, d] += mu * A[d, d] + 1e-9
        step = np.linalg.solve(A, -(J.T @ r))
        r2, J2, c2 = fun(x + step)
        if c2 < cost:
            flat = cost - c2 < rtol * cost
            x, r, J, cost, mu = x + step, r2, J2, c2, max(mu * 0.3, 1e-7)
            if flat:
                break
        else:
            mu *= 10.0
            if mu > 1e4:
                break
    return x


def _corner_fit(corners, goal: np.ndarray, weight: np.ndarray | float = 1.0, extra=None):
    """Residual function for :func:`_gauss_newton` pulling ``corners(x)`` -> (c (k, 3), J
    (k, 3, P)) onto ``goal`` (k, 3), each corner weighted by ``weight`` ((k,) or scalar);
    ``extra(c, J)`` -> (residuals (e,), Jacobian (e, P)): more rows on the same corners."""
    w = np.broadcast_to(np.asarray(weight, float), (len(goal),))

    def fun(x):
        c, J = corners(x)
        r = (w[:, None] * (c - goal)).ravel()
        Jr = (w[:, None, None] * J).reshape(len(r), -1)
        if extra is not None:
            re, Je = extra(c, J)
            r, Jr = np.concatenate([r, re]), np.vstack([Jr, Je])
        return r, Jr, 0.5 * r @ r

    return fun


_strips: dict = {}


def _strip_for(spec: TapeSpec) -> _Strip:
    """The strip of ``spec`` (cached: its chain's fixed arrays cost more than a fit step)."""
    key = (spec.segment_lengths.tobytes(), float(spec.width), np.asarray(spec.base_position, float).tobytes(),
           np.asarray(spec.base_rotation, float).tobytes(), STRIP_PLATES, STRIP_EDGE_T, STRIP_CENTRE_T,
           STRIP_IN_PLANE_PX)
    strip = _strips.get(key)
    if strip is None:
        if len(_strips) > 16:
            _strips.clear()
        strip = _strips[key] = _Strip(spec)
    return strip


def _strip_stage(chain: _Chain, fields: list[_Field], angles: np.ndarray):
    """The strip fitted to the views from the plate chain ``angles`` (n, 3). Returns
    output(frame_weight) -> the plate chain's angles (n, 3) fitted in 3-D to the strip: its
    corners at the model's nodes (the tip's weighted) and, by ``frame_weight``, its tip
    frame to the strip's (see :func:`_tip_frame_rows`)."""
    spec = chain.spec
    strip = _strip_for(spec)
    k, n = STRIP_PLATES, spec.n
    # Start: the strip closest in 3-D to the plate chain (its corners linearly
    # interpolated along the plates at the fine nodes).
    shape = forward_kinematics(spec, angles)
    t = np.arange(n * k + 1) / k
    i = np.minimum(t.astype(int), n - 1)
    f = (t - i)[:, None]
    target = np.concatenate([a[i] * (1 - f) + a[i + 1] * f for a in (shape.nodes, shape.left, shape.right)])
    x0 = np.zeros(strip.T.shape[1])
    x0[:3] = angles[0]
    x = _gauss_newton(_corner_fit(strip.corners, target), x0, 20, 1e-4)
    x = _gauss_newton(lambda y: strip.residuals(fields, y), x, STRIP_ITERATIONS, STRIP_RTOL)
    fine = forward_kinematics(strip.fine, strip.angles(x))
    # The output chain: the plate chain closest to the strip at the model's nodes.
    goal = np.concatenate([fine.nodes[::k], fine.left[::k], fine.right[::k]])
    w = np.ones(3 * (n + 1))
    w[[n, 2 * n + 1, 3 * n + 2]] = STRIP_TIP_WEIGHT

    def output(frame_weight: float) -> np.ndarray:
        extra = _tip_frame_rows(chain, fine.frames[-1], frame_weight) if frame_weight > 0 else None
        fun = _corner_fit(chain.corners, goal, w, extra)
        return _gauss_newton(fun, angles.ravel().copy(), 10, 1e-4).reshape(n, 3)

    output.tip = (fine.nodes[-1].copy(), fine.frames[-1].copy())   # the strip's end frame
    return output


def _tip_frame_rows(chain: _Chain, tip_frame: np.ndarray, weight: float):
    """``extra`` rows for :func:`_corner_fit` on ``chain``'s corners pulling its tip frame
    F_n (the last plate's direction and width axis) onto ``tip_frame`` (3, 3), ``weight``
    times as strongly as a corner (a unit-vector difference counts as moving a corner by
    the last plate's length times it)."""
    n, m = chain.n, chain.n + 1
    length, width = float(chain.spec.segment_lengths[-1]), float(chain.spec.width)
    s = weight * length

    def rows(c, J):
        ex, Jx = (c[n] - c[n - 1]) / length, (J[n] - J[n - 1]) / length
        ey, Jy = (c[m + n] - c[2 * m + n]) / width, (J[m + n] - J[2 * m + n]) / width
        return s * np.concatenate([ex - tip_frame[:, 0], ey - tip_frame[:, 1]]), s * np.vstack([Jx, Jy])

    return rows


# --------------------------------------------------------------------------- public

def _refine(chain: _Chain, fields: list[_Field], starts: np.ndarray, silhouette_costs, pool: list | None = None):
    """Local stage on candidate chains (B, n, 3): a few iterations on all at once, the
    best REFINE (by the robust cost) to convergence, ranked by the silhouette cost (eq.
    11). Returns (angles (n, 3), trace, eq.-11 cost) of the winner; appends every refined
    chain as (eq.-11 cost, angles) to ``pool`` (the hypotheses the verdict weighs), with
    the best ALTERNATIVES screened candidates whose tips lie more than DISTINCT_TIP_M from
    the refined ones' refined too (distinct shapes the robust cost ranked lower)."""
    traces: list[list[np.ndarray]] = [[] for _ in starts]
    params = starts.reshape(len(starts), -1)
    params, cost, (r, J, _) = _levenberg_marquardt(chain, fields, params, LM_SCREEN, traces)
    # Screened by the robust cost (ranking all by eq. 11 was measured no better on the
    # samples and worse on sim captures); the silhouette cost (eq. 11) picks the winner.
    # The screen's residuals carry over: no re-evaluation at the kept candidates.
    keep = np.argsort(cost)[:REFINE]
    if pool is not None and ALTERNATIVES > 0 and len(cost) > REFINE:
        # Distinct hypotheses: the best screened chains whose tips are far from every kept
        # one's, refined like the winner so that their costs compare.
        tips = chain.tips(params[:, :3 * chain.n].reshape(-1, chain.n, 3))
        far = np.ones(len(cost), bool)
        extra = []
        for k in np.argsort(cost):
            d = np.linalg.norm(tips[k] - tips[np.concatenate([keep, extra]).astype(int)], axis=1)
            if np.all(d > DISTINCT_TIP_M) and k not in keep:
                extra.append(k)
                if len(extra) == ALTERNATIVES:
                    break
        keep = np.concatenate([keep, np.array(extra, int)])
    if REFINE_EQ11 > 0 and len(cost) > REFINE:
        # Plus the best screened ones by the silhouette cost: where the model cannot follow
        # the tape (a tight curl at the tip) the robust boundary cost may prefer a wrong
        # branch that eq. 11 does not (measured on sim tip-curl captures).
        order = np.argsort(cost)
        rest = order[REFINE:][cost[order[REFINE:]] < EQ11_RANGE * cost[order[0]]]
        eq11 = silhouette_costs(params[rest, :3 * chain.n].reshape(-1, chain.n, 3))
        keep = np.concatenate([keep, rest[np.argsort(eq11)[:REFINE_EQ11]]]) if len(rest) else keep
    sub_traces = [traces[k] for k in keep]
    params, _, _ = _levenberg_marquardt(chain, fields, params[keep], LM_ITERATIONS, sub_traces,
                                        (r[keep], J[keep], cost[keep]))
    refined = params[:, :3 * chain.n].reshape(-1, chain.n, 3)
    costs = silhouette_costs(refined)
    best = int(np.argmin(costs))
    if pool is not None:
        pool += [(float(c), a) for c, a in zip(costs, refined)]
    return refined[best], sub_traces[best], float(costs[best])


def _mirrors(angles: np.ndarray) -> np.ndarray:
    """(2, n, 3): ``angles`` with every out-of-plane bend mirrored (θy -> -θy), and with the
    twist mirrored as well (the same silhouette seen from a camera facing the tape)."""
    a, b = angles.copy(), angles.copy()
    a[:, 1] *= -1
    b[:, 1] *= -1
    b[:, 0] *= -1
    return np.array([a, b])


def _variants(angles: np.ndarray) -> np.ndarray:
    """Chains near ``angles`` (n, 3) on other branches: from each joint on, the bend
    mirrored (θy -> -θy) or the twist turned by ±π/2 or flipped in sign — the ambiguities
    a silhouette leaves (a plate seen edge-on, a bend towards or away from a camera)."""
    out = []
    for j in range(len(angles)):
        for kind in range(4):
            a = angles.copy()
            if kind == 0:
                a[j:, 1] = -a[j:, 1]
            elif kind == 1:
                a[j, 0] = -a[j, 0]
            else:
                a[j, 0] += np.pi / 2 if kind == 2 else -np.pi / 2
            out.append(a)
    return np.array(out)


def fit_default(capture: Capture, callback: Callback | None = None, thorough: bool = False):
    """Fit by the project's method; returns (angles, trace, evaluations, fallback) where
    trace holds the winning candidate's angles after each local-stage iteration, and
    fallback (with the strip stage, else None) is (the plate fit's eq.-11 cost, [functions
    giving the chains to fall back to, in order, the plate fit last]) for estimate()'s
    guard."""
    chain = _Chain(capture.tape)
    fields = [_prepare(v, capture.scene) for v in capture.views]
    evaluator = CostEvaluator([f.target for f in fields], capture.scene)

    def silhouette_costs(angles: np.ndarray) -> np.ndarray:
        return evaluator.costs(chain.quads(angles))

    starts = np.array(_beam_search(capture.tape, fields))
    pool: list = []
    angles, trace, cost = _refine(chain, fields, starts, silhouette_costs, pool)
    # The classic silhouette ambiguity, a bend towards or away from the cameras: the
    # winner's mirror images are refined too, as hypotheses (and the winner if better).
    a2, t2, c2 = _refine(chain, fields, _mirrors(angles), silhouette_costs, pool)
    if c2 < cost:
        angles, trace, cost = a2, t2, c2
    worst_px = max(c * f.target.area / f.outline_px for c, f in zip(evaluator.view_costs(chain.quads(angles)[0]), fields))
    if thorough or cost > WIDE_COST or worst_px > WIDE_OFFSET_PX:
        # A poor fit: only these pay for a wider search (a finer, larger beam and the
        # other branches next to the winner); it replaces the first result only when its
        # silhouette cost is clearly lower.
        parts = [_variants(angles)] if WIDE_VARIANTS else []
        if WIDE_BEAM:
            parts.append(np.array(_beam_search(capture.tape, fields, _WIDE_GRID,
                                               THOROUGH_BEAM if thorough else WIDE_BEAM)))
        wide = np.concatenate(parts)
        a2, t2, c2 = _refine(chain, fields, wide, silhouette_costs, pool)
        if c2 < WIDE_GAIN * cost:
            angles, trace, cost = a2, trace + t2, c2
    fallback = None
    tip = None
    if STRIP:
        output = _strip_stage(chain, fields, angles)
        tip = output.tip
        plate = angles
        # What estimate() falls back to, in order, while the chain's silhouette cost is
        # above the guard: the chain without the tip-frame pull, then the plate fit.
        alternatives = [lambda: output(0.0)] if STRIP_FRAME_WEIGHT > 0 else []
        fallback = (cost, alternatives + [lambda: plate])
        angles = output(STRIP_FRAME_WEIGHT)
        trace = trace + [angles]
    winner = plate if STRIP else angles
    return angles, trace, evaluator.evaluations, fallback, _hypotheses(chain, pool, winner), tip


def _hypotheses(chain: _Chain, pool: list, winner: np.ndarray) -> list:
    """The distinct shapes among the refined chains ``pool`` [(eq.-11 cost, angles)]: best
    first, each tip more than DISTINCT_TIP_M from the winner's plate fit and from every
    better one's; as (cost, angles)."""
    out, tips = [], [chain.tips(winner[None])[0]]
    for cost, a in sorted(pool, key=lambda x: x[0]):
        tip = chain.tips(a[None])[0]
        if all(np.linalg.norm(tip - t) > DISTINCT_TIP_M for t in tips):
            out.append((cost, a))
            tips.append(tip)
    return out


_warmed = False


def warm() -> None:
    """Pay the default method's one-off costs of a process before any clock starts: the
    compiled kernels (see :func:`_kernels.warm`) and OpenCV's first calls of the filters a
    view's preparation uses (measured ~2 ms on the first fit of a process, then never)."""
    global _warmed
    if COMPILED:
        _kernels.warm()
    if _warmed:
        return
    _warmed = True
    mask = np.zeros((24, 32), bool)
    mask[8:16, 6:26] = True
    ignore = np.zeros_like(mask)
    ignore[:, :4] = True
    camera = Camera("warm", 32, 24, np.array([[20.0, 0, 16], [0, 20.0, 12], [0, 0, 1]]))
    for view in (View(camera, mask), View(camera, mask, ignore)):
        _prepare(view)


def _cost_roi(view: View, quads: np.ndarray) -> tuple[int, int, int, int] | None:
    """The smallest image rectangle (x0, y0, x1, y1) holding both the observed mask and the
    model's quads (m, 4, 3) in ``view``: every pixel outside it is background in both, so
    the cost there equals the full image's and renders far fewer pixels. None (the whole
    image) when the model does not project to finite pixels."""
    px = project_quads(view.camera, quads).reshape(-1, 2)
    if not np.all(np.isfinite(px)):
        return None
    x, y, w, h = cv2.boundingRect(view.mask.view(np.uint8))
    cam = view.camera
    lo = np.floor(px.min(axis=0)).astype(int) - 2
    hi = np.ceil(px.max(axis=0)).astype(int) + 3
    x0, y0 = max(0, min(x, lo[0])), max(0, min(y, lo[1]))
    x1, y1 = min(cam.width, max(x + w, hi[0])), min(cam.height, max(y + h, hi[1]))
    return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _costed(capture: Capture, angles: np.ndarray):
    """The chain's shape, its per-view silhouette costs (eq. 7), rendered only where the
    mask or the model is, and the evaluator that did it."""
    shape = forward_kinematics(capture.tape, angles)
    quads = shape.quads()
    evaluator = CostEvaluator([make_target(v, roi=_cost_roi(v, quads)) for v in capture.views], capture.scene)
    return shape, evaluator.view_costs(quads), evaluator


def _judge(capture: Capture, evaluator: CostEvaluator, view_costs: np.ndarray, shape, tip_position: np.ndarray,
           tip_rotation: np.ndarray, best_cost: float, hypotheses: list):
    """(verdict, reason, tip_views, alternatives) of the output ``shape`` whose
    ``view_costs`` ``evaluator`` gave; ``best_cost``: the plate fit's eq.-11 cost, the
    scale of the ``hypotheses`` [(cost, angles)]."""
    near = []
    for cost, a in hypotheses:
        if is_close_alternative(cost, best_cost):
            alt = forward_kinematics(capture.tape, a)
            near.append(Alternative(cost, alt.nodes[-1].copy(), alt.frames[-1].copy(), a))
    targets = evaluator.targets
    models = [m if t.valid is None else m & t.valid for m, t in zip(evaluator.model_masks(shape.quads()), targets)]
    j = assess(capture.views, capture.scene, capture.tape.width, view_costs, [t.observed for t in targets],
               models, [(t.x0, t.y0) for t in targets], tip_position, tip_rotation, best_cost,
               [(a.cost, a.tip_position) for a in near])
    return j.verdict, j.reason, j.tip_views, tuple(near), j.offsets_px


def _garbage(capture: Capture, faults: list, method: str, start: float) -> Estimate:
    """A "poor_fit" estimate of a capture whose views ``faults`` [(index, why)] hold no tape
    silhouette: the fit of the other views (a straight tape when none is left), costed on
    every view; nothing may act on it."""
    bad = {k for k, _ in faults}
    rest = [v for k, v in enumerate(capture.views) if k not in bad]
    if rest:
        est = estimate(dataclasses.replace(capture, views=rest), method)
        angles, tip = est.angles, (est.tip_position, est.tip_rotation)
    else:
        angles = np.zeros((capture.tape.n, 3))
    shape, view_costs, _ = _costed(capture, angles)
    if not rest:
        tip = (shape.nodes[-1].copy(), shape.frames[-1].copy())
    k, why = faults[0]
    reason = f"view {k} ({capture.views[k].camera.name}) is not a tape silhouette: {why}"
    return Estimate(shape.nodes, angles, tip[0], tip[1], combine(view_costs), view_costs,
                    time.perf_counter() - start, method, verdict=Verdict.POOR_FIT, verdict_reason=reason,
                    view_offsets_px=np.full(len(capture.views), np.inf))


def estimate(capture: Capture, method: str = "default", callback: Callback | None = None,
             thorough: bool = False) -> Estimate:
    """Fit the plate chain to ``capture``'s silhouettes.

    method: "default" (ours) or "paper" (the reference reproduction).
    callback(iteration, cost, angles (n, 3)): called per optimiser iteration with the
    silhouette cost (eq. 11) of that iterate; for the default method after the fit (the
    winner's iterations, costed once the clock has stopped), for the paper's method live
    (the objective of the node being optimised).
    Returns an :class:`Estimate`; ``time_s`` is the fitting time alone.
    """
    from .paper import fit_paper

    if method not in ("default", "paper"):
        raise EstimateError(f"unknown estimation method {method!r} (use 'default' or 'paper')")
    if not capture.views:
        raise EstimateError(f"{capture.name}: no camera views to fit")
    if method == "default":
        warm()  # once per process: compiling/loading the kernels is not fitting
    start = time.perf_counter()
    faults = [(k, mask_fault(v)) for k, v in enumerate(capture.views)]
    faults = [(k, f) for k, f in faults if f]
    if faults:
        return _garbage(capture, faults, method, start)
    fallback, hypotheses, tip = None, [], None
    if method == "default":
        angles, trace, evaluations, fallback, hypotheses, tip = fit_default(capture, thorough=thorough)
    else:
        angles, history, evaluations = fit_paper(capture, callback)
    shape, view_costs, evaluator = _costed(capture, angles)
    if fallback is not None:
        plate_cost, alternatives = fallback
        while alternatives and combine(view_costs) > STRIP_GUARD * plate_cost:
            # The chain taken from the strip explains the views far worse than the plate
            # chain's own fit: the tip-frame pull overshot or the strip's fit went astray.
            # The last alternative is the plate chain itself.
            angles = alternatives.pop(0)()
            trace = trace[:-1] + ([angles] if alternatives else [])
            shape, view_costs, evaluator = _costed(capture, angles)
            if not alternatives:
                tip = None   # back to the plate fit: the strip went astray
    plate_cost = fallback[0] if fallback is not None else combine(view_costs)
    # The tip frame: the strip's end (it follows a tip that curls within one plate, where
    # the last plate is a chord), else the plate chain's F_n at P_C[n].
    tip_position, tip_rotation = tip if tip is not None else (shape.nodes[-1].copy(), shape.frames[-1].copy())
    verdict, reason, tip_views, alternatives, offsets = _judge(capture, evaluator, view_costs, shape, tip_position, tip_rotation,
                                                      min(plate_cost, combine(view_costs)), hypotheses)
    elapsed = time.perf_counter() - start
    full = CostEvaluator([make_target(v) for v in capture.views], capture.scene)
    if method == "default":
        # The cost per iteration on the eq.-11 scale, for recordings and plots.
        history = [full.cost(forward_kinematics(capture.tape, a).quads()) for a in trace]
        if callback is not None:
            for k, (a, c) in enumerate(zip(trace, history), 1):
                callback(k, c, a)
    est = Estimate(shape.nodes, angles, tip_position, tip_rotation, combine(view_costs),
                   view_costs, elapsed, method, history, evaluations, verdict, reason, tip_views, alternatives,
                   trace=tuple(trace) if method == "default" else (), view_offsets_px=offsets)
    folded = float(shape.frames[0][:, 0] @ tip_rotation[:, 0]) < np.cos(np.radians(FOLD_DEG))
    if method == "default" and not thorough and verdict is Verdict.OK and folded:
        # A fold: the same fit's more thorough look, whose alternatives are weighed afresh.
        second = estimate(capture, method, thorough=True)
        return dataclasses.replace(second, time_s=est.time_s + second.time_s)
    if method == "default" and not thorough and verdict in (Verdict.POOR_FIT, Verdict.AMBIGUOUS, Verdict.HIDDEN):
        # Unsure: a second, more thorough look (a larger global search on the widest grid,
        # always) before answering. Its answer stands when it is "ok" (judged afresh) or
        # explains the views better; the time of both counts.
        second = estimate(capture, method, thorough=True)
        chosen = second if second.actionable or second.cost < est.cost else est
        return dataclasses.replace(chosen, time_s=est.time_s + second.time_s)
    return est
