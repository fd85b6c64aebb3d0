"""Rerun recordings of the cell: files, and the loggers of cameras, masks, fits and plans.

Every function takes the :class:`rerun.RecordingStream` to log to; nothing here touches
rerun's global recording. The story of an episode or a run (capture, estimate, plan,
motion, result on one ``step`` timeline, the arm and the tape as geometry) is told by
``cell/story.py`` with these loggers. One entity tree (paths relative to the recording root):

    world/cameras/<cam>                 Transform3D world_from_camera (static)
    world/cameras/<cam>/image           Pinhole K, resolution, drawn as a frustum (static; RDF = OpenCV axes)
    world/cameras/<cam>/image/rgb       Image, the colour frame
    world/cameras/<cam>/image/mask      SegmentationImage, observed silhouette (class 1)
    world/cameras/<cam>/image/model     SegmentationImage, model silhouette (class 2)
    world/cameras/<cam>/image/ignore    SegmentationImage, pixels that do not count (class 3)
    world/cameras/<cam>/image/model_outline   LineStrips2D, the model silhouette's outline
    world/tape/fit                      LineStrips3D centre line at each optimiser iteration
    world/tape/estimate                 LineStrips3D centre line of the fit
    world/tape/estimate/nodes           Points3D P_C[0..n]
    world/tape/estimate/plates          Mesh3D of the plate quads
    world/tape/estimate/outline         LineStrips3D, one closed outline per plate
    world/tape/tip                      Arrows3D tip frame (trunk, left, normal) of the fit
    world/tape/truth                    LineStrips3D true centre line
    world/tape/truth/tip                Arrows3D true tip frame
    world/tape/alternatives/<k>         LineStrips3D, faint: the hypotheses the verdict weighed
    world/scene                         Boxes3D, the scene's boxes (part, table)
    world/plan/waypoints                Points3D, labelled by waypoint name
    world/plan/path                     LineStrips3D through the waypoints in order
    world/plan/axes                     Arrows3D waypoint frames
    estimator/cost                      Scalars per optimiser iteration
    estimator/view_cost/<cam>           Scalars, each view's cost
    estimator/verdict                   TextLog: verdict, reason, costs, alternatives
    estimator/tip_error_mm              Scalars, against truth (simulator)
    grasp/result                        TextLog summary of a grasp
    grasp/<key>                         Scalars of each numeric result field
    (cell/story.py adds story, world/bodies/..., world/arm/flange, world/plan/approach,
    arm/joints, gripper/opening and probe/...)

Fits of several captures in one file (``tapecell estimate A B --rrd F``) are rooted at
``<capture name>/`` (the ``prefix`` argument of the fit loggers), and the blueprint gets a
tab per capture; their cost per iteration is on the ``iteration`` timeline
(:func:`fit_logger`), cleared again after use so it does not stamp unrelated entities.

Pixels: OpenCV puts the centre of the top-left pixel at (0, 0), rerun at (0.5, 0.5); the
conversion happens once, here (``_rerun_K``, ``_rerun_pixels``). Pinhole holds no lens
distortion: 2-D overlays are logged in distorted pixel coordinates and stay right.

The file is written to a hidden temporary sibling and renamed into place by
:func:`close_recording`, so a crashed run leaves no half-written ``.rrd`` behind.
"""
from __future__ import annotations

import atexit
import contextlib
import dataclasses
import os
import uuid
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from tapecell.estimator.capture import Capture, Truth
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.geometry import Camera
from tapecell.estimator.result import Estimate
from tapecell.estimator.silhouette import render_view
from tapecell.estimator.tape import TapeSpec, forward_kinematics

# Class ids of the segmentation overlays (AnnotationContext on each camera's image).
CLASS_MASK, CLASS_MODEL, CLASS_IGNORE = 1, 2, 3
_ANNOTATIONS = [
    (0, "background", (0, 0, 0, 0)),            # transparent: the image shows through
    (CLASS_MASK, "observed", (255, 200, 0)),
    (CLASS_MODEL, "model", (0, 160, 255)),
    (CLASS_IGNORE, "ignored", (120, 120, 120)),
]
_AXIS_COLORS = np.array([[230, 40, 40], [40, 200, 40], [40, 80, 230]], dtype=np.uint8)
FRAME_AXIS_LENGTH_M = 0.01  # tip/waypoint frame arrows: 10 mm, the scale of a plate


class RecordingError(TapecellError):
    """A recording file cannot be written."""


class RecordingFile(rr.RecordingStream):
    """A recording stream that writes an ``.rrd`` file atomically.

    path: the final file; temp_path: the hidden sibling written until :func:`close_recording`.
    """

    def __init__(self, path: Path, temp_path: Path, application_id: str) -> None:
        super().__init__(application_id, recording_id=uuid.uuid4())
        self.path = path
        self.temp_path = temp_path
        self.layout: dict[str, list[str]] = {}  # camera names per fit prefix, for the blueprint


# ---------------------------------------------------------------------------- file


def default_blueprint(camera_names: Sequence[str] = (),
                      roots: Mapping[str, Sequence[str]] | None = None) -> rrb.Blueprint:
    """The layout: 3-D world on the left; camera images, cost and arm plots on the right.

    roots: for recordings of several captures, camera names per prefix; each prefix gets
    a tab with its own world, cameras and cost.
    """
    if roots and any(roots):
        tabs = [_layout(_root(p), cams, name=p or "cell") for p, cams in roots.items()]
        return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)
    return rrb.Blueprint(_layout("", camera_names), collapse_panels=True)


def _layout(root: str, camera_names: Sequence[str], name: str | None = None) -> rrb.Container:
    cams = [rrb.Spatial2DView(origin=f"{root}world/cameras/{n}/image", name=n)
            for n in camera_names]
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin=f"{root}estimator", name="estimator cost"),
        rrb.TimeSeriesView(origin="arm", name="joints"),
        rrb.TimeSeriesView(origin="gripper", name="gripper"),
        rrb.TimeSeriesView(origin="grasp", name="grasp"),
        rrb.TimeSeriesView(origin="calibration", name="calibration"),
    )
    logs = rrb.TextLogView(origin="/", name="events")
    right = [rrb.Grid(*cams, name="cameras")] if cams else []
    right += [plots, logs]
    return rrb.Horizontal(
        rrb.Spatial3DView(origin=f"{root}world", name="world"),
        rrb.Vertical(*right),
        column_shares=[3, 2],
        name=name,
    )


def open_recording(path: str | os.PathLike, app_id: str = "tapecell",
                   camera_names: Sequence[str] = ()) -> RecordingFile:
    """A stream saving to ``path`` (``.rrd``) with the default blueprint.

    The data go to a temporary sibling until :func:`close_recording` renames it into place.
    ``camera_names`` lay out one 2-D view per camera; :func:`log_cameras` updates the
    layout with the cameras it is given.
    """
    path = Path(path)
    if path.is_dir():
        raise RecordingError(f"{path}: is a directory, expected an .rrd file name")
    # A unique hidden name rather than mkstemp, so the file gets the usual permissions.
    tmp = path.parent / f".{path.name}.{uuid.uuid4().hex}.tmp"
    stream = RecordingFile(path, tmp, app_id)
    # Known as open before its file exists: a SIGTERM from here on leaves no .tmp behind.
    _OPEN.add(stream)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        stream.save(tmp, default_blueprint=default_blueprint(camera_names))
    except (OSError, RuntimeError) as e:  # rerun reports file errors as RuntimeError
        _OPEN.discard(stream)
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise RecordingError(f"{path}: cannot write the recording ({e})") from None
    return stream


_OPEN: "set[RecordingFile]" = set()
"""Recordings not yet closed or discarded: removed at exit, so a process that ends without
closing one (an uncaught error, SIGTERM through the CLI) leaves no hidden .tmp file. Held
strongly: a stream whose opening was interrupted is referenced by nothing else, and a weak
set lost it (and its .tmp) as soon as it was collected."""


@atexit.register
def _discard_unclosed() -> None:
    for stream in list(_OPEN):
        with contextlib.suppress(Exception):
            discard_recording(stream)


def close_recording(stream: rr.RecordingStream) -> None:
    """Flush and close the stream; a :class:`RecordingFile` is renamed into place."""
    stream.flush()
    stream.disconnect()
    if isinstance(stream, RecordingFile) and stream.temp_path.exists():
        os.replace(stream.temp_path, stream.path)
    _OPEN.discard(stream)     # only now: until the rename, an interruption removes the .tmp


def discard_recording(stream: rr.RecordingStream) -> None:
    """Close the stream and remove its temporary file (a failed run writes nothing)."""
    stream.disconnect()
    _OPEN.discard(stream)
    if isinstance(stream, RecordingFile):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(stream.temp_path)


@contextlib.contextmanager
def recording(path: str | os.PathLike, app_id: str = "tapecell",
              camera_names: Sequence[str] = ()) -> Iterator[RecordingFile]:
    """``with recording(path) as stream:`` -- the file appears only if the block succeeds."""
    stream = open_recording(path, app_id, camera_names)
    try:
        yield stream
    except BaseException:
        discard_recording(stream)
        raise
    close_recording(stream)


# ---------------------------------------------------------------------------- helpers


def _rerun_K(K: np.ndarray) -> np.ndarray:
    """OpenCV intrinsics -> rerun's (pixel centres at +0.5)."""
    K = np.array(K, dtype=float)
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


def _rerun_pixels(uv: np.ndarray) -> np.ndarray:
    return np.asarray(uv, dtype=float).reshape(-1, 2) + 0.5


def _axes_arrows(origins: np.ndarray, rotations: np.ndarray, length: float) -> rr.Arrows3D:
    """Arrows3D of frames: (N, 3) origins, (N, 3, 3) world_from_frame rotations."""
    origins = np.asarray(origins, float).reshape(-1, 3)
    rotations = np.asarray(rotations, float).reshape(-1, 3, 3)
    vectors = length * np.transpose(rotations, (0, 2, 1)).reshape(-1, 3)  # columns x, y, z
    return rr.Arrows3D(vectors=vectors, origins=np.repeat(origins, 3, axis=0),
                       colors=np.tile(_AXIS_COLORS, (len(origins), 1)))


def _root(prefix: str | None) -> str:
    """Entity root of a fit: "" or "<escaped prefix>/" (several captures in one file)."""
    return f"{rr.escape_entity_path_part(prefix)}/" if prefix else ""


def _image_path(camera_name: str, prefix: str | None = None) -> str:
    return f"{_root(prefix)}world/cameras/{camera_name}/image"


def _class_image(mask: np.ndarray, class_id: int) -> np.ndarray:
    return np.asarray(mask, dtype=bool).astype(np.uint8) * np.uint8(class_id)


# ---------------------------------------------------------------------------- cameras


FRUSTUM_DEPTH_M = 0.12
"""How far the cameras' frusta reach into the 3-D view [m] (about a fifth of the way to the tape)."""


def log_cameras(stream: rr.RecordingStream, cameras: Iterable[Camera],
                prefix: str | None = None, blueprint: bool = True) -> None:
    """Each camera's pose, intrinsics (drawn as a frustum) and overlay colours (static),
    and, unless ``blueprint`` is False, a layout showing them."""
    cameras = list(cameras)
    for cam in cameras:
        stream.log(f"{_root(prefix)}world/cameras/{cam.name}",
                   rr.Transform3D(translation=cam.center, mat3x3=cam.R.T), static=True)
        stream.log(_image_path(cam.name, prefix),
                   rr.Pinhole(image_from_camera=_rerun_K(cam.K), resolution=[cam.width, cam.height],
                              camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=FRUSTUM_DEPTH_M,
                              color=[255, 255, 255], line_width=0.002),
                   rr.AnnotationContext(_ANNOTATIONS), static=True)
    if not blueprint:
        return
    names = [c.name for c in cameras]
    if isinstance(stream, RecordingFile):
        stream.layout[prefix or ""] = names
        blueprint = default_blueprint(names, stream.layout if prefix else None)
    else:
        blueprint = default_blueprint(names, {prefix: names} if prefix else None)
    stream.send_blueprint(blueprint, make_active=False, make_default=True)


def log_view(stream: rr.RecordingStream, camera: Camera, mask: np.ndarray,
             image: np.ndarray | None = None, model_mask: np.ndarray | None = None,
             ignore: np.ndarray | None = None, prefix: str | None = None) -> None:
    """One camera's frame: RGB image, observed mask, model silhouette and ignored pixels.

    mask, model_mask, ignore: (H, W) bool; image: (H, W, 3) uint8 RGB.
    """
    base = _image_path(camera.name, prefix)
    if image is not None:
        stream.log(f"{base}/rgb", rr.Image(np.asarray(image, np.uint8), color_model="RGB",
                                           draw_order=-10.0))
    stream.log(f"{base}/mask", rr.SegmentationImage(_class_image(mask, CLASS_MASK),
                                                    opacity=0.6, draw_order=0.0))
    if model_mask is not None:
        log_model(stream, camera, model_mask, prefix)
    if ignore is not None:
        stream.log(f"{base}/ignore", rr.SegmentationImage(_class_image(ignore, CLASS_IGNORE),
                                                          opacity=0.4, draw_order=2.0))


def log_model(stream: rr.RecordingStream, camera: Camera, model_mask: np.ndarray,
              prefix: str | None = None) -> None:
    """The model's silhouette in one camera's view, faint, with its outline on top: a
    mismatch with the observed mask shows at a glance. model_mask: (H, W) bool."""
    base = _image_path(camera.name, prefix)
    stream.log(f"{base}/model", rr.SegmentationImage(_class_image(model_mask, CLASS_MODEL),
                                                     opacity=0.35, draw_order=1.0))
    contours, _ = cv2.findContours(np.asarray(model_mask, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    strips = [_rerun_pixels(np.vstack([c.reshape(-1, 2), c.reshape(-1, 2)[:1]]).astype(float))
              for c in contours if len(c) > 1]
    stream.log(f"{base}/model_outline", rr.LineStrips2D(strips, radii=1.0, colors=[[0, 90, 255]],
                                                        draw_order=3.0))


def model_silhouette(camera: Camera, spec: TapeSpec, angles: np.ndarray, boxes: Sequence[Any] = ()) -> np.ndarray:
    """(H, W) bool silhouette of the plate model for (n, 3) ``angles`` [rad] seen by ``camera``
    (without what the scene's ``boxes`` hide from it).

    The estimator's own renderer, so the overlay shows exactly what its cost compares.
    """
    return render_view(camera, forward_kinematics(spec, angles), boxes)


# ---------------------------------------------------------------------------- tape


def _log_tape_shape(stream: rr.RecordingStream, base: str, spec: TapeSpec,
                    angles: np.ndarray) -> None:
    shape = forward_kinematics(spec, angles)
    quads = shape.quads()
    stream.log(base, rr.LineStrips3D([shape.nodes], radii=0.0004, colors=[[0, 160, 255]]))
    stream.log(f"{base}/nodes", rr.Points3D(shape.nodes, radii=0.0008, colors=[[0, 90, 200]]))
    n = len(quads)
    first = 4 * np.arange(n)[:, None]  # each quad is two triangles (0, 1, 2), (0, 2, 3)
    tri = np.concatenate([first + [0, 1, 2], first + [0, 2, 3]])
    stream.log(f"{base}/plates", rr.Mesh3D(vertex_positions=quads.reshape(-1, 3),
                                            triangle_indices=tri, albedo_factor=[0, 160, 255, 110]))
    outlines = np.concatenate([quads, quads[:, :1]], axis=1)  # closed loops
    stream.log(f"{base}/outline", rr.LineStrips3D(list(outlines), radii=0.0002,
                                                  colors=[[0, 90, 200]]))


def _log_alternative(stream: rr.RecordingStream, base: str, spec: TapeSpec, angles: np.ndarray) -> None:
    """A hypothesis the verdict weighed: its centre line and plate outlines, faint."""
    shape = forward_kinematics(spec, angles)
    quads = shape.quads()
    outlines = np.concatenate([quads, quads[:, :1]], axis=1)
    stream.log(base, rr.LineStrips3D([shape.nodes] + list(outlines), radii=0.0002, colors=[[255, 140, 0, 90]]))


def log_scene(stream: rr.RecordingStream, boxes: Sequence[Any], prefix: str | None = None) -> None:
    """The scene's boxes (the part, the table) that may hide the tape."""
    if not boxes:
        return
    stream.log(f"{_root(prefix)}world/scene", rr.Boxes3D(
        centers=[b.center for b in boxes], half_sizes=[b.half for b in boxes],
        quaternions=[rr.Quaternion(xyzw=_quat_xyzw(b.rotation)) for b in boxes],
        labels=[b.name for b in boxes], colors=[[150, 150, 150, 120]], fill_mode="solid"), static=True)


def _quat_xyzw(R: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, float)).as_quat().tolist()


def log_estimate(stream: rr.RecordingStream, estimate: Estimate, spec: TapeSpec,
                 view_names: Sequence[str] | None = None, prefix: str | None = None) -> None:
    """The fitted tape in 3-D (centre line, nodes, plates), its tip frame and view costs.

    view_names: camera names in the order of ``estimate.view_costs`` (default view0..).
    """
    root = _root(prefix)
    _log_tape_shape(stream, f"{root}world/tape/estimate", spec, estimate.angles)
    stream.log(f"{root}world/tape/tip", _axes_arrows(estimate.tip_position, estimate.tip_rotation,
                                              FRAME_AXIS_LENGTH_M))
    names = list(view_names) if view_names is not None else [
        f"view{i}" for i in range(len(estimate.view_costs))]
    for name, cost in zip(names, np.asarray(estimate.view_costs, float)):
        stream.log(f"{root}estimator/view_cost/{name}", rr.Scalars([cost]))
    stream.log(f"{root}estimator/final_cost", rr.Scalars([float(estimate.cost)]))
    verdict = getattr(estimate.verdict, "value", str(estimate.verdict))
    lines = [f"verdict: {verdict}" + (f" ({estimate.verdict_reason})" if estimate.verdict_reason else ""),
             f"cameras seeing the free end: {estimate.tip_views}",
             f"cost (eq. 11): {float(estimate.cost):.4f}; per view: "
             + ", ".join(f"{n} {c:.4f}" for n, c in zip(names, np.asarray(estimate.view_costs, float)))]
    offsets = np.asarray(getattr(estimate, "view_offsets_px", ()), float)
    if offsets.size:
        lines.append("mean boundary distance px: " + ", ".join(f"{n} {o:.2f}" for n, o in zip(names, offsets)))
    for k, alt in enumerate(estimate.alternatives):
        d = 1e3 * float(np.linalg.norm(np.asarray(alt.tip_position) - estimate.tip_position))
        lines.append(f"alternative {k}: cost {alt.cost:.4f}, tip {d:.0f} mm away")
        _log_alternative(stream, f"{root}world/tape/alternatives/{k}", spec, alt.angles)
    stream.log(f"{root}estimator/verdict", rr.TextLog("\n".join(lines),
                                                     level="INFO" if verdict == "ok" else "WARN"))


def log_truth(stream: rr.RecordingStream, truth: Truth, prefix: str | None = None) -> None:
    """The true centre line and tip frame (simulated captures)."""
    root = _root(prefix)
    stream.log(f"{root}world/tape/truth", rr.LineStrips3D([truth.points], radii=0.0004,
                                                   colors=[[40, 200, 40]]))
    stream.log(f"{root}world/tape/truth/tip", _axes_arrows(truth.tip_position, truth.tip_rotation,
                                                    FRAME_AXIS_LENGTH_M))


def fit_logger(stream: rr.RecordingStream, capture: Capture,
               prefix: str | None = None) -> Callable[[int, float, np.ndarray], None]:
    """An ``estimator.estimate`` callback logging the cost and the current centre line at
    each optimiser iteration (``iteration`` timeline)."""
    root = _root(prefix)

    def on_iteration(iteration: int, cost: float, angles: np.ndarray) -> None:
        stream.set_time("iteration", sequence=int(iteration))
        stream.log(f"{root}estimator/cost", rr.Scalars([float(cost)]))
        nodes = forward_kinematics(capture.tape, angles).nodes
        stream.log(f"{root}world/tape/fit", rr.LineStrips3D([nodes], radii=0.0002,
                                                            colors=[[160, 160, 160]]))
        stream.disable_timeline("iteration")

    return on_iteration


def log_fit_result(stream: rr.RecordingStream, capture: Capture, estimate: Estimate,
                   prefix: str | None = None) -> None:
    """The outcome of one fit: cameras, each view with the model overlay, the tape and the
    truth when known. ``prefix`` roots it all at "<prefix>/" (several captures, one file)."""
    log_cameras(stream, capture.cameras, prefix)
    for view in capture.views:
        log_view(stream, view.camera, view.mask, image=view.image,
                 model_mask=model_silhouette(view.camera, capture.tape, estimate.angles),
                 ignore=view.ignore, prefix=prefix)
    log_scene(stream, capture.scene, prefix)
    log_estimate(stream, estimate, capture.tape, [c.name for c in capture.cameras], prefix)
    if capture.truth is not None:
        log_truth(stream, capture.truth, prefix)
        error_mm = 1e3 * float(np.linalg.norm(estimate.tip_position - capture.truth.tip_position))
        stream.log(f"{_root(prefix)}estimator/tip_error_mm", rr.Scalars([error_mm]))


# ---------------------------------------------------------------------------- arm, plan, grasp


def log_plan(stream: rr.RecordingStream, waypoints: Mapping[str, np.ndarray]) -> None:
    """Named world_from_tool 4x4 waypoints, in the order they are visited."""
    names = list(waypoints)
    if not names:
        return
    poses = np.stack([np.asarray(waypoints[n], float).reshape(4, 4) for n in names])
    origins = poses[:, :3, 3]
    stream.log("world/plan/waypoints", rr.Points3D(origins, labels=names, radii=0.002,
                                                   colors=[[255, 120, 0]]))
    stream.log("world/plan/path", rr.LineStrips3D([origins], radii=0.0008, colors=[[255, 120, 0]]))
    stream.log("world/plan/axes", _axes_arrows(origins, poses[:, :3, :3], FRAME_AXIS_LENGTH_M))


def _as_mapping(result: Any) -> Mapping[str, Any]:
    if dataclasses.is_dataclass(result) and not isinstance(result, type):
        return dataclasses.asdict(result)
    return result


def log_result(stream: rr.RecordingStream, result: Any) -> None:
    """A grasp result (mapping or dataclass): one summary line, and each number as a series.

    A ``success`` field set to False makes the summary a warning.
    """
    fields = _as_mapping(result)
    parts = []
    for key, value in fields.items():
        if isinstance(value, (bool, np.bool_)):
            parts.append(f"{key}={bool(value)}")
            stream.log(f"grasp/{key}", rr.Scalars([float(value)]))
        elif isinstance(value, (int, float, np.integer, np.floating)):
            parts.append(f"{key}={value:.6g}")
            stream.log(f"grasp/{key}", rr.Scalars([float(value)]))
        elif isinstance(value, (str, type(None))):
            parts.append(f"{key}={value}")
    level = "WARN" if fields.get("success") is False else "INFO"
    stream.log("grasp/result", rr.TextLog(" ".join(parts), level=level))


def read_recording(path: str | os.PathLike) -> dict[str, list[dict[str, Any]]]:
    """An ``.rrd`` file's recording as ``{entity path: [row, ...]}`` (for tests and checks).

    Entity paths lose their leading "/". Each row is one logged message: a dict of
    component column ("Scalars:scalars", "Points3D:positions", ...) to its Python value,
    and of each timeline it is stamped on ("iteration", "sim_time" in ns, ...) to its time;
    static rows have no timelines. Rows are in logging order.
    """
    from rerun.chunk import RrdReader

    rows: dict[str, list[tuple[bytes, dict[str, Any]]]] = {}
    for chunk in RrdReader(str(path)).store().stream().to_chunks():
        batch = chunk.to_record_batch()
        entity = chunk.entity_path.lstrip("/")
        columns: dict[str, list[Any]] = {}
        row_ids = None
        for field, column in zip(batch.schema, batch.columns):
            kind = (field.metadata or {}).get(b"rerun:kind", b"").decode()
            if kind == "control":
                row_ids = column.to_pylist()
            elif kind == "index":
                if field.name == "log_time":
                    continue
                columns[field.name] = column.cast("int64").to_pylist()
            else:
                columns[field.name] = column.to_pylist()
        out = rows.setdefault(entity, [])
        for i in range(batch.num_rows):
            row = {k: v[i] for k, v in columns.items() if v[i] is not None}
            out.append((row_ids[i] if row_ids is not None else b"", row))
    # RowIds are time-ordered (TUIDs), so sorting restores logging order across chunks.
    return {e: [r for _, r in sorted(rs, key=lambda x: x[0])] for e, rs in rows.items()}
