"""Camera sources for the real cell: OpenCV ``VideoCapture`` devices/URLs, or a folder.

Both give RGB uint8 images keyed by camera name, the way the simulated cameras do, so the
calibration and probing procedures run unchanged.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from tapecell.estimator.errors import HardwareError, TapecellError


class CameraSourceError(TapecellError):
    """An image folder or file is missing or unreadable (bad input, exit 2)."""


class CameraDeviceError(HardwareError):
    """A camera device cannot be opened or gives no frame (hardware, exit 3)."""


class VideoCameras:
    """One ``cv2.VideoCapture`` per camera: ``devices`` are indices or URLs (str)."""

    def __init__(self, devices: Sequence[int | str], names: Sequence[str], flush_frames: int = 3) -> None:
        if len(devices) < len(names):
            raise CameraSourceError(f"{len(names)} cameras need {len(names)} devices, got {len(devices)}")
        self.names = list(names)
        self.flush_frames = flush_frames
        self._caps = {}
        try:
            for name, dev in zip(names, devices):
                cap = cv2.VideoCapture(dev)
                if not cap.isOpened():
                    raise CameraDeviceError(f"camera {name}: cannot open video device {dev!r}")
                self._caps[name] = cap
        except BaseException:
            self.close()
            raise

    def size(self, name: str) -> tuple[int, int]:
        cap = self._caps[name]
        return int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))

    def grab(self, index: int) -> dict[str, np.ndarray]:
        out = {}
        for name, cap in self._caps.items():
            # Drivers buffer a few frames: drop them so the image is taken after the move.
            for _ in range(self.flush_frames):
                cap.grab()
            ok, frame = cap.read()
            if not ok or frame is None:
                raise CameraDeviceError(f"camera {name}: no frame from the device")
            out[name] = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        return out

    def close(self) -> None:
        for cap in self._caps.values():
            cap.release()
        self._caps = {}


class FolderCameras:
    """Images from ``root/<index>/<camera>.png`` (index zero-padded to 3 digits or not),
    e.g. taken beforehand at the planned poses."""

    def __init__(self, root: str | Path, names: Sequence[str]) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise CameraSourceError(f"{self.root}: image folder not found")
        self.names = list(names)
        self._sizes: dict[str, tuple[int, int]] = {}

    def _path(self, index: int, name: str) -> Path:
        for folder in (f"{index:03d}", str(index)):
            for ext in (".png", ".jpg"):
                p = self.root / folder / f"{name}{ext}"
                if p.is_file():
                    return p
        raise CameraSourceError(f"{self.root}: no image for pose {index} camera {name} "
                                f"(expected {self.root / f'{index:03d}' / f'{name}.png'})")

    def grab(self, index: int) -> dict[str, np.ndarray]:
        out = {}
        for name in self.names:
            path = self._path(index, name)
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if img is None:
                raise CameraSourceError(f"{path}: not a readable image")
            out[name] = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
            self._sizes[name] = (img.shape[1], img.shape[0])
        return out

    def size(self, name: str) -> tuple[int, int]:
        if name not in self._sizes:
            self.grab(0)
        return self._sizes[name]

    def close(self) -> None:
        pass
