"""``tapecell sweep``: grasp campaigns over a grid of settings, with a summary and a report."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from tapecell.cli.options import MAX_SEED, add_force, add_seed, check_dir, positive_int
from tapecell.estimator.errors import TapecellError

from .episode import add_backend, add_randomize, randomize_of

HELP = """Run simulated grasp episodes over a grid of settings: every combination of the
--param values is one cell, each cell runs the same --n seeds (the same tapes under each
setting). Writes DIR/cell-NN/results.jsonl (resumable: a rerun skips finished episodes),
recordings of the episodes that did not grasp, DIR/summary.json (format tape-sweep/1: per
cell the success rate with a 95 % interval, refusals, failures, tip error median and p90,
time per episode) and DIR/report.html with PNG plots.

example:
  tapecell sweep --param cameras=2,3 --param randomize.calib_rot_deg=0,0.3 --n 50 --jobs 2 --out sweep/"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="grasp campaigns over a grid of settings, with a report", description=HELP,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", action="append", default=[], metavar="NAME=V1,V2,...",
                   help="a swept setting and its values (repeatable): cameras=2,3 or randomize.NAME=... with any "
                        "[randomize] setting (see tapecell episodes --help); a value may be a lo:hi range")
    p.add_argument("--n", type=positive_int, required=True, help="episodes per cell")
    add_seed(p, "first seed, 0 or more; every cell uses seed .. seed+n-1")
    p.add_argument("--jobs", type=positive_int, default=1, help="parallel workers (default 1)")
    p.add_argument("--cameras", type=int, choices=(2, 3), default=2,
                   help="cameras where --param cameras is not swept (default 2)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="sweep folder")
    p.add_argument("--config", type=Path, metavar="CELL.toml", help="cell file (default: the bundled one)")
    add_randomize(p)
    add_backend(p)
    add_force(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tapecell.cell.config import load_cell_config
    from tapecell.sim.sweep import parse_params, run_sweep

    cfg = load_cell_config(args.config)
    base = randomize_of(args, cfg)
    params = parse_params(args.param)
    if args.address and args.backend != "ray":
        raise TapecellError("--address needs --backend ray")
    if args.seed + args.n - 1 > MAX_SEED:
        raise TapecellError(f"--seed {args.seed} --n {args.n}: the last seed would pass {MAX_SEED}")
    # A sweep folder is resumed; any other non-empty folder is someone's files.
    check_dir(args.out, args.force or (args.out / "cell-00").is_dir())
    t0 = time.perf_counter()
    summary = run_sweep(params, args.n, args.seed, args.out, args.jobs, args.cameras,
                        args.config.resolve() if args.config else None, base, args.backend, args.address)
    for row in summary["rows"]:
        label = ", ".join(f"{k}={v}" for k, v in row["params"].items()) or "defaults"
        print(f"  {label:<44} {100 * row['rate']:5.1f} % ({100 * row['ci95'][0]:.1f}-{100 * row['ci95'][1]:.1f}) "
              f"refused {row['refused']} failed {row['failed']}  tip med {row['tip_error_mm']['median']} mm")
    print(f"wrote {args.out / 'summary.json'} and {args.out / 'report.html'} ({time.perf_counter() - t0:.0f} s)")
    return 0
