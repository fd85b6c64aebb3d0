"""``tapecell probe``: measure the true tape with the needle on the arm (paper sec. 4.1).

    tapecell probe --sim [--seed N] [--cameras 2|3] [--out FILE]
    tapecell probe --config CELL.toml --capture DIR [--out FILE] [--execute [--yes]]

Simulated: the cell captures and estimates the tape, then the needle approaches the
tape's tip and tip corners slowly along the tape normal until MuJoCo reports contact;
the measured points are compared with the estimate (the paper's e, eq. 12) and with the
simulator's truth. Real: the arm goes into freedrive (teach mode); the operator guides
the needle onto the tip (and corners) and presses Enter for each; the needle tip is saved
as a tape-truth/1 fragment next to the capture. Teach mode always ends. Without
``--execute`` nothing is connected; with it, the robot's address and what will happen are
shown and a typed 'yes' is asked for before any connection (``--yes`` for scripts).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tapecell.cli.options import add_force, add_robot_options, add_seed, check_files, confirm_robot
from tapecell.estimator.errors import TapecellError
from tapecell.estimator.io import atomic_write_json

from tapecell.cell.probe import (PROBE_LABELS, ProbeError, ProbeParams, approach_normal, estimate_errors,
                     guided_probe, tape_points, truth_fragment)


def register(subparsers) -> None:
    p = subparsers.add_parser("probe", help="measure the tape's tip with the needle",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true", help="probe the simulated tape")
    where.add_argument("--config", type=Path, metavar="CELL.toml", help="the real cell's file")
    add_seed(p, "simulation seed, 0 or more (default 0)")
    p.add_argument("--cameras", type=int, choices=(2, 3), default=2)
    p.add_argument("--capture", type=Path, metavar="DIR", help="real cell: the capture being probed")
    p.add_argument("--out", type=Path, help="where to write the tape-truth/1 fragment "
                                            "(real cell default: CAPTURE/probe.json)")
    add_robot_options(p, "start freedrive")
    add_force(p)
    p.set_defaults(func=run)


def probe_sim(cell, seed: int, n_cameras: int, log=print) -> dict:
    """Capture, estimate, probe; returns a dict with measured points and the errors [m]."""
    from tapecell.estimator import estimate
    from tapecell.sim.arm import SimArm
    from tapecell.sim.arm import SimArmError
    from tapecell.sim.prober import SimProber
    from tapecell.sim.ur5e import IKError
    from tapecell.sim.cell import SimCell

    with SimCell(cell, seed=seed, n_cameras=n_cameras, tool="needle") as sim:
        capture = sim.capture()
        est = estimate(capture)
        truth_tip = sim.tape_tip_frame()
        width = cell.tape.width
        params = ProbeParams()
        targets = tape_points(truth_tip[:3, 3], truth_tip[:3, :3], width, params.inset)
        est_points = tape_points(est.tip_position, est.tip_rotation, width, params.inset)
        arm = SimArm(sim, tool="needle")
        prober = SimProber(sim, arm, params)
        # Approach from the robot's side of the tape (the base is at the origin).
        normal = approach_normal(truth_tip[:3, 3], truth_tip[:3, 2], -truth_tip[:3, 3])
        points = []
        for label in PROBE_LABELS:
            try:
                points.append(prober.probe(label, targets[label], normal))
            except Exception as e:    # noqa: BLE001 - one unreachable point must not lose the others
                if isinstance(e, (ProbeError, IKError, SimArmError)):
                    log(f"{label}: not probed ({e})")
                    continue
                raise
        if not points:
            raise ProbeError(f"seed {seed}: no point of the tape could be probed")
        e_est = estimate_errors(points, est_points)
        e_truth = {p.label: float(np.linalg.norm(p.position - targets[p.label])) for p in points}
    for p in points:
        log(f"{p.label:>9}: measured {np.round(1000 * p.position, 2).tolist()} mm, "
            f"e (estimate vs measured, eq. 12) {1000 * e_est[p.label]:.2f} mm, "
            f"measured vs sim truth {1000 * e_truth[p.label]:.3f} mm")
    tip_truth_err = float(np.linalg.norm(est.tip_position - truth_tip[:3, 3]))
    log(f"estimate tip vs sim truth: {1000 * tip_truth_err:.2f} mm (cost {est.cost:.4f})")
    return {"points": points, "e_estimate": e_est, "e_truth": e_truth, "estimate_tip_error": tip_truth_err}


def probe_real(cell, args, prompt=None, log=print) -> int:
    from tapecell.cell.ur import URArm

    if args.capture is None:
        raise TapecellError("--capture DIR is needed on the real cell (the capture the probed points belong to)")
    if not args.capture.is_dir():
        raise TapecellError(f"{args.capture}: capture directory not found")
    out = args.out or args.capture / "probe.json"
    if not args.execute:
        log(f"would connect to {cell.robot.host}:{cell.robot.port}, start freedrive and record "
            f"{', '.join(PROBE_LABELS)} into {out}; nothing connected (add --execute)")
        return 0
    check_files([out], args.force)
    confirm_robot(cell.robot.host, cell.robot.port, [
        "start freedrive (teach mode): the arm's brakes release and it follows your hand; it makes no "
        "motion of its own",
        f"record the needle tip at {', '.join(PROBE_LABELS)} as you press Enter, into {out}"], args.yes)
    arm = URArm.from_config(cell, cell.tools.needle.flange_from_tcp)
    with arm:
        points = guided_probe(arm, cell.tools.needle.flange_from_tcp, PROBE_LABELS, prompt, log)
    atomic_write_json(out, truth_fragment(points, str(args.capture)))
    log(f"wrote {out} ({len(points)} points)")
    return 0


def run(args) -> int:
    from tapecell.cell.config import load_cell_config

    cell = load_cell_config(None if args.sim else args.config)
    if not args.sim:
        return probe_real(cell, args)
    check_files([args.out], args.force)
    result = probe_sim(cell, args.seed, args.cameras)
    if args.out is not None:
        atomic_write_json(args.out, truth_fragment(result["points"]))
        print(f"wrote {args.out}")
    return 0
