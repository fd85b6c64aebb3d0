"""Synthetic captures with ground truth, rendered by the estimator's own renderer.

The rig follows the paper (Table 1, sec. 4.2): 640x480 cameras with a 280x210 mm field
about 600 mm from the tape, a second camera 400 mm beside the first and an optional third
400 mm above it, the whole rig at a random orientation around the tape. The tape is either
a plate chain exactly like the model (``kind="chain"``) or a finer continuous strip bent
and twisted smoothly along its length (``kind="strip"``), which the 5-plate model can only
approximate. Options add the faults real captures have: noisy masks, slightly wrong
calibration, a known occluder with an ignore mask, lens distortion.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .capture import Capture, Truth, View
from .geometry import Camera, look_at, rot_x, rot_y, rot_z
from .occlusion import hidden
from .scene import Box
from .silhouette import project_quads, render, subdivide
from .tape import TapeShape, TapeSpec, forward_kinematics

FX_PX = 1371.0
"""Focal length [px] giving the paper's 210 mm field at 600 mm over 480 rows."""


@dataclass(frozen=True)
class SyntheticOptions:
    """What to simulate.

    kind: "chain" (a 5-plate chain, exactly representable) or "strip" (continuous).
    cameras: 2 or 3.
    noise: flip isolated pixels, roughen the boundary and punch small holes.
    miscalibration_px: typical reprojection error [px] of the written calibration.
    occluder: add a band occluding part of camera 0, with its ignore mask.
    distortion: render with radial lens distortion (and write it in the cameras).
    part: the tape stands on a box (the part, written as the capture's scene) that hides
    whatever goes behind it; the rig then faces the tape's front, as in the cell.
    """

    kind: str = "strip"
    cameras: int = 2
    noise: bool = False
    miscalibration_px: float = 0.0
    occluder: bool = False
    distortion: bool = False
    part: bool = False


PART_SIZE_M = (0.10, 0.10, 0.12)
"""The synthetic part's edges along the tape's trunk, width and normal at its base [m]."""
def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def rig_cameras(rng: np.random.Generator, target: np.ndarray, count: int = 2,
                distortion: bool = False, facing: np.ndarray | None = None) -> list[Camera]:
    """The paper's rig looking at ``target`` [m] from a random direction (or, given
    ``facing`` (3,), from within about 35 degrees of that direction from the target)."""
    world_from_rig = _random_rotation(rng)
    if facing is not None:
        # Rig z (the viewing direction) against ``facing``, rolled at random.
        z = -(np.asarray(facing, float) / np.linalg.norm(facing) + rng.normal(scale=0.35, size=3))
        z /= np.linalg.norm(z)
        x = np.cross(rng.normal(size=3), z)
        x /= np.linalg.norm(x)
        world_from_rig = np.column_stack([x, np.cross(z, x), z])
    # Rig frame: cameras on the -z side looking along +z, camera 1 along +x, camera 2 above.
    offsets = [np.array([-0.2, 0.0, -0.6]), np.array([0.2, 0.0, -0.6]), np.array([-0.2, -0.4, -0.6])]
    cams = []
    for k in range(count):
        center = target + world_from_rig @ (offsets[k] * rng.uniform(0.95, 1.05))
        aim = target + rng.normal(scale=0.01, size=3)
        R = look_at(center, aim, world_from_rig @ np.array([0.0, -1.0, 0.0])).T   # camera_from_world
        t = -R @ center
        f = FX_PX * rng.uniform(0.98, 1.02)
        K = np.array([[f, 0.0, 319.5 + rng.normal(scale=3)], [0.0, f, 239.5 + rng.normal(scale=3)], [0, 0, 1]])
        dist = np.zeros(5)
        if distortion:
            dist[:2] = [rng.uniform(-0.25, 0.05), rng.uniform(-0.1, 0.1)]
        cams.append(Camera(f"cam{k}", 640, 480, K, dist, R, t))
    return cams


def random_chain_angles(rng: np.random.Generator, n: int, scale: float = 0.35) -> np.ndarray:
    """(n, 3) joint angles of a plausible plate chain: mostly out-of-plane bending and
    twist, little in-plane bending (a tape is stiff across its width)."""
    a = np.empty((n, 3))
    a[:, 0] = rng.normal(scale=0.5 * scale, size=n)
    a[:, 1] = rng.normal(loc=rng.uniform(-1, 1) * scale, scale=scale, size=n)
    a[:, 2] = rng.normal(scale=0.15 * scale, size=n)
    return a


def strip_angles(rng: np.random.Generator, segments: int, droop: float = 0.0) -> np.ndarray:
    """(segments, 3) angles of a finely discretised continuous strip whose bending and
    twist rates vary smoothly (quadratically) along its length; ``droop`` [rad] > 0 bends
    it that much further away from its face (behind its base, as a tape hanging over the
    back of the part does)."""
    s = (np.arange(segments) + 0.5) / segments

    def profile(total: float, spread: float) -> np.ndarray:
        c = rng.normal(size=3) * spread
        rate = total + c[0] * (s - 0.5) + c[1] * ((s - 0.5) ** 2 - 1 / 12)
        return rate / segments

    bend = rng.uniform(0.3, 2.2) * rng.choice([-1, 1])
    if droop > 0:
        bend = abs(bend) + droop
    return np.stack([profile(rng.normal(scale=0.6), 1.5),
                     profile(bend, 2.5),
                     profile(rng.normal(scale=0.12), 0.3)], axis=1)


def roughen(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Segmentation-like noise: ragged boundary, speckles outside, pinholes inside."""
    m = mask.astype(np.float32)
    field = cv2.GaussianBlur(rng.normal(size=m.shape).astype(np.float32), (0, 0), 1.5)
    m = cv2.GaussianBlur(m, (0, 0), 1.0)
    near_edge = (m > 0.02) & (m < 0.98)
    out = np.where(near_edge, m + 0.35 * field / field.std(), m) > 0.5
    n = mask.size
    out.flat[rng.integers(0, n, size=8)] = True
    ys, xs = np.nonzero(mask)
    k = rng.integers(0, len(ys), size=min(6, len(ys)))
    out[ys[k], xs[k]] = False
    return out


def _occluder(camera: Camera, rng: np.random.Generator, mask: np.ndarray) -> np.ndarray:
    """A band (an arm link) crossing the tape's image in camera 0."""
    ys, xs = np.nonzero(mask)
    c = np.array([xs.mean(), ys.mean()]) + rng.normal(scale=15, size=2)
    d = np.array([np.cos(a := rng.uniform(0, np.pi)), np.sin(a)])
    p0, p1 = c - 800 * d, c + 800 * d
    band = np.zeros(mask.shape, np.uint8)
    cv2.line(band, tuple(np.rint(p0).astype(int)), tuple(np.rint(p1).astype(int)), 1,
             int(rng.uniform(25, 45)))
    return band.astype(bool)


def _perturb(camera: Camera, rng: np.random.Generator, px: float) -> Camera:
    """The camera with its pose wrong by about ``px`` pixels at the tape's distance."""
    if px <= 0:
        return camera
    ang = px / camera.K[0, 0]
    dR = rot_x(rng.normal(scale=ang)) @ rot_y(rng.normal(scale=ang)) @ rot_z(rng.normal(scale=ang))
    return camera.with_pose(dR @ camera.R, camera.t + rng.normal(scale=0.3 * px * 0.6 / camera.K[0, 0], size=3))


def make_capture(seed: int, options: SyntheticOptions = SyntheticOptions(),
                 n_plates: int = 5, length: float = 0.15, width: float = 0.03) -> Capture:
    """A random capture with its truth. Same seed and options, same capture."""
    return make_capture_with_angles(seed, options, n_plates, length, width)[0]


def make_capture_with_angles(seed: int, options: SyntheticOptions = SyntheticOptions(),
                             n_plates: int = 5, length: float = 0.15,
                             width: float = 0.03) -> tuple[Capture, np.ndarray]:
    """:func:`make_capture` and the true joint angles of the rendered chain [rad]
    ((n_plates, 3) for a chain, (60, 3) for a strip's fine segments)."""
    rng = np.random.default_rng(seed)
    base_rotation = _random_rotation(rng)
    base_position = rng.normal(scale=0.01, size=3)
    spec = TapeSpec(np.full(n_plates, length / n_plates), width, base_position, base_rotation)
    if options.kind == "chain":
        true_spec = spec
        angles = random_chain_angles(rng, n_plates)
    elif options.kind == "strip":
        segments = 60
        true_spec = TapeSpec(np.full(segments, length / segments), width, base_position, base_rotation)
        angles = strip_angles(rng, segments, droop=rng.uniform(0.5, 1.5) if options.part else 0.0)
    else:
        raise ValueError(f"unknown synthetic tape kind {options.kind!r}")
    shape = forward_kinematics(true_spec, angles)
    center = shape.nodes.mean(axis=0)
    boxes: tuple[Box, ...] = ()
    if options.part:
        size = np.array(PART_SIZE_M)
        boxes = (Box("part", base_position - base_rotation[:, 0] * size[0] / 2, size, base_rotation),)
    cameras = rig_cameras(rng, center, options.cameras, options.distortion,
                          facing=base_rotation[:, 2] if options.part else None)
    views = []
    for k, cam in enumerate(cameras):
        mask = _render_shape(cam, shape, boxes)
        ignore = None
        if options.occluder and k == 0:
            ignore = _occluder(cam, rng, mask)
            mask &= ~ignore
        if options.noise:
            mask = roughen(mask, rng)
            if ignore is not None:
                mask &= ~ignore
        views.append(View(_perturb(cam, rng, options.miscalibration_px), mask, ignore))
    s = np.concatenate([[0.0], np.cumsum(true_spec.segment_lengths)])
    truth = Truth(s, shape.nodes.copy(), shape.frames[-1].copy())
    return Capture(spec, views, truth, scene=boxes), angles


def _render_shape(camera: Camera, shape: TapeShape, boxes: tuple[Box, ...] = ()) -> np.ndarray:
    """The shape's silhouette; with ``boxes``, each plate cut into 4 x 4 cells, a cell drawn
    only when no box hides its centre (a box itself is background)."""
    quads = shape.quads()
    if boxes:
        quads = subdivide(quads, 4).reshape(-1, 4, 3)
        quads = quads[~hidden(camera.center, quads.mean(axis=1), boxes)]
    return render(project_quads(camera, quads), (camera.height, camera.width)).astype(bool)



def sample_like(seed: int) -> Capture:
    """A capture drawn like the shared sample set: a continuous strip with 2 or 3 cameras
    and, each with some probability, noise, miscalibration, an occluder or distortion."""
    rng = np.random.default_rng(10_000 + seed)
    kind = rng.choice(["clean", "noisy", "calib", "occluded", "distorted"], p=[0.35, 0.2, 0.15, 0.15, 0.15])
    options = SyntheticOptions(
        kind="strip", cameras=int(rng.choice([2, 3])), noise=kind == "noisy",
        miscalibration_px=0.7 if kind == "calib" else 0.0, occluder=kind == "occluded",
        distortion=kind == "distorted")
    return make_capture(seed, options)
