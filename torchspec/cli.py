"""The ``torchspec`` command."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._version import __version__

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchspec",
        description="Reflectance of nearly flat objects from a few HDR photographs under an extended light.",
    )
    parser.add_argument("--version", action="version", version=f"torchspec {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = commands.add_parser("demo", help="run the embedded default example and report accuracy and speed")
    demo.add_argument("-o", "--output", type=Path, default=None, help="folder for demo.json and demo.png")
    demo.add_argument("--pixels", type=int, default=65536, help="number of simulated pixels (default: 65536)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if args.command == "demo":
        if args.pixels < 1:
            parser.error(f"--pixels must be >= 1; got {args.pixels}")
        from . import demo

        demo.run(args.output, pixels=args.pixels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
