"""The ``torchspec`` command: :func:`main` runs one subcommand (:mod:`torchspec.cli.commands`) of the
parser :func:`~torchspec.cli.parser.build_parser` builds, and turns its errors into exit statuses."""

from __future__ import annotations

import io
import os
import re
import shlex
import sys
import traceback
import warnings

from .._version import __version__
from ..errors import TorchspecError
from ..pipeline.checkpoint import CHECKPOINT
from .commands import COMMANDS, INTERRUPTED
from .parser import OVERWRITE, build_parser

__all__ = [
    "BUG",
    "CHECKPOINT",
    "COMMANDS",
    "INTERRUPTED",
    "NUMBERS",
    "OVERWRITE",
    "PIPE_CLOSED",
    "build_parser",
    "main",
    "negative_values",
]

BUG = 70
"""The exit status of an internal error (a bug in torchspec): ``EX_SOFTWARE`` of ``sysexits.h``."""
PIPE_CLOSED = 141
"""The exit status when the reader of stdout closed it (``torchspec info | head -2``): 128 + SIGPIPE,
what a shell reports for a command a closed pipe stopped, as ``yes | head`` does."""


def main(argv: list[str] | None = None) -> int:
    """Run the ``torchspec`` command line ``argv`` (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 on success; 2 for a usage error or input torchspec refuses (a
        :class:`~torchspec.errors.TorchspecError`, or an ``OSError`` of a path), printed in one line
        without a traceback; 130 (:data:`INTERRUPTED`) for a command stopped by Ctrl-C at any point, said
        in one line (a fit's and an acquisition's say what is saved and the command that continues it);
        70 (``EX_SOFTWARE``) for a bug, printed with its traceback and a request to report it.
    """
    parser = build_parser()
    given = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(negative_values(given))
    args.argv = given  # the command line as typed: what an interrupted command says to run again
    if args.command is None:
        parser.print_help()
        return 2
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line(args.command)
            status = COMMANDS[args.command](parser, args)
        sys.stdout.flush()  # a reader that stopped (torchspec info | head -2) shows here, not at exit
        return status
    except KeyboardInterrupt:  # Ctrl-C where the command does not say more itself: one line, no traceback
        print(f"torchspec {args.command}: interrupted (Ctrl-C).", file=sys.stderr)
        return INTERRUPTED
    except BrokenPipeError:  # the reader of stdout stopped reading: nothing to say, and no one to say it to
        _silence_stdout()
        return PIPE_CLOSED
    except (TorchspecError, OSError) as exc:  # the user's input or filesystem: say what and where, no traceback
        print(f"torchspec {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Exception:  # anything else is a bug in torchspec
        traceback.print_exc()
        line = " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        print(f"torchspec {args.command}: internal error: this is a bug in torchspec {__version__}; please report it "
              f"with the traceback above and the command line: torchspec {line}", file=sys.stderr)
        return BUG


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so that Python's flush at exit does not fail on the closed pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, io.UnsupportedOperation):  # no file descriptor (a captured stdout)
        pass


def _warning_line(command: str):
    """A ``warnings.showwarning`` that prints a warning as one line naming the command (no source line)."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"torchspec {command}: warning: {message}", file=file or sys.stderr)

    return show


NUMBERS = re.compile(r"-\d*\.?\d+(?:[eE][-+]?\d+)?(?:,\s*[-+]?\d*\.?\d+(?:[eE][-+]?\d+)?)+")
"""A comma list of numbers that starts with a minus sign (``-0.5,0.5,0.7``); argparse takes a single
negative number (``--light -0.5 0.5 0.707``) as a value by itself."""


def negative_values(argv: list[str]) -> list[str]:
    """``argv`` with each option followed by a comma list of numbers that starts with a minus sign
    (:data:`NUMBERS`, as ``--light -0.5,0.5,0.7``) joined to it (``--light=-0.5,0.5,0.7``): argparse takes such a value
    for an option of its own and refuses it."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and NUMBERS.fullmatch(arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out
