"""Where an episode's time goes: stages and what runs inside them.

    python scripts/bench_episode_time.py --seed 0 --n 20            # this code
    python scripts/bench_episode_time.py --seed 0 --n 20 --no-reuse # a new simulated cell per episode

Runs the episodes one after the other in this process (after one warm-up episode, seed 4,
not counted: imports and loading the compiled kernels are a worker's start-up, not an
episode's) and prints per episode the stages the result records (capture, estimate,
probe, plan, execute) and, measured by wrapping them, the time in MuJoCo's physics steps
(mj_step), rendering (Renderer.render), the simulated arm's numerical IK and building the
simulated cell (SimCell.__init__). The physics steps are split by what they simulated:
steps with a contact (the pads on the tape: closing, the lift), steps with the tape awake
and untouched, and steps with the tape asleep (``SimCell.set_tape_sleep``). The outcomes
are printed too: a speed change must not change them.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict

os.environ.setdefault("MUJOCO_GL", "egl")

import tapecell  # noqa: E402

tapecell.one_blas_thread()   # before numpy loads

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from tapecell.sim import arm as sim_arm  # noqa: E402
from tapecell.sim import cell as sim_cell  # noqa: E402
from tapecell.sim import episode  # noqa: E402

spent: dict[str, float] = defaultdict(float)
counts: dict[str, int] = defaultdict(int)


def timed(name, fn):
    def wrapper(*a, **k):
        t0 = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            spent[name] += time.perf_counter() - t0
            counts[name] += 1
    return wrapper


PHYSICS = "physics (mj_step)"
PHYSICS_KINDS = ("  with contacts", "  tape awake", "  tape asleep")


def physics_timed(step):
    """mj_step, timed as a whole and by what it simulated (read after the step)."""
    def wrapper(m, d, *a):
        t0 = time.perf_counter()
        try:
            return step(m, d, *a)
        finally:
            dt = time.perf_counter() - t0
            asleep = d.ntree_awake < m.ntree
            kind = PHYSICS_KINDS[0] if d.ncon else PHYSICS_KINDS[2] if asleep else PHYSICS_KINDS[1]
            for k in (PHYSICS, kind):
                spent[k] += dt
                counts[k] += 1
    return wrapper


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--no-reuse", action="store_true", help="build a new simulated cell for every episode")
    args = ap.parse_args()
    episode.REUSE_CELL = not args.no_reuse
    mujoco.mj_step = physics_timed(mujoco.mj_step)
    mujoco.Renderer.render = timed("rendering", mujoco.Renderer.render)
    sim_arm.ik = timed("arm IK", sim_arm.ik)
    sim_cell.SimCell.__init__ = timed("cell build", sim_cell.SimCell.__init__)
    episode.run_episode(4, args.cameras)        # warm-up (a quick seed), not counted
    spent.clear()
    counts.clear()
    stages: dict[str, list[float]] = defaultdict(list)
    walls = []
    print(f"{'seed':>6} {'outcome':<8} {'wall s':>7}  stages [s]")
    for seed in range(args.seed, args.seed + args.n):
        t0 = time.perf_counter()
        doc = episode.run_episode(seed, args.cameras)
        walls.append(time.perf_counter() - t0)
        for k, v in doc["time_s"].items():
            stages[k].append(v)
        print(f"{seed:>6} {doc['outcome']:<8} {walls[-1]:>7.2f}  "
              + "  ".join(f"{k} {v:.2f}" for k, v in doc["time_s"].items()))
    total = sum(walls)
    print(f"\n{args.n} episodes, {total:.1f} s, {total / args.n:.2f} s per episode (mean), "
          f"median {np.median(walls):.2f} s; cell reused: {not args.no_reuse}")
    print(f"{'stage':<12} {'episodes':>8} {'mean s':>7} {'median s':>8} {'share':>6}")
    for k, v in stages.items():
        print(f"{k:<12} {len(v):>8} {np.mean(v):>7.3f} {np.median(v):>8.3f} {100 * sum(v) / total:>5.1f}%")
    print(f"{'inside':<24} {'calls/ep':>9} {'s/ep':>7} {'share':>6}")
    rest = sorted((k for k in spent if k != PHYSICS and k not in PHYSICS_KINDS), key=lambda k: -spent[k])
    for k in [PHYSICS, *PHYSICS_KINDS, *rest]:
        v = spent.get(k, 0.0)
        print(f"{k:<24} {counts.get(k, 0) / args.n:>9.0f} {v / args.n:>7.3f} {100 * v / total:>5.1f}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
