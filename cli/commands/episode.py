"""``tapecell episode`` (one sim grasp episode) and ``tapecell episodes`` (many)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tapecell.cli.options import MAX_SEED, add_force, add_seed, check_dir, check_files, positive_int
from tapecell.estimator.errors import TapecellError

EPISODE_HELP = """Run one simulated grasp episode: randomise the tape (seed), park the arm,
render, segment and estimate, plan a grasp at the tip, execute it with the simulated UR5e,
and check physically that both pads closed on the tape and that the tip followed the
gripper through the lift. Prints one tape-episode/1 JSON line; exit status 1 when the
grasp failed."""

EPISODES_HELP = """Run many episodes in parallel processes. DIR/results.jsonl gets one
tape-episode/1 line as each episode ends; a rerun skips seeds already there, so a crash
loses nothing. Ends with a summary: success rate with a 95 % interval, failure reasons,
error percentiles and time per episode."""


def _cameras(value: str) -> int:
    if value not in ("2", "3"):
        raise argparse.ArgumentTypeError("must be 2 or 3")
    return int(value)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("episode", help="one simulated grasp episode", description=EPISODE_HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seed(p, "tape randomisation seed, 0 or more (default 0)")
    p.add_argument("--cameras", type=_cameras, default=2, help="2 or 3 cameras (default 2)")
    p.add_argument("--rrd", type=Path, metavar="FILE", help="write a rerun recording of every step")
    p.add_argument("--config", type=Path, metavar="CELL.toml", help="cell file (default: the bundled one)")
    add_randomize(p)
    add_force(p)
    p.set_defaults(func=run_one)

    p = sub.add_parser("episodes", help="many simulated grasp episodes, with a summary",
                       description=EPISODES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=positive_int, required=True, help="number of episodes")
    add_seed(p, "first seed, 0 or more; episodes use seed .. seed+n-1")
    p.add_argument("--jobs", type=positive_int, default=1, help="parallel worker processes (default 1)")
    p.add_argument("--cameras", type=_cameras, default=2, help="2 or 3 cameras (default 2)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="results folder")
    p.add_argument("--rrd", choices=("all", "failures"), default=None,
                   help="write DIR/episode-NNNN.rrd for every episode (all) or only for those that did not "
                        "grasp (failures: what a reviewer usually wants)")
    p.add_argument("--config", type=Path, metavar="CELL.toml", help="cell file (default: the bundled one)")
    add_randomize(p)
    add_backend(p)
    add_force(p)
    p.set_defaults(func=run_many)


def add_randomize(p: argparse.ArgumentParser) -> None:
    p.add_argument("--randomize", action="append", metavar="NAME=VALUE", default=[],
                   help="domain randomisation on top of the cell file's [randomize] table (repeatable): VALUE is "
                        "a number (fixed), lo:hi (uniform) or, for cameras, a list (2,3); names: "
                        "light_azimuth_deg, light_elevation_deg, light_intensity, ambient, tape_rgb_jitter, "
                        "tape_width_mm, tape_length_mm, tape_thickness_mm, tape_stiffness_scale, tape_model, "
                        "calib_rot_deg, calib_trans_mm, mask_noise, cameras")


def add_backend(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=("process", "ray"), default="process",
                   help="process: a pool of --jobs local processes (default); ray: Ray tasks on a local Ray of "
                        "--jobs CPUs bound to 127.0.0.1, or on the cluster at --address (pip install "
                        "\"tapecell[ray]\")")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="with --backend ray: an existing Ray cluster's head (started with ray start --head)")


def randomize_of(args: argparse.Namespace, cfg) -> "object":
    """The cell file's [randomize] table with the command line's overrides."""
    from tapecell.sim.randomize import Randomize

    return Randomize.from_table(cfg.randomize, f"{cfg.source}: [randomize]").with_overrides(args.randomize)


def run_one(args: argparse.Namespace) -> int:
    from tapecell.sim.episode import run_episode
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config(args.config)  # a bad cell file is one clear error before any work
    randomize = randomize_of(args, cfg)
    check_files([args.rrd], args.force)
    doc = run_episode(args.seed, args.cameras, args.rrd, args.config, randomize)
    print(json.dumps(doc))
    if not doc["success"]:
        print(f"tapecell: episode {args.seed} failed: {doc['failure']}"
              + (f" ({doc['detail']})" if doc.get("detail") else ""), file=sys.stderr)
        return 1
    return 0


def run_many(args: argparse.Namespace) -> int:
    from tapecell.sim.episodes import run_episodes, summarize
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config(args.config)
    randomize = randomize_of(args, cfg)
    if args.address and args.backend != "ray":
        raise TapecellError("--address needs --backend ray")
    if args.seed + args.n - 1 > MAX_SEED:
        raise TapecellError(f"--seed {args.seed} --n {args.n}: the last seed would pass {MAX_SEED}")
    # A results folder is resumed (its results.jsonl is appended to); any other non-empty
    # folder is someone's files, kept unless --force (only results and recordings are written).
    if not (args.out / "results.jsonl").is_file():
        check_dir(args.out, args.force)
    else:
        check_dir(args.out, True)
    config = args.config.resolve() if args.config else None
    t0 = time.perf_counter()
    results = run_episodes(range(args.seed, args.seed + args.n), args.cameras, args.out, args.jobs,
                           args.rrd, config, backend=args.backend, address=args.address, randomize=randomize)
    print(summarize(results, time.perf_counter() - t0))
    return 0
