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
