"""Episodes per second against the number of workers, on this machine.

    python scripts/bench_scaling.py                       # process pool, 1 and 2 workers
    python scripts/bench_scaling.py --backends process,ray --workers 1,2 --n 12 --seed 20000

Each (backend, workers) pair runs the same seeds into a fresh temporary folder, exactly as
``tapecell episodes`` does (worker start-up, Ray start-up bound to 127.0.0.1, result
streaming included), and the table gives the wall time, episodes per second, the speed-up
over one worker of the same backend and the efficiency (speed-up / workers). The results
themselves must not depend on the backend or the worker count: the script checks that too.
"""
from __future__ import annotations

import argparse
import io
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

from tapecell.sim.episodes import run_episodes  # noqa: E402

VOLATILE = ("time_s", "recording")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=8, help="episodes per run (default 8)")
    ap.add_argument("--seed", type=int, default=20000, help="first seed (default 20000)")
    ap.add_argument("--workers", default="1,2", help="worker counts, comma-separated (default 1,2)")
    ap.add_argument("--backends", default="process", help="process and/or ray, comma-separated (default process)")
    ap.add_argument("--cameras", type=int, default=2)
    args = ap.parse_args()
    workers = [int(w) for w in args.workers.split(",")]
    seeds = list(range(args.seed, args.seed + args.n))
    print(f"{os.cpu_count()} CPUs; seeds {seeds[0]}-{seeds[-1]}, {args.cameras} cameras", file=sys.stderr)
    rows = []
    reference = None
    for backend in args.backends.split(","):
        base = None
        for w in workers:
            with tempfile.TemporaryDirectory(prefix="tapecell-scaling-") as tmp:
                t0 = time.perf_counter()
                results = run_episodes(seeds, args.cameras, Path(tmp), jobs=w, backend=backend,
                                       progress_stream=io.StringIO())
                wall = time.perf_counter() - t0
            stable = [{k: v for k, v in r.items() if k not in VOLATILE} for r in results]
            if reference is None:
                reference = stable
            same = stable == reference
            rate = len(results) / wall
            base = base or rate
            busy = sum(sum(r.get("time_s", {}).values()) for r in results) / len(results)
            rows.append((backend, w, len(results), wall, rate, rate / base, rate / base / w, busy, same))
            print(f"  {backend} x{w}: {wall:.1f} s", file=sys.stderr)
    print(f"{'backend':<8} {'workers':>7} {'episodes':>8} {'wall s':>7} {'ep/s':>6} {'speed-up':>8} "
          f"{'efficiency':>10} {'s/ep in stages':>14} {'same results':>12}")
    for b, w, n, wall, rate, up, eff, busy, same in rows:
        print(f"{b:<8} {w:>7} {n:>8} {wall:>7.1f} {rate:>6.3f} {up:>8.2f} {eff:>10.2f} {busy:>14.2f} "
              f"{'yes' if same else 'NO':>12}")
    return 0 if all(r[-1] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
