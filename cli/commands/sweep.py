"""``tapecell sweep``: grasp episodes over a grid of settings, a summary and a report."""
from __future__ import annotations

import argparse
import shlex
from pathlib import Path

from tapecell.cli.options import MAX_SEED, add_force, add_seed, check_dir, positive_int
from tapecell.estimator.errors import TapecellError

from .episode import RANDOMIZE_HELP, _cameras, add_backend_options, check_backend, load_randomize

SWEEP_HELP = """Run simulated grasp episodes over a grid of settings and report them.

Each --param NAME=V1,V2,... adds a dimension to the grid; the grid is every combination,
and each of its cells runs --n episodes on the same seeds (--seed .. --seed+n-1), on the
process pool or on Ray. Writes DIR/cells/<cell>/results.jsonl (tape-episode/1 lines, as
each episode ends; a rerun skips the episodes already there), DIR/summary.json
(tape-sweep/1: per cell the success rate with its 95 % interval, refusals, failures, tip
error median and p90, time per episode) and DIR/report.html with its plots in DIR/plots/
(success rate against each parameter, tip error distributions, failure reasons) and links
to the recordings of the episodes that did not grasp.

examples:
  tapecell sweep --param cameras=2,3 --param randomize.calib_rot_deg=0,0.3 --n 50 --out sweep1
  tapecell sweep --param randomize.tape_width_mm=20,30 --randomize light_intensity=0.3:0.9 \\
                 --n 200 --backend ray --address 127.0.0.1:6379 --out sweep2"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="grasp episodes over a grid of settings, with a summary and an HTML report",
                       description=SWEEP_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--param", action="append", required=True, metavar="NAME=V1,V2,...",
                   help="a swept parameter and its values (repeatable): 'cameras' (2, 3) or 'randomize.NAME' "
                        "with NAME a randomisation setting (see --randomize), each value a number or lo:hi "
                        "(a uniform range), e.g. randomize.calib_rot_deg=0,0.3 or randomize.tape_width_mm=15:25,25:35")
    p.add_argument("--n", type=positive_int, required=True, help="episodes per cell of the grid")
    add_seed(p, "first seed, 0 or more (default 0); every cell runs seeds seed .. seed+n-1")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    p.add_argument("--jobs", type=positive_int, default=1,
                   help="parallel workers (default 1): processes, or the CPUs of the local Ray with --backend ray")
    p.add_argument("--cameras", type=_cameras, default=2, help="2 or 3 cameras where 'cameras' is not swept (default 2)")
    p.add_argument("--randomize", action="append", metavar="NAME=VALUE",
                   help="randomisation in every cell besides the grid: " + RANDOMIZE_HELP)
    p.add_argument("--rrd", choices=("failures", "all", "none"), default="failures",
                   help="rerun recordings: of the episodes that did not grasp (default; the report links them), "
                        "of every episode, or none (faster)")
    p.add_argument("--config", type=Path, metavar="CELL.toml", help="cell file (default: the bundled one)")
    add_backend_options(p)
    add_force(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tapecell.cell.config import load_cell_config
    from tapecell.sim.sweep import CELLS, check_params, format_table, parse_param, run_sweep

    params = [parse_param(t) for t in args.param]
    check_params(params)
    cfg = load_cell_config(args.config)
    base = load_randomize(cfg, args.randomize)
    for p in params:          # a grid value that the base settings would make invalid shows now
        if p.setting is not None:
            for v in p.values:
                base.with_settings({p.setting: v}, f"--param {p.name}")
    check_backend(args)
    if args.seed + args.n - 1 > MAX_SEED:
        raise TapecellError(f"--seed {args.seed} --n {args.n}: the last seed would pass {MAX_SEED}")
    # A sweep folder is resumed; any other non-empty folder is someone's files (kept unless --force).
    check_dir(args.out, args.force or (args.out / CELLS).is_dir())
    config = args.config.resolve() if args.config else None
    command = " ".join(shlex.quote(a) for a in _command(args))
    summary = run_sweep(params, args.n, args.seed, args.out, args.jobs, args.backend, args.address, config, base,
                        args.cameras, None if args.rrd == "none" else args.rrd,
                        settings={"command": command, "config": str(config) if config else None,
                                  "address": args.address})
    print(format_table(summary))
    print(f"summary: {args.out / 'summary.json'}\nreport:  {args.out / 'report.html'}")
    return 0


def _command(args: argparse.Namespace) -> list[str]:
    """The command line that reproduces this sweep (for the report)."""
    words = ["tapecell", "sweep"]
    for p in args.param:
        words += ["--param", p]
    words += ["--n", str(args.n), "--seed", str(args.seed), "--cameras", str(args.cameras), "--jobs", str(args.jobs)]
    for r in args.randomize or []:
        words += ["--randomize", r]
    words += ["--rrd", args.rrd, "--backend", args.backend]
    if args.address:
        words += ["--address", args.address]
    if args.config:
        words += ["--config", str(args.config)]
    return words + ["--out", str(args.out)]
