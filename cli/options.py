"""What several subcommands share: option types that refuse bad values as usage errors,
the output checks made before any work, and the confirmation asked before a real arm may
move."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, Sequence

from tapecell.estimator.errors import TapecellError
from tapecell.estimator.io import check_new_file, check_output_dir

MAX_SEED = 2 ** 32 - 1


def seed(value: str) -> int:
    """A randomisation seed: an integer 0 .. 2^32-1 (NumPy's range)."""
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {value!r}") from None
    if not 0 <= n <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be between 0 and {MAX_SEED}, got {n}")
    return n


def positive_int(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {value!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more, got {n}")
    return n


def add_seed(p: argparse.ArgumentParser, help: str = "randomisation seed, 0 or more (default 0)") -> None:
    p.add_argument("--seed", type=seed, default=0, help=help)


def add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace output files that exist (only the files this command writes; "
                        "nothing else is removed)")


def check_files(paths: Sequence[Path | None], force: bool) -> None:
    """Check before any work that each output file can be written (see ``io.check_new_file``)."""
    for p in paths:
        if p is not None:
            check_new_file(p, force)


def check_dir(path: Path | None, force: bool) -> None:
    if path is not None:
        check_output_dir(path, force)


# --------------------------------------------------------------------- a real arm moves
def add_robot_options(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--execute", action="store_true",
                   help=f"real cell: connect to the robot and {what} (asks for a typed confirmation)")
    p.add_argument("--yes", action="store_true",
                   help="with --execute: do not ask for confirmation (for scripts; you are answering yes)")


def confirm_robot(host: str, port: int, actions: Sequence[str], yes: bool = False,
                  ask: Callable[[str], str] | None = None, stdin=None, log: Callable[[str], None] | None = None) -> None:
    """Show the robot's address and what will happen, then ask for 'yes' on the terminal,
    before any connection is opened. Raises :class:`TapecellError` (exit 2) with no
    terminal and no ``--yes``, and :class:`Cancelled` (exit 1) when the answer is not yes."""
    log = log or (lambda text: print(text, file=sys.stderr))
    stdin = stdin if stdin is not None else sys.stdin
    log(f"robot: UR arm at {host}:{port}")
    for line in actions:
        log(f"  - {line}")
    if yes:
        log("confirmed by --yes")
        return
    if not stdin.isatty():
        raise TapecellError("--execute asks for a typed confirmation on a terminal and standard input is not "
                            "one; nothing connected, nothing moved (add --yes to confirm in a script)")
    ask = ask or input
    try:
        answer = ask(f"Connect to {host}:{port} and do this on the real arm? Type 'yes': ")
    except EOFError:
        answer = ""
    if answer.strip().lower() != "yes":
        raise Cancelled("cancelled; nothing connected, nothing moved")


class Cancelled(TapecellError):
    """The operator did not confirm: nothing was done."""

    exit_code = 1
