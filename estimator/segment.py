"""Tape segmentation of colour images with OpenCV: HSV colour threshold and morphology.

The tape is distinctly coloured; the default parameters suit the blue tape of the
simulated cell. A capture may give its own parameters under ``"segmentation"`` in
``capture.json``, and the command line may override them.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Mapping

import cv2
import numpy as np

from .errors import CaptureError


@dataclass(frozen=True)
class SegmentationParams:
    """HSV box in OpenCV units (H 0-179, S and V 0-255) and morphology sizes [px].

    hue_min > hue_max wraps around 180 (for red tapes).
    open_px / close_px: elliptic kernel sizes of the opening (removes specks) and
    closing (fills pinholes); 0 disables the step.
    min_area_px: connected components smaller than this are dropped.
    """

    hue_min: int = 95
    hue_max: int = 130
    sat_min: int = 90
    val_min: int = 40
    open_px: int = 3
    close_px: int = 3
    min_area_px: int = 30

    def with_overrides(self, values: Mapping[str, Any] | None, source: str = "") -> "SegmentationParams":
        """A copy with ``values`` applied; unknown names or non-integers are a CaptureError."""
        if not values:
            return self
        where = f"{source}: " if source else ""
        known = {f.name for f in fields(self)}
        clean = {}
        for key, value in values.items():
            if key not in known:
                raise CaptureError(f"{where}unknown segmentation parameter '{key}' (known: {', '.join(sorted(known))})")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value != int(value) or value < 0:
                raise CaptureError(f"{where}segmentation parameter '{key}' must be a non-negative integer, got {value!r}")
            clean[key] = int(value)
        return replace(self, **clean)


def segment_tape(rgb: np.ndarray, params: SegmentationParams | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB image -> (H, W) bool tape mask."""
    p = params or SegmentationParams()
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    lo_s_v = (p.sat_min, p.val_min)
    if p.hue_min <= p.hue_max:
        mask = cv2.inRange(hsv, (p.hue_min, *lo_s_v), (p.hue_max, 255, 255))
    else:
        mask = cv2.inRange(hsv, (p.hue_min, *lo_s_v), (179, 255, 255)) | cv2.inRange(
            hsv, (0, *lo_s_v), (p.hue_max, 255, 255))
    if p.open_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (p.open_px, p.open_px))
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, k)
    if p.close_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (p.close_px, p.close_px))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, k)
    if p.min_area_px > 0:
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        keep = np.zeros(n, bool)
        keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= p.min_area_px
        mask = keep[labels]
    return mask.astype(bool)
