"""The global search: a beam search node by node. Every kept partial chain is extended by a
grid of joint angles; a candidate's score asks that its plate edges lie on the observed
boundary and its centre line inside the silhouette in every view (robust losses), plus a
weak prior on the angles and the penetration of scene boxes; a diverse beam keeps
candidates whose plate ends differ. Complete chains are ranked with their coverage of the
observed outline."""
from __future__ import annotations

import numpy as np

from . import _kernels_beam, _kernels_boxes, reference
from .config import DEFAULT, FitConfig, as_array
from .tape import TapeSpec, joint_rotations
from .views import Field


def diverse(order: np.ndarray, ends: np.ndarray, count: int, cfg: FitConfig = DEFAULT) -> np.ndarray:
    """Up to ``count`` of the candidates ``order`` (best first) whose new plate ends
    (``ends[k]``: centre, left and right corner (3, 3) [m]) lie at least ``cfg.diverse_m``
    from every better kept one's: without this the beam fills with near copies of one chain
    (twist variants of the same bends) and the other bend branch is lost."""
    if cfg.diverse_m <= 0 or len(order) <= count:
        return order[:count]
    if cfg.compiled:
        return _kernels_beam.diverse(order, ends, count, cfg.diverse_m)
    return reference.diverse(order, ends, count, cfg.diverse_m)


def beam_search(spec: TapeSpec, fields: list[Field], grid: np.ndarray | None = None, beam: int | None = None,
                cfg: FitConfig = DEFAULT) -> list[np.ndarray]:
    """Candidate chains (n, 3) from a node-by-node beam search over joint angles ``grid``
    (g, 3; default the config's) keeping ``beam`` partial chains (default the config's),
    best first."""
    grid = cfg.grid_angles() if grid is None else grid
    beam = cfg.beam if beam is None else beam
    edge_t, tip_t, centre_t = as_array(cfg.beam_edge_t), as_array(cfg.tip_t), as_array(cfg.centre_t)
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
    packed = _kernels_beam.pack_views(fields) if cfg.compiled else None
    prior = cfg.angle_prior * np.sum(grid ** 2, axis=1)
    for i in range(n):
        last = i == n - 1
        edge_count = 2 * len(edge_t) + (len(tip_t) if last else 0)
        if cfg.compiled:
            F, ends, pts = _kernels_beam.beam_candidates(np.ascontiguousarray(frames), np.ascontiguousarray(nodes), grid_r, float(spec.segment_lengths[i]), h,
                                                         edge_t, tip_t if last else no_tip, centre_t)
            F = F.reshape(len(nodes), len(grid), 3, 3)
            pts = pts.reshape(len(nodes), len(grid), -1, 3)
        else:
            F, ends, pts = reference.beam_candidates(frames, nodes, grid_r, spec.segment_lengths[i], h, last, cfg)
        boxes = fields[0].boxes if fields else ()
        pen = np.zeros(len(nodes) * len(grid))
        if boxes:
            depth, _ = _kernels_boxes.box_penetration(np.ascontiguousarray(ends.reshape(-1, 3), float),
                                                      *fields[0].box_arrays)   # the plates' end corners
            pen = 1e3 * cfg.beam_penetration * depth.reshape(len(pen), -1).sum(axis=-1)
        count = beam * (4 if last else 1)
        if cfg.compiled:
            # Only the diverse pool's candidates need their totals; the others are cut short,
            # their points scored from the new plate's far end back (where the candidates of
            # one parent differ most).
            along = np.concatenate([edge_t, edge_t, np.ones(len(tip_t)) if last else no_tip, centre_t])
            total = _kernels_beam.beam_totals(fields, packed, pts, edge_count, np.argsort(-along, kind="stable"),
                                              scores, prior, pen, cfg.diverse_pool * count, cfg.delta_out_px,
                                              cfg.delta_in_px)
        else:
            is_edge = np.arange(pts.shape[2]) < edge_count
            plate = np.zeros(pts.shape[:2])
            for f in fields:
                plate += f.weight * reference.beam_edge_cost(f, pts, is_edge, cfg)
            if boxes:
                plate += pen.reshape(plate.shape)
            total = (scores[:, None] + plate + prior[None, :]).reshape(-1)
        ends = ends.reshape(-1, 3, 3)
        keep = diverse(np.argsort(total)[:cfg.diverse_pool * count], ends, count, cfg)
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
    # Outline segments (corner indices into lefts + rights, and -1, -1: always counted): the
    # side, tip and base edges. Unlike the local stage's (FitConfig.crease_t), no joints'
    # lines: the beam scores no point on a joint's line, so a line there could cover the
    # outline while its plates leave the silhouette (with the lines here and in the local
    # stage, before points on them were scored, tuning captures got worse shapes); with the
    # fold test alone here it is not measured.
    seg = np.array([(k, k + 1, -1, -1) for k in range(n)] + [(m + k, m + k + 1, -1, -1) for k in range(n)]
                   + [(n, m + n, -1, -1), (0, m, -1, -1)])
    for f in fields:
        if len(f.outline) == 0:
            continue
        obs = f.outline[::cfg.beam_outline_step]
        cost = (_kernels_beam.beam_outline_cost(f, corners, seg, obs, cfg.delta_out_px) if cfg.compiled
                else reference.beam_outline_cost(f, corners, seg, obs, cfg))
        scores = scores + f.weight * cfg.beam_outline_step * cost
    order = np.argsort(scores)[:beam]
    return [history[k] for k in order]
