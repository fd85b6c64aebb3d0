"""The ``tapecell`` command.

Each subcommand lives in ``cli/commands/<name>.py`` and exposes ``register(subparsers)``,
which adds its parser and sets ``func``. Errors the user can cause (``TapecellError``)
print one line and exit with the error's code (see ``EXIT_CODES``); a usage error prints
one line and exits with 2; a Ctrl-C exits with 130, SIGTERM with 143 (after the same cleanup).
"""
from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading

from tapecell import __version__
from tapecell.estimator.errors import TapecellError

COMMANDS = ["estimate", "calibrate", "sim", "episode", "sweep", "run", "probe"]

EXIT_CODES = """exit status:
  0  done
  1  the task itself failed: a grasp missed, a fit not good enough to act on, a
     motion or plan refused by the safety checks, a calibration that failed
  2  bad input or usage: a missing, malformed or implausible file, a bad option,
     an output that would replace a file (see --force)
  3  the robot or other hardware failed: no answer within its deadline, a dropped
     connection, a protective stop, a camera that cannot be opened
  130 interrupted (Ctrl-C); 143 terminated (SIGTERM), after the same cleanup"""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line (and exit status 2)."""

    def error(self, message: str) -> None:  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="tapecell",
        description="Estimate floppy tape from camera silhouettes and grasp its tip with a UR "
                    "arm. Runs on the built-in MuJoCo cell (sim, episode, calibrate --sim) or on "
                    "the real cell (run/calibrate/probe --config CELL.toml --execute).",
        epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"tapecell {__version__}")
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
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if in_main_thread else None
    _TERMINATED.clear()
    try:
        code = int(args.func(args) or 0)
        if _TERMINATED.is_set():
            # The signal's exception landed where Python ignores exceptions (a finaliser,
            # __del__, running at that moment) and the command went on to its end.
            print("tapecell: terminated", file=sys.stderr)
            return 143
        return code
    except TapecellError as e:
        print(f"tapecell: error: {_one_line(e)}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("tapecell: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        print("tapecell: terminated", file=sys.stderr)
        return 143
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that cleanup (stopping an arm, removing
    temporary files) runs as for Ctrl-C."""


_TERMINATED = threading.Event()
"""Set by SIGTERM, in case its exception is swallowed (see main)."""


def _terminate(signum, frame) -> None:
    _TERMINATED.set()
    raise Terminated()


def _one_line(e: Exception) -> str:
    return " ".join(str(e).split())


if __name__ == "__main__":
    sys.exit(main())
