"""Known scene geometry: solid, opaque boxes (the part the tape is stuck on, the table).

A box hides whatever lies behind it from a camera, and the tape cannot pass through it
(formats.md, `scene`). Frames: a box's ``world_from_box`` rotation has the box's axes as
columns, in the world frame; ``size`` holds its full edge lengths [m].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from .errors import CaptureError
from .geometry import check_finite, check_rotation


@dataclass(frozen=True, eq=False)
class Box:
    """name; center: (3,) world [m]; size: (3,) full edge lengths [m]; rotation: (3, 3)
    world_from_box (the box's axes as columns)."""

    name: str
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray

    @property
    def half(self) -> np.ndarray:
        return 0.5 * np.asarray(self.size, float)

    @classmethod
    def from_json(cls, d: Any, source: str, index: int = 0) -> "Box":
        if not isinstance(d, Mapping):
            raise CaptureError(f"{source}: scene box {index} is not an object")
        name = str(d.get("name", f"box{index}"))
        for key in ("center", "size"):
            if key not in d:
                raise CaptureError(f"{source}: scene box {name!r} needs '{key}'")
        center = check_finite(d["center"], (3,), f"scene box {name!r} center", source)
        size = check_finite(d["size"], (3,), f"scene box {name!r} size", source)
        if np.any(size <= 0):
            raise CaptureError(f"{source}: scene box {name!r} size must be positive edge lengths [m]")
        if np.any(size > 20.0):
            raise CaptureError(f"{source}: scene box {name!r} size {size.tolist()} is not in metres")
        rotation = (check_rotation(d["rotation"], f"scene box {name!r} rotation", source)
                    if "rotation" in d else np.eye(3))
        return cls(name, center, size, rotation)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "center": np.asarray(self.center, float).tolist(),
                "size": np.asarray(self.size, float).tolist(),
                "rotation": np.asarray(self.rotation, float).tolist()}

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """(N,) bool: which world points (N, 3) lie inside the box shrunk by ``margin`` [m]."""
        local = (np.asarray(points, float) - self.center) @ self.rotation
        return np.all(np.abs(local) < self.half - margin, axis=-1)


def parse_scene(d: Any, source: str) -> tuple[Box, ...]:
    """The boxes of a capture's optional ``scene`` object (empty when absent)."""
    if d is None:
        return ()
    if not isinstance(d, Mapping) or not isinstance(d.get("boxes", []), list):
        raise CaptureError(f"{source}: 'scene' must be an object with a list 'boxes'")
    return tuple(Box.from_json(b, source, i) for i, b in enumerate(d.get("boxes", [])))


def scene_json(boxes: Sequence[Box]) -> dict[str, Any]:
    return {"boxes": [b.to_json() for b in boxes]}
