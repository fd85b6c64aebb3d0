"""One simulated grasp episode, end to end, checked physically.

randomise the tape -> park the arm out of view -> render, segment, estimate -> plan ->
execute with the simulated UR5e -> check that both pads closed on the tape, across it,
and that the tape held between them followed the gripper through the lift. The result is
a `tape-episode/1` dict.
"""
from __future__ import annotations

import atexit
import dataclasses

import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tapecell.cell.probe import (GRASP_CHECKED_M, GRASP_RECENTRE_M, PAST_END_MAX_M, PROBE_CONFIRM_M, PROBE_PAST_CLEAR_M,
                                 PROBE_WIDE_MARGIN_M, TRUNK_CHECK_M, clearly_closest, end_measurable,
                                 hypotheses_to_probe, hypothesis, replan_insets)
from tapecell.cell.poses import rotation_angle_between
from tapecell.estimator import Verdict, estimate, forward_kinematics
from tapecell.estimator.capture import Capture, View, load_cameras
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.geometry import rot_x, rot_y
from tapecell.estimator.metrics import centerline_at, errors

MIN_LIFT_M = 0.020
"""The gripper must rise at least this far with the tape for a success."""
FOLLOW_TOLERANCE_M = 0.008
"""The tape where the pads hold it must move with the gripper within this distance through
the lift. (Until 2026-11-26 the tape's tip had to: a grasp 30-48 mm back from the end, which
held the tape through the lift, failed as "slipped" where the free end beyond the pads
swung 11-15 mm; the tip's lag is still recorded.)"""


@dataclass
class EpisodeOutcome:
    """What the physical check found."""

    success: bool = False
    failure: str | None = None
    detail: str = ""
    pad_contacts: dict[str, int] = field(default_factory=dict)
    lift_m: float = 0.0
    tip_follow_error_m: float | None = None
    held_follow_error_m: float | None = None
    held_offset_m: float | None = None


def with_cameras(capture: Capture, cameras_file: Path) -> Capture:
    """The capture with its cameras replaced by calibrated ones, matched by name."""
    calibrated = {c.name: c for c in load_cameras(cameras_file)}
    views = []
    for v in capture.views:
        if v.camera.name not in calibrated:
            raise TapecellError(f"{cameras_file}: no camera '{v.camera.name}' (has {', '.join(calibrated)})")
        views.append(View(calibrated[v.camera.name], v.mask, v.ignore, v.image))
    return dataclasses.replace(capture, views=views)


def run_episode(seed: int, cameras: int = 2, recording: Path | None = None,
                config: Any = None, randomize: Any = None) -> dict[str, Any]:
    """Run one episode; returns its `tape-episode/1` dict. Errors the planner or the arm
    raise become the failure reason; anything else propagates. ``randomize``: a
    :class:`~tapecell.sim.randomize.Randomize` (default: the cell file's ``[randomize]``
    table); the values drawn for this seed are in the result's ``randomize``. ``config``: a
    cell file's path, an already loaded :class:`~tapecell.cell.config.CellConfig` (what a
    Ray task gets: the driver's file need not exist on the worker's machine), or None for
    the bundled one."""
    from .arm import SimArm

    from tapecell.cell.planner import PlanRefused, plan_for_estimate
    from tapecell.cell.safety import SafetyLimits

    from tapecell.cell.story import Story

    from .look import MotionSampler
    from .randomize import apply_to_capture, apply_to_config, apply_to_model

    cfg, randomize = _config_and_randomize(config, randomize)
    drawn = randomize.draw(seed)
    cameras = int(drawn.get("cameras", cameras))
    cfg = apply_to_config(cfg, drawn, seed)
    times: dict[str, float] = {}
    doc: dict[str, Any] = {"format": "tape-episode/1", "seed": int(seed), "cameras": int(cameras),
                           "success": False, "outcome": "refused", "verdict": None, "failure": None,
                           "tip_error_mm": None, "normal_error_deg": None}
    if drawn:
        doc["randomize"] = drawn
    cell = None
    errored = False
    # What each stage found, in order, for the recording (written at the end, if asked for).
    story = Story([p.name for p in cfg.camera_placements(cameras)])
    try:
        t0 = time.perf_counter()
        cell = _cell_for(cfg, seed, cameras, drawn.get("tape_model", "chain"),
                         drawn.get("tape_stiffness_scale", 1.0))
        apply_to_model(cell.model, drawn)
        sim_arm = SimArm(cell, tool="gripper")
        sim_arm.open_gripper()
        motion = MotionSampler(cell, sim_arm, story.samples)
        motion.start()
        motion.take("the arm parked, the gripper open")

        def look() -> Capture:
            """A capture as the estimator gets it: calibrated cameras, the drawn errors."""
            capture = cell.capture(rgb=recording is not None)
            if cfg.episode.cameras_file:
                capture = with_cameras(capture, _resolve(cfg, cfg.episode.cameras_file))
            capture = apply_to_capture(capture, drawn, seed)
            story.add("capture", float(cell.data.time), capture)
            return capture

        capture = look()
        times["capture"] = time.perf_counter() - t0

        est = estimate(capture)
        story.add("estimate", float(cell.data.time), (capture, est))
        times["estimate"] = est.time_s
        if not est.actionable and any(v.ignore is not None and v.ignore.any() for v in capture.views):
            # The arm hides part of the tape: park it out of every view and look again.
            t1 = time.perf_counter()
            sim_arm.park()
            capture = look()
            times["capture"] += time.perf_counter() - t1
            est = estimate(capture)
            story.add("estimate", float(cell.data.time), (capture, est))
            times["estimate"] += est.time_s
            doc["recaptured"] = True
        # From here on (the views are taken) the settled tape sleeps, is not stepped, until
        # a pad touches it: every contact, the grasp and the lift are simulated as before
        # (SimCell.set_tape_sleep). Not earlier: the tape still creeps by some micrometres
        # after settling, and the captures see it as they always did.
        cell.set_tape_sleep(True)
        if hypotheses_to_probe(est):
            # Two shapes explain the views, or too few cameras see the end: the needle,
            # which the cell carries for this, touches each hypothesis' tip (and goes past
            # it); the one it confirms (and only one) is kept.
            t1 = time.perf_counter()
            probes: list[dict] = []
            est, doc["probed"] = resolve_by_probing(cell, sim_arm, est, capture.tape.width, probes, capture,
                                                    doc)
            story.add("probes", float(cell.data.time), probes)
            story.add("estimate", float(cell.data.time), (capture, est), "after probing")
            times["probe"] = time.perf_counter() - t1
        elif end_measurable(est):
            # The tape goes on past the model's end, or the model does not explain the end
            # (an end hooked over within a few millimetres, which 30 mm plates cannot
            # follow): the needle touches the estimated tip and then steps along the tape
            # beyond it; where it still touches tape, there the end is at least.
            t1 = time.perf_counter()
            probes = []
            est, doc["probed_past_end_mm"] = measure_end_by_probing(cell, sim_arm, est, capture.tape.width, probes,
                                                                       capture, doc)
            story.add("probes", float(cell.data.time), probes)
            story.add("estimate", float(cell.data.time), (capture, est), "after probing")
            times["probe"] = time.perf_counter() - t1
        doc["verdict"] = est.verdict.value
        doc["tip_views"] = int(est.tip_views)
        if est.verdict_reason:
            doc["verdict_reason"] = est.verdict_reason
        err = errors(est.nodes, est.tip_rotation, capture.truth, est.tip_position)
        doc["tip_error_mm"] = round(err.tip_m * 1e3, 3)
        doc["normal_error_deg"] = round(err.normal_deg, 3)
        doc["cost"] = round(float(est.cost), 5)

        t0 = time.perf_counter()
        limits = SafetyLimits.from_cell(cfg)
        q_start = sim_arm.joints()
        try:
            plan = plan_for_estimate(est, capture.tape, cfg, limits, q_start=q_start)
        except PlanRefused as e:
            times["plan"] = time.perf_counter() - t0
            story.add("plan", float(cell.data.time), (None, q_start, e))
            doc.update(failure=e.reason, detail=e.detail)
            return doc
        times["plan"] = time.perf_counter() - t0
        story.add("plan", float(cell.data.time), (plan, q_start, None))
        if "probe" in times and plan.inset > GRASP_CHECKED_M + 1e-9:
            # The needle measured the end, but the jaw will hold the tape farther in than it
            # checked, along a shape the views could not settle: it touches the grasp point,
            # and the grasp is planned again about the tape it found there.
            t1 = time.perf_counter()
            probes = []
            offset = _grasp_point_touch(cell, sim_arm, est, plan.inset, cfg, probes, doc)
            story.add("probes", float(cell.data.time), probes)
            times["probe"] += time.perf_counter() - t1
            if isinstance(offset, str):
                doc.update(failure="estimate rejected", detail=offset)
                return doc
            if float(np.linalg.norm(offset)) > GRASP_RECENTRE_M:
                t0 = time.perf_counter()
                try:
                    plan = plan_for_estimate(est, capture.tape, cfg, limits, shift=offset, q_start=sim_arm.joints(),
                                             insets=replan_insets(cfg.grasp, plan.inset))
                except PlanRefused as e:
                    times["plan"] += time.perf_counter() - t0
                    story.add("plan", float(cell.data.time), (None, q_start, e))
                    doc.update(failure=e.reason, detail=e.detail + " (planned again about the tape the needle "
                               "touched at the grasp point)")
                    return doc
                times["plan"] += time.perf_counter() - t0
                story.add("plan", float(cell.data.time), (plan, q_start, None))
        # Where the jaw takes the tape: in from the tip [mm], and the approach variant.
        doc["grasp"] = {"inset_mm": round(plan.inset * 1e3, 1),
                        "tilt_deg": round(float(np.degrees(plan.approach_tilt_rad)), 1),
                        "pitch_deg": round(float(np.degrees(plan.approach_pitch_rad)), 1),
                        "flipped": plan.flipped}

        t0 = time.perf_counter()
        outcome = _execute_and_check(cell, sim_arm, plan, limits, motion)
        times["execute"] = time.perf_counter() - t0
        # "limits": the safety check refused the plan before the arm moved; anything else
        # after execution began acted on the tape.
        doc.update(success=outcome.success, failure=outcome.failure,
                   outcome="grasped" if outcome.success else "refused" if outcome.failure == "limits" else "failed")
        doc["pad_contacts"] = outcome.pad_contacts
        doc["lift_mm"] = round(outcome.lift_m * 1e3, 2)
        if outcome.tip_follow_error_m is not None:
            doc["tip_follow_error_mm"] = round(outcome.tip_follow_error_m * 1e3, 2)
        if outcome.held_follow_error_m is not None:
            doc["held_follow_error_mm"] = round(outcome.held_follow_error_m * 1e3, 2)
        if outcome.held_offset_m is not None:
            doc["held_offset_mm"] = round(outcome.held_offset_m * 1e3, 2)
        if outcome.detail:
            doc["detail"] = outcome.detail
        return doc
    except BaseException:
        errored = True   # an error, not a failed grasp: no recording
        raise
    finally:
        doc["time_s"] = {k: round(v, 4) for k, v in times.items()}
        if cell is not None:
            cell.step_hook = None
            if recording is not None and not errored:
                doc["recording"] = Path(recording).name
                story.write(recording, "tapecell-episode", motion.look, doc, _result_line(doc))
            if not _keep(cell, ok=not errored):
                cell.close()  # free the renderers' GL contexts, also after a refusal or an error


def _result_line(doc: dict[str, Any]) -> str:
    why = ""
    if doc.get("failure"):
        why = f": {doc['failure']}" + (f" ({doc['detail']})" if doc.get("detail") else "")
    return f"result: {doc.get('outcome')}{why}; tip error {doc.get('tip_error_mm')} mm"


REUSE_CELL = True
"""Keep the last episode's simulated cell (model, data, renderer) in this process and reuse
it for the next episode of the same cell config (``SimCell.reuse``): the results are the
same as with a new cell, without building the model and the EGL renderer again."""
_cache: dict[str, Any] = {}
atexit.register(lambda: release_cell())


def _cell_for(cfg, seed: int, cameras: int, tape_model: str = "chain", stiffness_scale: float = 1.0):
    """A simulated cell of ``cfg`` with ``cameras`` cameras at ``seed``, gripper mounted, with
    the plate tape (``tape_model`` "chain": a :class:`SimCell`) or the shell tape ("shell": a
    :class:`~tapecell.sim.shell.ShellSimCell` whose Young's modulus is scaled by
    ``stiffness_scale``): the process's kept one when it matches, else a new one."""
    import pickle

    from .cell import SimCell

    key = (pickle.dumps(cfg), int(cameras), tape_model)   # (the stiffness scale is in cfg's tape)
    cell = _cache.pop("cell", None)
    if cell is not None:
        if REUSE_CELL and _cache.get("key") == key and cell.reusable_for(seed):
            cell.reuse(seed)
            return cell
        cell.close()
    _cache["key"] = key
    if tape_model == "shell":
        from .shell import ShellSimCell

        return ShellSimCell(cfg, seed=seed, n_cameras=cameras, tool="gripper", stiffness_scale=stiffness_scale)
    return SimCell(cfg, seed=seed, n_cameras=cameras, tool="gripper")


def _keep(cell, ok: bool) -> bool:
    """Keep ``cell`` for the next episode (after an episode that ended normally)."""
    if REUSE_CELL and ok:
        _cache["cell"] = cell
        return True
    _cache.clear()
    return False


def release_cell() -> None:
    """Close the kept cell (its GL context), e.g. before a process forks or exits."""
    cell = _cache.pop("cell", None)
    _cache.clear()
    if cell is not None:
        cell.close()


PROBE_BEYOND_M = 0.006
"""Past every touched hypothesis' tip the needle also probes this far beyond its end along
the tape [m]: tape there means that end is not the tape's."""


class _Needle:
    """The needle on the simulated arm, for the probes of one episode: mounted on entering
    the ``with`` block; on leaving it (also on an error), the arm parked and the gripper
    remounted and opened. ``probes``, when given, gets each probe
    (label, aimed point, touched point or None, cell time) for the recording; ``notes`` (the
    episode's result), ``probed_corners_mm``: the corners' distances [mm] in order,
    ``probed_trunk_mm``: the trunk checks' (:meth:`trunk_on_tape`)."""

    def __init__(self, cell, sim_arm, probes: list | None, notes: dict | None = None):
        from tapecell.cell.probe import ProbeParams

        self.cell, self.sim_arm, self.probes, self.notes = cell, sim_arm, probes, notes
        self.params = ProbeParams()

    def __enter__(self) -> "_Needle":
        from .prober import SimProber

        self.sim_arm.select_tool("needle")
        try:
            self.prober = SimProber(self.cell, self.sim_arm, self.params)
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.sim_arm.park()
        finally:
            self.sim_arm.select_tool("gripper")
            self.sim_arm.open_gripper()

    def touch(self, label: str, target: np.ndarray, R: np.ndarray) -> tuple[float, np.ndarray] | None:
        """(distance [m] from ``target`` to where the needle touched tape, that point),
        approaching along the tape's normal (``R``'s third column) from the robot's side,
        else from the other side when that side is blocked (the needle's shaft already
        touching the tape at the start, or no reach); None when nothing was touched."""
        from tapecell.cell.probe import ProbeError, approach_normal
        from .arm import SimArmError
        from .ur5e import IKError

        target = np.asarray(target, float)
        first = approach_normal(target, R[:, 2], -target)
        for normal in (first, -first):
            touched = None
            try:
                touched = self.prober.probe(label, target, normal).position
            except Exception as e:    # noqa: BLE001 - an unreachable side is simply not a touch
                if not isinstance(e, (ProbeError, IKError, SimArmError)):
                    raise
            if self.probes is not None:
                self.probes.append({"label": label, "aimed": target, "touched": touched, "t": float(self.cell.data.time)})
            if touched is None:
                continue
            d = float(np.linalg.norm(touched - target))
            if d < 0.8 * self.params.standoff:
                return d, touched
        return None

    def distance(self, label: str, target: np.ndarray, R: np.ndarray) -> float | None:
        """:meth:`touch`'s distance alone."""
        hit = self.touch(label, target, R)
        return None if hit is None else hit[0]

    def clear_past(self, tip: np.ndarray, R: np.ndarray, label: str, beyond: float = PROBE_BEYOND_M) -> bool:
        """Is there no tape within PROBE_PAST_CLEAR_M of the point ``beyond`` [m] past the end
        at ``tip`` along the trunk of ``R``, a frame the needle's touches measured
        (:meth:`end_frame`), approached along its normal? A "tip" on the tape's body can pass
        the probe past it made along its own frame: in simulated episodes with every camera
        turned 0.5 deg (2 cameras) two such tips met tape there 6.0 and 9.6 mm from the
        point (more than PROBE_CONFIRM_M, which says the tape goes on; a lone touched tip is
        not refused for tape within PROBE_PAST_CLEAR_M, as one of several is), then their
        corners and trunk point were tape, and the touches tilted their frames 27-33 deg
        onto the tape (:meth:`_plane_frame`); along the measured frames the point past such
        tips was tape 1.6-4.6 mm away. Three such "ends", 12-44 mm from the tape's, were
        grasped (1032002, 1032007, 1034034); the nine right ends whose frames were measured
        in 1034000-, 1035000- and 1037000- (2 cameras; 0.5, 0 and 0.3 deg) touched nothing
        within the needle's reach there. ``label``: the probe's, for the recording; the
        distance [mm] (None: nothing touched) is noted as ``probed_past_mm``."""
        past = self.distance(label, tip + beyond * R[:, 0], R)
        if self.notes is not None:
            self.notes.setdefault("probed_past_mm", []).append(None if past is None else round(1e3 * past, 2))
        return past is None or past > PROBE_PAST_CLEAR_M

    def corners_on_tape(self, tip: np.ndarray, R: np.ndarray, width: float) -> bool:
        """Are both corners of the end at ``tip`` (frame ``R``) tape
        (:func:`tapecell.cell.probe.corners_on_tape` of their :meth:`corner_touches`)?"""
        from tapecell.cell.probe import corners_on_tape

        self.last_corners = self.corner_touches(tip, R, width)
        found = [None if h is None else h[0] for h in self.last_corners]
        if self.notes is not None:
            self.notes.setdefault("probed_corners_mm", []).extend(
                None if d is None else round(1e3 * d, 2) for d in found)
        return corners_on_tape(found)

    def trunk_on_tape(self, tip: np.ndarray, R: np.ndarray) -> bool:
        """Is the tape where the grasp will hold it: the point TRUNK_CHECK_M back from the end at
        ``tip`` along its trunk (frame ``R``), on the centre line, touched within
        TRUNK_TOUCH_M (see :data:`tapecell.cell.probe.TRUNK_TOUCH_M`)?"""
        from tapecell.cell.probe import TRUNK_TOUCH_M, trunk_point

        hit = self.last_trunk = self.touch("trunk", trunk_point(tip, R), R)
        if self.notes is not None:
            self.notes.setdefault("probed_trunk_mm", []).append(None if hit is None else round(1e3 * hit[0], 2))
        return hit is not None and hit[0] <= TRUNK_TOUCH_M

    def corner_touches(self, tip: np.ndarray, R: np.ndarray, width: float, turn: str = "") -> list:
        """:meth:`touch` at the two corners (left, right) of the end at ``tip`` (frame ``R``);
        ``turn``: added to the probes' labels."""
        from tapecell.cell.probe import tape_points

        points = tape_points(tip, R, width, self.params.inset)
        return [self.touch(f"corner {side}{turn}", points[f"tip_{side}"], R) for side in ("left", "right")]

    def end_frame(self, tip: np.ndarray, R: np.ndarray, width: float, plane: bool = True) -> np.ndarray | None:
        """The frame of the end at ``tip``: where both its corners at ``R`` are tape
        (:meth:`corners_on_tape`), the twist their touches measure (:meth:`_touched_frame`), else
        ``R``; where they are not, the twist the corners find (:meth:`_twist_frame`); None when
        neither is, or when the frame found fails the trunk check (:meth:`trunk_on_tape`: the
        tape leaves the end's trunk where the pads would hold it; the twist does not change
        that), a traced end's too (its frame is the trace's last 5 mm step; a tape curled
        tighter behind it would leave the jaw's straight inset as well). With ``plane``, the
        frame turned onto the plane of the corners' and the trunk point's touches
        (:meth:`_plane_frame`); a traced end keeps its trace's pitch (on a curl the touches
        2 and 12 mm in span a bend the trace followed step by step), its twist measured at
        the corners all the same. The frame measured is not checked by touching again, and
        the tip stays where it was confirmed: within a few mm of the touched plane, inside
        the open jaw's reach."""
        if self.corners_on_tape(tip, R, width):
            measured = self._touched_frame(tip, R, width)
            frame = R if measured is None else measured
        else:
            frame = self._twist_frame(tip, R, width)
        if frame is None or not self.trunk_on_tape(tip, frame):
            return None
        return self._plane_frame(frame) if plane else frame

    def _plane_frame(self, frame: np.ndarray) -> np.ndarray:
        """``frame`` (whose corners and trunk point were just touched, all tape) turned onto
        the plane of the three touches, where it is more than TOUCHED_TWIST_DEG off: the
        trunk from the trunk point's touch to the corners' midpoint, the left axis through
        the corners. Each touch is made along ``frame``'s normal, so an end pitched about
        its width axis is met nearer or further at the corners than at the trunk point
        (2 mm and 12 mm in from the end): confirmed ends whose corners were both touched
        3.4-3.7 mm off, their twist right, were 32-34 deg off in normal. Not where the turn
        is more than TOUCHED_MAX_DEG."""
        left, right = (h[1] for h in self.last_corners)
        trunk = 0.5 * (left + right) - self.last_trunk[1]
        if np.linalg.norm(trunk) < 0.5 * TRUNK_CHECK_M or trunk @ frame[:, 0] <= 0:
            return frame
        lateral = (left - right) / np.linalg.norm(left - right)
        along = trunk - (trunk @ lateral) * lateral       # the trunk square to the corners' line
        along /= np.linalg.norm(along)
        touched = np.column_stack([along, lateral, np.cross(along, lateral)])
        turn = np.degrees(rotation_angle_between(frame, touched))
        if turn <= TOUCHED_TWIST_DEG or turn > TOUCHED_MAX_DEG:
            return frame
        return touched

    def _touched_frame(self, tip: np.ndarray, R: np.ndarray, width: float) -> np.ndarray | None:
        """The frame the corners just touched at ``R`` measure (their touches' lateral axis,
        square to the trunk), where it turns ``R`` about the trunk by more than
        TOUCHED_TWIST_DEG (at most TOUCHED_MAX_DEG) and its own corners are tape, touched
        nearer than ``R``'s; else None (``R`` stands, and its corners' touches are restored
        as the last). Each corner is touched along ``R``'s normal: an end twisted by θ from
        ``R`` is met about (half the width less the inset)·tan θ nearer or further than
        aimed, within PROBE_CORNER_M up to ~40 deg, so corners "on tape" left confirmed ends
        10-40 deg off in normal, and a jaw pitched by the wrong normal closed one pad on
        air."""
        hits = self.last_corners
        measured = None if any(h is None for h in hits) else _corners_frame(R[:, 0], hits, width)
        if measured is None:
            return None
        turn = np.degrees(np.arccos(np.clip(measured[:, 1] @ R[:, 1], -1.0, 1.0)))
        if turn <= TOUCHED_TWIST_DEG or turn > TOUCHED_MAX_DEG:
            return None
        if self.corners_on_tape(tip, measured, width) and max(h[0] for h in self.last_corners) < max(h[0] for h in hits):
            return measured
        self.last_corners = hits    # R stands, and so do its corners' touches
        return None

    def _twist_frame(self, tip: np.ndarray, R: np.ndarray, width: float) -> np.ndarray | None:
        """The twist of an end whose corners at ``R`` are not both tape (a hooked end seen
        along its trunk leaves its twist tens of degrees off): ``R`` turned about its trunk
        by each of TWIST_SEARCH_DEG in turn, the first whose corners are both touched gives
        the lateral axis through the two touches (square to the trunk), kept when that
        frame's corners are tape too (else the next turn is tried). None when none is."""
        from tapecell.cell.probe import PROBE_CORNER_M

        trunk = R[:, 0]
        for deg in TWIST_SEARCH_DEG:
            turned = R @ rot_x(np.radians(deg))
            hits = self.corner_touches(tip, turned, width, f" turned {deg:+.0f} deg")
            if any(h is None or h[0] > PROBE_CORNER_M for h in hits):
                continue
            measured = _corners_frame(trunk, hits, width)
            if measured is not None and self.corners_on_tape(tip, measured, width):
                return measured
        return None


def _corners_frame(trunk: np.ndarray, hits: list, width: float) -> np.ndarray | None:
    """The end's frame with its trunk along ``trunk`` and its lateral axis through the two
    corners' touched points ``hits`` [(distance, point) left, right]; None where those lie
    less than half the ``width`` apart across the trunk (no measure of the lateral axis)."""
    left = hits[0][1] - hits[1][1]
    if np.linalg.norm(left - (left @ trunk) * trunk) < 0.5 * width:
        return None
    return _frame_along(trunk, left)


def _frame_along(trunk: np.ndarray, left: np.ndarray) -> np.ndarray:
    """The tape frame (columns trunk, left, normal) with its trunk along ``trunk`` and its
    left axis the part of ``left`` square to it."""
    t = trunk / np.linalg.norm(trunk)
    lat = left - (left @ t) * t
    lat = lat / np.linalg.norm(lat)
    return np.column_stack([t, lat, np.cross(t, lat)])


def _twisted(frame: np.ndarray, R: np.ndarray) -> str:
    """The words a reason gets where the needle's touches gave the end a frame other than ``R``."""
    return "" if frame is R else "; its frame measured by the needle's touches"


TWIST_SEARCH_DEG = (30.0, -30.0, 60.0, -60.0)
"""The turns about the trunk [deg] with which the needle looks for the corners of a confirmed
end whose own corners are not both tape (:meth:`_Needle.end_frame`)."""
SAME_END_M = 0.001
"""Hypotheses whose tips lie within this [m] of an earlier one's are not probed again
(:func:`resolve_by_probing`): the needle cannot tell them apart."""
TOUCHED_TWIST_DEG = 8.0
TOUCHED_MAX_DEG = 45.0
"""An end whose corners and trunk point are tape takes the frame their touches measure
(:meth:`_Needle._touched_frame`, :meth:`_Needle._plane_frame`) where it turns the end's frame
by more than TOUCHED_TWIST_DEG and at most TOUCHED_MAX_DEG [deg] (a larger turn is no
measurement of this end: corners "on tape" within PROBE_CORNER_M bound the twist to ~40 deg)."""


ONE_END_M = 0.008
"""Where several touched tips have their corners on tape and nothing PROBE_BEYOND_M past
them, and every tip touched on the tape lies within this [m] of the others, they are one
end to the needle (:func:`one_end`; fresh 961065, 3 cameras: the answer's tip, 1.3 mm off,
and an alternative's, 4.5 mm from it, were refused as two ends). A tip on the tape's body
is tape too, but with tape PROBE_BEYOND_M past it (6 mm): such tips lie within about that
of the end, and the one farthest out along the tape is kept (:func:`outermost`). Tips
farther apart stay refused (a tip on the tape's body, 28 mm from the end, was touched
closer than the end)."""


def one_end(tips: list) -> bool:
    """Do all of ``tips`` [(3,) m] lie within ONE_END_M of each other?"""
    return all(np.linalg.norm(a - b) <= ONE_END_M for i, a in enumerate(tips) for b in tips[i + 1:])


def outermost(ends: list) -> int:
    """The index of the end (tip (3,), frame (3, 3)) of ``ends`` farthest out along their
    mean trunk direction."""
    trunk = sum(R[:, 0] for _, R in ends)
    return int(np.argmax([float(tip @ trunk) for tip, _ in ends]))


def resolve_by_probing(cell, sim_arm, est, width: float, probes: list | None = None, capture: Capture | None = None,
                       notes: dict | None = None):
    """Probe the tips of an estimate that is not ok (ambiguous or hidden) and of its
    alternatives with the needle, and past each touched tip (tape there: not the end;
    where several tips are touched on the tape, tape within PROBE_PAST_CLEAR_M of the point
    past one, off its trunk's line, puts that tip on the tape's body: not the end either).
    Returns (the estimate to act on, with verdict "ok" when exactly one hypothesis was
    confirmed, else unchanged; per hypothesis the distance [mm] from the aimed point to
    the touched one, None where nothing was touched). A confirmed tip is kept only when both
    its corners are tape too (:func:`tapecell.cell.probe.corners_on_tape`), at its own twist
    or one the corners find (:meth:`_Needle.end_frame`). Where several tips are tape and
    nothing tells them apart, the only one whose corners are tape is kept, or, where every
    touched tip lies within ONE_END_M of the others (one end), the one farthest out of those
    whose corners are tape.
    Where none is confirmed:
    - the one touched tip with tape on its trunk's line beyond it is walked past
      (:func:`_walk_past`) to the end (not an end where the touches turned its trunk and
      tape lies a step further past it along the measured frame);
    - else, with none touched within PROBE_CONFIRM_M and ``capture`` given, every tip
      touched a few millimetres off (within REFIT_TOUCH_MAX_M) is refitted through its
      touch and probed again, the closest first (:func:`_refit_and_probe`);
    - else, with at most one tip on the tape, the tape is traced from every hypothesis' body
      (:func:`_traced`), kept where the ends found agree.
    The gripper is remounted and opened afterwards. ``probes``, ``notes``: see
    :class:`_Needle`."""
    from tapecell.cell.probe import REFIT_TOUCH_MAX_M, adopt, confirmed, tape_points

    hypotheses = [(est.tip_position, est.tip_rotation, None)]
    hypotheses += [(a.tip_position, a.tip_rotation, a) for a in est.alternatives]
    with _Needle(cell, sim_arm, probes, notes) as needle:
        inset = needle.params.inset
        # A hypothesis ending where an earlier one does is the same end to the needle (an
        # alternative whose plate fit ended 22 mm away and whose output chain ends at the
        # answer's, fit._cheapest_first: touched alike, the two were told apart by nothing).
        same = [any(np.linalg.norm(tip - hypotheses[j][0]) < SAME_END_M for j in range(k))
                for k, (tip, _, _) in enumerate(hypotheses)]
        hits = [None if same[k] else needle.touch(f"hypothesis {k}", tape_points(tip, R, width, inset)["tip"], R)
                for k, (tip, R, _) in enumerate(hypotheses)]
        found = [None if h is None else h[0] for h in hits]
        # A hypothesis whose "tip" lies on the tape's body touches tape too: the needle
        # also goes a little beyond each touched one's end, where the true end finds nothing.
        near = [k for k, d in enumerate(found) if d is not None and d <= PROBE_CONFIRM_M]
        short = []                       # touched tips with tape on their trunk's line beyond them
        for k in near:
            tip, R, _ = hypotheses[k]
            past = needle.distance(f"beyond hypothesis {k}", tip + PROBE_BEYOND_M * R[:, 0], R)
            if past is not None and past <= PROBE_CONFIRM_M:
                found[k] = None          # tape beyond its end: not the end
                short.append(k)
            elif past is not None and past <= PROBE_PAST_CLEAR_M and len(near) > 1:
                # Tape near the point past it, off its trunk's line: a tip on the tape's body
                # (as a refit's, PROBE_PAST_CLEAR_M), not the end, where another tip is on tape too.
                found[k] = None
        report = [None if d is None else round(1e3 * d, 2) for d in found]
        on_tape = [k for k, d in enumerate(found) if d is not None and d <= PROBE_CONFIRM_M]
        best, reason = confirmed(found), ""
        if best is None and len(on_tape) > 1:
            # Several tips lie on the tape (a fold's edge is tape as the true end is): probe
            # where the shapes disagree instead, each at the point of its own end farthest from
            # every other hypothesis; the one shape whose point is tape, and whose rivals' are
            # not, is kept (its tip touched too).
            k = _discriminate(cell, hypotheses, est, needle.distance)
            if k is not None and found[k] is not None and found[k] <= PROBE_CONFIRM_M:
                best = k
                reason = (f"hypothesis {best} confirmed by the needle where the hypotheses disagree "
                          f"(its tip touched {1e3 * found[k]:.1f} mm away)")
            elif k is None and (closest := clearly_closest(found)) is not None:
                # Nothing told where the shapes disagree: the one touched clearly closest.
                best = closest
                reason = (f"hypothesis {best} confirmed by the needle ({1e3 * found[best]:.1f} mm from its tip, every "
                          f"other {PROBE_WIDE_MARGIN_M * 1e3:.1f} mm farther or more)")
            elif k is None:
                # Nor which is closer: the one touched tip whose corners are tape, if only one.
                whole = [j for j in on_tape if needle.corners_on_tape(hypotheses[j][0], hypotheses[j][1], width)]
                if len(whole) == 1 and needle.trunk_on_tape(hypotheses[whole[0]][0], hypotheses[whole[0]][1]):
                    best = whole[0]
                    reason = (f"hypothesis {best} confirmed by the needle ({1e3 * found[best]:.1f} mm from its tip): the "
                              f"only touched tip of {len(on_tape)} whose corners are tape")
                elif len(whole) > 1 and one_end([hypotheses[j][0] for j in on_tape]):
                    # Several such ends, and every touched tip within ONE_END_M of the others:
                    # one end, measured more than once; the tip farthest out along the tape is
                    # kept (one on the body behind the end is tape too).
                    k = whole[outermost([hypotheses[j][:2] for j in whole])]
                    if needle.trunk_on_tape(hypotheses[k][0], hypotheses[k][1]):
                        best = k
                        reason = (f"hypothesis {best} confirmed by the needle ({1e3 * found[best]:.1f} mm from its "
                                  f"tip): the farthest out of {len(whole)} tips whose corners are tape, every touched "
                                  f"tip within {1e3 * ONE_END_M:.0f} mm of the others (one end)")
        elif best is not None:
            reason = f"hypothesis {best} confirmed by the needle ({1e3 * found[best]:.1f} mm from its tip)"
        frame = None
        if best is not None:
            # (Where its corners and trunk were checked already, to choose it, again: the
            # frame their touches measure is this end's.)
            frame = needle.end_frame(hypotheses[best][0], hypotheses[best][1], width)
            if frame is None:
                best = None              # a corner in the air at every twist: the "tip" is not the tape's end
            elif frame is not hypotheses[best][1] and not needle.clear_past(
                    hypotheses[best][0], frame, f"past hypothesis {best}'s measured end"):
                # The touches turned the end's frame: past the tip along the measured frame
                # there is tape, so the "tip" lies on the tape's body (the probe past it along
                # its own frame met the tape only farther off).
                best, frame = None, None
        if best is None and short == near and len(short) == 1:
            # The one tip touched is short: the tape goes on along its trunk (an end hidden
            # from the cameras, hanging on past the model's): the needle walks on along it.
            k = short[0]
            tip, R, _ = hypotheses[k]
            steps = [d for d in PAST_END_STEPS_M if d > PROBE_BEYOND_M]
            walked, end = _walk_past(needle, tip, R, width, steps, PROBE_BEYOND_M)
            if end is not None:
                nxt = next(d for d in steps if d > walked)
                reason = (f"hypothesis {k}'s end measured by the needle: tape at its tip and {1e3 * walked:.0f} mm "
                          f"past it along the tape, none at {1e3 * nxt:.0f} mm, tape at both corners there")
                out = adopt(est, k, est_spec(cell), reason)
                report[k] = round(1e3 * hits[k][0], 2)
                return dataclasses.replace(out, tip_position=tip + walked * R[:, 0], tip_rotation=end), report
        off = [k for k, h in enumerate(hits) if h is not None and PROBE_CONFIRM_M < h[0] <= REFIT_TOUCH_MAX_M]
        if best is None and not near and capture is not None:
            # Tips touched tape a few mm off, none on it: refit those shapes through their
            # touches, the closest touch first; the first refit the needle confirms is kept.
            for k in sorted(off, key=lambda j: hits[j][0]):
                refitted = _refit_and_probe(needle, capture, est, k, hits[k], PROBE_BEYOND_M, f"hypothesis {k}'s tip")
                if refitted is not None:
                    return refitted, report
        if best is None and len(on_tape) <= 1:
            # Nothing above found the end: trace the tape from each hypothesis' body. Kept
            # only where the ends traced agree (one end): a trace decides nothing between
            # hypotheses the needle could not tell apart, and never where several tips lie
            # on the tape (a fold's edge is tape as the true end is).
            first = None
            for k in range(len(hypotheses)):
                t = _traced(needle, est, k, capture, width)
                if t is None:
                    continue
                if first is None:
                    first = t
                elif np.linalg.norm(t.tip_position - first.tip_position) > PROBE_CONFIRM_M:
                    first = None     # two ends: no further trace can make them one
                    break
            if first is not None:
                return first, report
    if best is None:
        return est, report
    out = adopt(est, best, est_spec(cell), reason)
    if frame is not None and frame is not hypotheses[best][1]:
        out = dataclasses.replace(out, tip_rotation=frame, verdict_reason=reason + _twisted(frame, hypotheses[best][1]))
    return out, report


def _traced(needle: _Needle, est, k: int, capture: Capture | None, width: float):
    """Hypothesis ``k`` of ``est`` (0: itself, else its alternative k - 1) with its end where
    the needle's :func:`_trace` from its centre line found it, verdict "ok", when the views
    agree: the shape refitted through that end may be confirmed
    (:func:`tapecell.cell.probe.refit_hypothesis`: it explains them about as well as the
    best hypothesis, and as a whole, wrong at most at its end: a trace that stopped on the
    tape's body 29 mm from the end left a view unexplained) and ends within PROBE_CONFIRM_M
    of it. The traced end lies within PAST_END_MAX_M of the hypothesis' own, or, for a trace
    that started before the hypothesis' last plate (its end hidden, the shape wrong there),
    where the tape's length puts it: the length traced within PAST_END_MAX_M of the length
    that was left. Its frame is the one its corners give (:meth:`_Needle.end_frame`); where
    they are not tape (a trace runs some millimetres off the centre line as it goes), the
    refit's tip and frame, its corners tape. The refit is the shape acted on, with that end
    and frame. None otherwise."""
    from tapecell.cell.probe import refit_hypothesis

    if capture is None:
        return None
    shape = hypothesis(est, k)
    out = _trace(needle, shape.angles, capture.tape, width)
    if out is None:
        return None
    end, R, back, walked = out
    plate = float(capture.tape.segment_lengths[-1])
    if (np.linalg.norm(end - shape.tip_position) > PAST_END_MAX_M
            and (back < plate or abs(walked - back) > PAST_END_MAX_M)):
        return None                 # farther from the hypothesis' end than any end measured
    refitted = refit_hypothesis(capture, est, k, end, 2 * needle.params.inset)
    if refitted is None or np.linalg.norm(refitted.tip_position - end) > PROBE_CONFIRM_M:
        return None
    frame = needle.end_frame(end, R, width, plane=False)
    if frame is None:
        frame = needle.end_frame(refitted.tip_position, refitted.tip_rotation, width)
        if frame is None:
            return None
        end = refitted.tip_position
    reason = (f"the needle traced the tape from hypothesis {k}'s centre line {1e3 * walked:.0f} mm to its end, tape at "
              f"both corners there; the shape refitted through it explains the views")
    return dataclasses.replace(refitted, tip_position=end, tip_rotation=frame, verdict=Verdict.OK, verdict_reason=reason)


def _refit_and_probe(needle: _Needle, capture: Capture, est, k: int, hit, beyond: float, what: str):
    """Hypothesis ``k`` of ``est`` (0: itself, else its alternative k - 1) refitted through
    the needle's touch ``hit`` (distance [m], point) near its end
    (:func:`tapecell.estimator.touch.refit`: the touch within the last 2 ``inset`` of the
    end's centre line, where the needle aims ``inset`` inside the end), kept with verdict
    "ok" when the refit still explains the views (:func:`tapecell.cell.probe.refit_acceptable`)
    and the needle finds tape at the refit's tip (within PROBE_CONFIRM_M; it passes through
    the touch, so this mostly checks the needle's way there), none within PROBE_PAST_CLEAR_M
    of the point ``beyond`` [m] past it, and tape at both its corners (within PROBE_CORNER_M):
    the tip is then within about ``beyond`` of the end. Where the point past the tip is tape
    itself (within PROBE_CONFIRM_M: the tape goes on along the refit's end), the needle walks
    on: the shape is refitted through that touch and probed the same way, at most
    REFIT_WALK_STEPS refits in all. Else None."""
    from tapecell.cell.probe import PROBE_PAST_CLEAR_M, refit_hypothesis, tape_points

    angles, touched, walked = None, hit[1], 0
    while True:
        refitted = refit_hypothesis(capture, est, k, touched, 2 * needle.params.inset, angles)
        if refitted is None:
            return None
        tip, R = refitted.tip_position, refitted.tip_rotation
        at_tip = needle.distance("refitted tip", tape_points(tip, R, capture.tape.width, needle.params.inset)["tip"], R)
        if at_tip is None or at_tip > PROBE_CONFIRM_M:
            return None
        past = needle.touch("beyond the refitted tip", tip + beyond * R[:, 0], R)
        walked += 1
        if past is not None and past[0] <= PROBE_CONFIRM_M and walked < REFIT_WALK_STEPS:
            angles, touched = refitted.angles, past[1]   # tape goes on past the refit's end: walk on
            continue
        if past is not None and past[0] <= PROBE_PAST_CLEAR_M:
            return None             # tape near the point past the end (a touch on the tape's body)
        frame = needle.end_frame(tip, R, capture.tape.width)
        if frame is None:
            return None
        steps = f" (after {walked} refits along the tape)" if walked > 1 else ""
        reason = (f"refitted through the needle's touch {1e3 * hit[0]:.1f} mm from {what}{steps}: tape at its tip "
                  f"and corners, none {1e3 * beyond:.0f} mm past it{_twisted(frame, R)}")
        return dataclasses.replace(refitted, tip_rotation=frame, verdict=Verdict.OK, verdict_reason=reason)


REFIT_WALK_STEPS = 3
"""At most this many refits, each through the needle's touch past the previous refit's end
(:func:`_refit_and_probe`), before a tape that goes on past them all is refused."""


def _walk_past(needle: _Needle, tip: np.ndarray, R: np.ndarray, width: float, steps, start: float):
    """The needle probes the points ``steps`` [m] past ``tip`` along the trunk ``R[:, 0]``
    in order (tape known to go on to ``start`` [m] past it) until one finds no tape
    (nothing within PROBE_CONFIRM_M). Returns (how far past the tip tape was last touched
    [m], the end's frame when an end was found within the steps and its corners are tape
    there (:meth:`_Needle.end_frame`), else None). Where the touches turned that frame's trunk
    (by more than TOUCHED_TWIST_DEG; a twist alone keeps the line the walk cleared), the point
    past the end along the measured frame must be clear of tape
    (:meth:`_Needle.clear_past`), as for a confirmed tip, but a step further out (PROBE_BEYOND_M
    plus the last step: a walked end is known only to a step). Fresh 1046002 (3 cameras
    turned 0.5 deg) walked 6 mm along a curl whose tape the 9 mm probe met 6.6 mm off, took
    that as the end, its frame turned 32 deg onto the tape, and tape lay 3.5-7.4 mm from the
    points 6-15 mm past it along that frame; the grasp went 50 mm from the tape's end. The
    walked end of 868005 (tests/test_episode.py), 6.8 mm from the tape's, its frame turned 26
    deg, had tape 2.9 mm from the point 6 mm past it, none 9 mm and farther."""
    last = start
    for d in steps:
        h = needle.touch(f"past the end +{d * 1e3:.0f} mm", tip + d * R[:, 0], R)
        if h is None or h[0] > PROBE_CONFIRM_M:
            end = tip + last * R[:, 0]
            frame = needle.end_frame(end, R, width)
            turned = frame is not None and float(frame[:, 0] @ R[:, 0]) < np.cos(np.radians(TOUCHED_TWIST_DEG))
            if turned and not needle.clear_past(end, frame, "past the walked end", PROBE_BEYOND_M + d - last):
                frame = None
            return last, frame
        last = d
    return last, None


TRACE_STEP_M = 0.005
"""The needle's step along the tape when it traces it (:func:`_trace`) [m]."""
TRACE_BENDS_DEG = (0.0, 30.0, -30.0, 60.0, -60.0, 90.0, -90.0)
"""The bends about the tape's lateral axis [deg] the trace tries, in order, for its next step."""
TRACE_MAX_STEPS = 10
"""At most this many steps [TRACE_STEP_M each] of a trace."""
TRACE_BACK_M = (0.010, 0.020, 0.035, 0.045)
"""Where a trace starts: a point of the estimated centre line this far back from its tip
along it [m], the first the needle finds tape at. The last two lie on the plate before the
last: where the end hangs hidden behind the part, the last plate is often wrong and the
one before it still on the tape."""


def _back_along(shape, back: float) -> tuple[np.ndarray, np.ndarray]:
    """The point of ``shape``'s centre line ``back`` [m] of arc length back from its end (at
    most its base), and the frame of the plate it lies on (copied)."""
    lengths = np.linalg.norm(np.diff(shape.nodes, axis=0), axis=1)
    j = len(lengths) - 1
    while j > 0 and back >= lengths[j]:
        back -= lengths[j]
        j -= 1
    t = min(1.0, back / lengths[j])
    return shape.nodes[j + 1] - t * (shape.nodes[j + 1] - shape.nodes[j]), shape.frames[j + 1].copy()


def _trace(needle: _Needle, angles: np.ndarray, spec, width: float):
    """Trace the tape with the needle, from a point of the centre line of the plate chain
    ``angles`` (of the tape model ``spec``) TRACE_BACK_M back from its end along it (the
    first where tape is touched, within PROBE_CONFIRM_M) towards its end: each
    step TRACE_STEP_M along the trunk bent about the lateral axis by TRACE_BENDS_DEG (tape
    bends out of its plane; a hooked end curls), the first bend that touches tape within
    PROBE_CONFIRM_M taken, the trunk then along the last step; where no bend finds tape, a
    half step more is tried and the end is the last point touched. Returns (the end, the
    frame of the trace's last step, how far back from the chain's end it started and how
    far it traced [m]) or None (no tape where the trace starts, or tape beyond
    TRACE_MAX_STEPS)."""
    shape = forward_kinematics(spec, angles)
    start = None
    for back in TRACE_BACK_M:
        target, R = _back_along(shape, back)
        hit = needle.touch(f"trace start {1e3 * back:.0f} mm back", target, R)
        if hit is not None and hit[0] <= PROBE_CONFIRM_M:
            start = hit[1]
            break
    if start is None:
        return None
    p, walked = start, 0.0

    for step in range(TRACE_MAX_STEPS + 1):
        nxt = None
        for deg in TRACE_BENDS_DEG:
            Rb = R @ rot_y(-np.radians(deg))          # the trunk bent towards the normal by deg
            hit = needle.touch(f"trace step {step + 1} bend {deg:+.0f} deg", p + TRACE_STEP_M * Rb[:, 0], Rb)
            if hit is not None and hit[0] <= PROBE_CONFIRM_M and np.linalg.norm(hit[1] - p) > 0.5 * TRACE_STEP_M:
                nxt = hit[1]
                break
        if nxt is None:
            half = needle.touch("trace half step", p + 0.5 * TRACE_STEP_M * R[:, 0], R)
            if half is not None and half[0] <= PROBE_CONFIRM_M and (half[1] - p) @ R[:, 0] > 0:
                walked += float(np.linalg.norm(half[1] - p))
                p = half[1]
            return p, R, back, walked
        R = _frame_along(nxt - p, R[:, 1])
        walked += float(np.linalg.norm(nxt - p))
        p = nxt
    return None                     # tape on beyond the longest trace


PAST_END_STEPS_M = (0.003, 0.006, 0.009, 0.012, 0.016, 0.020, PAST_END_MAX_M)
"""Where the needle probes past a model's end that the views say is short [m, along its
trunk]; it stops at the first step without tape."""


def measure_end_by_probing(cell, sim_arm, est, width: float, probes: list | None = None, capture: Capture | None = None,
                           notes: dict | None = None):
    """For a ``poor_fit`` estimate whose views show tape past its end or do not explain
    its end (see :func:`tapecell.cell.probe.end_measurable`): the needle touches
    the estimate's tip (it must be tape, within PROBE_CONFIRM_M), then points on the
    centre line PAST_END_STEPS_M beyond it, until one finds no tape there. Returns (the
    estimate with verdict "ok" and its tip moved to the last point that was tape, or kept
    when the first step found none; the steps [mm] that were tape). The end kept must have
    tape at both its corners, at its own twist or one they find (:meth:`_Needle.end_frame`).
    Where the tip's probe touched tape a few millimetres off (within REFIT_TOUCH_MAX_M) and
    ``capture`` is given, the shape is refitted through the touch and its new tip probed
    (:func:`_refit_and_probe`, nothing PAST_END_STEPS_M[0] past it). Where none of this
    found the end (no tape at the tip, tape past the last step, a corner in the air, or no
    refit confirmed), the tape is traced from the estimate's body (:func:`_traced`, an end
    within PAST_END_MAX_M of the model's); the estimate is unchanged where that fails too.
    ``probes``, ``notes``: see :class:`_Needle`."""
    from tapecell.cell.probe import REFIT_TOUCH_MAX_M, tape_points

    tip, R = np.asarray(est.tip_position, float), np.asarray(est.tip_rotation, float)
    found: list[float] = []
    ended, end = False, None   # tape at the tip, an end found within the steps, its corners tape; its frame
    with _Needle(cell, sim_arm, probes, notes) as needle:
        hit = needle.touch("tip", tape_points(tip, R, width, needle.params.inset)["tip"], R)
        if hit is not None and hit[0] <= PROBE_CONFIRM_M:
            last, end = _walk_past(needle, tip, R, width, PAST_END_STEPS_M, 0.0)
            found = [d for d in PAST_END_STEPS_M if d <= last]
            ended = end is not None
        elif hit is not None and hit[0] <= REFIT_TOUCH_MAX_M and capture is not None:
            refitted = _refit_and_probe(needle, capture, est, 0, hit, PAST_END_STEPS_M[0], "the tip")
            if refitted is not None:
                return refitted, []
        report = [round(d * 1e3, 1) for d in found]
        if not ended:
            # Nothing above found the end: trace the tape from the estimate's body.
            traced = _traced(needle, est, 0, capture, width)
            if traced is not None:
                return traced, report
    if not ended:
        return est, report          # no tape at the tip, tape as far as the needle looked, or a corner in the air
    twist = _twisted(end, R)
    if not found:
        # Tape at the tip and none 3 mm past it: the model's end is the tape's; what the
        # views show past it is tape beside the end (a curl of its corner), not beyond.
        reason = (f"the needle touched tape at the tip and none {PAST_END_STEPS_M[0] * 1e3:.0f} mm past it: "
                  f"the model's end is the tape's{twist}")
        return dataclasses.replace(est, tip_rotation=end, verdict=Verdict.OK, verdict_reason=reason), report
    reason = (f"the tape's end measured by the needle: tape {found[-1] * 1e3:.0f} mm past the model's end, "
              f"none at {PAST_END_STEPS_M[len(found)] * 1e3:.0f} mm{twist}")
    return dataclasses.replace(est, tip_position=tip + found[-1] * R[:, 0], tip_rotation=end, verdict=Verdict.OK,
                               verdict_reason=reason), report


DISCRIMINATE_M = 0.008
"""A discriminating probe point lies at least this far from every other hypothesis' tape [m]."""


def _discriminate(cell, hypotheses, est, touch) -> int | None:
    """The one hypothesis the needle supports where the shapes disagree: for each, the point
    of its last two plates (3 mm in from their edges) farthest from the other hypotheses'
    plates (at least DISCRIMINATE_M), probed along its normal; supported when tape is touched
    within PROBE_CONFIRM_M of it. None unless exactly one is supported."""
    spec = est_spec(cell)
    shapes = [forward_kinematics(spec, est.angles if alt is None else alt.angles) for _, _, alt in hypotheses]

    def surface(shape, inset: float):
        n = len(shape.nodes) - 1
        pts, frames = [], []
        for j in range(max(0, n - 2), n):
            for t in np.linspace(0.0, 1.0, 16):
                for w in np.linspace(-1.0, 1.0, 7):
                    pts.append(shape.nodes[j] + t * (shape.nodes[j + 1] - shape.nodes[j])
                               + w * (0.5 * spec.width - inset) * shape.frames[j + 1][:, 1])
                    frames.append(shape.frames[j + 1])
        return np.array(pts), frames

    inner = [surface(sh, 0.003) for sh in shapes]
    whole = [surface(sh, 0.0)[0] for sh in shapes]
    supported = []
    for k, (pts, frames) in enumerate(inner):
        others = np.vstack([p for j, p in enumerate(whole) if j != k])
        d = np.min(np.linalg.norm(pts[:, None] - others[None], axis=2), axis=1)
        i = int(np.argmax(d))
        if d[i] < DISCRIMINATE_M:
            return None
        hit = touch(f"discriminate {k}", pts[i], frames[i])
        supported.append(hit is not None and hit <= PROBE_CONFIRM_M)
    return supported.index(True) if sum(supported) == 1 else None


def est_spec(cell):
    """The estimator's tape model of ``cell`` (the plate chain written in its captures)."""
    from tapecell.cell.config import tape_spec

    return tape_spec(cell.config, cell.config.tape.estimator_plates)


def _resolve(cfg, path: str) -> Path:
    p = Path(path)
    if not p.is_absolute() and cfg.source:
        p = Path(cfg.source).parent / p
    return p


def _grasp_point_touch(cell, sim_arm, est, inset: float, cfg, probes: list, notes: dict) -> str | np.ndarray:
    """The needle touches the estimated centre line ``inset`` [m] in from the end (the
    planner's grasp point, :func:`tapecell.cell.planner.grasp_frame`) and GRASP_STATION_M
    either side of it along the trunk, each along the tape's normal
    (:func:`tapecell.cell.probe.grasp_station`). Returns the tape's offset from the grasp point
    (3,) [m], or why the grasp is refused. ``notes``: ``probed_grasp_mm`` the touches'
    distances [mm] (the grasp point's first, then towards the base and past it),
    ``probed_grasp_off`` the offset [mm] and the turn [deg]."""
    from tapecell.cell.probe import grasp_station, grasp_station_aims, grasp_station_problem

    position, rotation, aims = grasp_station_aims(est, cfg, inset)
    touched = {}
    with _Needle(cell, sim_arm, probes, notes) as needle:
        for k, label in ((0, "grasp point"), (-1, "before the grasp point"), (1, "past the grasp point")):
            hit = needle.touch(label, aims[k], rotation)
            touched[k] = None if hit is None else hit[1]
            notes.setdefault("probed_grasp_mm", []).append(None if hit is None else round(1e3 * hit[0], 2))
            if hit is None:
                break
    where = f"{1e3 * inset:.0f} mm in from the end the needle measured"
    if touched[0] is None:
        return f"the needle found no tape at the grasp point {where}"
    offset, turn = grasp_station(position, rotation, touched)
    notes["probed_grasp_off"] = {"mm": round(1e3 * float(np.linalg.norm(offset)), 2),
                                 "deg": None if turn is None else round(turn, 1)}
    problem = grasp_station_problem(offset, turn)
    return offset if problem is None else f"grasp point {where}: {problem}"


def nearest_arc_length(s: np.ndarray, points: np.ndarray, p: np.ndarray) -> float:
    """The arc length [m] of the point of the polyline ``points`` (M, 3), sampled at arc
    lengths ``s`` (M,), nearest to ``p`` (3,)."""
    a, d = points[:-1], np.diff(points, axis=0)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-18), 0.0, 1.0)
    k = int(np.argmin(np.linalg.norm(a + t[:, None] * d - p, axis=1)))
    return float(s[k] + t[k] * (s[k + 1] - s[k]))


@dataclass(frozen=True)
class HeldPoint:
    """The tape where the jaw closed on it: the true centre line's point nearest the jaw's
    centre (the TCP, midway between the pads) then, by its arc length ``s`` [m] (so a tape
    sliding along itself through the pads lags), its position ``position`` (3,) [m] then,
    and the TCP's distance ``offset_m`` [m] from it."""

    s: float
    position: np.ndarray
    offset_m: float

    @classmethod
    def at(cls, truth, tcp: np.ndarray) -> "HeldPoint":
        s = nearest_arc_length(truth.s, truth.points, tcp)
        position = centerline_at(truth, [s])[0]
        return cls(s, position, float(np.linalg.norm(tcp - position)))

    def lag(self, truth, gripper_move: np.ndarray) -> float:
        """How far [m] the same point of the tape (``truth``: the true centre line now) ended
        from where moving with the gripper by ``gripper_move`` (3,) would have put it."""
        return float(np.linalg.norm(centerline_at(truth, [self.s])[0] - self.position - gripper_move))


def _execute_and_check(cell, sim_arm, plan, limits, motion) -> EpisodeOutcome:
    """Run the plan on the simulated arm and judge the grasp from the physics (``motion``
    samples each step's start)."""
    from tapecell.cell.planner import Speeds, execute_plan
    from tapecell.cell.arm import ArmError
    from tapecell.cell.safety import SafetyError
    from .arm_adapter import SimArmAdapter

    out = EpisodeOutcome()
    state: dict[str, Any] = {}

    def on_step(step, arm) -> None:
        motion.take(f"{step.action} {step.waypoint or ''}".rstrip() + " done")
        if step.action == "close_gripper":
            state["contacts_closed"] = cell.gripper_pad_contacts_with_tape()
            state["tip_before"] = cell.tape_tip_position()
            state["tcp_before"] = sim_arm.tcp_pose("gripper")[:3, 3].copy()
            state["held"] = HeldPoint.at(cell.truth(), state["tcp_before"])

    driver = SimArmAdapter(sim_arm)
    try:
        with driver:
            execute_plan(plan, driver, limits, Speeds(), on_step=on_step)
    except (SafetyError, ArmError) as e:
        out.failure, out.detail = ("limits" if isinstance(e, SafetyError) else "arm error"), str(e)
        return out
    closed = state.get("contacts_closed", {})
    out.pad_contacts = cell.gripper_pad_contacts_with_tape()
    if not (closed.get("left", 0) and closed.get("right", 0)):
        out.failure = "missed"
        out.detail = f"pad contacts with the tape on closing: {closed}"
        return out
    held: HeldPoint = state["held"]
    out.held_offset_m = held.offset_m
    reach = 0.5 * cell.config.tape.width + 0.5 * cell.config.tools.gripper.pad_size[0]
    if held.offset_m > reach:
        # Both pads touch tape, but the jaw's centre is off the tape's width by more than
        # half a pad: the tape lies on a pad's edge or outer face, not between the pads.
        out.failure = "missed"
        out.detail = (f"the jaw closed {held.offset_m * 1e3:.1f} mm from the tape's centre line (more than "
                      f"{reach * 1e3:.1f} mm: half the tape's width and half a pad)")
        return out
    gripper_move = sim_arm.tcp_pose("gripper")[:3, 3] - state["tcp_before"]
    tip_move = cell.tape_tip_position() - state["tip_before"]
    out.lift_m = float(np.linalg.norm(gripper_move))
    out.tip_follow_error_m = float(np.linalg.norm(tip_move - gripper_move))
    out.held_follow_error_m = held.lag(cell.truth(), gripper_move)
    if not (out.pad_contacts.get("left", 0) and out.pad_contacts.get("right", 0)) \
            or out.held_follow_error_m > FOLLOW_TOLERANCE_M:
        out.failure = "slipped"
        out.detail = (f"after the lift: pad contacts {out.pad_contacts}, the tape between the pads lagged the "
                      f"gripper by {out.held_follow_error_m * 1e3:.1f} mm (the tip by "
                      f"{out.tip_follow_error_m * 1e3:.1f} mm)")
        return out
    if out.lift_m < MIN_LIFT_M:
        out.failure = "short lift"
        out.detail = f"the gripper rose only {out.lift_m * 1e3:.1f} mm"
        return out
    out.success = True
    return out


def run_episode_safely(seed: int, cameras: int, recording: Path | None, config: Any,
                       randomize: Any = None) -> dict[str, Any]:
    """:func:`run_episode` for batch runs: an unexpected error becomes a failed episode
    ("error: ...") instead of ending the batch."""
    try:
        return run_episode(seed, cameras, recording, config, randomize)
    except TapecellError as e:
        return _failed(seed, cameras, "error", str(e), _drawn(seed, config, randomize))
    except Exception as e:  # a bug must not lose the other episodes; the reason keeps the trace
        return _failed(seed, cameras, "crash", f"{type(e).__name__}: {e} | {traceback.format_exc(limit=3)}",
                       _drawn(seed, config, randomize))


def _drawn(seed: int, config: Any, randomize: Any) -> dict[str, Any] | None:
    """The domain randomisation values :func:`run_episode` drew for ``seed`` (they depend on
    the seed alone), for the record of an episode that ended in an error; None where there
    are none or they cannot be drawn (the error may be the cell file's)."""
    try:
        return _config_and_randomize(config, randomize)[1].draw(seed) or None
    except Exception:
        return None


def _config_and_randomize(config: Any, randomize: Any):
    """(the loaded cell file, the randomisation) :func:`run_episode` uses: ``config`` a
    path, a loaded ``CellConfig`` or None (the bundled one); ``randomize`` None for the cell
    file's ``[randomize]`` table."""
    from tapecell.cell.config import CellConfig, load_cell_config
    from .randomize import Randomize

    cfg = config if isinstance(config, CellConfig) else load_cell_config(config)
    if randomize is None:
        randomize = Randomize.from_table(cfg.randomize, f"{cfg.source}: [randomize]")
    return cfg, randomize


def _failed(seed: int, cameras: int, reason: str, detail: str, drawn: dict[str, Any] | None = None) -> dict[str, Any]:
    """An episode that ended in an error: counted as failed (whether the arm had acted is
    not known). ``drawn``: the domain randomisation values of the seed, recorded as a
    finished episode records them."""
    doc = {"format": "tape-episode/1", "seed": int(seed), "cameras": int((drawn or {}).get("cameras", cameras)),
           "success": False, "outcome": "failed", "verdict": None, "failure": reason, "detail": detail,
           "tip_error_mm": None, "normal_error_deg": None, "time_s": {}}
    if drawn:
        doc["randomize"] = drawn
    return doc


failed_episode = _failed
