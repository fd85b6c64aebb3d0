#!/usr/bin/env python3
"""Episodes per second against worker count, per backend, and the same results on every
backend.

    python scripts/bench_scaling.py --seed 90000 --n 6 [--workers 1,2] [--cluster]

Runs the seeds seed..seed+n-1 (2 cameras) through the process pool and a local Ray (bound to
127.0.0.1) at each worker count, and with ``--cluster`` through a two-worker cluster started
here with ``ray start --head`` on loopback. Prints a table (episodes/s, speed-up over one
worker) and whether every backend gave identical per-episode results (all fields but the
timings).
"""
from __future__ import annotations

import argparse
import os
import secrets
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")   # Ray on loopback only
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


def _strip(doc: dict) -> dict:
    return {k: v for k, v in doc.items() if k != "time_s"}


def main(argv: list[str] | None = None) -> int:
    from tapecell.sim.episodes import run_episodes

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, required=True, help="first seed (a fresh range for every figure)")
    p.add_argument("--n", type=int, default=6, help="episodes per run (default 6)")
    p.add_argument("--workers", default="1,2", help="worker counts (default 1,2)")
    p.add_argument("--cluster", action="store_true", help="also a two-worker cluster from ray start --head")
    a = p.parse_args(argv)
    seeds = list(range(a.seed, a.seed + a.n))
    rows, results = [], {}
    work = Path(tempfile.mkdtemp(prefix="tapecell-scaling-"))
    try:
        for backend in ("process", "ray"):
            for w in [int(x) for x in a.workers.split(",")]:
                if backend == "ray":
                    import ray
                    if ray.is_initialized():
                        ray.shutdown()
                t0 = time.perf_counter()
                docs = run_episodes(seeds, 2, work / f"{backend}-{w}", jobs=w, backend=backend,
                                    progress_stream=open(os.devnull, "w"))
                rows.append((backend, w, len(docs) / (time.perf_counter() - t0)))
                results[(backend, w)] = [_strip(d) for d in docs]
        if a.cluster:
            import ray
            if ray.is_initialized():
                ray.shutdown()
            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                port = s.getsockname()[1]
            os.environ.update(RAY_AUTH_MODE="token", RAY_AUTH_TOKEN=secrets.token_hex(16))
            ray_bin = Path(sys.executable).parent / "ray"
            subprocess.run([str(ray_bin), "start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port),
                            "--num-cpus", "2", "--include-dashboard=false", "--disable-usage-stats"],
                           check=True, capture_output=True)
            try:
                t0 = time.perf_counter()
                docs = run_episodes(seeds, 2, work / "cluster", jobs=2, backend="ray", address=f"127.0.0.1:{port}",
                                    progress_stream=open(os.devnull, "w"))
                rows.append(("ray start", 2, len(docs) / (time.perf_counter() - t0)))
                results[("ray start", 2)] = [_strip(d) for d in docs]
            finally:
                ray.shutdown()
                subprocess.run([str(ray_bin), "stop", "--force"], capture_output=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"seeds {seeds[0]}..{seeds[-1]}, 2 cameras, {os.cpu_count()} cores")
    print(f"{'backend':<10} {'workers':>7} {'episodes/s':>11} {'speed-up':>9}")
    for backend, w, rate in rows:
        one = next((r for b, ww, r in rows if b == backend and ww == 1), None)
        print(f"{backend:<10} {w:>7} {rate:>11.3f} {rate / one if one else float('nan'):>8.2f}x")
    first = next(iter(results.values()))
    same = all(r == first for r in results.values())
    print(f"identical per-episode results on every backend: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
