"""The ``don-gym`` command line.

Each subcommand lives in its own module of this package with two functions:
``register(subparsers)`` adds its parser (keep imports there light) and
``run(args) -> int`` does the work and checks its outputs (:func:`don_gym.io.check_output_dir`)
before it. User errors (:class:`don_gym.errors.DonGymError`, a bad option), file-system faults
(``OSError``: a full or read-only disk, no permission) and Ctrl-C are printed as one line on
stderr, never as a traceback: exit status 2, and 130 for an interrupt.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

from don_gym.errors import DonGymError

# Subcommand modules, in the order --help lists them.
SUBCOMMANDS = ["embed", "build-dataset", "import-bop", "export", "train", "evaluate", "benchmark"]


def parse_size(text: str, option: str = "size") -> tuple[int, int]:
    """``"WIDTHxHEIGHT"`` -> ``(width, height)`` in pixels; a clear error naming ``option`` otherwise."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise DonGymError(f"{option} {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise DonGymError(f"{option} {text!r}: width and height must be positive")
    return width, height


def _whole_number(text: str, minimum: int, expected: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
    return value


def positive_int(text: str) -> int:
    """An argparse ``type`` for counts: a whole number >= 1; otherwise one line naming the value."""
    return _whole_number(text, 1, "a positive whole number")


def nonnegative_int(text: str) -> int:
    """An argparse ``type`` for seeds: a whole number >= 0; otherwise one line naming the value."""
    return _whole_number(text, 0, "a whole number >= 0")


def decay_rate(text: str) -> float:
    """An argparse ``type`` for a moving average's decay: a number in [0, 1); otherwise one line naming the value."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value < 1.0:  # NaN fails too
        raise argparse.ArgumentTypeError(f"{text!r}: expected a number in [0, 1), e.g. 0.999")
    return value


class _Parser(argparse.ArgumentParser):
    """Usage errors (a bad choice, a missing value) as one line like every other error, with a pointer to --help."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="don-gym",
        description=(
            "Dense Object Nets in simulation: optimal descriptors from meshes (Kupcsik et al. 2021), "
            "datasets, training, and a PyBullet Panda pick-and-place benchmark."
        ),
        epilog="Run 'don-gym COMMAND --help' for the options of each command.",
    )
    from don_gym import __version__

    parser.add_argument("--version", action="version", version=f"don-gym {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        module = importlib.import_module(f"don_gym.cli.{name.replace('-', '_')}")
        module.register(subparsers)
    return parser


def error_line(exc: BaseException) -> str:
    """One line for a user error or a file-system fault; an ``OSError`` names its file."""
    if isinstance(exc, OSError) and not isinstance(exc, DonGymError) and exc.filename is not None:
        names = f"{exc.filename} -> {exc.filename2}" if exc.filename2 is not None else str(exc.filename)
        text = f"{names}: {exc.strerror or exc}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


def main(argv: Sequence[str] | None = None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("don-gym: interrupted", file=sys.stderr)
        return 130
    try:
        return int(args.run(args) or 0)
    except (DonGymError, OSError) as exc:  # OSError: a full or read-only disk, no permission, a missing file
        print(f"don-gym {args.command}: error: {error_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"don-gym {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
