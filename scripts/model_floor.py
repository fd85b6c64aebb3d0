"""What the 5-plate model itself allows: the best chain fitted in 3-D to the TRUE tape.

    python scripts/model_floor.py [--captures DIR ...] [--weights 0 0.03 0.1 0.3]

For each capture with truth.json, the chain's angles are fitted (least squares, several
starts) to the true centre line at equal arc length, plus ``w`` times the difference of
the tip normals. The table shows the tip and normal errors reachable for each weight: the
floor below which no silhouette fit can go, and the trade-off between following the
centre line and matching the tip's normal (the tip frame is the last plate's, F_n).

The last line is the normal's floor for any chain that follows the tape: the last plate's
trunk is the chord between its two nodes, its normal is perpendicular to that chord, so
with both nodes on the true centre line the normal error is at least asin(|chord . n|)
(n: the true tip normal), whatever the twist.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import tapecell

tapecell.one_blas_thread()   # before numpy loads

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tapecell.estimator.bench import sample_captures  # noqa: E402
from tapecell.estimator.capture import Capture  # noqa: E402
from tapecell.estimator.metrics import Errors, centerline_at, errors  # noqa: E402
from tapecell.estimator.tape import forward_kinematics  # noqa: E402

SAMPLES_PER_PLATE = 12
STARTS = 8


def best_chain(capture: Capture, w: float) -> Errors:
    """Errors of the chain closest to the true centre line (and, weighted by w, tip normal)."""
    spec, truth = capture.tape, capture.truth
    s_nodes = np.concatenate([[0.0], np.cumsum(spec.segment_lengths)])
    seg = np.repeat(np.arange(spec.n), SAMPLES_PER_PLATE)
    t = np.tile(np.arange(1, SAMPLES_PER_PLATE + 1) / SAMPLES_PER_PLATE, spec.n)
    s = s_nodes[seg] + t * spec.segment_lengths[seg]
    target = np.vstack([truth.points[:1], centerline_at(truth, s)])

    def residuals(x: np.ndarray) -> np.ndarray:
        shape = forward_kinematics(spec, x.reshape(-1, 3))
        pts = shape.nodes[seg] + (shape.nodes[seg + 1] - shape.nodes[seg]) * t[:, None]
        pts = np.vstack([shape.nodes[:1], pts])
        return np.concatenate([(pts - target).ravel(), w * (shape.frames[-1][:, 2] - truth.tip_rotation[:, 2])])

    rng = np.random.default_rng(0)
    starts = [np.zeros(3 * spec.n)] + [rng.normal(scale=0.3, size=3 * spec.n) for _ in range(STARTS - 1)]
    best = min((least_squares(residuals, x0) for x0 in starts), key=lambda r: r.cost)
    shape = forward_kinematics(spec, best.x.reshape(-1, 3))
    return errors(shape.nodes, shape.frames[-1], truth)


def chord_floor_deg(capture: Capture) -> float:
    """Least tip normal error [deg] of any chain whose last two nodes lie on the true centre
    line at their arc lengths: the angle between the true normal and the plane normal to
    the last chord."""
    spec, truth = capture.tape, capture.truth
    length = float(np.sum(spec.segment_lengths))
    a, b = centerline_at(truth, np.array([length - spec.segment_lengths[-1], length]))
    chord = (b - a) / np.linalg.norm(b - a)
    return float(np.degrees(np.arcsin(min(1.0, abs(chord @ truth.tip_rotation[:, 2])))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", nargs="*", type=Path, default=[ROOT.parent / "shared" / "captures-sample"])
    ap.add_argument("--weights", nargs="*", type=float, default=[0.0, 0.03, 0.1, 0.3])
    args = ap.parse_args()
    captures = [c for c in sample_captures(args.captures) if c.truth is not None]
    if not captures:
        print("model_floor: no captures with truth.json found", file=sys.stderr)
        return 2
    print(f"{len(captures)} captures; best 5-plate chain fitted to the true tape")
    print(f"{'w':>6}  {'tip med':>7} {'tip p90':>7} {'tip max':>7}  {'normal med':>10} {'normal p90':>10}")
    for w in args.weights:
        e = [best_chain(c, w) for c in captures]
        tip = np.array([x.tip_m for x in e]) * 1e3
        nrm = np.array([x.normal_deg for x in e])
        print(f"{w:>6g}  {np.median(tip):7.2f} {np.percentile(tip, 90):7.2f} {tip.max():7.2f}  "
              f"{np.median(nrm):10.2f} {np.percentile(nrm, 90):10.2f}")
    floor = np.array([chord_floor_deg(c) for c in captures])
    print(f"{'chord':>6}  {0.0:7.2f} {0.0:7.2f} {0.0:7.2f}  {np.median(floor):10.2f} {np.percentile(floor, 90):10.2f}"
          "   (last two nodes on the true centre line; best twist)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
