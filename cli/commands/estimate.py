"""``tapecell estimate``: fit the tape model to one or more capture directories."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tapecell.estimator.capture import Capture, load_capture
from tapecell.cli.options import add_force, check_files
from tapecell.estimator.errors import OutputError, TapecellError
from tapecell.estimator.io import atomic_write_json, to_json
from tapecell.estimator.metrics import errors

HELP = """Fit the tape model to capture directories (tape-capture/1).

One capture without --out prints the tape-estimate/1 JSON on stdout. With --out DIR each
capture's estimate is written to DIR/<capture folder name>.json and a summary line per
capture goes to stderr (tip/node/normal errors where the capture holds truth.json).
A capture that fails to load reports one error line; the others still run, and the exit
status is 2 if any failed. An estimate whose verdict is not "ok" (a robot must not act on
it: ambiguous, hidden, poor_fit) is still written, its reason goes to stderr, and the exit
status is 1. Existing estimate files are not replaced without --force, and two captures
with the same folder name (a/cap, b/cap) are refused before any work."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("estimate", help="fit the tape to capture directories",
                       description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("captures", nargs="+", type=Path, metavar="CAPTURE_DIR")
    p.add_argument("--out", type=Path, metavar="DIR", help="write DIR/<name>.json per capture")
    p.add_argument("--method", choices=["default", "paper"], default="default",
                   help="default: ours (fast, robust); paper: the paper's sequential Nelder-Mead")
    p.add_argument("--rrd", type=Path, metavar="FILE", help="write a rerun recording of the fit(s)")
    p.add_argument("--segment", action="append", default=[], metavar="KEY=VALUE",
                   help="segmentation parameter for captures holding colour images "
                        "(hue_min, hue_max, sat_min, val_min, open_px, close_px, min_area_px)")
    add_force(p)
    p.set_defaults(func=run)


def _segmentation_overrides(items: list[str]) -> dict[str, int]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise TapecellError(f"--segment {item!r}: expected KEY=VALUE")
        try:
            out[key.strip()] = int(value)
        except ValueError:
            raise TapecellError(f"--segment {item!r}: value must be an integer") from None
    return out


HEADER = f"{'capture':<24} {'cams':>4} {'cost':>7} {'ms':>7} {'tip mm':>7} {'node mm':>8} {'normal':>7}"


def summary_line(name: str, capture: Capture, est) -> str:
    line = f"{name:<24} {len(capture.views):>4} {est.cost:>7.4f} {est.time_s * 1e3:>7.1f}"
    if capture.truth is not None:
        e = errors(est.nodes, est.tip_rotation, capture.truth)
        line += f" {e.tip_m * 1e3:>7.2f} {e.node_max_m * 1e3:>8.2f} {e.normal_deg:>6.1f}°"
    return line


def run(args: argparse.Namespace) -> int:
    from tapecell.estimator import estimate  # the fitting code is heavy: load it only when needed

    seg = _segmentation_overrides(args.segment)
    single = len(args.captures) == 1 and args.out is None
    names = _names(args.captures)
    if args.out is not None:
        if args.out.exists() and not args.out.is_dir():
            raise OutputError(f"{args.out}: exists and is a file; --out wants a folder")
        check_files([args.out / f"{n}.json" for n in names], args.force)
    check_files([args.rrd], args.force)
    stream = None
    if args.rrd is not None:
        from tapecell.cell.recording import (close_recording, discard_recording, fit_logger, log_fit_result,
                                             open_recording)
        stream = open_recording(args.rrd, app_id="tapecell-estimate")
    failed = refused = 0
    try:
        if not single:
            print(HEADER, file=sys.stderr)
        for path, name in zip(args.captures, names):
            try:
                capture = load_capture(path, seg)
                callback = None
                if stream is not None:
                    callback = fit_logger(stream, capture, prefix=None if single else name)
                est = estimate(capture, method=args.method, callback=callback)
                if stream is not None:
                    log_fit_result(stream, capture, est, prefix=None if single else name)
            except TapecellError as e:
                if single:
                    raise
                failed += 1
                print(f"{name:<24} error: {e}", file=sys.stderr)
                continue
            doc = est.to_json()
            if args.out is not None:
                atomic_write_json(args.out / f"{name}.json", doc)
            elif single:
                print(to_json(doc))
            else:
                print(to_json(doc, indent=None))
            if not single:
                print(summary_line(name, capture, est), file=sys.stderr)
            if not est.actionable:
                refused += 1
                print(f"tapecell: {name}: verdict {est.verdict.value}"
                      + (f" ({est.verdict_reason})" if est.verdict_reason else "")
                      + "; a robot must not act on this estimate", file=sys.stderr)
    except BaseException:
        if stream is not None:
            discard_recording(stream)   # a run that ends in an error leaves no file behind
        raise
    if stream is not None:
        close_recording(stream)
    if failed:
        print(f"{failed} of {len(args.captures)} captures failed", file=sys.stderr)
        return 2
    return 1 if refused else 0


def _names(captures: list[Path]) -> list[str]:
    """Each capture's folder name (its estimate file and recording prefix); two captures
    with the same name would overwrite each other, so that is refused before any work."""
    names: dict[str, Path] = {}
    for path in captures:
        name = path.resolve().name or str(path)
        if name in names:
            same = path.resolve() == names[name].resolve()
            raise TapecellError(f"{names[name]} and {path} " + ("are the same capture" if same else
                                f"have the same folder name '{name}'") + "; their estimates would "
                                "overwrite each other (estimate them into different --out folders)")
        names[name] = path
    return list(names)
