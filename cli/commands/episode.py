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
gripper through the lift. Only an "ok" estimate is acted on; a "hidden" or "ambiguous" one,
or a "poor_fit" for its end alone, is first settled with the needle where it can be (it
touches the hypotheses' tips, their corners and past them, measures an end along the
tape, walks on along a tape that goes on past a tip, refits the shape through a touch a
few mm off, or finds an end's twist at its corners; before acting it checks that the tape
lies on the end's trunk 12 mm back, where the pads will hold it), else refused. Prints one
tape-episode/1 JSON line ("outcome": grasped, refused or failed); exit status 1 when the
episode did not grasp."""

EPISODES_HELP = """Run many episodes in parallel: local processes (the default) or Ray tasks
(--backend ray: a local Ray bound to 127.0.0.1, or a running cluster with --address).
DIR/results.jsonl gets one tape-episode/1 line as each episode ends; a rerun skips seeds
already there, so a crash loses nothing, and an episode whose worker process dies is run
once more, then reported as failed ("worker died"). The same seeds give the same results
on every backend. Shows a progress bar with the rate and the time left on a terminal (plain
lines otherwise) and ends with a summary: success rate with a 95 % interval, failure
reasons, error percentiles and time per episode."""

RANDOMIZE_HELP = ("domain randomisation, NAME=VALUE (repeatable; overrides the cell file's [randomize] "
                  "table): VALUE a number (fixed), lo:hi (uniform) or, for cameras and tape_model, a "
                  "comma-separated list of choices. Names: light_azimuth_deg, light_elevation_deg, "
                  "light_intensity, ambient, tape_rgb_jitter, tape_width_mm, tape_length_mm, "
                  "tape_thickness_mm, tape_stiffness_scale, tape_model, calib_rot_deg, calib_trans_mm, "
                  "mask_noise, cameras. Each episode draws its values from its seed and records them")


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
    p.add_argument("--randomize", action="append", metavar="NAME=VALUE", help=RANDOMIZE_HELP)
    add_force(p)
    p.set_defaults(func=run_one)

    p = sub.add_parser("episodes", help="many simulated grasp episodes, with a summary",
                       description=EPISODES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=positive_int, required=True, help="number of episodes")
    add_seed(p, "first seed, 0 or more; episodes use seed .. seed+n-1")
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="parallel workers (default 1): processes, or the CPUs of the local Ray with --backend "
                        "ray (a cluster given by --address uses all of its CPUs)")
    p.add_argument("--cameras", type=_cameras, default=2, help="2 or 3 cameras (default 2)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="results folder")
    p.add_argument("--rrd", choices=("all", "failures"), default=None,
                   help="write DIR/episode-NNNN.rrd for every episode (all) or only for those that did not "
                        "grasp (failures: what a reviewer usually wants)")
    p.add_argument("--config", type=Path, metavar="CELL.toml", help="cell file (default: the bundled one)")
    p.add_argument("--randomize", action="append", metavar="NAME=VALUE", help=RANDOMIZE_HELP)
    add_backend_options(p)
    add_force(p)
    p.set_defaults(func=run_many)


def add_backend_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--backend", choices=("process", "ray"), default="process",
                   help="process: a pool of local processes (default); ray: Ray tasks (needs "
                        "pip install \"tapecell[ray]\")")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="with --backend ray: join the running Ray cluster whose head node listens there "
                        "(started with 'ray start --head'; its machines have tapecell installed); without it "
                        "a local Ray is started in this process, bound to 127.0.0.1")


def load_randomize(cfg, items: list[str] | None):
    """The cell file's [randomize] table with the command line's NAME=VALUE overrides."""
    from tapecell.sim.randomize import Randomize

    return Randomize.from_table(cfg.randomize, f"{cfg.source}: [randomize]").with_overrides(items)


def check_backend(args: argparse.Namespace) -> None:
    """Before any work: --address only with Ray, Ray installed, the cluster reachable."""
    if args.address is not None and args.backend != "ray":
        raise TapecellError("--address needs --backend ray")
    if args.backend == "ray":
        from tapecell.sim.ray_backend import check_reachable, import_ray, is_loopback, parse_address

        import_ray(loopback=args.address is None or is_loopback(parse_address(args.address)[0]))
        if args.address is not None:
            check_reachable(args.address)


def run_one(args: argparse.Namespace) -> int:
    from tapecell.sim.episode import run_episode
    from tapecell.cell.config import load_cell_config

    cfg = load_cell_config(args.config)  # a bad cell file is one clear error before any work
    randomize = load_randomize(cfg, args.randomize)
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
    randomize = load_randomize(cfg, args.randomize)
    check_backend(args)
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
