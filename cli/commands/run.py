"""``tapecell run``: the real cell — capture, estimate, plan, show the plan, and only with
``--execute`` (and a confirmation typed on a terminal) move the UR arm."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from tapecell.cli.options import add_force, add_robot_options, check_dir, check_files, confirm_robot
from tapecell.estimator.errors import TapecellError, TaskFailed

HELP = """Run the real cell once: grab one image per camera (OpenCV VideoCapture devices from
the cell file's [robot] camera_devices, or --images DIR holding DIR/000/<camera>.png),
segment the tape, estimate it with the calibrated cameras (--cameras FILE, tape-cameras/1
from `tapecell calibrate`), plan a grasp at its tip and print the plan. An estimate whose
verdict is not "ok" is refused (exit 1): a robot must not act on it. With --execute --probe,
an estimate that is "hidden" or "ambiguous" is settled with the needle first: the arm goes
into freedrive, you guide the needle onto the middle of the tape's end and press Enter, and
the hypothesis (the estimate or one of its alternatives) whose tip the needle confirms
(within 4 mm, the only one so near and 1.5 mm closer than any other) becomes the answer;
if none or several are, nothing moves. A "poor_fit" whose views show tape past the model's
end, or whose end the model does not explain, is measured the same way: the needle on
the tape's end, within 4 mm of the estimated end's line and at most 25 mm past it, moves
the tip there. A touch that confirms nothing but lies 4-12 mm from exactly one tip refits
that shape through it (kept when it still explains the views); elsewhere nothing moves. Then
you put the needle on the tape's centre line about 12 mm back from its end, where the pads
will hold it: that touch must lie 6-18 mm back along the settled end's trunk and bend off it
by at most 30 deg, else nothing moves (the trunk check). Where the plan then holds the tape
more than 18 mm in from that end (the planner's fallbacks, when no grasp nearer the end
passes), you also put the needle on the tape's middle at the grasp point and 6 mm either side
of it: tape more than 3 mm off the estimate along its normal there has the grasp planned again
about it (at that inset or up to 6 mm farther in); a touch skipped or more than 10 mm across
the tape from its point, or tape more than 10 mm or 30 deg off the estimate there, moves
nothing.
Any other "poor_fit" is refused: the model does not explain what was seen.

Nothing moves without --execute. With --execute the robot's address and the plan are
shown and you type 'yes' on the terminal BEFORE any connection is opened (--yes answers
for a script; with no terminal and no --yes nothing happens, exit 2). Then the arm is
connected, its kinematics are checked against the planner's, the plan is made again in
the controller's own kinematics from the arm's actual joints, and run only if it is the
plan you confirmed. Every target is checked against the cell file's workspace box,
keep-out zone and speed limits, and against the controller's safety limits, before it is
sent; every robot call has a deadline; the arm is stopped on any error."""

SAME_PLAN_M = 0.001
"""The plan made after connecting must put every TCP waypoint within this [m] (and
SAME_PLAN_RAD) of the plan that was confirmed."""
SAME_PLAN_RAD = 0.0175


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="the real cell: capture, estimate, plan (and --execute)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, required=True, metavar="CELL.toml", help="the cell file")
    p.add_argument("--cameras", type=Path, required=True, metavar="FILE",
                   help="calibrated cameras (tape-cameras/1)")
    p.add_argument("--images", type=Path, metavar="DIR", help="read images from DIR instead of the cameras")
    add_robot_options(p, "run the grasp plan on the arm")
    p.add_argument("--probe", action="store_true",
                   help="with --execute: settle a hidden or ambiguous estimate with the needle, guided by hand "
                        "in freedrive, before planning (see above)")
    p.add_argument("--rrd", type=Path, metavar="FILE", help="write a rerun recording of every step")
    p.add_argument("--save-capture", type=Path, metavar="DIR",
                   help="keep what the cameras saw as a tape-capture/1 directory (replay with tapecell estimate)")
    add_force(p)
    p.set_defaults(func=run)


def grab_capture(cfg, cameras, images: Path | None, cameras_file: str = "cameras"):
    """One image per camera, segmented into a capture of the cell's tape model, with the
    checks ``load_capture`` makes (an inverted mask, a camera that cannot see the tape)."""
    from tapecell.estimator.capture import Capture, View
    from tapecell.estimator.errors import CaptureError
    from tapecell.estimator.sanity import check_mask_coverage, check_view_geometry
    from tapecell.estimator.segment import segment_tape
    from tapecell.cell.config import scene_boxes, tape_spec

    from tapecell.cell.cameras_real import FolderCameras, VideoCameras

    tape = tape_spec(cfg, cfg.tape.estimator_plates)
    names = [c.name for c in cameras]
    if images is not None:
        source = FolderCameras(images, names)
    else:
        source = VideoCameras(list(cfg.robot.camera_devices)[:len(names)], names)
    try:
        frames = source.grab(0)
    finally:
        source.close()
    views = []
    for cam in cameras:
        img = frames[cam.name]
        if img.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"camera {cam.name}: image is {img.shape[1]}x{img.shape[0]} px but the "
                               f"calibration is for {cam.width}x{cam.height}")
        mask = segment_tape(img)
        if not np.any(mask):
            raise CaptureError(f"camera {cam.name} sees no tape")
        check_mask_coverage(mask, cam.name, f"the segmented image of camera {cam.name}")
        check_view_geometry(cam, tape, mask, cameras_file)
        views.append(View(cam, mask, None, img))
    # The part and the table hide the tape from some cameras: the estimator knows them.
    return Capture(tape, views, scene=scene_boxes(cfg))


def run(args: argparse.Namespace) -> int:
    from tapecell.estimator import estimate
    from tapecell.estimator.capture import load_cameras, save_capture
    from tapecell.cell.config import load_cell_config

    from tapecell.cell.planner import (REFERENCE_JOINTS, GripperGeometry, PlanRefused, Speeds, execute_plan,
                                       plan_for_estimate)
    from tapecell.cell.safety import SafetyLimits
    from tapecell.cell import probe
    from tapecell.cell.probe import end_measurable, hypotheses_to_probe
    from tapecell.cell.story import Story

    cfg = load_cell_config(args.config)
    cameras = load_cameras(args.cameras)
    if args.execute and not args.yes and not sys.stdin.isatty():
        raise TapecellError("--execute asks for a typed confirmation on a terminal and standard input is not "
                            "one; nothing connected, nothing moved (add --yes to confirm in a script)")
    check_files([args.rrd], args.force)
    check_dir(args.save_capture, args.force)
    limits = SafetyLimits.from_cell(cfg)
    gripper = GripperGeometry.from_config(cfg.tools.gripper)
    # What each stage found, in order: the recording (--rrd) is written from it at the end,
    # also when the run ends in a refusal or a robot error (then with that as its result).
    story = Story([c.name for c in cameras])
    result: dict = {"success": False, "outcome": "refused", "verdict": None, "failure": None}
    try:
        capture = grab_capture(cfg, cameras, args.images, str(args.cameras))
        story.add("capture", None, capture)
        if args.save_capture is not None:
            save_capture(capture, args.save_capture, rgb=True, force=args.force)
            print(f"saved the capture to {args.save_capture}", file=sys.stderr)
        est = estimate(capture)
        story.add("estimate", None, (capture, est))
        result["verdict"] = est.verdict.value
        tip_mm = ", ".join(f"{v * 1e3:.1f}" for v in est.tip_position)
        print(f"estimate: tip [{tip_mm}] mm, cost {est.cost:.4f}, verdict {est.verdict.value}, "
              f"{est.time_s * 1e3:.1f} ms")
        if not est.actionable:
            why = (f"the estimate's verdict is {est.verdict.value}"
                   + (f" ({est.verdict_reason})" if est.verdict_reason else "") + ": a robot must not act on it")
            if not hypotheses_to_probe(est) and not end_measurable(est):
                raise TaskFailed(f"{why}; nothing moved")
            if not (args.execute and args.probe):
                raise TaskFailed(f"{why}; nothing moved (--execute --probe settles it with the needle, guided by "
                                 "hand)")
            est = (measure_end_with_needle if end_measurable(est) else settle_with_needle)(cfg, capture, est, story,
                                                                                           args.yes)
            story.add("estimate", None, (capture, est), "after probing")
            result["verdict"] = est.verdict.value
            print(f"estimate after probing: {est.verdict_reason}")
            probed = True
        else:
            probed = False
        # The estimated tape moved onto the needle's touch at a far grasp point, and the
        # insets then tried (see _grasp_point_checked); None: as estimated.
        shift, insets = None, None

        def make_plan(q_start, ik=None):
            kw = {} if ik is None else {"ik": ik}
            return plan_for_estimate(est, capture.tape, cfg, limits, shift=shift, q_start=q_start, insets=insets, **kw)

        shown = make_plan(None)
        if probed and shown.inset > probe.GRASP_CHECKED_M + 1e-9:
            # The jaw would hold the tape farther in than the needle checked: the operator
            # touches the grasp point, and the grasp is planned again about the tape there.
            moved = _grasp_point_checked(cfg, est, shown.inset, story, args.yes)
            if moved is not None:
                shift, insets = moved
                try:
                    shown = make_plan(None)
                except PlanRefused as e:
                    raise PlanRefused(e.reason, f"{e.detail} (planned again about the tape the needle touched at "
                                                "the grasp point); nothing moved") from None
        story.add("plan", None, (shown, REFERENCE_JOINTS, None))
        print(shown.describe())
        if not args.execute:
            print("nothing moved (add --execute to run the plan on the arm)")
            # The recording shows the arm where the plan would grasp, said to be only planned.
            story.samples.append(_arm_sample(0.0, shown.waypoint("grasp").q,
                                             "the planned grasp pose (dry run: the arm did not move)"))
            result.update(outcome="planned", success=True)
            _write(args.rrd, story, result, "planned; nothing moved (no --execute)", gripper)
            return 0
        speeds = Speeds()
        confirm_robot(cfg.robot.host, cfg.robot.port, [
            f"run the grasp plan above ({len(shown.steps)} steps: joint moves at {speeds.joint:g} rad/s, the "
            f"approach at {speeds.approach:g} m/s, the lift at {speeds.lift:g} m/s), after checking it again "
            "from the arm's actual joints in the controller's kinematics"], args.yes)
        from tapecell.cell.ur import URArm

        arm = URArm.from_config(cfg, cfg.tools.gripper.flange_from_tcp)
        with arm:
            plan = make_plan(arm.joints(), ik=arm.ik)     # the controller's kinematics, from where it is
            _check_same_plan(shown, plan)
            t_start = time.perf_counter()
            story.samples.append(_arm_sample(0.0, arm.joints(), "connected; the confirmed plan starts"))

            def on_step(step, a):
                print(f"done: {step.action} {step.waypoint or ''}".rstrip())
                story.samples.append(_arm_sample(time.perf_counter() - t_start, a.joints(),
                                                 f"{step.action} {step.waypoint or ''}".rstrip() + " done"))

            execute_plan(plan, arm, limits, speeds, on_step=on_step)
        print("grasp executed")
        result.update(outcome="executed", success=True)
        _write(args.rrd, story, result, "the grasp plan ran to its end (the real cell has no truth to check it)",
               gripper)
    except TapecellError as e:
        # A refusal or a robot error is what a reviewer most needs to see: recorded with it.
        if story.events:
            result.update(failure=type(e).__name__, detail=str(e),
                          outcome="refused" if not story.samples else "failed")
            _write(args.rrd, story, result, f"{result['outcome']}: {e}", gripper)
        raise
    return 0


def settle_with_needle(cfg, capture, est, story, yes: bool, prompt=None, log=print):
    """Freedrive probing of the tape's end on the real arm: the operator guides the needle
    onto the middle of the tape's end; returns the estimate with the hypothesis the needle
    confirms as the answer (verdict ok), or, where it confirms none but exactly one
    hypothesis' tip lies a few millimetres from the touch (REFIT_TOUCH_MAX_M), that shape
    refitted through the touch when the refit still explains the views (:func:`_refit_through`);
    else raises :class:`TaskFailed` (nothing moved but by hand). The arm is connected for the
    probe only, and freedrive ends on every path."""
    from tapecell.cell.probe import PROBE_CONFIRM_M, REFIT_TOUCH_MAX_M, adopt, confirmed

    tips = [est.tip_position] + [a.tip_position for a in est.alternatives]
    touched, trunk_touch = _touch_end(cfg, yes,
                                      f"the estimate is {est.verdict.value} ({len(tips)} hypotheses of the tape's end)",
                                      "then plan the grasp for the hypothesis the needle confirms, show it and ask "
                                      "again before moving", prompt, log)
    distances = [float(np.linalg.norm(touched - t)) for t in tips]
    story.add("probes", None, [{"label": f"hypothesis {k}", "aimed": t, "touched": touched, "t": None}
                               for k, t in enumerate(tips)])
    k = confirmed(distances)
    listed = ", ".join(f"{1e3 * d:.1f}" for d in distances)
    near = [j for j, d in enumerate(distances) if d <= REFIT_TOUCH_MAX_M]
    if k is None and len(near) == 1 and distances[near[0]] > PROBE_CONFIRM_M:
        # One hypothesis' end a few mm from the touch, none on it: refit it through the touch.
        settled = _refit_through(capture, est, near[0], touched, f"hypothesis {near[0]}'s tip")
        if settled is not None:
            return _trunk_checked(settled, trunk_touch, story)
    if k is None:
        raise TaskFailed(f"the needle at [{', '.join(f'{v * 1e3:.1f}' for v in touched)}] mm confirms none of the "
                         f"{len(tips)} hypotheses of the tape's end (their tips are {listed} mm away; one must be "
                         f"within {PROBE_CONFIRM_M * 1e3:.0f} mm, the only one so near and clearly the closest); nothing moved")
    reason = f"hypothesis {k} confirmed by the needle ({1e3 * distances[k]:.1f} mm from its tip)"
    return _trunk_checked(adopt(est, k, capture.tape, reason), trunk_touch, story)


GRASP_TOUCH_ACROSS_M = 0.010
"""The operator's touches at a far grasp point (:func:`_grasp_point_checked`) must each lie
within this of the point aimed at across the tape's width [m] (half the tape's 30 mm width,
less a margin), and the two outer ones at least GRASP_STATION_M apart along it (the turn is
taken over the run between them): else they say nothing of the tape where the jaw will hold
it."""


def _grasp_point_checked(cfg, est, inset: float, story, yes: bool, prompt=None, log=print):
    """For a grasp planned ``inset`` [m] in from an end the needle settled, farther in than
    its checks reached (:data:`tapecell.cell.probe.GRASP_CHECKED_M`), the simulated cell's
    rule with the operator's hand: freedrive, the needle on the tape's middle at the grasp
    point and GRASP_STATION_M either side of it (:func:`tapecell.cell.probe.grasp_station`).
    Returns None when the tape at the grasp point is within GRASP_RECENTRE_M of the estimate
    along its normal, else (the offset (3,) [m] to move the estimated tape by, the insets to
    plan at: this one or farther in within the touched stretch); raises :class:`TaskFailed`
    (nothing moved but by hand) when a touch is skipped or lies more than
    GRASP_TOUCH_ACROSS_M across the tape from its point, the outer two are less than
    GRASP_STATION_M apart along it, or the tape there lies more than GRASP_SHIFT_MAX_M off or
    turns more than GRASP_TURN_MAX_DEG off the estimate."""
    from tapecell.cell import probe
    from tapecell.cell.ur import URArm

    position, rotation, aimed = probe.grasp_station_aims(est, cfg, inset)
    step = probe.GRASP_STATION_M
    where = ", ".join(f"{v * 1e3:.1f}" for v in position)
    labels = {0: f"middle where the jaw will hold it, {inset * 1e3:.0f} mm in from its end (about [{where}] mm)",
              -1: f"middle {(inset + step) * 1e3:.0f} mm in from its end, {step * 1e3:.0f} mm farther from the end",
              1: f"middle {(inset - step) * 1e3:.0f} mm in from its end, {step * 1e3:.0f} mm nearer the end"}
    confirm_robot(cfg.robot.host, cfg.robot.port, [
        f"the grasp holds the tape {inset * 1e3:.0f} mm in from its end, farther in than the needle checked: start "
        "freedrive (teach mode) again; the arm follows your hand, making no motion of its own",
        f"record the needle tip when you press Enter with it on the tape's middle where the jaw will hold it, then "
        f"{step * 1e3:.0f} mm farther from the end, then {step * 1e3:.0f} mm nearer it; freedrive then ends",
        "then plan the grasp about the tape there, show it and ask again before moving"], yes)
    arm = URArm.from_config(cfg, cfg.tools.needle.flange_from_tcp)
    with arm:
        points = {p.label: p.position for p in probe.guided_probe(arm, cfg.tools.needle.flange_from_tcp,
                                                                  list(labels.values()), prompt, log)}
    if any(label not in points for label in labels.values()):
        raise TaskFailed("the needle was not put on the tape at all three points where the jaw will hold it (needed "
                         f"for a grasp {inset * 1e3:.0f} mm in from the end); nothing moved")
    touched = {k: np.asarray(points[label], float) for k, label in labels.items()}
    story.add("probes", None, [{"label": labels[k], "aimed": aimed[k], "touched": touched[k], "t": None}
                               for k in labels])
    for k in labels:
        across = abs(float((touched[k] - aimed[k]) @ rotation[:, 1]))
        if across > GRASP_TOUCH_ACROSS_M:
            raise TaskFailed(f"the needle's touch on the tape's {labels[k]} is {across * 1e3:.1f} mm from that point "
                             f"across the tape (at most {GRASP_TOUCH_ACROSS_M * 1e3:.0f} mm); nothing moved")
    run = float((touched[1] - touched[-1]) @ rotation[:, 0])
    if run < step:
        raise TaskFailed(f"the needle's touches either side of the grasp point are {run * 1e3:.1f} mm apart along the "
                         f"tape (at least {step * 1e3:.0f} mm, the nearer one nearer the end); nothing moved")
    offset, turn = probe.grasp_station(position, rotation, touched)
    problem = probe.grasp_station_problem(offset, turn)
    if problem is not None:
        raise TaskFailed(f"{problem}; nothing moved")
    off = float(np.linalg.norm(offset)) * 1e3
    if off <= probe.GRASP_RECENTRE_M * 1e3:
        log(f"grasp point: the tape is {off:.1f} mm from the estimate there, {turn:.0f} deg off; planned as it was")
        return None
    log(f"grasp point: the tape is {off:.1f} mm off the estimate there, {turn:.0f} deg off; the grasp is planned "
        "again about it")
    return offset, probe.replan_insets(cfg.grasp, inset)


def _touch_end(cfg, yes: bool, what: str, then: str, prompt=None, log=print) -> tuple[np.ndarray, np.ndarray]:
    """After the operator's confirmation (``what`` the estimate is, ``then`` what follows):
    freedrive, the operator guides the needle onto the middle of the tape's end, then onto its
    centre line about TRUNK_CHECK_M back from the end (:data:`tapecell.cell.probe.TRUNK_CHECK_M`,
    where the pads will hold it), pressing Enter at each; returns the needle tip at both (3,),
    (3,) [m]. The arm is connected for this only, and freedrive ends on every path."""
    from tapecell.cell.probe import TRUNK_CHECK_M, guided_probe
    from tapecell.cell.ur import URArm

    back = f"centre line, about {TRUNK_CHECK_M * 1e3:.0f} mm back from its end"
    confirm_robot(cfg.robot.host, cfg.robot.port, [
        f"{what}: start freedrive (teach mode); the arm's brakes release and it follows your hand, making no "
        "motion of its own",
        f"record the needle tip when you press Enter with it on the middle of the tape's end, then on its {back}; "
        "freedrive then ends",
        then], yes)
    arm = URArm.from_config(cfg, cfg.tools.needle.flange_from_tcp)
    with arm:
        points = {p.label: p.position for p in guided_probe(arm, cfg.tools.needle.flange_from_tcp,
                                                            ["tip", back], prompt, log)}
    missing = [label for label in ("tip", back) if label not in points]
    if missing:
        raise TaskFailed(f"the needle was not put on the tape's {' and '.join(missing)} (both are needed); "
                         "nothing moved")
    return np.asarray(points["tip"], float), np.asarray(points[back], float)


def _trunk_checked(est, trunk_touch: np.ndarray, story):
    """``est`` (settled by the needle) when the operator's touch on the centre line behind its
    end passes the trunk check (:func:`tapecell.cell.probe.trunk_touch_problem`); else
    :class:`TaskFailed` (nothing moved but by hand). The touch goes into ``story`` against the
    point TRUNK_CHECK_M back along the settled end's trunk."""
    from tapecell.cell.probe import trunk_point, trunk_touch_problem

    aimed = trunk_point(est.tip_position, est.tip_rotation)
    story.add("probes", None, [{"label": "trunk", "aimed": aimed, "touched": trunk_touch, "t": None}])
    problem = trunk_touch_problem(est.tip_position, est.tip_rotation, trunk_touch)
    if problem is not None:
        raise TaskFailed(f"{problem}; nothing moved")
    return est


def measure_end_with_needle(cfg, capture, est, story, yes: bool, prompt=None, log=print):
    """Freedrive measurement of the tape's end for a ``poor_fit`` whose end the views place
    only roughly (:func:`tapecell.cell.probe.end_measurable`: tape past the model's end, or
    an end the model does not explain): the operator guides the needle onto the middle of
    the tape's end; where the touch lies on the estimated end's line (within 4 mm of it, from
    4 mm before the tip to 25 mm past it), the tip moves there along the tape and the
    estimate becomes "ok" (:func:`tapecell.cell.probe.measured_end`); off that line but
    within REFIT_TOUCH_MAX_M of the tip, the shape refitted through the touch when the refit
    still explains the views (:func:`_refit_through`); elsewhere :class:`TaskFailed` (nothing
    moved but by hand). The simulated cell measures the same
    ends by stepping the needle past the tip."""
    import dataclasses

    from tapecell.cell.probe import PAST_END_MAX_M, PROBE_CONFIRM_M, REFIT_TOUCH_MAX_M, measured_end
    from tapecell.estimator import Verdict
    from tapecell.estimator.verdict import PAST_END

    touched, trunk_touch = _touch_end(cfg, yes, f"the estimate is {est.verdict.value} ({est.verdict_reason})",
                                      "then plan the grasp at the end the needle measured, show it and ask again "
                                      "before moving", prompt, log)
    tip, trunk = np.asarray(est.tip_position, float), np.asarray(est.tip_rotation, float)[:, 0]
    story.add("probes", None, [{"label": "end", "aimed": tip, "touched": touched, "t": None}])
    end = measured_end(tip, trunk, touched)
    if end is None and float(np.linalg.norm(touched - tip)) <= REFIT_TOUCH_MAX_M:
        # Off the end's line but a few mm from the tip: refit the shape through the touch.
        settled = _refit_through(capture, est, 0, touched, "the tip", past_end=PAST_END in est.verdict_reason)
        if settled is not None:
            return _trunk_checked(settled, trunk_touch, story)
    if end is None:
        raise TaskFailed(f"the needle at [{', '.join(f'{v * 1e3:.1f}' for v in touched)}] mm is not on the estimated "
                         f"end's line (it must lie within {PROBE_CONFIRM_M * 1e3:.0f} mm of it, from "
                         f"{PROBE_CONFIRM_M * 1e3:.0f} mm before the tip to {PAST_END_MAX_M * 1e3:.0f} mm past it); "
                         "nothing moved")
    moved = float(np.linalg.norm(end - tip))
    reason = f"the tape's end measured by the needle: {moved * 1e3:.1f} mm past the model's end"
    return _trunk_checked(dataclasses.replace(est, tip_position=end, verdict=Verdict.OK, verdict_reason=reason),
                          trunk_touch, story)


def _refit_through(capture, est, k: int, touched: np.ndarray, what: str, past_end: bool = False):
    """Hypothesis ``k`` of ``est`` (0: itself, else its alternative k - 1) refitted through
    the operator's touch ``touched`` (3,) [m] on the middle of the tape's end
    (:func:`tapecell.estimator.touch.refit`, the touch within the end's last ``inset``),
    verdict "ok" when the refit still explains the views
    (:func:`tapecell.cell.probe.refit_acceptable`) and its tip is within PROBE_CONFIRM_M of
    the touch (the operator put the needle on the end: no further touch is asked for), and,
    with ``past_end`` (the views show tape past the model's end), the tip did not move back
    along the tape by more than PROBE_CONFIRM_M; else None."""
    import dataclasses

    from tapecell.cell.probe import PROBE_CONFIRM_M, ProbeParams, hypothesis, refit_hypothesis
    from tapecell.estimator import Verdict

    shape = hypothesis(est, k)
    refitted = refit_hypothesis(capture, est, k, touched, ProbeParams().inset)
    if refitted is None:
        return None
    if float(np.linalg.norm(refitted.tip_position - touched)) > PROBE_CONFIRM_M:
        return None
    back = float((shape.tip_position - refitted.tip_position) @ shape.tip_rotation[:, 0])
    if past_end and back > PROBE_CONFIRM_M:
        return None
    d = float(np.linalg.norm(touched - shape.tip_position))
    reason = (f"refitted through the needle's touch on the tape's end, {1e3 * d:.1f} mm from {what} "
              f"(from the views alone: {refitted.verdict.value})")
    return dataclasses.replace(refitted, verdict=Verdict.OK, verdict_reason=reason)


def _arm_sample(t: float, q, event: str):
    from tapecell.cell.story import BodySample, ur5e_poses

    q = np.asarray(q, float)
    return BodySample(float(t), ur5e_poses(q), q, None, frozenset(), event)


def _write(path, story, result, text: str, gripper) -> None:
    """The run's recording (``--rrd``), written atomically; nothing without --rrd."""
    if path is None:
        return
    from tapecell.cell.story import ur5e_look

    story.write(path, "tapecell-run", ur5e_look(gripper), result, text)


def _check_same_plan(shown, plan) -> None:
    """Refuse to run a plan other than the one the operator confirmed."""
    from tapecell.cell.poses import rotation_angle_between

    if list(shown.steps) != list(plan.steps):
        raise TaskFailed("the plan made from the arm's actual joints has other steps than the one you confirmed; "
                         "nothing moved (run again to see and confirm the new plan)")
    for a, b in zip(shown.waypoints, plan.waypoints):
        dp = float(np.linalg.norm(a.world_from_tcp[:3, 3] - b.world_from_tcp[:3, 3]))
        dr = rotation_angle_between(a.world_from_tcp[:3, :3], b.world_from_tcp[:3, :3])
        if dp > SAME_PLAN_M or dr > SAME_PLAN_RAD:
            raise TaskFailed(f"the plan made from the arm's actual joints puts the gripper {dp * 1e3:.1f} mm and "
                             f"{np.degrees(dr):.1f} deg away from the confirmed plan at '{a.name}'; nothing moved "
                             "(run again to see and confirm the new plan)")
