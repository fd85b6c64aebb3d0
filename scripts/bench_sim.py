"""Benchmark the simulated cell: capture time, RGB segmentation IoU, and the default
estimator's accuracy on sim captures, with 2 and 3 cameras.

    python scripts/bench_sim.py [--captures 50] [--config CELL.toml] [--no-estimate]

Prints one table per camera count (per rest-shape case and overall) and the targets:
capture (reset + settle + render all cameras) <= 1 s; tip error median <= 1.5 mm and no
gross failure (> 10 mm).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
os.environ.setdefault("MUJOCO_GL", "egl")

import tapecell  # noqa: E402

tapecell.one_blas_thread()   # before numpy loads

import numpy as np  # noqa: E402

from tapecell import estimator  # noqa: E402
from tapecell.estimator.metrics import errors  # noqa: E402
from tapecell.sim.cell import SimCell  # noqa: E402
from tapecell.cell.config import load_cell_config  # noqa: E402
from tapecell.sim.tape_shape import CASES  # noqa: E402


def run(n_cameras: int, captures: int, cfg, do_estimate: bool) -> list[dict]:
    rows = []
    with SimCell(cfg, 0, n_cameras=n_cameras) as cell:
        for seed in range(captures):
            t0 = time.perf_counter()
            cell.reset(seed)
            cap = cell.capture()
            t_capture = time.perf_counter() - t0
            ious = []
            for v in cap.views:
                true = cell.true_mask(v.camera.name)
                ious.append((true & v.mask).sum() / max(1, (true | v.mask).sum()))
            row = {"seed": seed, "case": cell.rest.case, "capture_s": t_capture,
                   "settle_s": cell.timing.settle_s, "iou_min": min(ious), "iou_med": float(np.median(ious))}
            if do_estimate:
                est = estimator.estimate(cap)
                e = errors(est.nodes, est.tip_rotation, cap.truth)
                row.update(tip_mm=e.tip_m * 1000, node_max_mm=e.node_max_m * 1000, normal_deg=e.normal_deg,
                           fit_s=est.time_s, cost=est.cost)
            rows.append(row)
    return rows


def table(rows: list[dict], n_cameras: int, do_estimate: bool) -> None:
    head = f"{'cameras':>7} {'case':>9} {'n':>3} {'capture ms (med/max)':>21} {'IoU med/min':>12}"
    if do_estimate:
        head += f" {'tip mm med':>10} {'tip mm max':>10} {'>10mm':>5} {'node max mm med':>15} {'normal deg med':>14}"
    print(head)
    for case in list(CASES) + ["all"]:
        sel = [r for r in rows if case == "all" or r["case"] == case]
        if not sel:
            continue
        cap = np.array([r["capture_s"] for r in sel]) * 1000
        iou_med = np.median([r["iou_med"] for r in sel])
        iou_min = np.min([r["iou_min"] for r in sel])
        line = (f"{n_cameras:>7} {case:>9} {len(sel):>3} {np.median(cap):>10.0f} / {cap.max():>7.0f}  "
                f"{iou_med:>6.4f}/{iou_min:.3f}")
        if do_estimate:
            tip = np.array([r["tip_mm"] for r in sel])
            line += (f" {np.median(tip):>10.2f} {tip.max():>10.2f} {int((tip > 10).sum()):>5} "
                     f"{np.median([r['node_max_mm'] for r in sel]):>15.2f} "
                     f"{np.median([r['normal_deg'] for r in sel]):>14.2f}")
        print(line)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--captures", type=int, default=50, help="captures per camera count (seeds 0..N-1)")
    ap.add_argument("--config", type=Path, default=None, help="cell file (default: bundled)")
    ap.add_argument("--no-estimate", action="store_true", help="only time captures and check segmentation")
    args = ap.parse_args()
    cfg = load_cell_config(args.config)
    do_est = not args.no_estimate
    all_rows = {}
    for n in (2, 3):
        all_rows[n] = run(n, args.captures, cfg, do_est)
        table(all_rows[n], n, do_est)
        print()
    worst = max(r["capture_s"] for rows in all_rows.values() for r in rows)
    print(f"target capture <= 1 s: worst {worst:.3f} s -> {'PASS' if worst <= 1.0 else 'FAIL'}")
    if do_est:
        for n, rows in all_rows.items():
            tip = np.array([r["tip_mm"] for r in rows])
            ok = np.median(tip) <= 1.5 and not np.any(tip > 10)
            print(f"target {n} cameras tip median <= 1.5 mm, none > 10 mm: median {np.median(tip):.2f} mm, "
                  f"{int((tip > 10).sum())} gross -> {'PASS' if ok else 'FAIL'}")
            bad = [f"{r['seed']}({r['case']}) {r['tip_mm']:.1f}" for r in rows if r["tip_mm"] > 10]
            if bad:
                print(f"   gross failures: {', '.join(bad)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
