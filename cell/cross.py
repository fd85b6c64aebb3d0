"""Sub-pixel detection of the calibration plate's cross (the paper's sec. 2.2).

The plate is a light square carrying a dark cross of two bars. The cross centre is found
projectively exactly: the two long edges of each bar are straight image lines (collinear
3-D edges stay collinear under a pinhole), their four intersections are the corners of
the small central square, and the diagonals of that square meet at the image of the
centre. Edge points are located to sub-pixel precision where the grey-level profile
across the edge crosses the midpoint between the cross's and the plate's levels, which is
unbiased for any symmetric blur (lens, antialiasing).

A view is rejected, with a reason from :data:`REASONS`, when the cross is missing, cut by
the image border, seen too obliquely, or partly hidden.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tapecell.estimator.geometry import Camera

REASONS = ("missing", "border", "oblique", "occluded")


@dataclass(frozen=True)
class CrossParams:
    """Tolerances of the detector.

    border_px: a cross closer than this to the image edge counts as cut by the border [px].
    max_oblique_deg: largest angle between the plate normal and the line of sight [deg],
        estimated from the foreshortening of the two bars.
    max_edge_rms_px: largest RMS distance of edge points from their fitted line [px];
        more means something cuts into the cross.
    max_arm_ratio: largest ratio of opposite arms' lengths (perspective alone stays far
        below it; a hidden arm end exceeds it).
    min_contrast: smallest grey-level difference between plate and cross (0..255).
    min_bar_px: smallest bar width in the image [px] worth measuring.
    """

    border_px: float = 3.0
    max_oblique_deg: float = 60.0
    max_edge_rms_px: float = 0.3
    max_arm_ratio: float = 1.35
    min_contrast: float = 40.0
    min_bar_px: float = 3.0


@dataclass(frozen=True, eq=False)
class CrossDetection:
    """Result of one detection.

    center_px: (2,) the cross centre [px], None when rejected.
    reason: None when accepted, else one of :data:`REASONS`.
    detail: a short human-readable explanation of the decision.
    corners_px: (4, 2) corners of the central square [px] (None when not measured).
    oblique_deg: estimated angle between plate normal and line of sight [deg].
    edge_rms_px: RMS distance of the edge points from their four lines [px].
    """

    center_px: np.ndarray | None
    reason: str | None
    detail: str = ""
    corners_px: np.ndarray | None = None
    oblique_deg: float | None = None
    edge_rms_px: float | None = None

    @property
    def ok(self) -> bool:
        return self.reason is None


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
    return img.astype(np.uint8)


def _reject(reason: str, detail: str, **kw) -> CrossDetection:
    return CrossDetection(None, reason, detail, **kw)


def detect_cross(image: np.ndarray, params: CrossParams = CrossParams()) -> CrossDetection:
    """Find the cross centre in an RGB (H, W, 3) or grey (H, W) uint8 image."""
    gray = _gray(image)
    h, w = gray.shape
    thr, _ = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    dark = (gray <= thr).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=8)
    ring_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    best_bad: tuple[int, CrossDetection] | None = None
    candidates = []
    for k in range(1, n):
        x0, y0, bw, bh, area = stats[k]
        if area < 12 * params.min_bar_px ** 2 or area > 0.25 * h * w:
            continue
        # A plate cross is a dark blob surrounded by light plate on most of its rim.
        pad = 4
        xa, ya, xb, yb = max(x0 - pad, 0), max(y0 - pad, 0), min(x0 + bw + pad, w), min(y0 + bh + pad, h)
        blob = (labels[ya:yb, xa:xb] == k).astype(np.uint8)
        ring = cv2.dilate(blob, ring_kernel).astype(bool) & ~blob.astype(bool)
        roi = gray[ya:yb, xa:xb]
        ring_vals = roi[ring]
        if ring_vals.size == 0:
            continue
        light = ring_vals > thr
        if light.mean() < 0.5:
            continue
        plate_level = float(np.median(ring_vals[light]))
        cross_level = float(np.median(roi[blob.astype(bool)]))
        if plate_level - cross_level < params.min_contrast:
            continue
        touches = x0 <= params.border_px or y0 <= params.border_px or \
            x0 + bw >= w - params.border_px or y0 + bh >= h - params.border_px
        candidates.append((area, k, touches, light.mean(), plate_level, cross_level))
    if not candidates:
        return _reject("missing", "no dark cross on a light plate in the image")
    candidates.sort(key=lambda c: -c[0])
    for area, k, touches, light_frac, plate_level, cross_level in candidates:
        if touches:
            det = _reject("border", "the cross touches the image border")
        else:
            blob = (labels == k).astype(np.uint8)
            det = _measure(gray, blob, plate_level, cross_level, params)
            if det.ok and light_frac < 0.97:
                det = _reject("occluded", f"only {light_frac:.0%} of the cross's rim is plate",
                              oblique_deg=det.oblique_deg, edge_rms_px=det.edge_rms_px)
        if det.ok:
            return det
        rank = REASONS.index(det.reason)
        if best_bad is None or rank > best_bad[0]:
            best_bad = (rank, det)
    return best_bad[1]


def _polygon(blob: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The blob's outline simplified to a polygon (12 corners for a whole cross) and the
    estimated bar width [px]."""
    contours, _ = cv2.findContours(blob, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    c = max(contours, key=cv2.contourArea)
    area, perim = cv2.contourArea(c), cv2.arcLength(c, True)
    bar_px = 2.0 * area / max(perim, 1e-9)     # a cross of bar width w and span L: A~2Lw, P~4L
    # Pixel noise on the outline can leave extra corners at a tight tolerance: loosen it
    # step by step, never beyond half a bar width (which would cut the cross's corners).
    for frac in (0.2, 0.28, 0.36, 0.45):
        poly = cv2.approxPolyDP(c, frac * bar_px, True).reshape(-1, 2).astype(float)
        if len(poly) <= 12:
            break
    return poly, bar_px


def _measure(gray: np.ndarray, blob: np.ndarray, plate_level: float, cross_level: float,
             params: CrossParams) -> CrossDetection:
    found = _polygon(blob)
    if found is None:
        return _reject("missing", "no contour")
    poly, bar_px = found
    if bar_px < params.min_bar_px:
        return _reject("oblique", f"bars only {bar_px:.1f} px wide")
    if len(poly) != 12:
        return _reject("occluded", f"the dark blob has {len(poly)} corners, a cross has 12")
    # Orient the polygon counter-clockwise in image coordinates and find its 4 concave corners.
    signed = 0.5 * np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    if signed < 0:
        poly = poly[::-1]
    prev, nxt = np.roll(poly, 1, axis=0), np.roll(poly, -1, axis=0)
    turn = _cross2(poly - prev, nxt - poly)
    concave = np.flatnonzero(turn < 0)
    if len(concave) != 4 or np.any(np.diff(concave) != 3):
        return _reject("occluded", "the outline is not a cross (concave corners out of place)")
    # Rotate so each arm is (concave, convex, convex) -> next concave.
    poly = np.roll(poly, -concave[0], axis=0)
    centre0 = poly[[0, 3, 6, 9]].mean(axis=0)
    arm_ends = np.array([(poly[3 * i + 1] + poly[3 * i + 2]) / 2 for i in range(4)])
    arms = arm_ends - centre0
    lengths = np.linalg.norm(arms, axis=1)
    ratio = max(lengths[0] / lengths[2], lengths[2] / lengths[0], lengths[1] / lengths[3], lengths[3] / lengths[1])
    bars = np.stack([arm_ends[0] - arm_ends[2], arm_ends[1] - arm_ends[3]], axis=1)
    sv = np.linalg.svd(bars, compute_uv=False)
    oblique = float(np.degrees(np.arccos(np.clip(sv[1] / sv[0], 0.0, 1.0))))
    if oblique > params.max_oblique_deg:
        return _reject("oblique", f"plate seen {oblique:.0f} deg off its normal", oblique_deg=oblique)
    if ratio > params.max_arm_ratio:
        return _reject("occluded", f"opposite arms differ by a factor {ratio:.2f}", oblique_deg=oblique)
    mid = 0.5 * (plate_level + cross_level)
    lines, rms = _fit_bar_edges(gray, poly, centre0, mid, bar_px)
    if lines is None:
        return _reject("occluded", "too few edge points", oblique_deg=oblique)
    if rms > params.max_edge_rms_px:
        return _reject("occluded", f"edges are not straight (RMS {rms:.2f} px)", oblique_deg=oblique, edge_rms_px=rms)
    (a_pos, a_neg), (b_pos, b_neg) = lines
    corners = np.array([_intersect(a_pos, b_pos), _intersect(a_neg, b_pos),
                        _intersect(a_neg, b_neg), _intersect(a_pos, b_neg)])
    centre = _intersect(_line_through(corners[0], corners[2]), _line_through(corners[1], corners[3]))
    if not np.all(np.isfinite(centre)) or np.linalg.norm(centre - centre0) > bar_px:
        return _reject("occluded", "edge lines do not meet at the cross", oblique_deg=oblique, edge_rms_px=rms)
    return CrossDetection(centre, None, "ok", corners, oblique, rms)


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """z component of the cross product of 2-D vectors (..., 2)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _line_through(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Homogeneous line through two points."""
    return np.cross([p[0], p[1], 1.0], [q[0], q[1], 1.0])


def _intersect(l1: np.ndarray, l2: np.ndarray) -> np.ndarray:
    x = np.cross(l1, l2)
    return x[:2] / x[2] if abs(x[2]) > 1e-12 else np.full(2, np.nan)


def _bilinear(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Grey levels at sub-pixel positions (..., 2) (pixel centres at integers)."""
    flat = pts.reshape(-1, 2).astype(np.float32)
    vals = cv2.remap(gray.astype(np.float32), flat[:, :1].reshape(-1, 1), flat[:, 1:].reshape(-1, 1),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return vals.reshape(pts.shape[:-1])


def _edge_points(gray: np.ndarray, p: np.ndarray, q: np.ndarray, outward: np.ndarray,
                 mid: float, half: float) -> np.ndarray:
    """Sub-pixel points of the straight edge from p to q (dark inside, light along ``outward``)."""
    length = np.linalg.norm(q - p)
    n = max(int(length * 0.6), 2)
    s = np.linspace(0.2, 0.8, n)
    base = p[None] + s[:, None] * (q - p)[None]
    offs = np.arange(-half, half + 1e-9, 0.2)
    samples = base[:, None, :] + offs[None, :, None] * outward[None, None, :]
    prof = _bilinear(gray, samples) - mid            # dark (<0) -> light (>0)
    out = []
    for i in range(n):
        sign = np.sign(prof[i])
        idx = np.flatnonzero((sign[:-1] < 0) & (sign[1:] >= 0))
        if len(idx) != 1:
            continue
        j = idx[0]
        a, b = prof[i, j], prof[i, j + 1]
        o = offs[j] + (offs[j + 1] - offs[j]) * (-a / (b - a))
        out.append(base[i] + o * outward)
    return np.array(out).reshape(-1, 2)


def _fit_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares line: homogeneous form and the points' distances to it."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c)
    normal = vt[1]
    line = np.array([normal[0], normal[1], -normal @ c])
    return line, points @ normal - normal @ c


def _fit_bar_edges(gray, poly, centre0, mid, bar_px):
    """Fit the two long edges of both bars; returns ((A+, A-), (B+, B-)) lines and RMS."""
    half = max(min(0.45 * bar_px, 4.0), 1.0)
    groups: dict[tuple[int, int], list[np.ndarray]] = {}
    for arm in range(4):
        c_in, e1, e2, c_out = poly[3 * arm], poly[3 * arm + 1], poly[3 * arm + 2], poly[(3 * arm + 3) % 12]
        direction = (e1 + e2) / 2 - centre0
        direction /= np.linalg.norm(direction)
        for p, q in ((c_in, e1), (e2, c_out)):
            edge = (q - p) / np.linalg.norm(q - p)
            outward = np.array([edge[1], -edge[0]])      # right-hand normal of a CCW outline (y down)
            if np.dot(outward, (p + q) / 2 - centre0) - np.dot(direction, (p + q) / 2 - centre0) * np.dot(outward, direction) < 0:
                outward = -outward
            side = int(np.sign(_cross2(direction, (p + q) / 2 - centre0)) * (1 if arm < 2 else -1))
            groups.setdefault((arm % 2, side), []).append(_edge_points(gray, p, q, outward, mid, half))
    lines, resid = [], []
    for bar in (0, 1):
        pair = []
        for side in (1, -1):
            pts = np.concatenate(groups.get((bar, side), [np.zeros((0, 2))]))
            if len(pts) < 6:
                return None, np.inf
            line, d = _fit_line(pts)
            pair.append(line)
            resid.append(d)
        lines.append(tuple(pair))
    r = np.concatenate(resid)
    return lines, float(np.sqrt(np.mean(r ** 2)))


def plate_image(camera: Camera, world_from_plate: np.ndarray, plate_size: float, cross_width: float,
                cross_length: float, background: int = 60, plate: int = 235, cross: int = 20,
                supersample: int = 8, blur_px: float = 0.0) -> np.ndarray:
    """A synthetic grey image of the plate seen by ``camera`` (distortion ignored).

    The cross centre is the plate frame's origin, its face the plate's x-y plane. The image
    is drawn ``supersample`` times larger and area-averaged down, so edges carry true
    sub-pixel information; an optional Gaussian blur [px] imitates a lens. Used to check
    the detector against a known answer.
    """
    s = supersample
    H, W = camera.height * s, camera.width * s
    img = np.full((H, W), background, np.uint8)
    hw, cw, cl = plate_size / 2, cross_width / 2, cross_length / 2

    def poly(xy):
        pts = np.c_[np.asarray(xy, float), np.zeros(len(xy)), np.ones(len(xy))] @ world_from_plate.T
        px = camera.project(pts[:, :3])
        # Pixel centres at integers: the supersampled pixel (i*s + (s-1)/2) is pixel i.
        return np.round((px * s + (s - 1) / 2) * 16).astype(np.int32)

    cv2.fillPoly(img, [poly([(-hw, -hw), (hw, -hw), (hw, hw), (-hw, hw)])], plate, cv2.LINE_8, 4)
    cv2.fillPoly(img, [poly([(-cl, -cw), (cl, -cw), (cl, cw), (-cl, cw)])], cross, cv2.LINE_8, 4)
    cv2.fillPoly(img, [poly([(-cw, -cl), (cw, -cl), (cw, cl), (-cw, cl)])], cross, cv2.LINE_8, 4)
    out = cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)
    if blur_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), blur_px)
    return out
