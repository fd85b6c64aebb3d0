"""The estimator's verdict: may a robot act on this estimate? (formats.md, `verdict`).

Three questions, each judged so that a threshold means the same with 2 or 3 cameras:

- Does the shape explain every view? Per view, the silhouette mismatch (the XOR of eq.
  5-6, in pixels) divided by the outline's length [px] (the shorter of the observed and
  the model's: a mask of noise has a huge outline, the model's stays a tape's) is the
  mean distance between the model's and the observed boundary [px]: about 0.5-1.5 px on
  good fits whatever the view's size or thickness, where the area-normalised eq. 7 cost of
  an edge-on view is several times that of a face-on one. Above ``POOR_OFFSET_PX`` in any
  view: ``poor_fit``. The shape is the plate chain, or the strip the tip frame comes from
  where the strip explains its worst view better (a bend within one plate's length). Where
  a view is above it, the share of its mismatch within ``BOX_OUTLINE_PX`` of a scene box's
  projected outline is left out (:func:`box_edge_offsets`).
- Do two cameras locate the free end? The estimate's last ``TIP_SPAN_M`` of centre line
  and its tip corners are projected into each view; a view locates the free end when at
  least ``TIP_SEEN_FRACTION`` of those points fall inside the image, outside its ignore
  mask and in front of every scene box; the view does not show the tape going behind a
  scene box where the model does not (``BOX_CUT_PX``); the end stands against the background there (the
  tip edge's middle and both corners within ``EDGE_PX`` of observed background, or a
  stretch of it from a corner within ``EDGE_RUN_PX`` of background and ``EDGE_RUN_TAPE_PX`` of
  observed tape: a tip over the tape's own body is not located by that
  silhouette); the tape's continuation past the tip would be seen, or background is seen
  before the occluder; no observed tape leaves the image near the tip edge
  (``BORDER_CLEAR_PX``; a corner of the end touching the border is not the tape leaving,
  ``BORDER_RUN_FRACTION``); at most ``LOCATE_UNEXPLAINED_PX`` of observed tape near the tip is
  unexplained; and it does not see the end edge-on as a sliver (``THIN_END_PX``), unless
  the model explains that whole view (``SLIVER_STRAY_PX``) and another view locates the
  end without being a sliver. Fewer than two such views: ``hidden``.
- Can the end's depth be told? The cameras that see it must look at it from directions at
  least ``MIN_PARALLAX_DEG`` apart, else ``ambiguous``.
- Does a distinct shape explain the views nearly as well? An alternative whose tip is more
  than ``DISTINCT_TIP_M`` from the estimate's, refined like the winner, whose silhouette
  cost (eq. 11) is at most ``AMBIGUOUS_RATIO`` times the winner's (plus
  ``AMBIGUOUS_ABS``): ``ambiguous``.

The thresholds and the rates of wrong "ok" and needless refusals measured with them are
in the README (``scripts/bench_verdict.py``).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Callable, Sequence

import cv2
import numpy as np

from .capture import View
from .occlusion import hidden
from .result import Verdict
from .scene import Box
from .silhouette import signed_area
from .views import box_hulls, box_outline_mask, box_outline_px

POOR_OFFSET_PX = 2.5
"""Mean boundary distance [px] in a view above which the fit does not explain it. 3.0 until
2026-11-27: fresh part-1010016 was "ok" 10.4 mm off with a view at 2.72 px (the tape coming
out from behind the part bent the wrong way, its curled end's image a few px from the true
one in both views); on 2,339 development captures (964000- to 997000-) 2.5 changed one
answer, a refusal's reason (part-976000, 44 mm off, hidden -> poor_fit); it refuses the
older test capture part-924052, right (1.1 mm off) with a view at 2.99 px."""
END_OFFSET_PX = 2.5
"""Mean boundary distance [px] around the tip's projection above which a view that sees the
free end does not explain it: the end itself is wrong (a curl the model did not follow)
however well the rest fits."""
END_WINDOW_PX = 20
"""Half size of the window around the tip's projection in which the free end's own fit is
judged [px]."""
EDGE_PX = 8
"""A view sees the free end only where the end stands against the background: the tip edge
(its two corners and its middle) must lie within this many pixels (a square; ~3 mm at the
tape) of observed background (a tip in front of or behind the tape's own body is not
located by that silhouette; 3 px refused 7 of 60 good sim fits whose estimated edge was a
few px in). 10 px until 2026-11-27: part-997000 was "ok" 9.4 mm off, its tip edge 10-11 px
inside one view's outline all along (the silhouette's edge there a fold, the end over the
body); 8 px changed no other answer on about 2,300 development captures (964000-,
970000-, 976000-, 981000-, part 988000- and 997000-) but refusals' reasons, 6 px refused a
right one.
Until 2026-11-27 the middle and one corner sufficed: a tip edge running from the outline
into the body passed, one corner on the outline and the middle 10 px in (part-990066,
"ok" 32.6 mm off; part-990031, "ok" 7.0 mm off, alike)."""
BOX_OUTLINE_PX = 3.0
"""Tip edge points this close [px] to a scene box's projected outline are not at the tape's
own outline (the fit's ``box_edge_px`` alike)."""
EDGE_RUN_PX = 5.0
EDGE_RUN_TAPE_PX = 3
EDGE_RUN_GAP_PX = 3.0
EDGE_RUN_FRACTION = 0.125
EDGE_RUN_MIN_PX = 6.0
"""... or a stretch of the tip edge from a corner, at least this fraction of its width and
this long in the image [px], must lie within EDGE_RUN_PX (Euclidean) of observed
background, within EDGE_RUN_TAPE_PX (a square) of observed tape (a model edge out over the
background is no edge seen) and BOX_OUTLINE_PX + EDGE_RUN_GAP_PX clear of every scene
box's projected outline: an end hooked over the tape's body shows part of its edge
against the background (a notch's side), and that part locates it. (The wrong "ok" that
made the rule above had the tip edge 8 px inside the silhouette an eighth of its width
from the corner.) Until 2026-11-27 EDGE_RUN_PX was 3 px in a square (up to 4.2 px
diagonally), the tape's distance and the box gap alike: with both corners now asked for above, the hooked ends of
shell tapes, half their edge 4-5 px in along the outline, went to this rule (shell-c2 and
-c3-970017, 1.5-2.1 mm off). 5 px in a square (7 px diagonally) let through an edge whose
stretch dived into the body 6.6 px in (occluded-976024, "ok" 6.6 mm off); observed tape
within 5 px instead of 3 let a stretch out over the background through (occluded-996052,
"ok" 6.2 mm off where the thorough look of a "hidden" answer finds it 0.3 mm off)."""
FOLD_DEG = 120.0
"""A free end that turns back by more than this [deg] from the tape's first plate is folded
back towards the body; an "ok" fit of a fold gets the estimator's thorough second look,
whose wider search finds the shapes folded the other way (alternatives): where a fold's
end meets the body's outline, a notch in a silhouette is as well the fold's edge with the
end over the body (a wrong "ok" 16 mm off in an episode)."""
END_FOLD_DEG = 100.0
"""... and so is an end whose tip frame turns by more than this [deg] from the plate before
the tape's last one (a tight fold at the end, however the tape hangs from its base):
a shape bending sideways at the end explains the views of a hairpin fold over the body
with a "notch" of its own, and the first look's search may miss the hairpin (two wrong
"ok" 20 and 23 mm off in episodes, 850037 and 832172, their ends turned 122 and 111 deg;
the thorough look finds the hairpin in both). Measured from the tape's first plate
instead, at 75 deg, the look doubled the median fit time: most tapes turn 90 deg where
they hang over the part's edge."""
BEYOND_M = (0.003, 0.006)
"""Distances [m] past the tip, along its trunk, where a view that locates the end must be
able to see: where the tape's continuation would be hidden by a scene box, lie on ignored
pixels or leave the image, the silhouette may end at that occluder's edge, not at the tape's
end (a wrong "ok" 13 mm off: a shell tape whose end went on behind the part)."""
CONTINUATION_GAP_PX = 3.0
"""... and it must lie this many pixels more than BOX_OUTLINE_PX clear of every scene box's
projected outline, and this far inside the image."""
CONTINUATION_STEPS = 12
"""Points per line, evenly up to BEYOND_M's last, at which a view is asked whether it shows
background past the tip before an occluder."""
TIP_SPAN_M = 0.005
"""Length of the free end [m] whose visibility decides whether a camera sees it."""
TIP_SEEN_FRACTION = 0.5
"""Fraction of the free end's points a camera must see to count as seeing it."""
MIN_PARALLAX_DEG = 10.0
"""The cameras that see the free end must look at it from directions at least this far apart
[deg] (the cell's are ~35 deg apart): from nearly one direction its depth is undetermined,
and shapes whose tips lie anywhere along it explain the views alike (``ambiguous``)."""
UNEXPLAINED_MARGIN_PX = 3
"""Observed tape within this many pixels of the model's silhouette counts as explained (and
model within it of observed tape as supported): calibration error of a few pixels."""
UNEXPLAINED_PX = 30
"""A region of observed tape the model does not explain, beyond the margin and reaching the
tip's window, longer than this [px] (about 10 mm at the tape): the tape goes on past the
model's end, such as an end seen edge-on as a thin sliver, which the mean boundary distance
averages away (a wrong "ok" 60 mm off). 15 px refused good fits of curled ends, where an
edge-on plate's thin line lies a few pixels off the observed one."""
LOCATE_UNEXPLAINED_PX = 15
"""A view locates the free end only where observed tape left unexplained near the tip (see
``UNEXPLAINED_PX``) is at most this long [px, ~5 mm at the tape]: a shorter unexplained
region does not make the fit poor, but the view's end may be elsewhere (a wrong "ok" 12.9 mm
off had 25 px of it in the one view that located the end besides a sliver)."""
LOCATE_BAND_PX = 7.5
"""... where the region departs from the model's silhouette by more than this [px]
somewhere: a band along the model's edge, nowhere farther from it (UNEXPLAINED_MARGIN_PX
and 4.5 px more, ~2 mm at the tape), is an edge of the model a few pixels off (a corner of a
curled end, an edge-on end a little tilted, calibration error), not tape the model left
out. On the development captures of 964000-, 970000-, 976000- and 981000- (2,746 looks,
123 views with more than 15 px): the views of right answers (tip within 3 mm) showed 4.1
px and more (52 of 98 at most 7.5), those of answers more than 5 mm off 8.5 px and more
(calib_rot-976018, 5.2 mm; shell-c3-964019, 32 mm, 10.0 px); 11 px made an answer 8.7 mm
off "ok" (shell-c3-964007). 7.5 px turned 18 needless refusals of 2,283 captures "ok", no
wrong one."""
BOX_CUT_PX = 12
"""A view does not locate the free end where its observed tape goes behind a scene box
(BOX_CUT_RING_PX) away from the model (BOX_CUT_EXPLAINED_PX) along at least this many
pixels of one edge of the box's projected outline: the tape goes on there, out of that
camera's sight, and the end the model shows the view may be a fold of the tape's side, not
its end. (A wrong "ok" 56.5 mm off, fresh shell-c2-1052024: the part hid the tape's lower
end in both views; the model folded its last plate so that its tip edge ran down the
silhouette's side, and one view showed the tape's leg going behind the part along 59 px of
the part's edge away from the model.) Measured along one edge, not as a count of outline
pixels: a tape's side passing a box's corner lies near it along a few pixels of each of two
edges (part-1043043, a right "ok" 0.6 mm off: 18 outline pixels, 7 px along one edge). The
development figures are in the README (`hidden`). Boxes a camera does not see whole in
front of it (the table, from the cell's cameras) are left out, as by the outline rules."""
BOX_CUT_RING_PX = 3
"""The observed outline goes behind a box where it lies within this many pixels outside the
box's projected outline (or less than BOX_CUT_TAPE_DEPTH_PX inside it), with background
(the box) inside the outline within this of it and no observed tape well inside it (a tape
passing in front of the box's edge is over the box's projection there)."""
BOX_CUT_GAP_PX = 3.0
"""... the stretch along the edge unbroken: its pixels' places along it no more than this
[px] apart (a tape's side grazing the outline at a few places is no cut: part-1059058, a
right "ok" 0.4 mm off, had 25 outline pixels in four places spanning 37 px of one edge)."""
BOX_CUT_TAPE_DEPTH_PX = 1.5
"""... observed tape counts as passing in front of the box only this far [px] inside its
projected outline: where the box hides the tape, segmentation and the pixel grid leave the
silhouette's edge a pixel in or out of the outline."""
BOX_CUT_EXPLAINED_PX = 6
"""... and not within this many pixels of the model's base edge, of its tip edge (the end's
own edge ending at the box's outline: the outline rules judge it, ``BOX_OUTLINE_PX``), or of
where the model's chain before its last plate goes behind a box too (the model's tape going
on behind it there; its last plate alone folded behind the box does not count). Shell
tape 1043025's right end ends at the part's outline in one view, 24 outline pixels along
its tip edge: none left."""


def _box_edges(view: View, boxes: Sequence[Box]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per scene box seen whole in front of ``view``'s camera, its projected outline (the
    convex hull of :func:`views.box_outline_px`) as (each edge's start (k, 2), the edge
    (k, 2), its unit normal pointing in (k, 2)) [px]."""
    out = []
    for hull in box_hulls(view.camera, boxes):
        poly = hull[:, 0].astype(float)
        if not np.all(np.isfinite(poly)) or len(poly) < 3:
            continue
        turn = 1.0 if signed_area(poly) > 0 else -1.0
        edge = np.roll(poly, -1, axis=0) - poly
        inward = turn * np.column_stack([-edge[:, 1], edge[:, 0]]) / np.maximum(
            np.linalg.norm(edge, axis=1), 1e-12)[:, None]
        out.append((poly, edge, inward))
    return out


def _to_segments(points: np.ndarray, a: np.ndarray, edge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance (N, k), place along (N, k)) [px] from each image point (N, 2) to the
    segments starting at ``a`` (k, 2) along ``edge`` (k, 2): to the nearest point of each,
    and that point's distance from the segment's start."""
    rel = points[:, None, :] - a[None]
    squared = np.maximum((edge * edge).sum(axis=1), 1e-12)
    t = np.clip(np.einsum("nkj,kj->nk", rel, edge) / squared, 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * edge[None], axis=2), t * np.sqrt(squared)


def _box_depth_px(edges: list, points: np.ndarray) -> np.ndarray:
    """(N,) how far [px] each image point (N, 2) lies inside the boxes' projected outlines
    (:func:`_box_edges`): for a box, the least of its distances to its edges' lines inside,
    minus the distance to the outline outside; the greatest over the boxes, -inf without
    any. Exact geometry at the points, whatever crop they were taken from."""
    out = np.full(len(points), -np.inf)
    for a, edge, inward in edges:
        depth = np.min(np.einsum("nkj,kj->nk", points[:, None, :] - a[None], inward), axis=1)
        outside = depth < 0
        if outside.any():
            # Outside, the Euclidean distance to the outline's nearest edge segment (the
            # lines' distance would reach farther round a corner).
            depth[outside] = -np.min(_to_segments(points[outside], a, edge)[0], axis=1)
        out = np.maximum(out, depth)
    return out


def _along_edges(edges: list, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each image point (N, 2): which box outline edge is nearest it (an index over
    every box's edges, (N,)) and where along that edge its nearest point lies [px from the
    edge's start] (N,)."""
    best = np.full(len(points), np.inf)
    which = np.zeros(len(points), int)
    along = np.zeros(len(points))
    rows, base = np.arange(len(points)), 0
    for a, edge, _ in edges:
        d, place = _to_segments(points, a, edge)
        k = np.argmin(d, axis=1)
        closer = d[rows, k] < best
        best[closer] = d[rows, k][closer]
        which[closer] = base + k[closer]
        along[closer] = place[rows, k][closer]
        base += len(a)
    return which, along


def box_cuts(view: View, boxes: Sequence[Box], observed: np.ndarray, origin: tuple[int, int],
             at_least: int = 0, edges: list | None = None) -> np.ndarray:
    """(N, 2) image pixels (x, y) of the observed outline where the tape goes behind a scene
    box (BOX_CUT_RING_PX): outline pixels of ``observed`` (the view's silhouette crop whose
    top-left pixel is ``origin``; nothing outside it is tape) within BOX_CUT_RING_PX outside
    a box's projected outline or less than BOX_CUT_TAPE_DEPTH_PX inside it, with a pixel of
    background inside a box within BOX_CUT_RING_PX and no observed tape at least
    BOX_CUT_TAPE_DEPTH_PX inside a box within BOX_CUT_RING_PX + 2 (the tape passing in front
    of the box's edge: its sides just outside the box lie that close to its tape inside),
    none within BOX_CUT_RING_PX + 2 of ignored pixels (what is under them is unknown). Pixel
    centres are measured against the exact projected outlines, so the answer does not depend
    on the crop. Fewer than ``at_least`` outline pixels near a box: those, untested (as many
    as the cuts at most). ``edges``: the boxes' :func:`_box_edges` in this view, when made."""
    edges = _box_edges(view, boxes) if edges is None else edges
    if not edges:
        return np.zeros((0, 2), int)
    obs = np.pad(observed.astype(np.uint8), 1)     # nothing outside the crop is tape
    outline = obs & (1 - cv2.erode(obs, np.ones((3, 3), np.uint8)))
    ys, xs = np.nonzero(outline[1:-1, 1:-1])
    pixels = np.column_stack([xs + origin[0], ys + origin[1]])
    depth = _box_depth_px(edges, pixels.astype(float))
    pixels = pixels[(depth < BOX_CUT_TAPE_DEPTH_PX) & (depth >= -BOX_CUT_RING_PX)]
    if not len(pixels) or len(pixels) < at_least:
        return pixels
    h, w = observed.shape
    cam = view.camera
    r = BOX_CUT_RING_PX
    offsets = _NEAR_CUT                                                        # (m, 2) as (dx, dy)
    near = pixels[:, None, :] + offsets[None]                                  # (N, m, 2)
    in_image = (near[..., 0] >= 0) & (near[..., 0] < cam.width) & (near[..., 1] >= 0) & (near[..., 1] < cam.height)
    nx, ny = np.clip(near[..., 0], 0, cam.width - 1), np.clip(near[..., 1], 0, cam.height - 1)
    cx, cy = near[..., 0] - origin[0], near[..., 1] - origin[1]
    in_crop = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
    tape = in_crop & (observed[np.clip(cy, 0, h - 1), np.clip(cx, 0, w - 1)] > 0)
    depth = _box_depth_px(edges, near.reshape(-1, 2).astype(float)).reshape(near.shape[:2])
    in_ring = (offsets ** 2).sum(axis=1) <= r * r
    keep = (np.any(in_ring[None] & in_image & (depth >= 0) & ~tape, axis=1)
            & ~np.any(tape & (depth >= BOX_CUT_TAPE_DEPTH_PX), axis=1))
    if view.ignore is not None:
        keep &= ~np.any(in_image & view.ignore[ny, nx], axis=1)
    return pixels[keep]


def unexplained_cut_px(view: View, boxes: Sequence[Box], observed: np.ndarray, origin: tuple[int, int],
                       base_edge: np.ndarray, tip_edge: np.ndarray,
                       body_hidden: Callable[[], np.ndarray]) -> float:
    """How far [px] ``view``'s observed outline goes behind a scene box (:func:`box_cuts`)
    away from the model (BOX_CUT_EXPLAINED_PX), along one edge of a box's projected outline
    (the longest unbroken stretch, BOX_CUT_GAP_PX: a tape's side passing a box's corner
    makes a few pixels along each of two edges): away from the model's base edge and its
    tip edge (each (2, 3), corner to corner; an edge behind the camera explains nothing)
    and from ``body_hidden()``, a uint8 0/1 crop like ``observed`` of the pixels where a box
    hides the model's chain before its last plate (drawn only when asked). Below
    BOX_CUT_PX, a count of outline pixels near a box, untested (:func:`box_cuts`'
    ``at_least``: at least as long)."""
    edges = _box_edges(view, boxes)
    cuts = box_cuts(view, boxes, observed, origin, at_least=BOX_CUT_PX, edges=edges)
    if len(cuts) < BOX_CUT_PX:
        return float(len(cuts))
    r = BOX_CUT_EXPLAINED_PX
    points = cuts.astype(float)
    explained = np.zeros(len(cuts), bool)
    cam = view.camera
    for edge in (base_edge, tip_edge):
        edge = np.asarray(edge, float)
        uv = cam.project(edge)
        if np.all(cam.to_camera(edge)[:, 2] > 0) and np.all(np.isfinite(uv)):
            explained |= _to_segments(points, uv[:1], uv[1:] - uv[:1])[0][:, 0] <= r
    hidden_px = body_hidden()
    if hidden_px.any():
        near = cv2.dilate(hidden_px, _disc(r).astype(np.uint8))
        h, w = near.shape
        cx, cy = cuts[:, 0] - origin[0], cuts[:, 1] - origin[1]
        inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        explained[inside] |= near[cy[inside], cx[inside]] > 0
    if explained.all():
        return 0.0
    which, along = _along_edges(edges, points[~explained])
    longest = 0.0
    for k in np.unique(which):
        # The longest unbroken stretch along that edge (pixels a few apart at most): a side
        # grazing the outline at a few places is no cut.
        at = np.sort(along[which == k])
        breaks = np.flatnonzero(np.diff(at) > BOX_CUT_GAP_PX)
        starts, ends = np.r_[0, breaks + 1], np.r_[breaks, len(at) - 1]
        longest = max(longest, float(np.max(at[ends] - at[starts])) + 1.0)
    return longest


BEHIND_BOX = "shows the tape going behind a scene box where the model does not"
"""The words a ``hidden`` reason adds for a view that does not locate the end for
``BOX_CUT_PX``."""
PAST_END = "shows tape past the model's end"
"""The words of a ``poor_fit`` reason for tape going on past the model's end (the rest of
the shape explains the views): a robot with a needle may measure where the end is."""
END_UNEXPLAINED = "does not explain the free end"
"""The words of a ``poor_fit`` reason for a view whose free end the model does not explain
(END_OFFSET_PX), which an episode's needle may settle."""

EDGEWISE_MAX_DEG = 18.0
"""A tape hardly bends within its own plane (edgewise): an "ok" estimate whose plate chain
turns the next plate's trunk more than this out of a plate's plane towards its width axis, at
any joint but the last (see :func:`edgewise_bend`), is a shape no tape takes (``poor_fit``,
and the second look). On fresh captures
the fit does not tune on (part 877000, plate-chain sim 879000, shell 879500), the 120 right
"ok" estimates (tip within 5 mm) bent edgewise by 1.3 deg median, 2.8 deg p90, 12 deg at most;
the two wrong "ok" (part captures 17 and 69 mm off, a twist and an edgewise bend explaining
a silhouette the part cuts) by 21 and 33 deg; wrong estimates of other verdicts by 20-47."""


EDGEWISE = "bends within the tape's plane"
"""The words of a ``poor_fit`` reason for an edgewise bend (EDGEWISE_MAX_DEG)."""


def edgewise_bend(frames: np.ndarray) -> tuple[float, int]:
    """(the largest edgewise bend [deg] of a plate chain's body, the joint where it is) from
    its frames (n+1, 3, 3) (``forward_kinematics``: plate i's frame frames[i + 1], columns
    trunk, width, normal): at joint i (between plates i - 1 and i), the angle of plate i's
    trunk out of plate i - 1's plane towards its width axis; joints 1 to n - 2. The last
    joint is left out: the output chain's last plate is pulled towards the strip's tip frame
    (``FitConfig.strip_frame_weight``), a chord of an end curled within it (a fresh part
    capture's right "ok", 1.2 mm off, bent 57 deg edgewise there)."""
    F = np.asarray(frames, float)
    if len(F) < 4:
        return 0.0, 0
    s_ = np.einsum("ij,ij->i", F[2:-1, :, 0], F[1:-2, :, 1])
    deg = np.degrees(np.arcsin(np.clip(np.abs(s_), 0.0, 1.0)))
    k = int(np.argmax(deg))
    return float(deg[k]), k + 1


END_ON_DEG = 15.0
"""A view whose line of sight to the tip lies within this angle [deg] of the estimated end's
trunk sees the end end-on: its depth along that line is less constrained, and a shape
curled another way may explain the view as well. An "ok" estimate with such a view gets the
estimator's thorough second look before it answers (``end_on``; a wrong
"ok" 14.9 mm off in a simulated episode, 839020, its end 13 deg from the second camera's
line of sight, was a search miss: the thorough look finds the true shape, 1.0 mm off).
Such a view counted as not locating the end before: on fresh verdict benches that made
1.4-4.3 % of the captures needless refusals on three ranges (fits 0.2-3.6 mm off) and
caught no wrong "ok"."""
MIN_TRUNK_PX = 3.0
"""The tape's last 10 mm must project at least this long [px] for the direction past the tip
to be known (an end seen end-on: every unexplained region counts as past the end)."""
UNEXPLAINED_MIN_AREA_PX = 8
"""Regions smaller than this [px] are segmentation speckles, not tape."""
DISTINCT_TIP_M = 0.010
"""Tips further apart than this [m] make two shapes distinct hypotheses (formats.md)."""
AMBIGUOUS_RATIO = 1.25
AMBIGUOUS_ABS = 0.005
"""A distinct alternative with eq.-11 cost <= AMBIGUOUS_RATIO * best + AMBIGUOUS_ABS
explains the views nearly as well as the estimate."""


@dataclass(frozen=True)
class Judgement:
    """verdict; reason: one line why (empty when "ok"); tip_views: cameras seeing the free
    end; offsets_px: (views,) mean boundary distance per view [px]."""

    verdict: Verdict
    reason: str
    tip_views: int
    offsets_px: np.ndarray
    by_strip: bool = False
    """the offsets are the strip's (:func:`explaining_offsets`), not the plate chain's"""
    hooked_across: bool = False
    """a view that locates the end does so only as a hooked end (:func:`outline_rule`) with
    both of the tip edge's corners at the outline and its middle inside the silhouette"""
    base_px: float = float("nan")
    """the worst view's mean boundary distance around the tape's base [px], where the "ok"
    answers' base check measured it (``estimator.fit``), else NaN"""


def _outline(m: np.ndarray) -> tuple[float, float]:
    """(area, outline length) [px] of a uint8 0/1 mask: its pixels and its boundary pixels."""
    x, y, w, h = cv2.boundingRect(m)
    roi = cv2.copyMakeBorder(m[y:y + h, x:x + w], 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    return float(cv2.countNonZero(roi)), float(cv2.countNonZero(roi - cv2.erode(roi, np.ones((3, 3), np.uint8))))


MAX_COVER = 0.4
"""A mask whose tape covers more than this fraction of its image is not a tape's silhouette
(an inverted or white mask)."""
MAX_REGIONS = 200
"""... nor one split into more regions than this (noise); a tape's mask is one region and a
few speckles."""
MIN_AREA_PX = 30
"""... nor one with fewer tape pixels than this."""


def mask_fault(view: View) -> str:
    """Why ``view``'s mask is not a tape's silhouette ('' when it may be one)."""
    m = view.mask.astype(np.uint8)
    if view.ignore is not None:
        m[view.ignore] = 0
    area = cv2.countNonZero(m)
    total = m.size - (0 if view.ignore is None else int(np.count_nonzero(view.ignore)))
    if area < MIN_AREA_PX:
        return f"its mask shows {area} tape pixels"
    if area > MAX_COVER * max(total, 1):
        return f"its mask covers {100 * area / max(total, 1):.0f} % of the image (inverted or white?)"
    x, y, w, h = cv2.boundingRect(m)
    regions = cv2.connectedComponents(m[y:y + h, x:x + w], connectivity=8)[0] - 1
    if regions > MAX_REGIONS:
        return f"its mask is {regions} separate regions (noise)"
    return ""


def sizes(masks: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(areas, outline lengths), each (views,) [px], of uint8 0/1 silhouettes (any crop
    holding them): their pixels and their boundary pixels; at least 1."""
    out = np.array([_outline(m) for m in masks]).reshape(-1, 2)
    return np.maximum(out[:, 0], 1.0), np.maximum(out[:, 1], 1.0)


def boundary_offsets(view_costs: np.ndarray, areas: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(views,) mean boundary distance [px]: eq.-7 cost x observed area / outline length."""
    return np.asarray(view_costs, float) * np.asarray(areas, float) / np.asarray(lengths, float)


STRIP_PLATE_MAX_PX = 4.5
"""The strip's offsets stand for the plate chain's (:func:`explaining_offsets`) only where
the plate chain's worst view is within this mean boundary distance [px]: the plate chain is
the shape a robot plans around (its faces are kept clear of the open gripper), and may not
be far off where the strip is not."""


def view_offsets(view_costs: np.ndarray, observed: Sequence[np.ndarray], models: Sequence[np.ndarray]) -> np.ndarray:
    """(views,) mean boundary distance [px] of the model silhouettes ``models`` whose eq.-7
    costs are ``view_costs`` against ``observed`` (uint8 0/1 crops): the outline length is
    the shorter of the two (a mask of noise has a huge outline, the model's stays a tape's)."""
    areas, lengths = sizes(observed)
    return boundary_offsets(view_costs, areas, np.minimum(lengths, sizes(models)[1]))


def box_edge_offsets(views: Sequence[View], boxes: Sequence[Box], observed: Sequence[np.ndarray],
                     models: Sequence[np.ndarray], origins: Sequence[tuple[int, int]],
                     offsets_px: np.ndarray) -> np.ndarray:
    """``offsets_px`` (views,), where a view is not explained by them (above POOR_OFFSET_PX),
    without the share of the pixels where the view and the model disagree that lies within
    BOX_OUTLINE_PX of a scene box's projected outline: there a few pixels of where the tape
    comes out from behind the box are the box's pose and the calibration, known to a few
    pixels, not the shape (the fit's ``box_edge_px`` alike). part-988045 was "not
    explained" at 3.3 px with its tip 0.4 mm off. ``observed``, ``models``: uint8 0/1 crops
    with top-left pixels ``origins``."""
    out = np.array(offsets_px, float)
    if not boxes:
        return out
    for k in np.nonzero(out > POOR_OFFSET_PX)[0]:
        diff = cv2.bitwise_xor(observed[k], models[k])
        total = cv2.countNonZero(diff)
        if total:
            near = box_outline_mask(views[k].camera, boxes, diff.shape, origins[k], BOX_OUTLINE_PX)
            out[k] *= cv2.countNonZero(cv2.bitwise_and(diff, 1 - near)) / total
    return out


def explaining_offsets(plate_offsets: np.ndarray, strip_offsets: Callable[[], np.ndarray] | None) -> np.ndarray:
    """The per-view mean boundary distances [px] that judge whether the estimate explains
    the views: the plate chain's, or, where they leave a view unexplained (above
    POOR_OFFSET_PX, up to STRIP_PLATE_MAX_PX), the strip's (the continuous strip the tip
    frame comes from, computed only then) if its worst view is better explained. A 30 mm
    plate cannot follow a tape that bends within its length, so a right fit's plate chain
    may miss a bent stretch's outline by several pixels that the strip follows. (An "ok"
    this gives gets the estimator's second look, as an unsure estimate does.)"""
    worst = float(np.max(plate_offsets))
    if strip_offsets is None or not POOR_OFFSET_PX < worst <= STRIP_PLATE_MAX_PX:
        return plate_offsets
    strip = np.asarray(strip_offsets(), float)
    return strip if np.max(strip) < np.max(plate_offsets) else plate_offsets


def end_points(tip_position: np.ndarray, tip_rotation: np.ndarray, width: float) -> np.ndarray:
    """(k, 3) world points of the free end: the centre line's last TIP_SPAN_M and the tip's
    two corners."""
    back = tip_position - TIP_SPAN_M * tip_rotation[:, 0]
    t = np.linspace(0.0, 1.0, 6)[:, None]
    line = back + t * (tip_position - back)
    half = 0.5 * width * tip_rotation[:, 1]
    return np.vstack([line, tip_position + half, tip_position - half])


BASE_OFFSET_PX = 3.0
"""An "ok" estimate is a ``poor_fit`` where, in a view, the observed tape around the tape's
base (where it is stuck, known from the cell file) lies more than this [px] mean boundary
distance from the model's: the base cannot move, so a misfit there is the camera's
calibration (or the cell file's base) being off, and the fitted shape bends to make up for
it elsewhere. On 2026-11-27, simulated captures (975000-975019, 2 and 3 cameras) with every
camera turned by 0.5 deg (`calib_rot_deg`) showed 4.3-11.1 px in their worst view, and 12 of
them were "ok" 4.0-12.1 mm off at 4.8-9.0 px (3 of 29 "ok" grasps of a sweep were 11-14 mm
off); with the true cameras the worst view showed 1.7 px; synthetic captures of every kind
(964000-) at most 3.4 px among "ok" (part, where the box hides the base). Turned by 0.3 deg
(a sweep's 21 episodes, 977000-977010, 2 and 3 cameras), estimates 1.2-4.9 mm off showed
3.5-5.2 px: 3.5 px, tried first, refused 9 of them; 4.5 px refuses 4 (4.5-5.2 px, 1.3-4.9 mm
off) and still every "ok" of the 0.5 deg set.
3.0 px since 2026-11-27: a fresh sweep with every camera turned 0.5 deg (1015000-1015019)
grasped on two 2-camera "ok"s 10.2 and 13.7 mm off whose bases showed 3.5 and 4.0 px (0.2
px with the true cameras); on turned simulated captures (976000- and 981000-, 0.5 deg and 2
px, 2 and 3 cameras, chain and shell tape, 130 each) 3.0 px left no "ok" more than 10 mm
off (4.5 px: two, 11.6 and 12.8 mm) and one more than 5 mm off in each (4.5 px: 6 and 9),
and with three cameras it sends more answers through the cameras' correction, whose tips
come closer (e.g. 3.5 -> 0.6 mm); on calibrated captures of every bench kind (the same
ranges, ~540 each) it changed no answer. 2.5 px moved two corrected 3-camera answers
further off (0.55 -> 1.53, 2.21 -> 3.04 mm); 2.0 px refused right ones. What it costs: with
two cameras, answers turned 0.3 deg (3.5-5.2 px above, 1.2-4.9 mm off) are refused rather
than grasped (since 2026-11-27, the twentieth session, two cameras are corrected from the
views too, anchored at this base: ``estimator.recalibrate``); and a calibrated part capture whose base the
part half hides can show 3-3.4 px (part-891011, 3.1 px, 3 cameras, refused; none in
976000-/981000-)."""
BASE_WINDOW_PX = 40
"""... measured within this radius [px] of the base's projection ..."""
BASE_OCCLUDED_PX = 12
"""... not within this [px] of where a scene box (or an ignore mask) hides the model (the
outline there is the occluder's: a synthetic part capture's coarse occlusion showed 8 px) ..."""
BASE_MIN_OUTLINE_PX = 10
"""... and only where at least this many outline pixels of the observed tape remain."""


def base_offsets(views: Sequence[View], base_position: np.ndarray, observed: Sequence[np.ndarray],
                 models: Sequence[np.ndarray], unoccluded: Sequence[np.ndarray],
                 origins: Sequence[tuple[int, int]]) -> np.ndarray:
    """(views,) mean boundary distance [px] between the observed silhouette and the model's
    around the tape's base (BASE_WINDOW_PX), where no occluder hides the model (``models``:
    the model as seen, ``unoccluded``: as if no box or ignore mask hid it; uint8 0/1 crops
    at ``origins``, as :func:`assess` takes them): the XOR pixels over the observed
    outline's length there; 0 for a view with too little observed outline there
    (BASE_MIN_OUTLINE_PX). (The longer of the observed and the model's outlines as the
    divisor, tried after review, let 4 of the 12 "ok" estimates of 975000- turned 0.5 deg
    through, 5.5-9.3 mm off.)"""
    out = np.zeros(len(views))
    k3 = np.ones((3, 3), np.uint8)
    kb = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BASE_OCCLUDED_PX + 1, 2 * BASE_OCCLUDED_PX + 1))
    for k, (v, o, m, full, (x0, y0)) in enumerate(zip(views, observed, models, unoccluded, origins)):
        col, row = v.camera.project(np.asarray(base_position, float)[None])[0] - (x0, y0)
        if not (np.isfinite(col) and np.isfinite(row)):
            continue
        # Every count is within BASE_WINDOW_PX of the base: the crops' window around it (the
        # erosion and the dilation read their neighbourhoods from margins around it, the
        # same pixels as on the whole crop).
        h, w = o.shape
        wx0, wx1 = max(0, int(np.floor(col)) - BASE_WINDOW_PX), min(w, int(np.ceil(col)) + BASE_WINDOW_PX + 1)
        wy0, wy1 = max(0, int(np.floor(row)) - BASE_WINDOW_PX), min(h, int(np.ceil(row)) + BASE_WINDOW_PX + 1)
        if wx1 <= wx0 or wy1 <= wy0:
            continue
        window = (slice(wy0, wy1), slice(wx0, wx1))
        yy, xx = np.ogrid[window]
        near = (xx - col) ** 2 + (yy - row) ** 2 <= BASE_WINDOW_PX ** 2
        around, inner = _margin(window, BASE_OCCLUDED_PX + 1, (h, w))
        hid = (full[around].astype(bool) & ~m[around].astype(bool)).astype(np.uint8)
        if hid.any():
            near &= ~cv2.dilate(hid, kb)[inner].astype(bool)
        around, inner = _margin(window, 1, (h, w))
        eroded = cv2.erode(o[around].astype(np.uint8), k3)[inner]
        obs = o[window].astype(bool)
        outline = int(np.count_nonzero(obs & ~eroded.astype(bool) & near))
        if outline >= BASE_MIN_OUTLINE_PX:
            out[k] = np.count_nonzero((obs ^ m[window].astype(bool)) & near) / outline
    return out


def _margin(window: tuple[slice, slice], margin: int, shape: tuple[int, int]) -> tuple[tuple, tuple]:
    """The crop ``window`` (rows, columns) grown by ``margin`` px within an array of
    ``shape``, and the window's place in it: a filter run on the grown crop gives, at the
    window's pixels, what it gives on the whole array."""
    (rows, cols), (h, w) = window, shape
    y0, x0 = max(0, rows.start - margin), max(0, cols.start - margin)
    grown = (slice(y0, min(h, rows.stop + margin)), slice(x0, min(w, cols.stop + margin)))
    return grown, (slice(rows.start - y0, rows.stop - y0), slice(cols.start - x0, cols.stop - x0))


def end_offsets(views: Sequence[View], observed: Sequence[np.ndarray], models: Sequence[np.ndarray],
                origins: Sequence[tuple[int, int]], tip_position: np.ndarray) -> np.ndarray:
    """(views,) mean boundary distance [px] within END_WINDOW_PX of the tip's projection:
    how well the free end itself is explained in each view (inf where it projects outside
    the crops). ``observed``, ``models``: uint8 crops with top-left pixels ``origins``."""
    out = np.full(len(views), np.inf)
    r = END_WINDOW_PX
    for k, v in enumerate(views):
        uv = v.camera.project(np.asarray(tip_position, float)[None])[0]
        if not np.all(np.isfinite(uv)):
            continue
        x0, y0 = origins[k]
        u, w = int(round(uv[0])) - x0, int(round(uv[1])) - y0
        o, m = observed[k], models[k]
        h, wd = o.shape
        a0, a1, b0, b1 = max(0, w - r), min(h, w + r + 1), max(0, u - r), min(wd, u + r + 1)
        if a1 <= a0 or b1 <= b0:
            continue
        ow, mw = o[a0:a1, b0:b1], m[a0:a1, b0:b1]
        xor = float(cv2.countNonZero(cv2.bitwise_xor(ow, mw)))
        # Over the longer outline, and at least the window's width: a silhouette seen
        # edge-on, a line of a pixel or two that segmentation breaks up, has almost no
        # outline to divide by.
        length = max(_outline(ow)[1] if ow.any() else 0.0, _outline(mw)[1] if mw.any() else 0.0, 2.0 * r)
        out[k] = xor / length
    return out


def _unexplained_mask(observed: np.ndarray, model: np.ndarray) -> np.ndarray:
    """uint8 0/1: the observed tape farther than UNEXPLAINED_MARGIN_PX from the model's
    silhouette (uint8 0/1 crops alike)."""
    k = np.ones((2 * UNEXPLAINED_MARGIN_PX + 1,) * 2, np.uint8)
    return cv2.bitwise_and(observed, cv2.bitwise_not(cv2.dilate(model, k)) & 1)


def unexplained_px(observed: np.ndarray, model: np.ndarray, tip_px: np.ndarray,
                   trunk_px: np.ndarray | None = None) -> float:
    """The longest region [px] (its bounding box's longer side) of observed tape farther than
    UNEXPLAINED_MARGIN_PX from the model's silhouette that reaches within END_WINDOW_PX of
    the tip's projection ``tip_px`` (crop coordinates). With ``trunk_px`` (the image
    direction of the tape's last centimetre towards the tip), the farthest distance from the
    tip of its pixels ahead of the tip along it: how far the tape goes on past the model's
    end (a region beside the end, where a plate cuts across a curl of the body, does not
    count for its length behind the tip). uint8 0/1 crops alike. See :func:`unexplained`."""
    regions, ahead, _ = unexplained(observed, model, tip_px, trunk_px)
    return regions if trunk_px is None else ahead


def unexplained(observed: np.ndarray, model: np.ndarray, tip_px: np.ndarray,
                trunk_px: np.ndarray | None = None, half_edge_px: np.ndarray | None = None) -> tuple[float, float, float]:
    """The measures of :func:`unexplained_px` in one pass: (the longest region's bounding
    box side, how far tape goes on ahead of the tip along ``trunk_px``) [px]; the second is
    the first where the trunk's direction is unknown (None, or an end seen end-on: every
    region counts as past the end). Third, the longest region's side among those that
    depart from the model's silhouette by more than LOCATE_BAND_PX somewhere (a band along
    the model's edge, within it everywhere, is the model's edge a few pixels off, not tape
    the model leaves out: see LOCATE_UNEXPLAINED_PX); a region's departure is taken over all
    of it, also where it lies far from the tip (which errs towards counting it). ``half_edge_px``: the image vector
    from the tip to one corner of the tip edge; with it, the distance ahead is taken from
    the tip edge (the segment between the corners), not from its middle: a thin band of tape along the tip
    edge (an end edge a little curved or tilted against the model's straight one, as a
    shell tape's) goes on a few pixels past the end, not half the tape's width. (The
    reverse, model over background there, was measured and dropped: an edge-on end is a
    thin line whose offset of a few pixels leaves 40-70 px long slivers on good fits, and
    it caught no wrong fit.)"""
    if not np.all(np.isfinite(tip_px)):
        return 0.0, 0.0, 0.0
    h, w = observed.shape
    u, v = int(round(tip_px[0])), int(round(tip_px[1]))
    r = END_WINDOW_PX
    a0, a1, b0, b1 = max(0, v - r), min(h, v + r + 1), max(0, u - r), min(w, u + r + 1)
    if a1 <= a0 or b1 <= b0:
        return 0.0, 0.0, 0.0
    extra = _unexplained_mask(observed, model)
    if cv2.countNonZero(extra[a0:a1, b0:b1]) == 0:
        return 0.0, 0.0, 0.0
    _, labels, stats, _ = cv2.connectedComponentsWithStats(extra, connectivity=8)
    from_model = None
    along = None
    if trunk_px is not None and np.all(np.isfinite(trunk_px)) and np.linalg.norm(trunk_px) >= MIN_TRUNK_PX:
        along = np.asarray(trunk_px, float) / np.linalg.norm(trunk_px)
    longest = ahead = departing = 0.0
    for label in np.unique(labels[a0:a1, b0:b1]):
        x, y, bw, bh, area = stats[label]
        if not label or area < UNEXPLAINED_MIN_AREA_PX:
            continue
        longest = max(longest, float(max(bw, bh)))
        inside = labels[y:y + bh, x:x + bw] == label
        if from_model is None:
            # Each pixel's Euclidean distance [px] from the model's silhouette (exact, not
            # the 3x3 mask's approximation, which errs by up to 0.4 px at this range; a
            # model that covers nothing: far).
            from_model = (cv2.distanceTransform((model == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                          if model.any() else np.full(model.shape, np.inf, np.float32))
        if float(from_model[y:y + bh, x:x + bw][inside].max()) > LOCATE_BAND_PX:
            departing = max(departing, float(max(bw, bh)))
        if along is not None:
            ys, xs = np.nonzero(inside)
            d = np.column_stack([xs + x - tip_px[0], ys + y - tip_px[1]])
            d = d[d @ along >= 0.0]
            if len(d):
                ahead = max(ahead, float(_from_segment(d, _across(half_edge_px, along, trunk_px)).max()))
    return longest, (longest if along is None else ahead), departing


def _across(half: np.ndarray | None, along: np.ndarray, trunk_px: np.ndarray) -> np.ndarray | None:
    """The part of the tip edge's half vector ``half`` [px] square to the trunk's image
    direction ``along`` (unit), at most HALF_EDGE_MAX times the projected ``trunk_px``'s
    length: a tip edge seen edge-on projects along the trunk, and tape past the end along it
    must count in full; a corner projected near the camera's plane is not a measure."""
    if half is None or not np.all(np.isfinite(half)):
        return None
    across = np.asarray(half, float) - (np.asarray(half, float) @ along) * along
    cap = HALF_EDGE_MAX * float(np.linalg.norm(trunk_px))
    size = float(np.linalg.norm(across))
    return across if size <= cap else across * (cap / size)


HALF_EDGE_MAX = 3.0
"""The tip edge's half vector in the image counts up to this many times the projected
length of the trunk's last 10 mm (the tape's half width is 15 mm: 1.5 times, foreshortened
alike)."""


def _from_segment(d: np.ndarray, half: np.ndarray | None) -> np.ndarray:
    """Distances [px] of image offsets ``d`` (k, 2) from the tip to the segment from -half
    to +half (the tip edge, finite: see :func:`_across`; a point where ``half`` is None)."""
    if half is None or float(half @ half) < 1e-9:
        return np.linalg.norm(d, axis=1)
    t = np.clip(d @ half / float(half @ half), -1.0, 1.0)
    return np.linalg.norm(d - t[:, None] * np.asarray(half, float), axis=1)


THIN_END_PX = 2.0
"""A view whose observed tape is at most this many pixels thick (half-width: the largest
distance to background) everywhere within END_WINDOW_PX of the tip's projection sees the
end edge-on: every pixel of a 1-3 px sliver is on its outline, so the tip edge's middle
"on the outline" says nothing about where along the sliver the end is (a wrong "ok"
12.9 mm off, its model end 25 px short of the sliver's)."""


def _thin_at(observed: np.ndarray, origin: tuple[int, int], tip_px: np.ndarray) -> bool:
    """Is the observed tape within END_WINDOW_PX of ``tip_px`` (image pixels) a sliver?"""
    h, w = observed.shape
    u, v = int(round(tip_px[0])) - origin[0], int(round(tip_px[1])) - origin[1]
    r = END_WINDOW_PX
    a0, a1, b0, b1 = max(0, v - r), min(h, v + r + 1), max(0, u - r), min(w, u + r + 1)
    if a1 <= a0 or b1 <= b0:
        return False
    window = np.ascontiguousarray(observed[a0:a1, b0:b1])
    if not window.any():
        return False
    half = cv2.distanceTransform(np.pad(window, 1), cv2.DIST_L2, 3)
    return float(half.max()) <= THIN_END_PX


SLIVER_STRAY_PX = 2
"""A sliver view (see THIN_END_PX) locates the end only where the model explains that view
whole: at most this many of its observed pixels lie farther than UNEXPLAINED_MARGIN_PX from
the model's silhouette; and another view locates the end without being a sliver (nothing
near its end left unexplained, LOCATE_UNEXPLAINED_PX). (A thinning sliver's end is where
segmentation loses it, not necessarily the tape's: a wrong "ok" 81 mm off had its model end
where the sliver broke into dots, and with the episodes' segmentation, which drops the dots,
its sliver ended there cleanly; the other view's observed end, 100 px beyond the model's,
was unexplained, so that view did not locate the end.) Until 2026-11-26 every view had to be
explained whole: on fresh simulated captures (880000, 2 cameras) 4 of 30, their ends within
1 mm, were "hidden" for 20-46 observed pixels the plate chain left out along the body in the
locating view."""


def _explained(observed: np.ndarray, model: np.ndarray) -> bool:
    """Is every observed pixel but SLIVER_STRAY_PX within UNEXPLAINED_MARGIN_PX of the
    model's silhouette? uint8 0/1 crops alike."""
    return cv2.countNonZero(_unexplained_mask(observed, model)) <= SLIVER_STRAY_PX


def _near_background(observed: np.ndarray, x: int, y: int, r: int) -> bool:
    """Is there observed background within ``r`` px (a square) of crop pixel (x, y)? (The
    crop's outside counts as background.)"""
    h, w = observed.shape
    x0, x1, y0, y1 = x - r, x + r + 1, y - r, y + r + 1
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return True
    return bool((observed[y0:y1, x0:x1] == 0).any())


@functools.lru_cache(maxsize=8)
def _disc(r: float) -> np.ndarray:
    """(2k+1, 2k+1) bool: the offsets within ``r`` px (Euclidean) of the centre, k = floor(r)."""
    k = int(np.floor(r))
    dy, dx = np.mgrid[-k:k + 1, -k:k + 1]
    return dx * dx + dy * dy <= r * r


_NEAR_CUT = np.argwhere(_disc(BOX_CUT_RING_PX + 2))[:, ::-1] - int(np.floor(BOX_CUT_RING_PX + 2))
"""(m, 2) the pixel offsets (dx, dy) :func:`box_cuts` looks at around an outline pixel."""


def _background_within(observed: np.ndarray, x: int, y: int, r: float) -> bool:
    """Is there observed background within ``r`` px (Euclidean: a disc) of crop pixel (x,
    y)? (The crop's outside counts as background.)"""
    h, w = observed.shape
    k = int(np.floor(r))
    if x - k < 0 or y - k < 0 or x + k + 1 > w or y + k + 1 > h:
        return True
    return bool((observed[y - k:y + k + 1, x - k:x + k + 1][_disc(r)] == 0).any())


def _near_tape(observed: np.ndarray, x: int, y: int, r: int) -> bool:
    """Is there observed tape within ``r`` px (a square) of crop pixel (x, y)?"""
    h, w = observed.shape
    x0, x1, y0, y1 = max(0, x - r), min(w, x + r + 1), max(0, y - r), min(h, y + r + 1)
    return x1 > x0 and y1 > y0 and bool(observed[y0:y1, x0:x1].any())


def _on_outline(view: View, observed: np.ndarray, origin: tuple[int, int], points: np.ndarray,
                boxes: Sequence[Box] = ()) -> bool:
    """Does the tip edge lie at the observed outline (:func:`outline_rule`)?"""
    return bool(outline_rule(view, observed, origin, points, boxes))


def outline_rule(view: View, observed: np.ndarray, origin: tuple[int, int], points: np.ndarray,
                 boxes: Sequence[Box] = ()) -> str:
    """Which rule puts the tip edge at the observed outline: "edge", "hook", "hook_across"
    (a hooked end whose tip edge has both corners within EDGE_PX of background but not its
    middle), or "" (none). Does the tip edge (``points`` (k, 3), k odd, evenly from one corner to the other)
    lie at the observed outline? Either its middle and both corners project within EDGE_PX
    of observed background (one corner on the outline and the rest running into the body
    is an end over the body), or a stretch of it from a corner, at least EDGE_RUN_FRACTION
    of its width, lies within EDGE_RUN_PX (Euclidean) of it and EDGE_RUN_TAPE_PX of observed
    tape, on the outline (an end
    hooked over the body: part of its edge is seen against the background, the rest over
    the body); the stretch is tested at its sample points only (with 9 points: the corner
    and the point an eighth of the width in). (A tape seen end-on puts its
    corners near the outline and its middle inside the silhouette, where nothing locates
    the end.) A point within BOX_OUTLINE_PX of a scene box's projected outline does not
    count (the silhouette's edge there may be the box's, where the tape goes behind it: a
    wrong "ok" 41 mm off laid its tip edge along the part's edge), nor, for the stretch,
    within EDGE_RUN_GAP_PX more."""
    uv = view.camera.project(points)
    k = len(points)
    near_box = box_outline_px(view.camera, boxes, uv)
    loose, tight = [], []
    for (u, v), box in zip(uv, near_box):
        if not (np.isfinite(u) and np.isfinite(v)):
            loose.append(False)
            tight.append(False)
            continue
        x, y = int(round(u)) - origin[0], int(round(v)) - origin[1]
        loose.append(box >= BOX_OUTLINE_PX and _near_background(observed, x, y, EDGE_PX))
        # On the outline: background within EDGE_RUN_PX (Euclidean) and observed tape within
        # EDGE_RUN_TAPE_PX (a model edge out over the background is no edge seen).
        tight.append(box >= BOX_OUTLINE_PX + EDGE_RUN_GAP_PX and _background_within(observed, x, y, EDGE_RUN_PX)
                     and _near_tape(observed, x, y, EDGE_RUN_TAPE_PX))
    if loose[k // 2] and loose[0] and loose[-1]:
        return "edge"
    run = int(np.ceil(EDGE_RUN_FRACTION * (k - 1))) + 1
    long_enough = [np.linalg.norm(uv[a] - uv[b]) >= EDGE_RUN_MIN_PX for a, b in ((0, run - 1), (k - 1, k - run))]
    if (all(tight[:run]) and long_enough[0]) or (all(tight[k - run:]) and long_enough[1]):
        return "hook_across" if loose[0] and loose[-1] else "hook"
    return ""


def _visible(view: View, points: np.ndarray, boxes: Sequence[Box]) -> np.ndarray:
    """(k,) which of ``points`` (k, 3) ``view`` sees: in front of the camera and inside its
    image, not on ignored pixels, in front of every scene box."""
    cam = view.camera
    uv = cam.project(points)
    ok = np.all(np.isfinite(uv), axis=1) & (cam.to_camera(points)[:, 2] > 0)
    u = np.where(ok, np.rint(uv[:, 0]), -1).astype(int)
    v = np.where(ok, np.rint(uv[:, 1]), -1).astype(int)
    ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    if view.ignore is not None:
        ok[ok] &= ~view.ignore[v[ok], u[ok]]
    if boxes:
        ok &= ~hidden(cam.center, points, boxes)
    return ok


BORDER_CLEAR_PX = 20.0
"""A view does not locate the end where observed tape on the image's border lies within this
many pixels of the tip edge's projection: the tape leaves the image there and may go on out
of view (a wrong "ok" 49 mm off on a fresh shell capture: the tape left all three images at
the bottom, and the model's last plate, turned along the outline, ended at the border)."""
BORDER_RUN_FRACTION = 0.5
"""... unless the tape on the border near the tip edge (within BORDER_CLEAR_PX plus the tip
edge's length of it, ignored pixels on the border counted as tape) is shorter than this
fraction of the tip edge's length in the image: a corner of the end touching the border,
not the tape crossing it (which takes about its width: 51-77 px against a 59-79 px
tip edge in that wrong "ok"; a corner touched 1-14 px against 34-61 px in shell-963019, a
needless "hidden" 0.4-0.7 mm off, before 2026-11-27)."""


def _clear_of_border(view: View, observed: np.ndarray, origin: tuple[int, int], points: np.ndarray) -> bool:
    """Is the tape clear of the image's border at the tip edge ``points`` (k, 3, from one
    corner to the other)? Not where observed tape on the border lies within BORDER_CLEAR_PX
    of the tip edge's projection and the tape on the border within BORDER_CLEAR_PX plus the
    tip edge's length of it is at least BORDER_RUN_FRACTION of that length: the tape may
    cross the border there. Ignored pixels on the border count as tape (the tape may lie
    under them), and the border's sides are counted together (a band crossing an image
    corner). ``observed``: the view's silhouette crop whose top-left pixel is ``origin``."""
    cam = view.camera
    (h, w), (x0, y0) = observed.shape, origin
    if x0 > 0 and y0 > 0 and x0 + w < cam.width and y0 + h < cam.height:
        return True                       # the crop touches no image border
    # The crop's pixels on the image's border (image coordinates, each once).
    xs, ys = np.arange(x0, x0 + w), np.arange(y0, y0 + h)
    sides = [np.column_stack([xs, np.full(w, y)]) for y in (0, cam.height - 1) if y0 <= y < y0 + h]
    sides += [np.column_stack([np.full(h, x), ys]) for x in (0, cam.width - 1) if x0 <= x < x0 + w]
    pixels = np.unique(np.vstack(sides), axis=0)
    tape = observed[pixels[:, 1] - y0, pixels[:, 0] - x0] > 0
    if not tape.any():
        return True
    uv = cam.project(points)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if not len(uv):
        return False
    d = np.linalg.norm(pixels[:, None, :] - uv[None, :, :], axis=2).min(axis=1)
    if d[tape].min() > BORDER_CLEAR_PX:
        return True
    # The length counts ignored pixels on the border as tape.
    counted = tape | view.ignore[pixels[:, 1], pixels[:, 0]] if view.ignore is not None else tape
    edge_px = float(np.linalg.norm(uv[-1] - uv[0]))
    return bool(np.count_nonzero(counted & (d <= BORDER_CLEAR_PX + edge_px)) < BORDER_RUN_FRACTION * edge_px)


def _continuation_visible(view: View, boxes: Sequence[Box], tip_position: np.ndarray,
                           tip_rotation: np.ndarray, width: float, observed: np.ndarray | None = None,
                           origin: tuple[int, int] = (0, 0)) -> bool:
    """Would most points BEYOND_M past the tip edge (its middle and near its corners) be
    seen by ``view`` (see :func:`_visible`)? Or, where they would not, does the view show
    background past the tip before the occluder (``observed``: the view's silhouette crop
    whose top-left pixel is ``origin``): walking out from the tip edge along the trunk, on
    at least two of three lines, a seen pixel of background comes before any point the view
    cannot see (the silhouette ends short of the image's border, the box or the ignored
    pixels, so its end is the tape's)."""
    across = np.outer([-0.4, 0.0, 0.4], width * tip_rotation[:, 1])
    points = np.vstack([tip_position + d * tip_rotation[:, 0] + across for d in BEYOND_M])
    if int(np.count_nonzero(_visible(view, points, boxes))) > len(points) // 2:
        return True
    if observed is None:
        return False
    steps = np.linspace(0.0, BEYOND_M[-1], CONTINUATION_STEPS + 1)[1:]
    lines = (tip_position + across[:, None, :] + steps[None, :, None] * tip_rotation[:, 0]).reshape(-1, 3)
    seen = _visible(view, lines, boxes).reshape(len(across), -1)
    uv = view.camera.project(lines)
    # Background a few pixels short of a box's outline may be the box hiding the tape
    # (segmentation loses a pixel or two at an occluding edge; the box's pose and the
    # calibration are known to a few pixels): only background clear of every box's outline
    # and of the image's border counts.
    clear = box_outline_px(view.camera, boxes, uv) >= BOX_OUTLINE_PX + CONTINUATION_GAP_PX
    clear &= ((uv[:, 0] >= CONTINUATION_GAP_PX) & (uv[:, 0] < view.camera.width - CONTINUATION_GAP_PX)
              & (uv[:, 1] >= CONTINUATION_GAP_PX) & (uv[:, 1] < view.camera.height - CONTINUATION_GAP_PX))
    clear = clear.reshape(len(across), -1)
    uv = uv.reshape(len(across), -1, 2)
    h, w = observed.shape
    ended = 0
    for line_seen, line_clear, line_uv in zip(seen, clear, uv):
        for ok, free, (u, v) in zip(line_seen, line_clear, line_uv):
            if not ok:
                break
            x, y = int(round(u)) - origin[0], int(round(v)) - origin[1]
            if free and (not (0 <= x < w and 0 <= y < h) or observed[y, x] == 0):
                ended += 1
                break
    return ended >= 2


def seeing_views(views: Sequence[View], points: np.ndarray, boxes: Sequence[Box]) -> list[bool]:
    """Per view: does it see at least TIP_SEEN_FRACTION of ``points`` (k, 3)?"""
    return [bool(_visible(v, points, boxes).mean() >= TIP_SEEN_FRACTION) for v in views]


def assess(views: Sequence[View], boxes: Sequence[Box], width: float, view_costs: np.ndarray,
           observed: Sequence[np.ndarray], models: Sequence[np.ndarray], origins: Sequence[tuple[int, int]],
           tip_position: np.ndarray, tip_rotation: np.ndarray, best_cost: float,
           alternatives: Sequence[tuple[float, np.ndarray]],
           strip_offsets: Callable[[], np.ndarray] | None = None,
           cut_px: Callable[[int], float] | None = None) -> Judgement:
    """The whole judgement of an estimate (see the module's text). ``observed``, ``models``:
    each view's observed silhouette (ignored pixels cleared) and the estimate's, as uint8
    0/1 crops whose top-left pixels are ``origins``; ``view_costs``: eq. 7 per view.
    ``strip_offsets``: () -> the per-view mean boundary distances [px] of the strip the tip
    frame comes from (the estimator's strip stage), which stand for the plate chain's where
    these do not explain a view and the strip's worst view is better explained (see
    :func:`explaining_offsets`). ``cut_px``: view k -> :func:`unexplained_cut_px` of the
    estimate in it (asked only of views that would locate the end; None: no scene boxes)."""
    plate_offsets = box_edge_offsets(views, boxes, observed, models, origins,
                                     view_offsets(view_costs, observed, models))
    offsets = explaining_offsets(plate_offsets, strip_offsets)
    seen = seeing_views(views, end_points(tip_position, tip_rotation, width), boxes)
    edge = tip_position + np.outer(np.linspace(-0.5, 0.5, 9), width * tip_rotation[:, 1])
    rules = [outline_rule(v, o, xy, edge, boxes) if s_ else "" for s_, v, o, xy in zip(seen, views, observed, origins)]
    seen = [bool(r) and _continuation_visible(v, boxes, tip_position, tip_rotation, width, o, xy)
            for r, v, o, xy in zip(rules, views, observed, origins)]
    # Observed tape near the tip that the model leaves unexplained, per view that sees the
    # end: the regions of it that depart from the model beyond a band along its edge
    # (LOCATE_BAND_PX), and how far any of it goes on past the tip.
    back = tip_position - 0.010 * tip_rotation[:, 0]
    corner = tip_position + 0.5 * width * tip_rotation[:, 1]
    extra, beyond, tips = [], [], []
    for s_, v, o, m, xy in zip(seen, views, observed, models, origins):
        uv = v.camera.project(np.vstack([tip_position, back, corner]))
        tips.append(uv[0])
        _, ahead, regions = (unexplained(o, m, uv[0] - np.asarray(xy, float), uv[0] - uv[1], uv[2] - uv[0])
                             if s_ else (0.0, 0.0, 0.0))
        extra.append(regions)
        beyond.append(ahead)
    # A view locates the end (counts towards the two) where little near it is left
    # unexplained (LOCATE_UNEXPLAINED_PX) and it does not see the end edge-on as a sliver; a view that sees the end
    # but does not locate it is still held against the model below. (A sliver whose end
    # coincides with the model's was tried as locating the end: on fresh shell captures it
    # let through an "ok" 81 mm off.)
    cuts: dict[int, float] = {}

    def clear_of_boxes(k: int) -> bool:
        if cut_px is None:
            return True
        cuts[k] = cut_px(k)
        return cuts[k] < BOX_CUT_PX

    candidates = [s_ and x <= LOCATE_UNEXPLAINED_PX and _clear_of_border(v, o, xy, edge) and clear_of_boxes(k)
                  for k, (s_, x, v, o, xy) in enumerate(zip(seen, extra, views, observed, origins))]
    thin = [c and _thin_at(o, xy, tip) for c, o, xy, tip in zip(candidates, observed, origins, tips)]
    locates = [c and not t for c, t in zip(candidates, thin)]
    if any(locates) and any(thin):
        # A sliver view counts where another view locates the end and the model explains
        # the sliver view whole (SLIVER_STRAY_PX).
        locates = [lo or (t and _explained(o, m)) for lo, t, o, m in zip(locates, thin, observed, models)]
    ends = end_offsets(views, observed, models, origins, tip_position)
    verdict, reason = judge(offsets, sum(locates), best_cost, tip_position, alternatives)
    behind = [k for k, n in cuts.items() if n >= BOX_CUT_PX]
    if verdict is Verdict.HIDDEN and behind:
        reason += "; " + ", ".join(f"view {k} {BEHIND_BOX} ({cuts[k]:.0f} px along it)" for k in behind)
    if verdict is not Verdict.POOR_FIT:
        for k, tape in enumerate(beyond):
            if tape > UNEXPLAINED_PX:
                verdict, reason = Verdict.POOR_FIT, (
                    f"view {k} {PAST_END} over {tape:.0f} px (> {UNEXPLAINED_PX} px)")
                break
    parallax = _parallax_deg([v.camera.center for v, s_ in zip(views, locates) if s_], tip_position)
    if verdict is Verdict.OK and parallax < MIN_PARALLAX_DEG:
        verdict, reason = Verdict.AMBIGUOUS, (f"the cameras that see the free end look at it from directions "
                                              f"{parallax:.1f} deg apart (< {MIN_PARALLAX_DEG:g}): its depth is "
                                              f"undetermined")
    bad_end = [k for k in range(len(views)) if seen[k] and ends[k] > END_OFFSET_PX]
    if verdict is not Verdict.POOR_FIT and bad_end:
        k = bad_end[0]
        verdict, reason = Verdict.POOR_FIT, (f"view {k} {END_UNEXPLAINED}: mean boundary distance "
                                             f"{ends[k]:.1f} px around the tip > {END_OFFSET_PX:g} px")
    across = any(lo and r == "hook_across" for lo, r in zip(locates, rules))
    return Judgement(verdict, reason, sum(locates), offsets, offsets is not plate_offsets, across)


def end_on(view: View, tip_position: np.ndarray, tip_rotation: np.ndarray) -> bool:
    """Does ``view`` see the estimated end along its trunk (within END_ON_DEG of its line of
    sight)? Its silhouette then holds the end's depth along that line open."""
    ray = np.asarray(tip_position, float) - view.camera.center
    cos = abs(float(ray @ tip_rotation[:, 0])) / max(float(np.linalg.norm(ray)), 1e-12)
    return cos > np.cos(np.radians(END_ON_DEG))


def is_close_alternative(cost: float, best_cost: float) -> bool:
    """Does a hypothesis of eq.-11 ``cost`` explain the views nearly as well as the best?"""
    return cost <= AMBIGUOUS_RATIO * best_cost + AMBIGUOUS_ABS


def _parallax_deg(centers: Sequence[np.ndarray], point: np.ndarray) -> float:
    """The widest angle [deg] between two of the rays from ``centers`` to ``point``."""
    rays = [(c - point) / np.linalg.norm(c - point) for c in centers]
    best = 0.0
    for i in range(len(rays)):
        for j in range(i + 1, len(rays)):
            best = max(best, float(np.degrees(np.arccos(np.clip(rays[i] @ rays[j], -1.0, 1.0)))))
    return best


def judge(offsets_px: np.ndarray, tip_views: int, best_cost: float, best_tip: np.ndarray,
          alternatives: Sequence[tuple[float, np.ndarray]]) -> tuple[Verdict, str]:
    """The verdict and its reason from per-view boundary distances [px], the number of
    cameras that see the free end, and the alternatives (eq.-11 cost, tip (3,)) found."""
    worst = int(np.argmax(offsets_px))
    if offsets_px[worst] > POOR_OFFSET_PX:
        return Verdict.POOR_FIT, (f"view {worst} is not explained: mean boundary distance "
                                  f"{offsets_px[worst]:.1f} px > {POOR_OFFSET_PX:g} px")
    if tip_views < 2:
        return Verdict.HIDDEN, f"{tip_views} camera(s) see the free end, 2 needed"
    rival = rival_reason(best_cost, best_tip, alternatives)
    return (Verdict.AMBIGUOUS, rival) if rival else (Verdict.OK, "")


def rival_reason(best_cost: float, best_tip: np.ndarray, alternatives: Sequence[tuple[float, np.ndarray]]) -> str:
    """Why an estimate of eq.-11 cost ``best_cost`` with its tip at ``best_tip`` is
    ambiguous: the first of ``alternatives`` (eq.-11 cost, tip (3,)) whose tip is more than
    DISTINCT_TIP_M away and that explains the views nearly as well; "" when none does."""
    for cost, tip in alternatives:
        d = float(np.linalg.norm(np.asarray(tip) - best_tip))
        if d > DISTINCT_TIP_M and is_close_alternative(cost, best_cost):
            return (f"a shape with its tip {1e3 * d:.0f} mm away explains the views "
                    f"nearly as well (cost {cost:.3f} vs {best_cost:.3f})")
    return ""
