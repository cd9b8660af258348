"""The ``don-gym`` command line.

Each subcommand lives in its own module of this package with two functions:
``register(subparsers)`` adds its parser (keep imports there light) and
``run(args) -> int`` does the work. User errors (:class:`don_gym.errors.DonGymError`)
are printed as one line on stderr with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from don_gym.errors import DonGymError

# Subcommand modules, in the order --help lists them.
SUBCOMMANDS = ["embed", "build-dataset", "export", "train", "evaluate", "benchmark"]


def parse_size(text: str, option: str = "size") -> tuple[int, int]:
    """``"WIDTHxHEIGHT"`` -> ``(width, height)`` in pixels; a clear error naming ``option`` otherwise."""
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise DonGymError(f"{option} {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 320x240") from None
    if width < 1 or height < 1:
        raise DonGymError(f"{option} {text!r}: width and height must be positive")
    return width, height


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (DonGymError, FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        print(f"don-gym {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"don-gym {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
