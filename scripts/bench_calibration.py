"""Benchmark: camera calibration on the simulated cell against the simulator's true cameras,
and what the calibrated cameras cost the estimator.

    python scripts/bench_calibration.py [--captures 30] [--seed 0]

Part 1 calibrates the 2- and 3-camera cells (the full procedure: planned poses, rendered
images, cross detection, DLT + calibrateCamera) and prints per camera the focal, principal
point, centre and rotation errors and the RMS against the targets (0.2 %, 1 px, 1 mm,
0.05 deg, 0.1 px). Part 2 estimates ``--captures`` simulated captures twice, with the
true and with the calibrated cameras (same masks), and prints the median tip errors;
the target is a rise of at most 0.3 mm.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import tapecell  # noqa: E402

tapecell.one_blas_thread()   # before numpy loads

import numpy as np  # noqa: E402

TARGETS = {"focal_pct": 0.2, "principal_px": 1.0, "centre_mm": 1.0, "rotation_deg": 0.05, "rms_px": 0.1}


def part1(cell, seed: int) -> dict:
    from tapecell.cell.calibration import camera_errors
    from tapecell.cli.commands.calibrate import calibrate_sim

    print(f"{'cams':>4} {'camera':>6} {'focal %':>8} {'pp px':>7} {'centre mm':>10} {'rot deg':>8} "
          f"{'rms px':>7} {'poses':>6} {'rejected':>9} {'time s':>7}  ok")
    calibrated = {}
    for n in (2, 3):
        t0 = time.perf_counter()
        result, true = calibrate_sim(cell, seed, n, log=lambda _: None)
        dt = time.perf_counter() - t0
        truth = {c.name: c for c in true}
        calibrated[n] = result.cameras
        for name, fit in result.fits.items():
            e = camera_errors(fit.camera, truth[name])
            row = {"focal_pct": e["focal_pct"], "principal_px": e["principal_px"], "centre_mm": 1000 * e["centre_m"],
                   "rotation_deg": e["rotation_deg"], "rms_px": fit.camera.rms_px}
            ok = all(row[k] <= TARGETS[k] for k in TARGETS)
            print(f"{n:>4} {name:>6} {row['focal_pct']:>8.4f} {row['principal_px']:>7.3f} {row['centre_mm']:>10.4f} "
                  f"{row['rotation_deg']:>8.4f} {row['rms_px']:>7.4f} {int(fit.inliers.sum()):>6} "
                  f"{sum(result.rejections[name].values()):>9} {dt:>7.1f}  {'yes' if ok else 'NO'}")
    print("targets: focal <= 0.2 %, principal point <= 1 px, centre <= 1 mm, rotation <= 0.05 deg, rms <= 0.1 px")
    return calibrated


def part2(cell, cameras, n_captures: int, seed0: int) -> None:
    from tapecell.estimator import estimate
    from tapecell.estimator.metrics import errors
    from tapecell.sim.cell import SimCell

    by_name = {c.name: c for c in cameras}
    tip_true, tip_cal = [], []
    t0 = time.perf_counter()
    with SimCell(cell, seed=seed0, n_cameras=len(cameras)) as sim:
        for k in range(n_captures):
            sim.reset(seed0 + k)
            cap = sim.capture()
            views = [dataclasses.replace(v, camera=by_name[v.camera.name]) for v in cap.views]
            cap_cal = dataclasses.replace(cap, views=views)
            for c, out in ((cap, tip_true), (cap_cal, tip_cal)):
                est = estimate(c)
                out.append(1000 * errors(est.nodes, est.tip_rotation, cap.truth).tip_m)
    a, b = np.array(tip_true), np.array(tip_cal)
    rise = float(np.median(b) - np.median(a))
    print(f"\n{n_captures} sim captures ({len(cameras)} cameras), seeds {seed0}..{seed0 + n_captures - 1}, "
          f"{time.perf_counter() - t0:.0f} s")
    print(f"{'cameras':>12} {'median tip mm':>14} {'p90 tip mm':>11} {'max tip mm':>11}")
    print(f"{'true':>12} {np.median(a):>14.3f} {np.percentile(a, 90):>11.3f} {a.max():>11.3f}")
    print(f"{'calibrated':>12} {np.median(b):>14.3f} {np.percentile(b, 90):>11.3f} {b.max():>11.3f}")
    print(f"median rise {rise:+.3f} mm (target <= 0.3 mm): {'yes' if rise <= 0.3 else 'NO'}; "
          f"largest per-capture change {np.max(np.abs(b - a)):.3f} mm")


def main() -> int:
    from tapecell.cell.config import load_cell_config

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    cell = load_cell_config()
    calibrated = part1(cell, args.seed)
    part2(cell, calibrated[2], args.captures, 100 + args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
