"""Light files of RTI tools: the ``.lp`` of RTIBuilder, Relight and RTIViewer, and the
``lights.txt`` of photometric-stereo data sets (directions only, images matched by order).

An ``.lp`` file is a count on its first line, then one line per light: ``image-name x y z``, the
direction towards the light in the image frame (x right, y up, z towards the camera). Real files
break this in every way, and :func:`read_light_file` takes them as they are:

- a count that disagrees with the lines: the lines are used, with a note saying so (an importer
  that finds the counted lines' images, and none of the lines' beyond the count, keeps only the
  counted ones: :func:`keep_counted`);
- trailing spaces, tabs, blank lines, CRLF or CR line ends, a UTF-8 byte-order mark;
- vectors that are not unit length: normalised, with a note when the norm is off by more than
  :data:`NORM_NOTE` (5 %);
- folder paths before the name, POSIX or Windows (``C:\\rti\\img01.jpg``), and names with spaces
  (everything before the last three numbers is the name); surrounding quotes are dropped;
- comma decimals (``0,25``).

What cannot be read (a line without three numbers, a zero or non-finite vector, a light at or
below the horizon, the same image twice) is a :class:`LightFileError` naming the file and line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path, PureWindowsPath

from ..errors import TorchspecError

__all__ = [
    "HORIZON",
    "LIFT",
    "NORM_NOTE",
    "LightEntry",
    "LightFile",
    "LightFileError",
    "direction_notes",
    "keep_counted",
    "light_entry",
    "read_light_file",
]

NORM_NOTE = 0.05
"""A direction whose norm differs from 1 by more than this is normalised with a note (the
tools' files hold norms of 0.80-1.06); within it, silently."""

HORIZON = 0.05
"""A unit direction with ``-HORIZON < z < LIFT`` (within ~3 degrees of the horizon: what a light
file measures) is a grazing light, lifted to ``z = LIFT`` with a note; below, an error."""
LIFT = 1e-3
"""The ``z`` of a direction lifted to just above the horizon (the capture format needs ``z > 0``)."""


class LightFileError(TorchspecError):
    """A light file that cannot be read; the message names the file and line."""


@dataclass(frozen=True)
class LightEntry:
    """One light of a light file.

    Attributes:
        name: the image's file name as written (path and all), ``None`` in a file of directions
            only (matched to images by order).
        direction: unit vector towards the light (``z > 0``), image frame.
        line: the 1-based line of the file it was read from.
        norm: the norm of the vector as written.
        lifted: the vector was at the horizon (``-HORIZON < z / norm < LIFT``) and was moved to
            ``z = LIFT``, its azimuth kept.
        where: where in the file it was read when that is not a line (``images[3]`` of a
            Relight JSON file); ``None`` for a line.
    """

    name: str | None
    direction: tuple[float, float, float]
    line: int
    norm: float
    lifted: bool = False
    where: str | None = None

    @property
    def place(self) -> str:
        """``line N``, or :attr:`where`, for messages."""
        return self.where or f"line {self.line}"

    @property
    def basename(self) -> str | None:
        """The file name without any folder (POSIX or Windows separators)."""
        return None if self.name is None else PureWindowsPath(self.name).name


@dataclass(frozen=True)
class LightFile:
    """A light file as read.

    Attributes:
        path: the file.
        entries: the lights, in the file's order.
        declared: the count on the first line (``None`` when the file has none).
        notes: what was assumed to read it (a count that disagrees, vectors normalised by more
            than :data:`NORM_NOTE`), one sentence each, naming the file and line.
        folder: the folder of the images (a Relight project names its own); ``None``: the file's.
        positions: ``(K, 3)`` light positions where the file gives them (a Relight dome,
            :mod:`torchspec.io.relight`), in units of the image's width, origin at the image's
            centre, x right, y up, z towards the camera; ``None`` otherwise.
    """

    path: Path
    entries: tuple[LightEntry, ...]
    declared: int | None
    notes: tuple[str, ...]
    folder: Path | None = None
    positions: tuple[tuple[float, float, float], ...] | None = None

    @property
    def image_folder(self) -> Path:
        """Where the images are: :attr:`folder`, or the file's folder."""
        return self.folder if self.folder is not None else self.path.parent

    @property
    def named(self) -> bool:
        """Whether the entries name their images (an ``.lp``), or only give directions."""
        return all(entry.name is not None for entry in self.entries)


def _number(text: str) -> float | None:
    """A float from ``text``, a comma decimal accepted (``0,25``); ``None`` when it is not one."""
    for candidate in (text, text.replace(",", ".")):
        try:
            value = float(candidate)
        except ValueError:
            continue
        return value
    return None


def _lines(path: Path) -> list[str]:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise LightFileError(f"{path}: cannot be read: {error.strerror or error}.") from error
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")  # names from Windows tools; every byte decodes
    return text.splitlines()  # \n, \r\n and \r


def _entry(path: Path, number: int, text: str) -> LightEntry:
    """One light line: ``name x y z`` or ``x y z``."""
    tokens = text.split()
    values = [_number(token) for token in tokens[-3:]]
    if len(tokens) < 3 or any(value is None for value in values):
        raise LightFileError(
            f"{path}: line {number} must be 'image-name x y z' (or 'x y z'); got {text.strip()!r}. "
            "Fix or delete the line."
        )
    name = None
    if len(tokens) > 3:
        name = text.strip().rsplit(None, 3)[0].strip("\"'")
    return light_entry(path, values, name, line=number)


def light_entry(
    path: Path, vector, name: str | None, *, line: int = 0, where: str | None = None, remedy: str = "delete the line"
) -> LightEntry:
    """A light towards ``vector`` (any length), checked and normalised (a light at the horizon
    lifted, see :data:`HORIZON`); :class:`LightFileError` naming ``path`` and the line (or
    ``where``) for a zero, non-finite or below-the-horizon vector."""
    x, y, z = (float(v) for v in vector)
    place = where or f"line {line}"
    norm = math.sqrt(x * x + y * y + z * z)
    if not math.isfinite(norm) or norm == 0:
        raise LightFileError(f"{path}: {place} must give a non-zero finite direction; got ({x:g}, {y:g}, {z:g}).")
    if not z / norm > -HORIZON:
        raise LightFileError(
            f"{path}: {place} must give a direction above the surface (z > 0); got "
            f"({x:g}, {y:g}, {z:g}). A light below the horizon lights nothing: {remedy}."
        )
    lifted = not z / norm >= LIFT
    if lifted:  # at the horizon, within what a light file can measure: just above it
        planar = math.sqrt(max(1 - LIFT * LIFT, 0.0)) / math.hypot(x, y)
        direction = (x * planar, y * planar, LIFT)
    else:
        direction = (x / norm, y / norm, z / norm)
    return LightEntry(name=name, direction=direction, line=line, norm=norm, lifted=lifted, where=where)


def direction_notes(path: Path, entries) -> list[str]:
    """The notes of entries normalised by more than :data:`NORM_NOTE`, or lifted to the horizon."""
    notes = []
    for entry in entries:
        if abs(entry.norm - 1) > NORM_NOTE:
            notes.append(
                f"{path}: {entry.place}: the direction's norm is {entry.norm:.4g}; normalised to a unit vector."
            )
        if entry.lifted:
            notes.append(
                f"{path}: {entry.place}: the light is at the horizon (z within {HORIZON:g} of 0 after "
                f"normalising); lifted to z = {LIFT:g}, its azimuth kept."
            )
    return notes


def read_light_file(path: str | Path) -> LightFile:
    """Read an ``.lp`` file (``count``, then ``image-name x y z`` per line) or a file of directions
    only (``count``, then ``x y z``; a first line of three numbers is read as a light).

    Returns:
        :class:`LightFile`; its ``notes`` say what was assumed (a count that disagrees with the
        lines: the lines are used; a vector normalised by more than 5 %).

    Raises:
        LightFileError: the file cannot be read, lists no light, or a line cannot be read (the
            message names the file and line); an image listed twice; lines that name images
            mixed with lines that do not.

    Example:
        >>> from tempfile import mkdtemp
        >>> lp = Path(mkdtemp()) / "dirs.lp"
        >>> _ = lp.write_bytes(b"3\\r\\nC:\\\\rti\\\\img 1.jpg 0,6 0 0,8\\r\\nimg2.jpg 0 0.6 0.8  \\r\\n")
        >>> lights = read_light_file(lp)
        >>> [(e.basename, e.direction) for e in lights.entries]
        [('img 1.jpg', (0.6, 0.0, 0.8)), ('img2.jpg', (0.0, 0.6, 0.8))]
        >>> print(lights.notes[0])  # doctest: +ELLIPSIS
        /.../dirs.lp: line 1 says 3 lights but 2 lines follow; the 2 lines are used.
    """
    path = Path(path)
    numbered = [
        (k + 1, line) for k, line in enumerate(_lines(path)) if line.strip() and not line.lstrip().startswith("#")
    ]
    declared = None
    if numbered and len(numbered[0][1].split()) == 1:
        count = _number(numbered[0][1].strip())
        if count is None or count != int(count) or count < 0:
            raise LightFileError(
                f"{path}: line {numbered[0][0]} must be the number of lights; got {numbered[0][1].strip()!r}."
            )
        declared = int(count)
        head, numbered = numbered[0][0], numbered[1:]
    if not numbered:
        raise LightFileError(f"{path} must list at least one light ('image-name x y z' per line); got none.")
    entries = [_entry(path, number, text) for number, text in numbered]
    notes = []
    if declared is not None and declared != len(entries):
        notes.append(
            f"{path}: line {head} says {declared} lights but {len(entries)} lines follow; the {len(entries)} lines "
            "are used."
        )
    notes += direction_notes(path, entries)
    kinds = {entry.name is None for entry in entries}
    if len(kinds) > 1:
        first = next(entry for entry in entries if entry.name is None)
        raise LightFileError(
            f"{path}: line {first.line} must name its image like the other lines ('image-name x y z'); got "
            "a direction only."
        )
    seen: dict[str, int] = {}
    for entry in entries:
        if entry.name is None:
            continue
        key = entry.name.replace("\\", "/").lower()
        if key in seen:
            raise LightFileError(
                f"{path}: line {entry.line} names {entry.name!r}, already named on line {seen[key]}; list each "
                "image once."
            )
        seen[key] = entry.line
    return LightFile(path=path, entries=tuple(entries), declared=declared, notes=tuple(notes))


def keep_counted(lights: LightFile, why: str) -> LightFile:
    """``lights`` (an ``.lp`` whose count, ``declared``, is below its lines) cut to its first
    ``declared`` lights: the lines beyond the count are dropped, and so are their notes and the note
    that the count disagrees, in place of which one note names the lines ignored and ``why``."""
    if lights.declared is None or not 0 < lights.declared < len(lights.entries):
        raise ValueError(f"{lights.path}: keep_counted needs a count below the lines; got {lights.declared}.")
    kept, dropped = lights.entries[: lights.declared], lights.entries[lights.declared :]
    places = ", ".join(entry.place for entry in dropped[:5]) + (" ..." if len(dropped) > 5 else "")
    note = (
        f"{lights.path}: its count says {lights.declared} lights but {len(lights.entries)} lines follow; the "
        f"{lights.declared} counted lines are used and "
        + ("the line" if len(dropped) == 1 else f"the {len(dropped)} lines")
        + f" beyond the count ({places}) {'is' if len(dropped) == 1 else 'are'} ignored: {why}."
    )
    return replace(lights, entries=kept, notes=(note, *direction_notes(lights.path, kept)))
