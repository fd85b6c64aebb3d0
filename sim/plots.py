"""Small PNG charts drawn with OpenCV (already a dependency) for the sweep report: points
with intervals, dot strips, horizontal bars. Sizes in pixels; colours BGR."""
from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np

W, H = 720, 360
LEFT, RIGHT, TOP, BOTTOM = 70, 20, 40, 70
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK = (40, 40, 40)
GRID = (225, 225, 225)
BLUE = (180, 110, 30)
RED = (50, 50, 200)


def _canvas(title: str) -> np.ndarray:
    img = np.full((H, W, 3), 255, np.uint8)
    cv2.putText(img, title, (LEFT, 25), FONT, 0.6, INK, 1, cv2.LINE_AA)
    return img


def _text(img: np.ndarray, s: str, x: int, y: int, scale: float = 0.4, align: str = "left") -> None:
    (w, _), _ = cv2.getTextSize(s, FONT, scale, 1)
    x = x - w // 2 if align == "centre" else x - w if align == "right" else x
    cv2.putText(img, s, (int(x), int(y)), FONT, scale, INK, 1, cv2.LINE_AA)


def _y_axis(img: np.ndarray, lo: float, hi: float, label: str, ticks: int = 5) -> callable:
    def y_of(v: float) -> int:
        return int(round(H - BOTTOM - (v - lo) / max(hi - lo, 1e-12) * (H - TOP - BOTTOM)))
    for k in range(ticks + 1 if ticks else 0):
        v = lo + (hi - lo) * k / ticks
        y = y_of(v)
        cv2.line(img, (LEFT, y), (W - RIGHT, y), GRID, 1)
        _text(img, f"{v:.3g}", LEFT - 6, y + 4, align="right")
    cv2.line(img, (LEFT, TOP), (LEFT, H - BOTTOM), INK, 1)
    cv2.line(img, (LEFT, H - BOTTOM), (W - RIGHT, H - BOTTOM), INK, 1)
    _text(img, label, 8, TOP - 8)
    return y_of


def _x_label(img: np.ndarray, label: str, x: int) -> None:
    """A category's label under the axis, one line per comma-separated part."""
    for k, part in enumerate(label.split(", ")):
        _text(img, part, x, H - BOTTOM + 18 + 16 * k, align="centre")


def _x_slots(n: int) -> list[int]:
    span = W - LEFT - RIGHT
    return [int(LEFT + span * (k + 0.5) / max(n, 1)) for k in range(n)]


def rates_with_intervals(title: str, labels: Sequence[str], rates: Sequence[float],
                         intervals: Sequence[tuple[float, float]]) -> np.ndarray:
    """Success rate [0-1] per label, each with its 95 % interval as an error bar."""
    img = _canvas(title)
    lo = min([0.9] + [a for a, _ in intervals])
    lo = float(np.floor(lo * 10) / 10)
    y_of = _y_axis(img, lo, 1.0, "success rate")
    for x, label, r, (a, b) in zip(_x_slots(len(labels)), labels, rates, intervals):
        cv2.line(img, (x, y_of(a)), (x, y_of(b)), BLUE, 2)
        for v in (a, b):
            cv2.line(img, (x - 6, y_of(v)), (x + 6, y_of(v)), BLUE, 2)
        cv2.circle(img, (x, y_of(r)), 5, RED, -1, cv2.LINE_AA)
        _text(img, f"{100 * r:.1f}%", x + 8, y_of(r) - 6)
        _x_label(img, label, x)
    return img


def dot_strips(title: str, labels: Sequence[str], values: Sequence[Sequence[float]], unit: str) -> np.ndarray:
    """Each label's values as a strip of dots (log scale from 0.1), with its median and p90 marked."""
    img = _canvas(title)
    finite = [v for vs in values for v in vs if v is not None and np.isfinite(v)]
    top = max(finite + [1.0])
    lo, hi = np.log10(0.1), np.log10(max(top, 1.0) * 1.2)
    y_log = _y_axis(img, lo, hi, unit, ticks=0)
    for v in (0.1, 0.3, 1, 3, 10, 30, 100, 300):
        if lo <= np.log10(v) <= hi:
            y = y_log(np.log10(v))
            cv2.line(img, (LEFT, y), (W - RIGHT, y), GRID, 1)
            _text(img, f"{v:g}", LEFT - 6, y + 4, align="right")
    rng = np.random.default_rng(0)
    for x, label, vs in zip(_x_slots(len(labels)), labels, values):
        vs = np.array([v for v in vs if v is not None and np.isfinite(v)], float)
        for v in vs:
            cv2.circle(img, (int(x + rng.uniform(-15, 15)), y_log(np.log10(max(v, 0.1)))), 2, BLUE, -1)
        if len(vs):
            for q, colour in ((50, RED), (90, INK)):
                y = y_log(np.log10(max(np.percentile(vs, q), 0.1)))
                cv2.line(img, (x - 22, y), (x + 22, y), colour, 2)
        _x_label(img, label, x)
    _text(img, "red: median, black: p90", W - RIGHT - 200, TOP - 8)
    return img


def bars(title: str, counts: dict[str, int]) -> np.ndarray:
    """Horizontal bars, one per reason, longest first."""
    img = _canvas(title)
    items = sorted(counts.items(), key=lambda kv: -kv[1])[:10]
    if not items:
        _text(img, "none", LEFT, H // 2, 0.6)
        return img
    top = max(v for _, v in items)
    row = (H - TOP - 20) / max(len(items), 1)
    for k, (label, v) in enumerate(items):
        y = int(TOP + 10 + k * row)
        x1 = int(LEFT + 180 + (W - LEFT - RIGHT - 220) * v / top)
        cv2.rectangle(img, (LEFT + 180, y), (x1, int(y + row * 0.7)), BLUE, -1)
        _text(img, label[:28], LEFT + 172, int(y + row * 0.5), align="right")
        _text(img, str(v), x1 + 6, int(y + row * 0.5))
    return img
