"""Loading, validating and saving captures (`tape-capture/1`), truth (`tape-truth/1`)
and cameras files (`tape-cameras/1`), as fixed in formats.md.

Every fault raises :class:`CaptureError` with one line naming the file and the problem.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import cv2
import numpy as np

from .errors import CaptureError, OutputError
from .geometry import Camera, check_finite, check_rotation
from .io import atomic_dir, atomic_write_json, to_json
from .sanity import check_mask_coverage, check_tape_units, check_view_geometry
from .scene import Box, parse_scene, scene_json
from .segment import SegmentationParams, segment_tape
from .tape import TapeSpec

CAPTURE_FORMAT = "tape-capture/1"
TRUTH_FORMAT = "tape-truth/1"
CAMERAS_FORMAT = "tape-cameras/1"


@dataclass(frozen=True, eq=False)
class View:
    """What one camera saw.

    camera: its calibration.
    mask: (H, W) bool tape silhouette.
    ignore: (H, W) bool, True where a pixel is unknown (occluded by a known object), or None.
    image: (H, W, 3) uint8 RGB image when the capture holds one, else None.
    """

    camera: Camera
    mask: np.ndarray
    ignore: np.ndarray | None = None
    image: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth of a capture.

    s: (M,) arc length of each sample along the true centre line [m].
    points: (M, 3) the centre line at those arc lengths, base first [m].
    tip_rotation: (3, 3) the true frame at the tip (trunk, left, normal columns).
    """

    s: np.ndarray
    points: np.ndarray
    tip_rotation: np.ndarray

    @property
    def tip_position(self) -> np.ndarray:
        return self.points[-1]

    def to_json(self) -> dict[str, Any]:
        return {"format": TRUTH_FORMAT, "s": np.asarray(self.s).tolist(),
                "points": np.asarray(self.points).tolist(),
                "tip_rotation": np.asarray(self.tip_rotation).tolist()}


@dataclass(frozen=True, eq=False)
class Capture:
    """A set of simultaneous views of one tape, with its model dimensions and the known
    scene boxes (the part, the table) that may hide it and that it cannot pass through."""

    tape: TapeSpec
    views: list[View]
    truth: Truth | None = None
    path: Path | None = None
    segmentation: Mapping[str, Any] = field(default_factory=dict)
    scene: tuple[Box, ...] = ()

    @property
    def cameras(self) -> list[Camera]:
        return [v.camera for v in self.views]

    @property
    def name(self) -> str:
        return self.path.name if self.path is not None else "capture"


def _read_json(path: Path) -> Any:
    if not path.is_file():
        raise CaptureError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureError(f"{path}: cannot read ({e})") from None
    except json.JSONDecodeError as e:
        raise CaptureError(f"{path}: not valid JSON ({e.msg} at line {e.lineno})") from None


def _check_format(doc: Any, expected: str, source: Path) -> None:
    if not isinstance(doc, dict):
        raise CaptureError(f"{source}: expected a JSON object")
    fmt = doc.get("format")
    if fmt != expected:
        raise CaptureError(f"{source}: unknown format {fmt!r}, expected {expected!r}")


def parse_tape(d: Any, source: str) -> TapeSpec:
    if not isinstance(d, Mapping):
        raise CaptureError(f"{source}: 'tape' is missing or not an object")
    if "segment_lengths" not in d or "width" not in d or "base" not in d:
        raise CaptureError(f"{source}: 'tape' needs segment_lengths, width and base")
    lengths = check_finite(d["segment_lengths"], None, "tape segment_lengths", source).reshape(-1)
    if lengths.size == 0 or np.any(lengths <= 0):
        raise CaptureError(f"{source}: tape segment_lengths must be one or more positive lengths")
    width = float(check_finite(d["width"], (), "tape width", source))
    if width <= 0:
        raise CaptureError(f"{source}: tape width must be positive")
    base = d["base"]
    if not isinstance(base, Mapping) or "position" not in base or "rotation" not in base:
        raise CaptureError(f"{source}: tape base needs position and rotation")
    position = check_finite(base["position"], (3,), "tape base position", source)
    rotation = check_rotation(base["rotation"], "tape base rotation", source)
    return TapeSpec(lengths, width, position, rotation)


def _read_mask(path: Path, camera: Camera, what: str) -> np.ndarray:
    if not path.is_file():
        raise CaptureError(f"{path}: {what} file not found (camera {camera.name})")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CaptureError(f"{path}: cannot decode {what} image")
    if img.ndim == 3:
        img = img[..., :3].max(axis=2) if img.shape[2] >= 3 else img[..., 0]
    if img.shape != (camera.height, camera.width):
        raise CaptureError(f"{path}: {what} is {img.shape[1]}x{img.shape[0]} px but camera "
                           f"{camera.name} is {camera.width}x{camera.height}")
    if img.dtype != np.uint8:  # 16-bit masks: scale to 8 bits before thresholding
        img = (img.astype(np.float64) * 255.0 / np.iinfo(img.dtype).max).astype(np.uint8)
    return img >= 128


def _read_rgb(path: Path, camera: Camera) -> np.ndarray:
    if not path.is_file():
        raise CaptureError(f"{path}: image file not found (camera {camera.name})")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise CaptureError(f"{path}: cannot decode image")
    if bgr.shape[:2] != (camera.height, camera.width):
        raise CaptureError(f"{path}: image is {bgr.shape[1]}x{bgr.shape[0]} px but camera "
                           f"{camera.name} is {camera.width}x{camera.height}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def load_capture(path: str | Path, segmentation: Mapping[str, Any] | None = None) -> Capture:
    """Load and validate a capture directory.

    ``segmentation`` overrides the capture's own segmentation parameters for cameras that
    give a colour ``image`` instead of a ``mask``.
    """
    root = Path(path)
    if not root.is_dir():
        raise CaptureError(f"{root}: capture directory not found")
    cj = root / "capture.json"
    if not cj.is_file():
        raise CaptureError(f"{root}: missing capture.json")
    doc = _read_json(cj)
    _check_format(doc, CAPTURE_FORMAT, cj)
    if doc.get("units", "m") != "m":
        raise CaptureError(f"{cj}: units must be 'm', got {doc.get('units')!r}")
    tape = parse_tape(doc.get("tape"), str(cj))
    check_tape_units(tape, str(cj))
    cams = doc.get("cameras")
    if not isinstance(cams, list) or len(cams) < 1:
        raise CaptureError(f"{cj}: needs at least one camera")
    seg_doc = doc.get("segmentation") or {}
    if not isinstance(seg_doc, Mapping):
        raise CaptureError(f"{cj}: 'segmentation' must be an object")
    params = SegmentationParams().with_overrides(seg_doc, str(cj)).with_overrides(segmentation, "command line")
    views, names = [], set()
    for cd in cams:
        camera = Camera.from_json(cd, str(cj))
        if camera.name in names:
            raise CaptureError(f"{cj}: camera name {camera.name!r} appears twice")
        names.add(camera.name)
        image = None
        if cd.get("mask"):
            mask_path = root / str(cd["mask"])
            mask = _read_mask(mask_path, camera, "mask")
            if cd.get("image"):
                image = _read_rgb(root / str(cd["image"]), camera)
        elif cd.get("image"):
            mask_path = root / str(cd["image"])
            image = _read_rgb(mask_path, camera)
            mask = segment_tape(image, params)
        else:
            raise CaptureError(f"{cj}: camera {camera.name} has neither 'mask' nor 'image'")
        check_mask_coverage(mask, camera.name, str(mask_path))
        ignore = _read_mask(root / str(cd["ignore"]), camera, "ignore mask") if cd.get("ignore") else None
        visible = mask if ignore is None else mask & ~ignore
        if not visible.any():
            raise CaptureError(f"{root}: camera {camera.name} sees no tape")
        check_view_geometry(camera, tape, visible, str(cj))
        views.append(View(camera, mask, ignore, image))
    scene = parse_scene(doc.get("scene"), str(cj))
    truth = load_truth(root / "truth.json") if (root / "truth.json").exists() else None
    return Capture(tape, views, truth, root, dict(seg_doc), scene)


def load_truth(path: str | Path) -> Truth:
    path = Path(path)
    doc = _read_json(path)
    _check_format(doc, TRUTH_FORMAT, path)
    for key in ("s", "points", "tip_rotation"):
        if key not in doc:
            raise CaptureError(f"{path}: missing '{key}'")
    s = check_finite(doc["s"], None, "s", str(path)).reshape(-1)
    points = check_finite(doc["points"], (s.size, 3), "points", str(path))
    if s.size < 2 or np.any(np.diff(s) < 0):
        raise CaptureError(f"{path}: 's' must hold two or more non-decreasing arc lengths")
    R = check_rotation(doc["tip_rotation"], "tip_rotation", str(path), tol=1e-4)
    return Truth(s, points, R)


def _png(mask: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.where(mask, 255, 0).astype(np.uint8))
    assert ok
    return buf.tobytes()


def capture_json(capture: Capture, rgb: bool = False) -> dict[str, Any]:
    cams = []
    for v in capture.views:
        d = v.camera.to_json()
        d.pop("rms_px", None)
        d["mask"] = f"{v.camera.name}.png"
        if v.ignore is not None:
            d["ignore"] = f"{v.camera.name}_ignore.png"
        if rgb and v.image is not None:
            d["image"] = f"{v.camera.name}_rgb.png"
        cams.append(d)
    doc: dict[str, Any] = {"format": CAPTURE_FORMAT, "units": "m", "tape": capture.tape.to_json(), "cameras": cams}
    if capture.segmentation:
        doc["segmentation"] = dict(capture.segmentation)
    if capture.scene:
        doc["scene"] = scene_json(capture.scene)
    return doc


def save_capture(capture: Capture, path: str | Path, rgb: bool = False, force: bool = False) -> Path:
    """Write ``capture`` as a `tape-capture/1` directory (with truth.json when known).

    A new or empty ``path`` appears complete or not at all. A non-empty one is refused
    (:class:`~estimator.errors.OutputError`) unless ``force``; then only the capture's own
    files are replaced and nothing else in it is touched (see ``io.atomic_dir``)."""
    path = Path(path)
    if force and capture.truth is None and (path / "truth.json").exists():
        raise OutputError(f"{path}: holds a truth.json that this capture (without truth) would not "
                          "replace, and a later load would take it for this capture's; choose another folder")
    with atomic_dir(path, force) as tmp:
        (tmp / "capture.json").write_text(to_json(capture_json(capture, rgb)) + "\n")
        for v in capture.views:
            (tmp / f"{v.camera.name}.png").write_bytes(_png(v.mask))
            if v.ignore is not None:
                (tmp / f"{v.camera.name}_ignore.png").write_bytes(_png(v.ignore))
            if rgb and v.image is not None:
                ok, buf = cv2.imencode(".png", cv2.cvtColor(v.image, cv2.COLOR_RGB2BGR))
                (tmp / f"{v.camera.name}_rgb.png").write_bytes(buf.tobytes())
        if capture.truth is not None:
            (tmp / "truth.json").write_text(to_json(capture.truth.to_json()) + "\n")
    return path


def save_truth(truth: Truth, path: str | Path) -> None:
    atomic_write_json(path, truth.to_json())


def load_cameras(path: str | Path) -> list[Camera]:
    """Read a `tape-cameras/1` file."""
    path = Path(path)
    doc = _read_json(path)
    _check_format(doc, CAMERAS_FORMAT, path)
    cams = doc.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CaptureError(f"{path}: needs at least one camera")
    return [Camera.from_json(c, str(path)) for c in cams]


def save_cameras(cameras: Sequence[Camera], path: str | Path) -> None:
    """Write a `tape-cameras/1` file atomically."""
    atomic_write_json(path, {"format": CAMERAS_FORMAT, "cameras": [c.to_json() for c in cameras]})
