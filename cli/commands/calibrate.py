"""``tapecell calibrate``: calibrate the cameras with the robot-held cross plate.

    tapecell calibrate --sim [--seed N] [--cameras 2|3] --out FILE [--rrd FILE]
    tapecell calibrate --config CELL.toml --out FILE [--execute [--yes]] [--rrd FILE]
                       [--images DIR]

On the simulated cell the arm carries the plate through the planned grid, the cameras
render, and the result is compared with the simulator's true cameras. On the real cell
the arm is a UR5e over ur_rtde (behind the safety checks) and images come from OpenCV
``VideoCapture`` (the cell file's ``robot.camera_devices``) or a folder; without
``--execute`` the planned poses are printed and checked, and nothing moves. With
``--execute`` the robot's address and what will happen are shown and a typed 'yes' is
asked for on the terminal before any connection is opened (``--yes`` answers for a
script; with no terminal and no ``--yes`` nothing happens, exit 2).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from tapecell.cli.options import add_force, add_robot_options, add_seed, check_files, confirm_robot
from tapecell.estimator.capture import save_cameras

from tapecell.cell.calibration import (CalibrationResult, PlannedPose, camera_errors, plan_poses,
                           run_calibration)


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate the cameras with the cross plate on the arm",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true", help="calibrate the simulated cell")
    where.add_argument("--config", type=Path, metavar="CELL.toml", help="the real cell's file")
    add_seed(p, "simulation seed, 0 or more (default 0)")
    p.add_argument("--cameras", type=int, choices=(2, 3), default=2, help="simulated cameras (default 2)")
    p.add_argument("--out", type=Path, required=True, help="tape-cameras/1 file to write")
    p.add_argument("--rrd", type=Path, help="write a rerun recording of every step")
    add_robot_options(p, "move the arm through the planned poses")
    p.add_argument("--images", type=Path, metavar="DIR",
                   help="real cell: read pose images from DIR/<pose>/<camera>.png instead of cameras")
    add_force(p)
    p.set_defaults(func=run)


# ------------------------------------------------------------------------- simulation
class SimCameras:
    """Camera source rendering the simulated cell's cameras (tape hidden: the real cell is
    calibrated without a tape, and the sim's tape does not collide with the plate)."""

    def __init__(self, sim_cell) -> None:
        self.sim = sim_cell
        self.names = list(sim_cell.camera_names)
        sim_cell.show_tape(False)

    def size(self, name: str) -> tuple[int, int]:
        cam = self.sim.camera(name)
        return cam.width, cam.height

    def grab(self, index: int) -> dict[str, np.ndarray]:
        return {n: self.sim.render_rgb(n) for n in self.names}


def calibrate_sim(cell, seed: int = 0, n_cameras: int = 2, rec=None, log=print):
    """Calibrate the simulated cell; returns (CalibrationResult, true cameras). The arm is
    the physically simulated UR5e behind the same Arm interface and safety checks as on the
    real cell: it drives through every pose and the cameras render where it settled."""
    from tapecell.sim.arm import SimArm
    from tapecell.sim.cell import SimCell

    from tapecell.cell.safety import SafeArm, SafetyLimits
    from tapecell.sim.arm_adapter import SimArmAdapter

    poses = plan_poses(cell, n_cameras)
    with SimCell(cell, seed=seed, n_cameras=n_cameras, tool="plate") as sim:
        source = SimCameras(sim)
        arm = SafeArm(SimArmAdapter(SimArm(sim)), SafetyLimits.from_config(cell.limits), cell.tools.plate.flange_from_tcp)
        with arm:
            arm.move_joints(poses[0].joints, 0.5, 1.0)
            result = run_calibration(cell, arm, source, poses, rec=rec, log=log)
        true = sim.cameras()
    return result, true


def report(result: CalibrationResult, true=None, log=print) -> None:
    """One line per camera: RMS, outliers and (when known) the errors against the truth."""
    truth = {c.name: c for c in (true or [])}
    for name, fit in result.fits.items():
        c = fit.camera
        line = (f"{name}: rms {c.rms_px:.3f} px, {int(fit.inliers.sum())} poses used, {fit.n_outliers} outliers, "
                f"fx {c.K[0, 0]:.1f} fy {c.K[1, 1]:.1f} cx {c.K[0, 2]:.2f} cy {c.K[1, 2]:.2f} px, "
                f"dist {np.round(c.dist, 4).tolist()}")
        if name in truth:
            e = camera_errors(c, truth[name])
            line += (f" | vs truth: focal {e['focal_pct']:.3f} %, principal point {e['principal_px']:.2f} px, "
                     f"centre {1000 * e['centre_m']:.3f} mm, rotation {e['rotation_deg']:.4f} deg")
        log(line)


# ----------------------------------------------------------------------------- real
def print_plan(cell, poses: list[PlannedPose], log=print) -> None:
    from tapecell.cell.safety import SafetyLimits, check_joint_move

    limits = SafetyLimits.from_config(cell.limits)
    q_prev = np.asarray(cell.arm.home_joints, float)
    for p in poses:
        # Same check the SafeArm makes before sending a move (the path from the previous pose).
        check_joint_move(limits, q_prev, p.joints, 0.5, 1.0,
                         _check_points(cell))
        q_prev = p.joints
        log(f"pose {p.index + 1:3d}: cross at {np.round(p.point, 4).tolist()} m, flange "
            f"{np.round(p.flange_pose, 4).tolist()}, joints {np.round(p.joints, 3).tolist()} rad, view "
            + ", ".join(f"{k} {v:.0f} deg" for k, v in p.view_deg.items()))
    log(f"{len(poses)} poses planned and checked against the workspace and keep-out limits; "
        "nothing moved (add --execute to run)")


def _check_points(cell):
    from tapecell.cell.safety import check_points_flange

    return check_points_flange(cell.tools.plate.flange_from_tcp)


def calibrate_real(cell, args, rec=None, log=print) -> CalibrationResult:
    from tapecell.cell.cameras_real import FolderCameras, VideoCameras
    from tapecell.cell.ur import URArm

    n = len(cell.robot.camera_devices)
    poses = plan_poses(cell, min(n, len(cell.cameras.camera)))
    if not args.execute:
        print_plan(cell, poses, log)
        return None
    names = [c.name for c in cell.cameras.camera[:len(poses[0].view_deg)]]
    images = f"images from {args.images}" if args.images is not None else \
        f"images from camera devices {list(cell.robot.camera_devices[:len(names)])}"
    # The image source first: a missing folder or camera is found before you are asked.
    if args.images is not None:
        source = FolderCameras(args.images, names)
    else:
        source = VideoCameras(cell.robot.camera_devices[:len(names)], names)
    try:
        confirm_robot(cell.robot.host, cell.robot.port, [
            f"move the arm (cross plate mounted) through {len(poses)} planned calibration poses at 0.3 rad/s, "
            f"starting with a joint move to {np.round(poses[0].joints, 3).tolist()} rad",
            f"take {images} at each pose and write {args.out}"], args.yes)
        # URArm checks every target against the limits itself, the plate's TCP included.
        # The calibration grid's joint moves pass the wrist near the part (the collision
        # check against the part and the table would refuse some): only the workspace and
        # keep-out box are checked here, as before that check existed.
        arm = URArm.from_config(cell, cell.tools.plate.flange_from_tcp, obstacles=False)
        with arm:
            arm.move_joints(poses[0].joints, 0.3, 0.5)
            return run_calibration(cell, arm, source, poses, rec=rec, log=log, joint_speed=0.3, joint_accel=0.5)
    finally:
        source.close()


# ------------------------------------------------------------------------------ main
def run(args) -> int:
    from tapecell.cell.config import load_cell_config

    from tapecell.cell.recording import close_recording, discard_recording, open_recording

    cell = load_cell_config(None if args.sim else args.config)
    if args.sim or args.execute:      # the files are checked before the arm moves, not after
        check_files([args.out, args.rrd], args.force)
    rec = open_recording(args.rrd, "tapecell-calibrate") if args.rrd else None
    t0 = time.perf_counter()
    try:
        if args.sim:
            result, true = calibrate_sim(cell, args.seed, args.cameras, rec)
        else:
            result, true = calibrate_real(cell, args, rec), None
    except BaseException:
        if rec is not None:
            discard_recording(rec)
        raise
    if rec is not None:
        close_recording(rec)
    if result is None:
        return 0
    report(result, true)
    save_cameras(result.cameras, args.out)
    print(f"wrote {args.out} ({len(result.cameras)} cameras, {time.perf_counter() - t0:.1f} s)")
    return 0
