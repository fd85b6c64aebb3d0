"""Accuracy and speed of the estimation methods on a set of captures, in one run.

Used by ``scripts/bench_estimator.py`` (and the CLI). Fit times are measured with OpenCV
on one thread, as the targets are stated for one core.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import cv2
import numpy as np

from .capture import Capture, load_capture
from .fit import estimate
from .metrics import errors


@dataclass(frozen=True)
class Row:
    """One capture fitted by one method: errors [mm, deg] and fit time [s]."""

    capture: str
    method: str
    tip_mm: float
    node_max_mm: float
    normal_deg: float
    time_s: float
    cost: float
    cameras: int = 0


def sample_captures(dirs: Sequence[Path]) -> list[Capture]:
    """Every capture (a folder holding capture.json and truth.json) in ``dirs``."""
    out = []
    for d in dirs:
        d = Path(d)
        found = [d] if (d / "capture.json").is_file() else sorted(p.parent for p in d.glob("*/capture.json"))
        out += [load_capture(p) for p in found]
    return [c for c in out if c.truth is not None]


def run(captures: Iterable[tuple[str, Capture]], methods: Sequence[str]) -> list[Row]:
    """Fit every capture with every method (interleaved, so both see the same machine state)."""
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    rows = []
    try:
        for name, capture in captures:
            for method in methods:
                est = estimate(capture, method)
                e = errors(est.nodes, est.tip_rotation, capture.truth)
                rows.append(Row(name, method, 1e3 * e.tip_m, 1e3 * e.node_max_m, e.normal_deg, est.time_s, est.cost,
                                len(capture.views)))
    finally:
        cv2.setNumThreads(previous)
    return rows


def summary(rows: Sequence[Row], methods: Sequence[str], title: str = "") -> str:
    """The benchmark table: one line per method."""
    head = (f"{'method':<8} {'n':>3} {'tip med':>8} {'tip p90':>8} {'tip max':>8} {'>10mm':>6} "
            f"{'node max':>9} {'normal med':>10} {'t med ms':>9} {'t p95 ms':>9} {'speedup':>8}")
    lines = [title, head] if title else [head]
    medians = {}
    for m in methods:
        r = [x for x in rows if x.method == m]
        if r:
            medians[m] = float(np.median([x.time_s for x in r]))
    ref = medians.get("paper")
    for m in methods:
        r = [x for x in rows if x.method == m]
        if not r:
            continue
        tip = np.array([x.tip_mm for x in r])
        t = np.array([x.time_s for x in r]) * 1e3
        speed = f"{ref / medians[m]:7.1f}x" if ref else "      -"
        lines.append(f"{m:<8} {len(r):>3} {np.median(tip):8.2f} {np.percentile(tip, 90):8.2f} {tip.max():8.2f} "
                     f"{int(np.sum(tip > 10)):>6} {max(x.node_max_mm for x in r):9.2f} "
                     f"{np.median([x.normal_deg for x in r]):10.2f} {np.median(t):9.2f} {np.percentile(t, 95):9.2f} "
                     f"{speed:>8}")
    counts = sorted({x.cameras for x in rows})
    if len(counts) > 1:
        # The time target holds for 2 and for 3 cameras: the median of each on its own.
        for m in methods:
            parts = []
            for k in counts:
                t = [x.time_s for x in rows if x.method == m and x.cameras == k]
                if t:
                    parts.append(f"{k} cameras {1e3 * np.median(t):.2f} ms (n={len(t)})")
            if parts:
                lines.append(f"{m:<8} t med by camera count: {', '.join(parts)}")
    return "\n".join(lines)


def details(rows: Sequence[Row]) -> str:
    """One line per capture and method."""
    lines = [f"{'capture':<16} {'method':<8} {'tip mm':>7} {'node mm':>8} {'normal':>7} {'ms':>7} {'cost':>6}"]
    for x in rows:
        lines.append(f"{x.capture:<16} {x.method:<8} {x.tip_mm:7.2f} {x.node_max_mm:8.2f} {x.normal_deg:7.2f} "
                     f"{1e3 * x.time_s:7.2f} {x.cost:6.3f}")
    return "\n".join(lines)


# ------------------------------------------------------------------ verdict benchmark
WRONG_OK_MM = 10.0
"""An "ok" whose tip is further off than this is a wrong "ok" (issue target: none)."""
GOOD_TIP_MM = 3.0
"""A refusal of a fit whose tip is within this and seen by two cameras is needless."""


@dataclass(frozen=True)
class VerdictRow:
    """One capture: its kind, the verdict, errors [mm, deg] and fit time [s].

    true_tip_views: cameras whose observed mask holds the true tip (not hidden, ignored or
    outside the image); error: the one-line refusal when the capture was rejected as input;
    garbage: the capture holds a garbage mask, so only a refusal is right.
    """

    kind: str
    capture: str
    cameras: int
    verdict: str
    tip_mm: float
    normal_deg: float
    time_s: float
    true_tip_views: int
    error: str = ""
    garbage: bool = False
    worst_offset_px: float = np.nan
    alternative_ratio: float = np.nan


def true_tip_views(capture: Capture, radius_px: int = 2) -> int:
    """How many views' observed masks hold the true tip (within ``radius_px``)."""
    if capture.truth is None:
        return 0
    n = 0
    for v in capture.views:
        uv = v.camera.project(capture.truth.points[-1:])[0]
        if not np.all(np.isfinite(uv)):
            continue
        x, y = int(round(uv[0])), int(round(uv[1]))
        x0, y0 = max(0, x - radius_px), max(0, y - radius_px)
        x1, y1 = min(v.camera.width, x + radius_px + 1), min(v.camera.height, y + radius_px + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        seen = v.mask[y0:y1, x0:x1]
        if v.ignore is not None:
            seen = seen & ~v.ignore[y0:y1, x0:x1]
        n += bool(seen.any())
    return n


def verdict_row(kind: str, name: str, capture: Capture, garbage: bool = False) -> VerdictRow:
    """Fit ``capture`` and judge the answer against its truth (inf errors when refused as
    input); ``garbage``: the capture holds a garbage mask, only a refusal is right."""
    from .errors import TapecellError

    views = true_tip_views(capture)
    try:
        est = estimate(capture)
    except TapecellError as e:
        return VerdictRow(kind, name, len(capture.views), "error", np.inf, np.inf, 0.0, views, str(e), garbage)
    tip, normal = np.inf, np.inf
    if capture.truth is not None:
        e = errors(est.nodes, est.tip_rotation, capture.truth, est.tip_position)
        tip, normal = 1e3 * e.tip_m, e.normal_deg
    ratio = min((a.cost / est.cost for a in est.alternatives), default=np.nan)
    return VerdictRow(kind, name, len(capture.views), est.verdict.value, tip, normal, est.time_s, views, "", garbage,
                      float(np.max(est.view_offsets_px)), ratio)


def verdict_summary(rows: Sequence[VerdictRow]) -> str:
    """Per kind of capture: "ok" rate, wrong "ok" (tip > 10 mm off, or any "ok" on garbage),
    needless refusals (not "ok" though the tip is within 3 mm and two cameras see it),
    accuracy among "ok" and fit time; then the same over all captures, and over all but
    the garbage masks (where "ok" is never right: the share of "ok" a tape's captures get)."""
    head = (f"{'kind':<12} {'n':>4} {'ok %':>6} {'wrong ok':>8} {'needless':>8} {'ambig':>5} {'hidden':>6} "
            f"{'poor':>5} {'error':>5} {'tip med':>7} {'tip p90':>7} {'tip max':>7} {'nrm med':>7} "
            f"{'t med':>6} {'t p95':>6}")
    lines = [head]
    kinds = list(dict.fromkeys(r.kind for r in rows))
    tape = "not garbage"
    for kind in kinds + ["all"] + ([tape] if any(x.garbage for x in rows) else []):
        r = [x for x in rows if kind == "all" or x.kind == kind or (kind == tape and not x.garbage)]
        if not r:
            continue
        ok = [x for x in r if x.verdict == "ok"]
        wrong = sum(x.tip_mm > WRONG_OK_MM or x.garbage for x in ok)
        needless = sum(x.verdict != "ok" and not x.garbage and x.tip_mm <= GOOD_TIP_MM and x.true_tip_views >= 2
                       for x in r)
        ok = [x for x in ok if not x.garbage]
        count = {v: sum(x.verdict == v for x in r) for v in ("ambiguous", "hidden", "poor_fit", "error")}
        tip = np.array([x.tip_mm for x in ok]) if ok else np.array([np.nan])
        nrm = np.array([x.normal_deg for x in ok]) if ok else np.array([np.nan])
        t = np.array([x.time_s for x in r if x.verdict != "error"]) * 1e3
        t = t if t.size else np.array([np.nan])
        lines.append(f"{kind:<12} {len(r):>4} {100 * len(ok) / len(r):6.1f} {wrong:>8} "
                     f"{100 * needless / len(r):7.1f}% {count['ambiguous']:>5} {count['hidden']:>6} "
                     f"{count['poor_fit']:>5} {count['error']:>5} {np.median(tip):7.2f} "
                     f"{np.percentile(tip, 90):7.2f} {tip.max():7.2f} {np.median(nrm):7.2f} "
                     f"{np.median(t):6.2f} {np.percentile(t, 95):6.2f}")
    return "\n".join(lines)
