"""The ``tapecell`` command.

Each subcommand lives in ``cli/commands/<name>.py`` and exposes ``register(subparsers)``,
which adds its parser and sets ``func``. Errors the user can cause (``TapecellError``)
print one line and exit with status 2; a Ctrl-C exits with 130.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from tapecell.estimator.errors import TapecellError

COMMANDS = ["estimate", "calibrate", "sim", "episode", "run", "probe"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tapecell",
        description="Estimate floppy tape from camera silhouettes and grasp its tip with a UR "
                    "arm. Runs on the built-in MuJoCo cell (sim, episode, calibrate --sim) or on "
                    "the real cell (run/calibrate/probe --config CELL.toml --execute).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"tapecell.cli.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TapecellError as e:
        print(f"tapecell: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("tapecell: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
