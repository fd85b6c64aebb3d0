"""Grasp benchmark: many sim episodes with 2 and 3 cameras, in parallel, with a table.

    python scripts/bench_episodes.py --seed 10000 [--n 200] [--jobs 2] [--out runs/bench] [--cameras 2 3]
                                     [--tape chain|shell]

Take a fresh --seed range for every reported figure. Results go to
OUT/<k>cams/results.jsonl (resumable: a rerun skips finished seeds). The table gives, per
camera count, grasped / refused (nothing touched the tape) / failed (acted and missed),
each with its 95 % interval, the reasons of refusals and failures, tip error percentiles,
time per episode and the wall time of the run. Targets (issue 14): grasped >= 99 % (2
cameras) and >= 99.5 % (3), failed 0, refused <= 1 %. ``--tape shell``: on the MuJoCo
flexible-shell tape, which is not the estimator's model (``tape_model = "shell"``).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import tapecell

tapecell.one_blas_thread()   # before numpy loads

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tapecell.sim.episodes import outcome_of, run_episodes, summarize, wilson_interval  # noqa: E402
from tapecell.cell.config import load_cell_config  # noqa: E402
from tapecell.sim.randomize import Randomize  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, required=True, help="first seed (a fresh range for every figure)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cameras", type=int, nargs="+", default=[2, 3])
    ap.add_argument("--out", type=Path, default=Path("runs/bench"))
    ap.add_argument("--tape", choices=("chain", "shell"), default="chain",
                    help="the simulated tape: the plate chain (default) or the flexible shell")
    args = ap.parse_args()
    randomize = None     # the cell file's [randomize] table
    if args.tape == "shell":
        cfg = load_cell_config()
        randomize = Randomize.from_table(cfg.randomize).with_settings({"tape_model": "shell"})
    rows = []
    for cams in args.cameras:
        t0 = time.perf_counter()
        results = run_episodes(range(args.seed, args.seed + args.n), cams, args.out / f"{cams}cams", args.jobs,
                               randomize=randomize)
        wall = time.perf_counter() - t0
        print(f"\n== {cams} cameras ==\n{summarize(results, wall)}")
        rows.append((cams, results, wall))
    print("\ncams     n  grasped  95% interval    refused  95% interval    failed  95% interval  "
          "tip med  tip p90  s/episode  wall s")
    for cams, results, wall in rows:
        n = len(results)
        cells = []
        for outcome in ("grasped", "refused", "failed"):
            k = sum(outcome_of(r) == outcome for r in results)
            lo, hi = wilson_interval(k, n)
            cells.append(f"{100 * k / n:6.1f}%  {100 * lo:5.1f}-{100 * hi:5.1f}%")
        tip = np.array([r["tip_error_mm"] for r in results if r.get("tip_error_mm") is not None])
        per = np.median([sum(r.get("time_s", {}).values()) for r in results])
        print(f"{cams:>4} {n:>5} {cells[0]}  {cells[1]}  {cells[2]}  "
              f"{np.median(tip):7.2f}  {np.percentile(tip, 90):7.2f}  {per:9.2f}  {wall:6.0f}")
    print("(wall s is 0 for seeds already in the results file; delete OUT to time a fresh run)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
