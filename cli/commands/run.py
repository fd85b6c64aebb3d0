"""``tapecell run``: the real cell — capture, estimate, plan, show the plan, and only with
``--execute`` (and a confirmation typed on a terminal) move the UR arm."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from tapecell.estimator.errors import TapecellError

HELP = """Run the real cell once: grab one image per camera (OpenCV VideoCapture devices from
the cell file's [robot] camera_devices, or --images DIR holding DIR/000/<camera>.png),
segment the tape, estimate it with the calibrated cameras (--cameras FILE, tape-cameras/1
from `tapecell calibrate`), plan a grasp at its tip and print the plan.

Nothing moves without --execute. With --execute the arm (ur_rtde, [robot] host) is
connected, the plan is made from its actual joints, shown, and run only after you type
'yes' on the terminal. Every target is checked against the cell file's workspace box,
keep-out zone and speed limits, and against the controller's safety limits, before it is
sent; the arm is stopped on any error."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="the real cell: capture, estimate, plan (and --execute)",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", type=Path, required=True, metavar="CELL.toml", help="the cell file")
    p.add_argument("--cameras", type=Path, required=True, metavar="FILE",
                   help="calibrated cameras (tape-cameras/1)")
    p.add_argument("--images", type=Path, metavar="DIR", help="read images from DIR instead of the cameras")
    p.add_argument("--execute", action="store_true", help="really move the arm (asks for confirmation)")
    p.add_argument("--rrd", type=Path, metavar="FILE", help="write a rerun recording of every step")
    p.add_argument("--save-capture", type=Path, metavar="DIR",
                   help="keep what the cameras saw as a tape-capture/1 directory (replay with tapecell estimate)")
    p.set_defaults(func=run)


def confirm(prompt: str = "Execute this plan on the real arm? Type 'yes': ") -> bool:
    """Ask on the terminal (``run`` has checked that there is one)."""
    try:
        return input(prompt).strip().lower() == "yes"
    except EOFError:
        return False


def grab_capture(cfg, cameras, images: Path | None):
    """One image per camera, segmented into a capture of the cell's tape model."""
    import numpy as np

    from tapecell.estimator.capture import Capture, View
    from tapecell.estimator.errors import CaptureError
    from tapecell.estimator.segment import segment_tape
    from tapecell.cell.config import tape_spec

    from tapecell.cell.cameras_real import FolderCameras, VideoCameras

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
        views.append(View(cam, mask, None, img))
    return Capture(tape_spec(cfg, cfg.tape.estimator_plates), views)


def run(args: argparse.Namespace) -> int:
    from tapecell.estimator import estimate
    from tapecell.estimator.capture import load_cameras, save_capture
    from tapecell.cell.config import load_cell_config

    from tapecell.cell import recording as rec
    from tapecell.cell.planner import GraspParams, GripperGeometry, Speeds, TipFrame, execute_plan, plan_grasp
    from tapecell.cell.safety import SafetyLimits

    cfg = load_cell_config(args.config)
    cameras = load_cameras(args.cameras)
    if args.execute and not sys.stdin.isatty():
        raise TapecellError("--execute asks for confirmation on a terminal, and standard input is not one; "
                            "nothing moved")
    limits = SafetyLimits.from_config(cfg.limits)
    stream = rec.open_recording(args.rrd, "tapecell-run", [c.name for c in cameras]) if args.rrd else None
    try:
        capture = grab_capture(cfg, cameras, args.images)
        if args.save_capture is not None:
            save_capture(capture, args.save_capture, rgb=True)
            print(f"saved the capture to {args.save_capture}", file=sys.stderr)
        est = estimate(capture, callback=rec.fit_logger(stream, capture) if stream else None)
        if stream is not None:
            rec.log_fit_result(stream, capture, est)
        tip_mm = ", ".join(f"{v * 1e3:.1f}" for v in est.tip_position)
        print(f"estimate: tip [{tip_mm}] mm, cost {est.cost:.4f}, {est.time_s * 1e3:.1f} ms")

        def make_plan(q_start):
            plan = plan_grasp(TipFrame.from_estimate(est), GraspParams.from_config(cfg.grasp),
                              GripperGeometry.from_config(cfg.tools.gripper), limits,
                              q_start=q_start, tape_points=est.nodes)
            if stream is not None:
                rec.log_plan(stream, plan.tool_waypoints())
            print(plan.describe())
            return plan

        if not args.execute:
            make_plan(None)
            print("nothing moved (add --execute to run the plan on the arm)")
            return 0
        from tapecell.cell.ur import URArm
        arm = URArm(cfg.robot.host, cfg.robot.port, limits, flange_from_tool=cfg.tools.gripper.flange_from_tcp)
        from tapecell.cell.poses import pose6_to_matrix
        with arm:
            plan = make_plan(arm.joints())
            if not confirm():
                print("cancelled; nothing moved")
                return 1

            def on_step(step, a):
                print(f"done: {step.action} {step.waypoint or ''}".rstrip())
                if stream is not None:
                    rec.log_arm_state(stream, time.perf_counter() - t_start, pose6_to_matrix(a.tcp_pose()), a.joints())

            t_start = time.perf_counter()
            execute_plan(plan, arm, limits, Speeds(), on_step=on_step)
        print("grasp executed")
        return 0
    finally:
        if stream is not None:
            rec.close_recording(stream)
