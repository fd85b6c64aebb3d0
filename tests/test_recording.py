"""Rerun recordings: every logger writes a file that reads back with the values logged."""
from __future__ import annotations

import shutil
import subprocess

import cv2
import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from tapecell.cell import recording as rec
from tapecell.cell.story import BodyLook, BodySample, Shape, Story
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
    trace = tuple(fit_angles * (k + 1) / 5 for k in range(5))
    estimate = Estimate(fit_shape.nodes, fit_angles, fit_shape.nodes[-1], fit_shape.frames[-1],
                        cost=0.12, view_costs=np.array([0.1, 0.14]), time_s=0.01, history=history, trace=trace)
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


def _plan(waypoints):
    """A grasp plan as the recorder reads it (names, steps, the first waypoint's joints)."""
    from types import SimpleNamespace

    from tapecell.cell.kinematics import fk
    from tapecell.cell.poses import matrix_to_pose6

    q_pre = np.array([-1.5, -1.9, 2.2, -1.9, -1.6, 0.0])
    flange = fk(q_pre)
    pre = SimpleNamespace(name="pregrasp", world_from_tcp=flange, flange_pose=matrix_to_pose6(flange), q=q_pre)
    return SimpleNamespace(steps=[SimpleNamespace(action="move_linear", waypoint=n) for n in waypoints],
                           approach_tilt_rad=0.0, flipped=False, waypoints=[pre],
                           tool_waypoints=lambda: waypoints)


def _look():
    """Two bodies: a box "arm/link" and a capsule "tools/needle" hidden in the last sample."""
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.05]
    return BodyLook(("arm/link", "tools/needle"),
                    (Shape(0, "box", (0.01, 0.02, 0.03), T, (200, 200, 200, 255)),
                     Shape(1, "capsule", (0.004, 0.02), np.eye(4), (90, 90, 90, 255))))


def _samples():
    out = []
    for k in range(3):
        poses = np.stack([np.eye(4), np.eye(4)])
        poses[:, :3, 3] = [0.3, 0.1 * k, 0.4]
        out.append(BodySample(0.5 * k, poses, np.arange(6) * 0.1 + k, 0.085 - 0.04 * k,
                              frozenset({"tools/needle"}) if k == 2 else frozenset(),
                              "close_gripper done" if k == 1 else None))
    return out


def _write_everything(path, scene):
    """A whole story: capture, estimate (with an optimiser trace), plan, three motion
    samples, a failed result."""
    waypoints = {}
    for k, name in enumerate(("approach", "pregrasp", "grasp", "lift")):
        pose = np.eye(4)
        pose[:3, :3] = rot_x(np.pi)
        pose[:3, 3] = [0.05, 0.0, 0.1 - 0.02 * k]
        waypoints[name] = pose
    story = Story(["cam0", "cam1"])
    story.add("capture", 0.0, scene["capture"])
    story.add("estimate", 0.0, (scene["capture"], scene["estimate"]))
    story.add("plan", 0.0, (_plan(waypoints), np.zeros(6), None))
    story.samples.extend(_samples())
    story.write(path, "tapecell-test", _look(), {"success": False, "tip_error_mm": 1.25, "reason": "slipped"},
                "result: failed: slipped")
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
        "story", "world/cameras/cam0", "world/cameras/cam1", "world/cameras/cam0/image",
        "world/cameras/cam0/image/rgb", "world/cameras/cam0/image/mask",
        "world/cameras/cam0/image/model", "world/cameras/cam0/image/model_outline",
        "world/cameras/cam0/image/ignore", "world/cameras/cam1/image/model",
        "world/tape/fit", "world/tape/estimate", "world/tape/estimate/nodes", "world/tape/estimate/plates",
        "world/tape/estimate/outline", "world/tape/tip", "world/tape/truth",
        "world/tape/truth/tip", "estimator/cost", "estimator/view_cost/cam0",
        "estimator/view_cost/cam1", "estimator/final_cost", "estimator/verdict", "estimator/tip_error_mm",
        "world/bodies/arm/link", "world/bodies/arm/link/box", "world/bodies/tools/needle/capsule",
        "world/arm/flange", "arm/joints", "world/plan/waypoints", "world/plan/path", "world/plan/axes",
        "world/plan/approach", "gripper/opening", "grasp/result", "grasp/tip_error_mm", "grasp/success",
    }
    missing = expected - set(recorded["data"])
    assert not missing


def test_one_timeline_tells_the_story_in_order(recorded, scene):
    """Every logged row that is not static is on the ``step`` timeline, and the story's
    lines come in the order the stages ran, each on its own step (motion samples without
    an event take steps of their own, with no line)."""
    data = recorded["data"]
    story = data["story"]
    steps = [r["step"] for r in story]
    assert steps[:8] == list(range(8)) and all(a < b for a, b in zip(steps, steps[1:]))
    assert steps[-1] == 3 + len(scene["estimate"].trace) + 3   # capture, iterations, verdict, plan, 3 samples, result
    texts = [r["TextLog:text"][0] for r in story]
    n_iter = len(scene["estimate"].trace)
    assert texts[0].startswith("capture: 2 cameras")
    assert [t.split(",")[0] for t in texts[1:1 + n_iter]] == [f"estimate: iteration {k}" for k in range(1, n_iter + 1)]
    assert texts[1 + n_iter].startswith("estimate: verdict ok")
    assert texts[2 + n_iter].startswith("plan: 4 steps")
    assert texts[-2] == "close_gripper done" and texts[-1] == "result: failed: slipped"
    for entity, rows in data.items():
        for r in rows:
            stamped = {k for k in r if k in ("step", "sim_time", "iteration")}
            assert not stamped or "step" in stamped, entity


def test_cost_per_iteration_and_view(recorded, scene):
    """One cost per optimiser iteration, overall and per view, on the iterations' steps:
    the eq.-7 costs of each traced chain, as the estimator computes them."""
    from tapecell.estimator.silhouette import CostEvaluator, make_target

    data, est, capture = recorded["data"], scene["estimate"], scene["capture"]
    evaluator = CostEvaluator([make_target(v) for v in capture.views], capture.scene)
    expected = np.array([evaluator.view_costs(forward_kinematics(capture.tape, a).quads()) for a in est.trace])
    rows = data["estimator/cost"]
    assert [r["step"] for r in rows] == list(range(1, len(est.trace) + 1))
    assert [r["Scalars:scalars"][0] for r in rows] == pytest.approx(np.sqrt((expected ** 2).sum(axis=1)))
    for k, name in enumerate(("cam0", "cam1")):
        costs = [r["Scalars:scalars"][0] for r in data[f"estimator/view_cost/{name}"] if "step" in r]
        assert costs[:len(est.trace)] == pytest.approx(expected[:, k])
    assert costs[-1] == pytest.approx(0.14)    # the final view cost, after the iterations


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


def test_bodies_move_as_sampled(recorded):
    """Each body's world pose per motion sample (step and sim_time); a body hidden in a
    sample (a tool not mounted) is scaled to next to nothing (0 is invalid to the viewer);
    its shapes are logged once."""
    data = recorded["data"]
    link = data["world/bodies/arm/link"]
    assert [r["sim_time"] for r in link] == [0, 500_000_000, 1_000_000_000]
    steps = [r["step"] for r in link]
    assert steps == sorted(steps) and len(set(steps)) == 3
    assert [r["Transform3D:translation"][0][1] for r in link] == pytest.approx([0.0, 0.1, 0.2])
    assert [r["Transform3D:scale"][0] for r in data["world/bodies/tools/needle"]] == [
        [1, 1, 1], [1, 1, 1], pytest.approx([1e-6] * 3)]
    box = _only(data, "world/bodies/arm/link/box")
    assert box["Boxes3D:half_sizes"] == [pytest.approx([0.01, 0.02, 0.03])]
    assert box["Boxes3D:centers"] == [pytest.approx([0.0, 0.0, 0.05])]
    capsule = _only(data, "world/bodies/tools/needle/capsule")   # from its centre back half its length
    assert capsule["Capsules3D:lengths"] == pytest.approx([0.04])
    assert capsule["Capsules3D:translations"] == [pytest.approx([0.0, 0.0, -0.02])]
    joints = data["arm/joints"]
    assert joints[-1]["Scalars:scalars"] == pytest.approx(np.arange(6) * 0.1 + 2)


def test_plan_gripper_and_result(recorded):
    data = recorded["data"]
    wp = _only(data, "world/plan/waypoints")
    assert wp["Points3D:labels"] == list(recorded["waypoints"])
    positions = np.array([p[:3, 3] for p in recorded["waypoints"].values()])
    np.testing.assert_allclose(wp["Points3D:positions"], positions, atol=1e-6)
    np.testing.assert_allclose(_only(data, "world/plan/path")["LineStrips3D:strips"][0], positions,
                               atol=1e-6)
    approach = np.array(_only(data, "world/plan/approach")["LineStrips3D:strips"][0])
    from tapecell.cell.kinematics import fk
    np.testing.assert_allclose(approach[0], fk(np.zeros(6))[:3, 3], atol=1e-6)    # from q_start
    opening = data["gripper/opening"]
    assert [r["Scalars:scalars"][0] for r in opening] == pytest.approx([0.085, 0.045, 0.005])
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


def test_default_blueprint_shows_world_cameras_plots_and_story(recorded):
    assert any({"world", "world/cameras/cam0/image", "world/cameras/cam1/image", "estimator", "arm", "/"}
               <= origins | {"/"} for origins in _blueprint_origins(recorded["path"]))


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
    stream.log("estimator/cost", rr.Scalars([1.0]))
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
