"""What every experiment script shares: its command line (a config and an output folder)."""

from __future__ import annotations

import argparse
from pathlib import Path

ROOT = Path(__file__).parents[1]


def parse_args(doc: str, config: str, argv: list[str] | None = None) -> argparse.Namespace:
    """``--config`` (default ``configs/<config>``) and ``--output`` (default ``experiments/results``)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / config)
    parser.add_argument("--output", type=Path, default=ROOT / "experiments" / "results")
    return parser.parse_args(argv)
