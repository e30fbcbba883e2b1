"""Atomic file writes: write to a temporary name in the same folder, then rename, so an
interruption never leaves a half-written file under the final name."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_path", "save_figure", "write_json"]


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` in one rename.

    Example:
        >>> folder = Path(tempfile.mkdtemp())
        >>> with atomic_path(folder / "out.txt") as tmp:
        ...     _ = tmp.write_text("done")
        >>> [path.name for path in folder.iterdir()], (folder / "out.txt").read_text()
        (['out.txt'], 'done')
        >>> (folder / "out.txt").unlink(); folder.rmdir()
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        if tmp.exists():  # mkstemp makes it private (0600): give it the mode a new file gets
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_figure(figure, path: str | Path, *, dpi: int = 110) -> None:
    """Save a matplotlib figure as PNG, atomically, and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=dpi, format="png")
    plt.close(figure)


def write_json(path: str | Path, data) -> None:
    """Write ``data`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")


def read_json(path: Path, error: type[Exception], missing: str):
    """The JSON document at ``path``; ``error`` naming the file when it is missing (with the hint
    ``missing``), unreadable, not UTF-8 or not valid JSON (with the line and column)."""
    if not path.is_file():
        raise error(f"{path} must exist; got no such file. {missing}")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as cause:
        raise error(
            f"{path} must be valid JSON; got {cause.msg} at line {cause.lineno} column {cause.colno}. Fix the syntax."
        ) from cause
    except (OSError, UnicodeDecodeError) as cause:
        raise error(f"{path} must be a readable UTF-8 file; got {cause}.") from cause
