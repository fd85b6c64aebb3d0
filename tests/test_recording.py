"""Rerun recordings: every logger writes a file that reads back with the values logged."""
from __future__ import annotations

import shutil
import subprocess

import cv2
import numpy as np
import pytest
from rerun.chunk import RrdReader

from tapecell.cell import recording as rec
from tapecell.estimator.capture import Capture, Truth, View
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.geometry import Camera, look_at, rot_x, rot_z
from tapecell.estimator.result import Estimate
from tapecell.estimator.tape import TapeSpec, forward_kinematics

W, H = 64, 48


def _look_at(name: str, eye: np.ndarray, target: np.ndarray) -> Camera:
    """A camera at ``eye`` looking at ``target``, image y roughly along world -z."""
    camera_from_world = look_at(eye, target, [0.0, 0.0, -1.0]).T
    K = np.array([[250.0, 0, (W - 1) / 2], [0, 250.0, (H - 1) / 2], [0, 0, 1]])
    return Camera(name, W, H, K, np.zeros(5), camera_from_world, -camera_from_world @ eye)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(7)
    spec = TapeSpec(np.full(5, 0.01), 0.008, np.array([0.0, 0.0, 0.0]), rot_z(0.3))
    true_angles = rng.normal(0.0, 0.15, (5, 3))
    fit_angles = true_angles + rng.normal(0.0, 0.02, (5, 3))
    centre = np.array([0.025, 0.0, 0.0])
    cameras = [_look_at("cam0", np.array([0.02, -0.25, 0.2]), centre),
               _look_at("cam1", np.array([0.05, 0.25, 0.2]), centre)]
    true_shape = forward_kinematics(spec, true_angles)
    fit_shape = forward_kinematics(spec, fit_angles)
    truth = Truth(np.concatenate([[0.0], np.cumsum(spec.segment_lengths)]), true_shape.nodes,
                  true_shape.frames[-1])
    history = [0.9, 0.5, 0.31, 0.2, 0.12]
    estimate = Estimate(fit_shape.nodes, fit_angles, fit_shape.nodes[-1], fit_shape.frames[-1],
                        cost=0.12, view_costs=np.array([0.1, 0.14]), time_s=0.01, history=history)
    views = []
    for cam in cameras:
        mask = rec.model_silhouette(cam, spec, true_angles)
        ignore = np.zeros((H, W), bool)
        ignore[:4] = True
        image = np.dstack([mask * 200, mask * 100, np.full((H, W), 30)]).astype(np.uint8)
        views.append(View(cam, mask, ignore, image))
    capture = Capture(spec, views, truth)
    return dict(spec=spec, cameras=cameras, capture=capture, estimate=estimate, truth=truth,
                true_angles=true_angles, fit_angles=fit_angles)


def _write_everything(path, scene):
    cams = scene["cameras"]
    stream = rec.open_recording(path, camera_names=[c.name for c in cams])
    rec.log_cameras(stream, cams)
    for view in scene["capture"].views:
        model = rec.model_silhouette(view.camera, scene["spec"], scene["fit_angles"])
        rec.log_view(stream, view.camera, view.mask, image=view.image, model_mask=model,
                     ignore=view.ignore)
    for i, cost in enumerate(scene["estimate"].history):
        rec.log_cost(stream, i, cost)
    rec.log_estimate(stream, scene["estimate"], scene["spec"], [c.name for c in cams])
    rec.log_truth(stream, scene["truth"])

    rec.log_joint_names(stream, [f"q{i}" for i in range(6)])
    links = [np.eye(4) for _ in range(3)]
    for k, z in enumerate((0.0, 0.1, 0.2)):
        links[k][:3, 3] = [0.0, 0.0, z]
    for step in range(3):
        flange = np.eye(4)
        flange[:3, 3] = [0.3, 0.1 * step, 0.4]
        rec.log_arm_state(stream, 0.5 * step, flange, np.arange(6) * 0.1 + step, links)
    waypoints = {}
    for k, name in enumerate(("approach", "pregrasp", "grasp", "lift")):
        pose = np.eye(4)
        pose[:3, :3] = rot_x(np.pi)
        pose[:3, 3] = [0.05, 0.0, 0.1 - 0.02 * k]
        waypoints[name] = pose
    rec.log_plan(stream, waypoints)
    rec.log_gripper(stream, 1.0, 0.085, "open")
    rec.log_gripper(stream, 1.5, 0.002, "close")
    rec.log_result(stream, {"success": False, "tip_error_mm": 1.25, "reason": "slipped"})
    rec.close_recording(stream)
    return waypoints


@pytest.fixture(scope="module")
def recorded(scene, tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "episode.rrd"
    waypoints = _write_everything(path, scene)
    return dict(path=path, data=rec.read_recording(path), waypoints=waypoints)


def _only(data, entity):
    rows = data[entity]
    assert len(rows) == 1, (entity, rows)
    return rows[0]


def test_file_is_complete_and_no_temporary_left(recorded):
    path = recorded["path"]
    assert path.is_file() and path.stat().st_size > 0
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_every_entity_is_recorded(recorded):
    expected = {
        "world/cameras/cam0", "world/cameras/cam1", "world/cameras/cam0/image",
        "world/cameras/cam0/image/rgb", "world/cameras/cam0/image/mask",
        "world/cameras/cam0/image/model", "world/cameras/cam0/image/ignore",
        "world/cameras/cam1/image/model",
        "world/tape/estimate", "world/tape/estimate/nodes", "world/tape/estimate/plates",
        "world/tape/estimate/outline", "world/tape/tip", "world/tape/truth",
        "world/tape/truth/tip", "estimator/cost", "estimator/view_cost/cam0",
        "estimator/view_cost/cam1", "estimator/final_cost",
        "world/arm/flange", "world/arm/links", "world/arm/links/origins", "world/arm/links/axes",
        "arm/joints", "world/plan/waypoints", "world/plan/path", "world/plan/axes",
        "gripper/opening", "gripper/events", "grasp/result", "grasp/tip_error_mm",
        "grasp/success",
    }
    missing = expected - set(recorded["data"])
    assert not missing


def test_cost_series_on_iteration_timeline(recorded, scene):
    rows = recorded["data"]["estimator/cost"]
    assert [r["iteration"] for r in rows] == list(range(5))
    assert [r["Scalars:scalars"][0] for r in rows] == pytest.approx(scene["estimate"].history)
    # The iteration timeline is cleared after use: later entities are not stamped with it.
    assert "iteration" not in _only(recorded["data"], "world/tape/estimate")
    view_costs = [_only(recorded["data"], f"estimator/view_cost/{n}")["Scalars:scalars"][0]
                  for n in ("cam0", "cam1")]
    assert view_costs == pytest.approx([0.1, 0.14])


def test_tape_geometry_matches(recorded, scene):
    data, est, truth = recorded["data"], scene["estimate"], scene["truth"]
    strip = np.array(_only(data, "world/tape/estimate")["LineStrips3D:strips"][0])
    np.testing.assert_allclose(strip, est.nodes, atol=1e-6)
    tip = _only(data, "world/tape/tip")
    np.testing.assert_allclose(np.array(tip["Arrows3D:origins"]), np.tile(est.tip_position, (3, 1)),
                               atol=1e-6)
    vectors = np.array(tip["Arrows3D:vectors"])
    np.testing.assert_allclose(vectors.T / rec.FRAME_AXIS_LENGTH_M, est.tip_rotation, atol=1e-5)
    quads = forward_kinematics(scene["spec"], est.angles).quads()
    plates = _only(data, "world/tape/estimate/plates")
    np.testing.assert_allclose(np.array(plates["Mesh3D:vertex_positions"]), quads.reshape(-1, 3),
                               atol=1e-6)
    triangles = np.array(plates["Mesh3D:triangle_indices"])
    assert len(triangles) == 2 * len(quads)
    assert sorted(set(triangles.ravel())) == list(range(4 * len(quads)))
    true_strip = np.array(_only(data, "world/tape/truth")["LineStrips3D:strips"][0])
    np.testing.assert_allclose(true_strip, truth.points, atol=1e-6)


def test_cameras_pose_and_intrinsics(recorded, scene):
    data = recorded["data"]
    for cam in scene["cameras"]:
        pose = data[f"world/cameras/{cam.name}"][-1]  # logged again by the calibration
        assert "sim_time" not in pose  # static
        np.testing.assert_allclose(pose["Transform3D:translation"][0], cam.center, atol=1e-6)
        # rerun stores 3x3 matrices column-major.
        world_from_camera = np.array(pose["Transform3D:mat3x3"][0]).reshape(3, 3).T
        np.testing.assert_allclose(world_from_camera, cam.R.T, atol=1e-6)
        pinhole = data[f"world/cameras/{cam.name}/image"][-1]
        K = np.array(pinhole["Pinhole:image_from_camera"][0]).reshape(3, 3).T
        expected = cam.K.copy()
        expected[:2, 2] += 0.5  # rerun puts the first pixel's centre at 0.5
        np.testing.assert_allclose(K, expected, atol=1e-5)
        assert pinhole["Pinhole:resolution"][0] == [W, H]
        classes = {c["class_id"]: c["class_description"]["info"]["label"]
                   for c in pinhole["AnnotationContext:context"][0]}
        assert classes == {0: "background", rec.CLASS_MASK: "observed", rec.CLASS_MODEL: "model",
                           rec.CLASS_IGNORE: "ignored"}
        # The background class is fully transparent: the camera image shows through.
        background = next(c for c in pinhole["AnnotationContext:context"][0] if c["class_id"] == 0)
        assert background["class_description"]["info"]["color"] & 0xFF == 0


def test_images_read_back_pixel_exact(recorded, scene):
    data = recorded["data"]
    for view in scene["capture"].views:
        base = f"world/cameras/{view.camera.name}/image"
        mask = np.array(_only(data, f"{base}/mask")["SegmentationImage:buffer"][0],
                        np.uint8).reshape(H, W)
        np.testing.assert_array_equal(mask, view.mask.astype(np.uint8) * rec.CLASS_MASK)
        model = np.array(_only(data, f"{base}/model")["SegmentationImage:buffer"][0],
                         np.uint8).reshape(H, W)
        expected = rec.model_silhouette(view.camera, scene["spec"], scene["fit_angles"])
        np.testing.assert_array_equal(model, expected.astype(np.uint8) * rec.CLASS_MODEL)
        ignore = np.array(_only(data, f"{base}/ignore")["SegmentationImage:buffer"][0],
                          np.uint8).reshape(H, W)
        assert (ignore == rec.CLASS_IGNORE).sum() == 4 * W
        rgb = np.array(_only(data, f"{base}/rgb")["Image:buffer"][0], np.uint8).reshape(H, W, 3)
        np.testing.assert_array_equal(rgb, view.image)


def test_arm_over_time(recorded):
    data = recorded["data"]
    flange = data["world/arm/flange"]
    assert [r["sim_time"] for r in flange] == [0, 500_000_000, 1_000_000_000]
    assert [r["Transform3D:translation"][0][1] for r in flange] == pytest.approx([0.0, 0.1, 0.2])
    joints = data["arm/joints"]
    temporal = [r for r in joints if "sim_time" in r]
    assert temporal[-1]["Scalars:scalars"] == pytest.approx(np.arange(6) * 0.1 + 2)
    names = [r for r in joints if "SeriesLines:names" in r]
    assert names[0]["SeriesLines:names"] == [f"q{i}" for i in range(6)]
    links = data["world/arm/links/origins"][-1]["Points3D:positions"]
    assert np.array(links)[:, 2] == pytest.approx([0.0, 0.1, 0.2])


def test_plan_gripper_and_result(recorded):
    data = recorded["data"]
    wp = _only(data, "world/plan/waypoints")
    assert wp["Points3D:labels"] == list(recorded["waypoints"])
    positions = np.array([p[:3, 3] for p in recorded["waypoints"].values()])
    np.testing.assert_allclose(wp["Points3D:positions"], positions, atol=1e-6)
    np.testing.assert_allclose(_only(data, "world/plan/path")["LineStrips3D:strips"][0], positions,
                               atol=1e-6)
    opening = data["gripper/opening"]
    assert [r["Scalars:scalars"][0] for r in opening] == pytest.approx([0.085, 0.002])
    assert [r["sim_time"] for r in opening] == [1_000_000_000, 1_500_000_000]
    assert [r["TextLog:text"][0] for r in data["gripper/events"]] == ["open", "close"]
    result = _only(data, "grasp/result")
    assert result["TextLog:level"] == ["WARN"]
    assert "reason=slipped" in result["TextLog:text"][0]
    assert _only(data, "grasp/tip_error_mm")["Scalars:scalars"] == pytest.approx([1.25])
    assert _only(data, "grasp/success")["Scalars:scalars"] == [0.0]


def _blueprint_origins(path) -> list[set[str]]:
    """Space origins of the views of each blueprint in the file."""
    reader = RrdReader(str(path))
    out = []
    for entry in reader.blueprints():
        origins = set()
        for chunk in reader.store(store=entry).stream().to_chunks():
            batch = chunk.to_record_batch()
            if "ViewBlueprint:space_origin" in batch.schema.names:
                for value in batch.column("ViewBlueprint:space_origin").to_pylist():
                    origins.update(v.lstrip("/") for v in value or [])
        out.append(origins)
    return out


def test_default_blueprint_shows_world_cameras_and_cost(recorded):
    assert any({"world", "world/cameras/cam0/image", "world/cameras/cam1/image", "estimator"}
               <= origins for origins in _blueprint_origins(recorded["path"]))


def test_model_silhouette_covers_the_projected_plates(scene):
    """The overlay covers points sampled inside each plate, and no pixel lies farther than
    one pixel from the projected plates."""
    spec, cam = scene["spec"], scene["cameras"][0]
    sil = rec.model_silhouette(cam, spec, scene["true_angles"])
    quads = forward_kinematics(spec, scene["true_angles"]).quads()
    rng = np.random.default_rng(1)
    a, b = rng.uniform(0.15, 0.85, (2, 400, 1))
    inside = [(1 - a) * (1 - b) * q[0] + a * (1 - b) * q[1] + a * b * q[2] + (1 - a) * b * q[3]
              for q in quads]  # bilinear samples inside each plate
    uv = np.rint(cam.project(np.concatenate(inside))).astype(int)
    assert sil[uv[:, 1], uv[:, 0]].all()
    # The plates' polygons drawn 8x finer, grown by one pixel, contain every overlay pixel.
    fine = np.zeros((H * 8, W * 8), np.uint8)
    for q in cam.project(quads.reshape(-1, 3)).reshape(-1, 4, 2):
        cv2.fillPoly(fine, [np.rint(((q + 0.5) * 8 - 0.5) * 16).astype(np.int32)], 1, shift=4)
    grown = cv2.dilate(fine, np.ones((17, 17), np.uint8))
    ys, xs = np.nonzero(sil)
    assert grown[ys * 8 + 4, xs * 8 + 4].all()
    assert sil.sum() > 50


def test_log_fit_logs_a_whole_capture(scene, tmp_path):
    path = tmp_path / "fit.rrd"
    with rec.recording(path) as stream:
        rec.log_fit(stream, scene["capture"], scene["estimate"])
    data = rec.read_recording(path)
    for cam in ("cam0", "cam1"):
        assert f"world/cameras/{cam}/image/model" in data
        assert f"world/cameras/{cam}/image/rgb" in data
    costs = data["estimator/cost"]
    assert [r["iteration"] for r in costs] == list(range(5))
    assert [r["Scalars:scalars"][0] for r in costs] == pytest.approx(scene["estimate"].history)
    assert "world/tape/truth" in data


def test_fit_logger_and_prefixed_captures(scene, tmp_path):
    """Two captures in one file: each under its own root, with a blueprint tab each, and the
    callback's per-iteration costs on the iteration timeline."""
    path = tmp_path / "two.rrd"
    fit_angles = scene["fit_angles"]
    with rec.recording(path) as stream:
        for name in ("clean 00", "clean-01"):
            callback = rec.fit_logger(stream, scene["capture"], prefix=name)
            for i, cost in enumerate(scene["estimate"].history):
                callback(i + 1, cost, fit_angles * (i + 1) / 5)
            rec.log_fit_result(stream, scene["capture"], scene["estimate"], prefix=name)
    data = rec.read_recording(path)
    for root in ("clean\\ 00", "clean-01"):
        costs = data[f"{root}/estimator/cost"]
        assert [r["iteration"] for r in costs] == [1, 2, 3, 4, 5]
        assert [r["Scalars:scalars"][0] for r in costs] == pytest.approx(scene["estimate"].history)
        last_fit = np.array(data[f"{root}/world/tape/fit"][-1]["LineStrips3D:strips"][0])
        np.testing.assert_allclose(last_fit, scene["estimate"].nodes, atol=1e-6)
        assert f"{root}/world/cameras/cam1/image/model" in data
        assert f"{root}/world/tape/truth" in data
    assert "world/tape/estimate" not in data
    assert any({"clean\\ 00/world", "clean-01/world", "clean-01/world/cameras/cam0/image",
                "clean\\ 00/estimator"} <= origins for origins in _blueprint_origins(path))


def test_failed_block_leaves_no_file(scene, tmp_path):
    path = tmp_path / "fail.rrd"
    with pytest.raises(RuntimeError):
        with rec.recording(path) as stream:
            rec.log_cameras(stream, scene["cameras"])
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_file_appears_only_on_close(scene, tmp_path):
    path = tmp_path / "late.rrd"
    stream = rec.open_recording(path)
    rec.log_cost(stream, 0, 1.0)
    stream.flush()
    assert not path.exists()
    rec.close_recording(stream)
    assert path.is_file()
    assert rec.read_recording(path)["estimator/cost"][0]["Scalars:scalars"] == [1.0]


def test_unwritable_path_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(rec.RecordingError, match="cannot write the recording"):
        rec.open_recording(blocker / "x.rrd")
    with pytest.raises(rec.RecordingError, match="is a directory"):
        rec.open_recording(tmp_path)
    assert isinstance(rec.RecordingError("x"), TapecellError)


@pytest.mark.skipif(shutil.which("rerun") is None, reason="rerun CLI not installed")
def test_rerun_cli_verifies_the_file(recorded):
    out = subprocess.run(["rerun", "rrd", "verify", str(recorded["path"])], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
