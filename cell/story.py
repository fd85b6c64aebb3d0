"""A recording that tells a grasp's story in order: capture, estimate, plan, motion, result.

The stages of an episode (simulator) or a run (real cell) do their work without knowing
about recordings; they return what they found (a :class:`~tapecell.estimator.capture.Capture`,
an :class:`~tapecell.estimator.result.Estimate` with its optimiser trace, a
:class:`~tapecell.cell.planner.GraspPlan` or the refusal, the arm's motion as
:class:`BodySample` s, the result), and one :class:`Recorder` logs them afterwards.

Everything is logged on one timeline, ``step`` (a sequence): each event advances it by one,
also the ones that take no cell time (an optimiser iteration, the verdict, the plan), so
scrubbing it replays the story. Motion samples are stamped with ``sim_time`` (cell time,
a duration) as well. The viewer opens on ``step`` at its end: the last images, the fitted
and true tape, the arm where it stopped, and the whole cost and joint plots.

The 3-D scene is geometry: a :class:`BodyLook` lists named bodies (arm links, tools, in
the simulator also the tape's plates) and the primitive shapes attached to each; a sample
is every body's world pose at one time. The simulator builds its look from the MuJoCo
model's own geoms (``sim/look.py``); the real cell from the UR5e's DH model
(:func:`ur5e_look`), as capsules along its links.

Entities added to ``cell/recording.py``'s tree:

    story                               TextLog, one line per step (what happened)
    world/bodies/<name>                 Transform3D world_from_body per motion sample
    world/bodies/<name>/shapes          Boxes3D / Capsules3D / Cylinders3D / Ellipsoids3D (static)
    world/plan/approach                 LineStrips3D, the TCP's path on the joint move
    estimator/view_cost/<cam>           Scalars per optimiser iteration and view
    probe/<label>                       Points3D where the needle aimed and what it touched
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from tapecell.estimator.capture import Capture
from tapecell.estimator.result import Estimate
from tapecell.estimator.silhouette import CostEvaluator, make_target
from tapecell.estimator.tape import forward_kinematics

from . import recording as rec
from .kinematics import DH_A, DH_D, dh_frames

TIMELINE = "step"
HIDDEN_SCALE = 1e-6
"""Scale of a body not shown at a step (a tool not mounted): a 100 mm tool becomes 0.1 um."""


@dataclass(frozen=True)
class Shape:
    """A primitive attached to body ``body`` (index into :attr:`BodyLook.names`).

    kind: "box" (size = half extents x, y, z), "capsule" or "cylinder" (size = radius,
    half length along the shape's z), "sphere" (size = radius); body_from_shape: 4x4 [m];
    rgba: 0-255."""

    body: int
    kind: str
    size: tuple[float, ...]
    body_from_shape: np.ndarray
    rgba: tuple[int, int, int, int]


@dataclass(frozen=True)
class BodyLook:
    """Named bodies ("arm/shoulder", "tape/3", "tools/gripper_finger_left") and their shapes.

    Each body's entity holds its world pose, so no name is a path prefix of another's
    (rerun would compose the two transforms)."""

    names: tuple[str, ...]
    shapes: tuple[Shape, ...]


@dataclass(frozen=True)
class BodySample:
    """The bodies at one time: t [s] cell time, world_from_body (k, 4, 4) in the look's
    order, joints (6,) [rad], gripper opening [m] (None when unknown), hidden: names of the
    bodies not shown then (tools not mounted), event: what began at this sample."""

    t: float
    world_from_body: np.ndarray
    joints: np.ndarray
    gripper_opening: float | None = None
    hidden: frozenset[str] = frozenset()
    event: str | None = None


# ------------------------------------------------------------------------ the real cell's arm
_LINK_RADII = (0.060, 0.054, 0.045, 0.038, 0.038, 0.038, 0.032)
_ARM_GREY = (190, 192, 198, 255)
_JOINT_BLUE = (90, 150, 210, 255)


def ur5e_look(gripper: Any = None) -> BodyLook:
    """The UR5e as capsules from its DH model (real cell): one body per DH frame 0..6; a
    capsule along each link's offsets (d along the previous z, a along x) and a joint
    housing (cylinder) at each frame's z axis; with ``gripper`` (a
    :class:`~tapecell.cell.planner.GripperGeometry`) its open fingers and palm as boxes on
    the flange."""
    names = tuple(["arm/base"] + [f"arm/link{i}" for i in range(1, 7)])
    shapes: list[Shape] = []
    for i in range(6):
        # Frame i -> i+1: rotate about z_i, then d along z_i, then a along the new x.
        if DH_D[i] > 1e-6:            # along z of frame i (body i)
            shapes.append(_capsule(i, np.zeros(3), np.array([0.0, 0.0, DH_D[i]]), _LINK_RADII[i], _ARM_GREY))
        if abs(DH_A[i]) > 1e-6:       # along x of frame i+1, ending at its origin (body i+1)
            shapes.append(_capsule(i + 1, np.array([-DH_A[i], 0.0, 0.0]), np.zeros(3), _LINK_RADII[i], _ARM_GREY))
        T = np.eye(4)
        shapes.append(Shape(i, "cylinder", (_LINK_RADII[i] * 1.15, _LINK_RADII[i] * 1.2), T, _JOINT_BLUE))
    shapes.append(Shape(6, "cylinder", (0.032, 0.008), _translation([0.0, 0.0, -0.008]), (60, 60, 64, 255)))
    if gripper is not None:
        flange_from_tcp = np.asarray(gripper.flange_from_tcp, float)
        tcp_z = float(flange_from_tcp[2, 3])
        shapes.append(_capsule(6, np.zeros(3), np.array([0.0, 0.0, max(tcp_z - 0.03, 0.01)]), 0.025,
                               (50, 50, 55, 255)))
        for lo, hi in gripper.finger_boxes_tcp():
            T = flange_from_tcp @ _translation(0.5 * (np.asarray(lo) + np.asarray(hi)))
            shapes.append(Shape(6, "box", tuple(0.5 * (np.asarray(hi) - np.asarray(lo))), T, (70, 70, 76, 255)))
    return BodyLook(names, tuple(shapes))


def ur5e_poses(q: Sequence[float]) -> np.ndarray:
    """(7, 4, 4) world_from_body of :func:`ur5e_look` at joints ``q`` [rad]."""
    return dh_frames(np.asarray(q, float))


def _translation(p: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def _capsule(body: int, a: np.ndarray, b: np.ndarray, radius: float, rgba) -> Shape:
    """A capsule between points a and b of body ``body`` (its z along b - a)."""
    d = b - a
    length = float(np.linalg.norm(d))
    z = d / length
    x = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = 0.5 * (a + b)
    return Shape(body, "capsule", (radius, 0.5 * length), T, tuple(rgba))


# ------------------------------------------------------------------------ the story
@dataclass
class Story:
    """What a grasp's stages found, in order, kept for its recording (cheap: references).

    ``add(stage, t, found)`` after each stage: "capture" (a Capture), "estimate" ((Capture,
    Estimate)), "probes" (list of probe mappings), "plan" ((GraspPlan or None, q_start,
    refusal or None)); ``samples`` gets the arm's motion as it happens. :meth:`write` logs
    it all with one :class:`Recorder`."""

    camera_names: Sequence[str] = ()
    events: list[tuple[str, float | None, int, Any, str]] = field(default_factory=list)
    samples: list[BodySample] = field(default_factory=list)

    def add(self, stage: str, t: float | None, found: Any, note: str = "") -> None:
        self.events.append((stage, t, len(self.samples), found, note))

    def write(self, path: Any, app_id: str, look: BodyLook | None, result: Mapping[str, Any],
              result_text: str) -> None:
        """The recording at ``path`` (written atomically): the stages in order, the motion
        samples between them where they were taken, ``result`` last."""
        with rec.recording(path, app_id=app_id) as stream:
            r = Recorder(stream, look, self.camera_names)
            shown = captures = 0
            for stage, t, n_samples, found, note in self.events:
                r.motion(self.samples[shown:n_samples])
                shown = max(shown, n_samples)
                if t is not None:
                    r.sim_time = t
                if stage == "capture":
                    r.capture(found, "capture" if not captures else "capture again, the arm parked out of view")
                    captures += 1
                elif stage == "estimate":
                    r.estimate(*found, text=f"estimate {note}".strip(), iterations=not note)
                elif stage == "probes":
                    r.probes(found)
                elif stage == "plan":
                    r.plan(*found)
                else:
                    raise ValueError(f"unknown stage {stage!r}")
            r.motion(self.samples[shown:])
            r.result({k: v for k, v in result.items() if not isinstance(v, (dict, list))}, result_text)


# ------------------------------------------------------------------------ the recorder
class Recorder:
    """Logs a grasp's stages to ``stream`` in the order they are given, each on its own
    ``step``. ``look``: the bodies :meth:`motion` moves (static shapes logged once)."""

    def __init__(self, stream: rr.RecordingStream, look: BodyLook | None = None,
                 camera_names: Sequence[str] = ()) -> None:
        self.stream = stream
        self.look = look
        self.step = -1
        self.sim_time: float | None = None
        self._cameras_logged = False
        self.camera_names = list(camera_names)
        stream.send_blueprint(blueprint(camera_names), make_active=True, make_default=True)
        if look is not None:
            self._log_shapes(look)

    # -- the timeline
    def advance(self, text: str, level: str = "INFO", sim_time: float | None = None) -> None:
        """The next step: what happened, at cell time ``sim_time`` [s] when known."""
        self.step += 1
        self.stream.set_time(TIMELINE, sequence=self.step)
        if sim_time is not None:
            self.sim_time = float(sim_time)
        if self.sim_time is not None:
            self.stream.set_time("sim_time", duration=self.sim_time)
        self.stream.log("story", rr.TextLog(text, level=level))

    # -- the stages
    def capture(self, capture: Capture, text: str = "capture", sim_time: float | None = None) -> None:
        """The images and masks every camera took (the cameras and the scene once)."""
        names = [v.camera.name for v in capture.views]
        self.advance(f"{text}: {len(names)} cameras ({', '.join(names)})", sim_time=sim_time)
        if not self._cameras_logged:
            self.stream.send_blueprint(blueprint(self.camera_names or names, capture.tape.base_position),
                                       make_active=True, make_default=True)
            rec.log_cameras(self.stream, capture.cameras, blueprint=False)
            rec.log_scene(self.stream, capture.scene)
            self._cameras_logged = True
        for view in capture.views:
            rec.log_view(self.stream, view.camera, view.mask, image=view.image, ignore=view.ignore)

    def estimate(self, capture: Capture, est: Estimate, text: str = "estimate", iterations: bool = True) -> None:
        """The optimiser's iterations unless ``iterations`` is False (one step each: the
        chain, the cost overall and per view), then the final chain with its silhouette outline on every view, the verdict
        and the alternatives; the truth and the tip error when the capture has them."""
        names = [v.camera.name for v in capture.views]
        trace = list(est.trace) if iterations else []
        if trace:
            evaluator = CostEvaluator([make_target(v) for v in capture.views], capture.scene)
            for k, angles in enumerate(trace, 1):
                shape = forward_kinematics(capture.tape, angles)
                view_costs = evaluator.view_costs(shape.quads())
                cost = float(np.sqrt(np.sum(view_costs ** 2)))
                self.advance(f"{text}: iteration {k}, cost {cost:.4f}")
                self.stream.log("estimator/cost", rr.Scalars([cost]))
                for name, c in zip(names, view_costs):
                    self.stream.log(f"estimator/view_cost/{name}", rr.Scalars([float(c)]))
                self.stream.log("world/tape/fit", rr.LineStrips3D([shape.nodes], radii=0.0003,
                                                                  colors=[[170, 170, 170]]))
        verdict = est.verdict.value
        self.advance(f"{text}: verdict {verdict}" + (f" ({est.verdict_reason})" if est.verdict_reason else "")
                     + f", cost {est.cost:.4f}, {est.time_s * 1e3:.0f} ms",
                     level="INFO" if verdict == "ok" else "WARN")
        self.stream.log("world/tape/fit", rr.Clear(recursive=False))
        for view in capture.views:
            model = rec.model_silhouette(view.camera, capture.tape, est.angles, capture.scene)
            rec.log_model(self.stream, view.camera, model)
        rec.log_estimate(self.stream, est, capture.tape, names)
        if capture.truth is not None:
            rec.log_truth(self.stream, capture.truth)
            error_mm = 1e3 * float(np.linalg.norm(est.tip_position - capture.truth.tip_position))
            self.stream.log("estimator/tip_error_mm", rr.Scalars([error_mm]))

    def probes(self, probes: Sequence[Mapping[str, Any]]) -> None:
        """Needle probes: each a mapping with ``label``, ``aimed`` (3,), ``touched`` (3,) or
        None, and ``t`` [s]."""
        for p in probes:
            touched = p.get("touched")
            aimed = np.asarray(p["aimed"], float)
            if touched is None:
                text = f"probe {p['label']}: nothing touched"
            else:
                text = (f"probe {p['label']}: touched "
                        f"{1e3 * float(np.linalg.norm(np.asarray(touched) - aimed)):.1f} mm from the aim")
            self.advance(text, sim_time=p.get("t"))
            points = [aimed] + ([np.asarray(touched, float)] if touched is not None else [])
            colors = [[255, 0, 200]] + ([[0, 230, 120]] if touched is not None else [])
            self.stream.log(f"probe/{rr.escape_entity_path_part(p['label'])}",
                            rr.Points3D(points, radii=0.0015, colors=colors))

    def plan(self, plan: Any = None, q_start: Sequence[float] | None = None, refusal: Any = None) -> None:
        """The grasp plan (waypoints, the TCP's path on the joint move from ``q_start``),
        or the planner's refusal."""
        if plan is None:
            self.advance(f"plan refused: {getattr(refusal, 'reason', '')}: {getattr(refusal, 'detail', refusal)}",
                         level="WARN")
            return
        self.advance(f"plan: {len(plan.steps)} steps, approach tilt {np.degrees(plan.approach_tilt_rad):.0f} deg"
                     + (", jaw flipped" if plan.flipped else ""))
        rec.log_plan(self.stream, plan.tool_waypoints())
        if q_start is not None:
            from .poses import invert, pose6_to_matrix

            pre = plan.waypoints[0]
            flange_from_tcp = invert(pose6_to_matrix(pre.flange_pose)) @ pre.world_from_tcp
            qs = np.linspace(np.asarray(q_start, float), pre.q, 24)
            path = np.array([(dh_frames(q)[-1] @ flange_from_tcp)[:3, 3] for q in qs])
            self.stream.log("world/plan/approach", rr.LineStrips3D([path], radii=0.0015, colors=[[255, 170, 60]]))

    def motion(self, samples: Sequence[BodySample]) -> None:
        """The bodies, joints and gripper at each sample, one step each."""
        samples = _moving(samples)
        if not samples:
            return
        names = self.look.names if self.look is not None else ()
        steps = np.arange(self.step + 1, self.step + 1 + len(samples))
        times = np.array([s.t for s in samples])
        index = [rr.TimeColumn(TIMELINE, sequence=steps), rr.TimeColumn("sim_time", duration=times)]
        poses = np.stack([s.world_from_body for s in samples])          # (m, k, 4, 4)
        for j, name in enumerate(names):
            # A hidden body (a tool not mounted) is scaled to next to nothing (a scale of 0
            # is an invalid transform to the viewer, which then shows an error).
            scale = np.array([[HIDDEN_SCALE] * 3 if name in s.hidden else [1.0] * 3 for s in samples])
            self.stream.send_columns(f"world/bodies/{name}", indexes=index, columns=rr.Transform3D.columns(
                translation=poses[:, j, :3, 3], mat3x3=poses[:, j, :3, :3], scale=scale))
        self.stream.send_columns("arm/joints", indexes=index,
                                 columns=rr.Scalars.columns(scalars=np.stack([s.joints for s in samples])))
        openings = [(i, s.gripper_opening) for i, s in enumerate(samples) if s.gripper_opening is not None]
        if openings:
            idx = [i for i, _ in openings]
            self.stream.send_columns("gripper/opening",
                                     indexes=[rr.TimeColumn(TIMELINE, sequence=steps[idx]),
                                              rr.TimeColumn("sim_time", duration=times[idx])],
                                     columns=rr.Scalars.columns(scalars=[o for _, o in openings]))
        flange = np.array([ur5e_poses(s.joints)[-1] for s in samples])
        self.stream.send_columns("world/arm/flange", indexes=index, columns=rr.Transform3D.columns(
            translation=flange[:, :3, 3], mat3x3=flange[:, :3, :3]))
        for i, s in enumerate(samples):
            if s.event:
                self.stream.set_time(TIMELINE, sequence=int(steps[i]))
                self.stream.set_time("sim_time", duration=float(s.t))
                self.stream.log("story", rr.TextLog(s.event, level="INFO"))
        self.step = int(steps[-1])
        self.sim_time = float(times[-1])
        self.stream.set_time(TIMELINE, sequence=self.step)

    def result(self, fields: Mapping[str, Any], text: str) -> None:
        """The outcome: one line (a warning unless it succeeded) and each number as a series."""
        ok = fields.get("success") is not False
        self.advance(text, level="INFO" if ok else "WARN")
        rec.log_result(self.stream, fields)

    # -- static geometry
    def _log_shapes(self, look: BodyLook) -> None:
        for j, name in enumerate(look.names):
            mine = [s for s in look.shapes if s.body == j]
            for kind in ("box", "capsule", "cylinder", "sphere"):
                group = [s for s in mine if s.kind == kind]
                if group:
                    self.stream.log(f"world/bodies/{name}/{kind}", _shapes(kind, group), static=True)


def _shapes(kind: str, group: Sequence[Shape]) -> Any:
    T = np.stack([s.body_from_shape for s in group])
    quats = [rr.Quaternion(xyzw=q) for q in _quats_xyzw(T[:, :3, :3])]
    colors = [s.rgba for s in group]
    if kind == "box":
        return rr.Boxes3D(half_sizes=[s.size[:3] for s in group], centers=T[:, :3, 3], quaternions=quats,
                          colors=colors, fill_mode="solid")
    if kind == "sphere":
        return rr.Ellipsoids3D(half_sizes=[[s.size[0]] * 3 for s in group], centers=T[:, :3, 3], colors=colors,
                               fill_mode="solid")
    radius = np.array([s.size[0] for s in group])
    half = np.array([s.size[1] for s in group])
    if kind == "cylinder":
        return rr.Cylinders3D(lengths=2 * half, radii=radius, centers=T[:, :3, 3], quaternions=quats,
                              colors=colors, fill_mode="solid")
    # Capsules3D starts at its translation and runs along +z: from the centre back half a length.
    starts = T[:, :3, 3] - half[:, None] * T[:, :3, 2]
    return rr.Capsules3D(lengths=2 * half, radii=radius, translations=starts, quaternions=quats,
                         colors=colors, fill_mode="solid")


def _quats_xyzw(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


MOTION_STEP_M = 0.002
"""A motion sample is recorded when some body moved this far since the last recorded one
(or it marks an event, or it is the last): pauses (settling, the gripper closing on its
own) take no steps, and a long probing run stays a few MB."""


def _moving(samples: Sequence[BodySample]) -> list[BodySample]:
    kept: list[BodySample] = []
    for i, s in enumerate(samples):
        if kept and not s.event and i < len(samples) - 1 and s.hidden == kept[-1].hidden:
            moved = np.max(np.linalg.norm(s.world_from_body[:, :3, 3] - kept[-1].world_from_body[:, :3, 3], axis=1),
                           initial=0.0)
            opening = (s.gripper_opening or 0.0) - (kept[-1].gripper_opening or 0.0)
            if moved < MOTION_STEP_M and abs(opening) < MOTION_STEP_M:
                continue
        kept.append(s)
    return kept


# ------------------------------------------------------------------------ layout
EYE_OFFSET_M = (0.50, 0.30, 0.30)
"""Where the 3-D view's eye starts, from the tape's base [m]: beyond the tape as seen from
the robot (along the robot-to-tape direction, across it, up), so the arm comes towards the
viewer and does not hide the tape; near enough to see the tape's plates."""


def blueprint(camera_names: Sequence[str], look_target: Sequence[float] | None = None) -> rrb.Blueprint:
    """3-D scene on the left (looking at ``look_target`` when given); the camera views, the
    cost and arm plots and the story on the right; opened on the ``step`` timeline at its
    end (following), so the whole story is shown."""
    cams = [rrb.Spatial2DView(origin=f"world/cameras/{n}/image", name=n) for n in camera_names]
    plots = rrb.Horizontal(
        rrb.TimeSeriesView(origin="estimator", name="estimator cost (per view, overall)",
                           contents=["$origin/**", "- $origin/tip_error_mm"]),   # mm would squash the costs
        rrb.Tabs(rrb.TimeSeriesView(origin="arm", name="joints [rad]"),
                 rrb.TimeSeriesView(origin="gripper", name="gripper [m]"),
                 rrb.TimeSeriesView(origin="grasp", name="result")),
    )
    story = rrb.TextLogView(origin="/", name="story")
    right = ([rrb.Horizontal(*cams, name="cameras")] if cams else []) + [plots, story]
    eye = None
    if look_target is not None:
        target = np.asarray(look_target, float)
        along = np.array([target[0], target[1], 0.0])
        along = along / np.linalg.norm(along) if np.linalg.norm(along) > 1e-6 else np.array([0.0, 1.0, 0.0])
        across = np.cross([0.0, 0.0, 1.0], along)
        offset = EYE_OFFSET_M[0] * along + EYE_OFFSET_M[1] * across + [0.0, 0.0, EYE_OFFSET_M[2]]
        eye = rrb.archetypes.EyeControls3D(position=target + offset, look_target=target,
                                           eye_up=[0.0, 0.0, 1.0])
    world = rrb.Spatial3DView(origin="world", name="cell (estimate blue, truth green, alternatives orange)",
                              eye_controls=eye)
    return rrb.Blueprint(
        rrb.Horizontal(world, rrb.Vertical(*right, row_shares=[3, 2, 2][:len(right)]), column_shares=[5, 4]),
        rrb.TimePanel(timeline=TIMELINE, play_state="following", expanded=False),
        rrb.SelectionPanel(expanded=False), rrb.BlueprintPanel(expanded=False),
    )
