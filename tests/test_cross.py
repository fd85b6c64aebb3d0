"""The cross detector on synthetic (exactly known) and rendered images."""
import os

import cv2
import numpy as np
import pytest

from tapecell.cell.cross import detect_cross, plate_image
from tapecell.estimator.geometry import Camera, rot_x, rot_y, rot_z

K = np.array([[1371.0, 0, 319.5], [0, 1371.0, 239.5], [0, 0, 1]])
CAM = Camera("c", 640, 480, K, np.zeros(5), np.eye(3), np.zeros(3))


def _plate(R, p):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _image(T, blur=0.7, noise=2.0, seed=0):
    img = plate_image(CAM, T, 0.08, 0.006, 0.06, blur_px=blur).astype(float)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def test_subpixel_accuracy_on_synthetic_perspective_views():
    rng = np.random.default_rng(3)
    errs = []
    for i in range(25):
        R = rot_z(rng.uniform(-np.pi, np.pi)) @ rot_x(np.radians(rng.uniform(-35, 35))) @ rot_y(np.radians(rng.uniform(-35, 35)))
        T = _plate(R, [rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), rng.uniform(0.5, 0.65)])
        d = detect_cross(_image(T, seed=i))
        if d.ok:
            errs.append(np.linalg.norm(d.center_px - CAM.project(T[:3, 3][None])[0]))
    assert len(errs) >= 20
    assert np.sqrt(np.mean(np.square(errs))) < 0.05
    assert max(errs) < 0.12


def test_rejects_missing_cross():
    d = detect_cross(np.full((480, 640), 120, np.uint8))
    assert not d.ok and d.reason == "missing"


def test_rejects_cross_cut_by_border():
    T = _plate(np.eye(3), [0.125, 0.0, 0.6])        # cross centre ~ 37 px from the right edge
    d = detect_cross(_image(T))
    assert not d.ok and d.reason == "border"


def test_rejects_oblique_view():
    T = _plate(rot_y(np.radians(68)), [0.0, 0.0, 0.6])
    d = detect_cross(_image(T))
    assert not d.ok and d.reason == "oblique"


def test_rejects_partly_hidden_cross():
    T = _plate(rot_z(0.3), [0.0, 0.0, 0.6])
    img = _image(T)
    assert detect_cross(img).ok
    # A light object (a cable, a finger) over the end of one arm.
    cv2.rectangle(img, (360, 170), (420, 300), 235, -1)
    d = detect_cross(img)
    assert not d.ok and d.reason == "occluded"
    # A dark one across the plate next to the centre.
    img2 = _image(T)
    cv2.line(img2, (300, 100), (340, 400), 20, 5)
    d2 = detect_cross(img2)
    assert not d2.ok and d2.reason in ("occluded", "missing")


@pytest.fixture(scope="module")
def sim_plate():
    from tapecell.cell.config import load_cell_config
    from tapecell.sim.cell import SimCell
    from tapecell.cell.calibration import plan_poses
    from tapecell.cli.commands.calibrate import SimCameras
    from tapecell.sim.arm_adapter import SimArmAdapter
    from tapecell.sim.arm import SimArm

    cell = load_cell_config()
    poses = plan_poses(cell, 2)
    with SimCell(cell, seed=0, n_cameras=2, tool="plate") as sim:
        src = SimCameras(sim)
        arm = SimArmAdapter(SimArm(sim), teleport=True)
        arm.connect()
        out = []
        for p in poses[:4]:
            arm.move_joints(p.joints, 0.5, 1.0)
            out.append((p, src.grab(p.index), {c.name: c for c in sim.cameras()}))
        yield out


def test_rendered_cross_detected_to_subpixel(sim_plate):
    for pose, images, cams in sim_plate:
        for name, img in images.items():
            d = detect_cross(img)
            assert d.ok, d.detail
            err = np.linalg.norm(d.center_px - cams[name].project(pose.point[None])[0])
            assert err < 0.1
