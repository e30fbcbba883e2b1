"""The rule every command that writes follows for its output, checked before any work:

- the output can be written: no file stands where its folder must be (or where a parent folder
  must be), and the nearest existing folder accepts a new file (a real probe, so a read-only
  filesystem or a folder without permission is found, not guessed);
- the output is apart from what the command reads (:func:`check_apart`): not the input folder,
  inside it or holding it;
- the output holds no other work: a non-empty folder (or an existing file) is refused unless the
  caller passes ``overwrite``, with one line naming the path and the flag. A folder that holds the
  command's own resumable job (its ``job`` marker: a fit's checkpoint, an acquisition's plan) is
  left to the command's resume logic, which checks that it is the same job.

:func:`check_output` is the rule; the command line passes ``flag="--overwrite"`` so that the
message names its option, the Python API the default ``"overwrite=True"``.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

from .errors import TorchspecError

__all__ = ["OutputError", "TEMPORARY", "check_apart", "check_output", "content"]

TEMPORARY = re.compile(r"\..+\.part(\.[^.]+)?$")
"""The names :func:`torchspec.atomic.atomic_path` writes to before its rename: not content."""
_LISTED = 3
"""Entries of a refused folder that the message names."""


class OutputError(TorchspecError):
    """An output that cannot be written, or that holds other work and no ``overwrite`` was given."""


def content(folder: Path) -> list[str]:
    """The names in ``folder`` (sorted) that are content: all but temporaries of atomic writes; ``[]``
    for a folder that does not exist."""
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if not TEMPORARY.match(p.name))


def _writable(path: Path) -> None:
    """Refuse ``path`` when a file stands where it or one of its parent folders must be, or when the
    nearest existing folder does not accept a new file."""
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing != path and not existing.is_dir():
        raise OutputError(
            f"cannot write the output {path}: {existing} is a file, not a folder. Choose another path, or move "
            "the file."
        )
    probe_in = existing if existing.is_dir() else existing.parent
    try:
        fd, name = tempfile.mkstemp(prefix=".torchspec-probe.", suffix=".part", dir=probe_in)
    except OSError as error:
        raise OutputError(
            f"cannot write the output {path}: {probe_in} does not accept new files ({error.strerror or error}). "
            "Choose a folder you can write to."
        ) from error
    os.close(fd)
    os.unlink(name)


def check_output(
    path: str | Path,
    *,
    overwrite: bool = False,
    folder: bool = True,
    job: str | None = None,
    flag: str = "overwrite=True",
) -> Path:
    """Check, before any work, that ``path`` can be written and holds no other work.

    Args:
        path: the output: a folder (``folder=True``) or a file.
        overwrite: allow replacing what ``path`` holds (a non-empty folder is written into: files of
            the same names are replaced, others stay).
        folder: whether ``path`` is a folder (else a file).
        job: the name, inside the folder, that marks the command's own resumable job (e.g. a fit's
            ``.torchspec-fit``); a folder holding it passes, its resume logic decides.
        flag: how the message names ``overwrite``: ``--overwrite`` on the command line.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        OutputError: a file where the folder must be (or a folder where the file must be), a parent
            that is a file, a folder that does not accept new files, or content without ``overwrite``.

    Example:
        >>> root = Path(tempfile.mkdtemp())
        >>> check_output(root / "maps") == root / "maps"     # absent: fine
        True
        >>> _ = (root / "maps").mkdir(), (root / "maps" / "normal.exr").write_text("old")
        >>> check_output(root / "maps", flag="--overwrite")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        torchspec.outputs.OutputError: the output ... holds 1 entry (normal.exr); add --overwrite to replace ...
        >>> check_output(root / "maps", overwrite=True).name
        'maps'
    """
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise OutputError(f"the output {path} must be a folder; got a file in the way. Choose another path.")
    if not folder and path.is_dir():
        raise OutputError(f"the output {path} must be a file; got a folder in the way. Choose another path.")
    _writable(path)
    if folder:
        entries = content(path)
        if not entries or overwrite or (job is not None and (path / job).exists()):
            return path
        shown = ", ".join(entries[:_LISTED]) + (", ..." if len(entries) > _LISTED else "")
        raise OutputError(
            f"the output {path} holds {len(entries)} entr{'y' if len(entries) == 1 else 'ies'} ({shown}); "
            f"add {flag} to replace what it holds, or choose another folder."
        )
    if path.exists() and not overwrite:
        raise OutputError(f"the output {path} exists; add {flag} to replace it, or choose another name.")
    return path


def check_apart(output: str | Path, source: str | Path, what: str) -> None:
    """Refuse an ``output`` folder that is the folder ``source`` the command reads (``what`` names it:
    ``the capture``), lies inside it, or holds it: the output would be mixed with its input (and, with
    ``overwrite``, the input's files of the same names replaced).

    Raises:
        OutputError: naming both paths.

    Example:
        >>> check_apart("work/maps", "work/capture", "the capture")  # siblings: fine
        >>> check_apart("work/capture", "work/capture", "the capture")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        torchspec.outputs.OutputError: the output work/capture is the capture work/capture; ...
    """
    out, read = Path(output).resolve(), Path(source).resolve()
    if out == read:
        where = "is"
    elif out.is_relative_to(read):
        where = "lies inside"
    elif read.is_relative_to(out):
        where = "holds"
    else:
        return
    raise OutputError(
        f"the output {output} {where} {what} {source}; writing there would mix the output with what the command "
        f"reads. Choose a folder outside {source}."
    )
