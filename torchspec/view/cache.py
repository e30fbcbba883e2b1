"""The coarse levels of a map folder's pyramid kept on disk, so that the next ``torchspec view``
of the same maps shows the whole painting at once instead of after a pass over every row.

Where: ``MAPS/.torchspec-view/``, torchspec's own folder (marked by its ``CACHEDIR.TAG``, which
backup tools skip); when it cannot be written there (a read-only folder, or a ``.torchspec-view``
that is not marked as torchspec's), ``$XDG_CACHE_HOME/torchspec/view/<hash>/`` (``~/.cache``
without ``XDG_CACHE_HOME``; ``<hash>``: of the maps folder's resolved path); when neither can be
written, nowhere (one line on stderr): the view works as without a cache. Deleting either folder
is always safe.

What: ``level_L.bin`` for each level the pyramid holds in memory but level 0 (``Pyramid.kept``,
or 1, to the coarsest; none for maps that fit in one tile): every plane of the tile's textures
``(h, w)`` in its texture's dtype (float32 or float16, the tile's own rounding), little-endian,
one after the other; and ``levels.json``, written last, which names what they were made from: the
maps folder's ``.exr`` and ``.json`` files (name, size, modification and change times in ns), the
pyramid (tile size, textures, the levels' sizes), :data:`VERSION` and torchspec's version, and each
level file's bytes and CRC-32. Every file is written atomically (a temporary name, then a rename).

Trust: the levels are read only when all of that matches now and a level's file has those bytes and
that CRC; otherwise they are made again from the maps (and written again), so a changed map file
never shows stale tiles, nor a damaged cache garbage. A file in a folder not marked as torchspec's
is never replaced.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import sys
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from .._version import __version__
from ..atomic import atomic_path, write_json

__all__ = ["FOLDER", "VERSION", "LevelCache", "Stopped", "sources", "user_folder"]

VERSION = 1
"""The cache's format, and the levels' values: bumped when either changes (the reduction of
:mod:`torchspec.view.tiles`, its planes, this layout)."""
FOLDER = ".torchspec-view"
"""The cache's folder beside the maps."""
INDEX = "levels.json"
TAG = "CACHEDIR.TAG"
_SIGNATURE = "Signature: 8a477f597d28d172789f06886806bc55"  # https://bford.info/cachedir/
_TAG_TEXT = (
    f"{_SIGNATURE}\n# torchspec view: the coarse levels of the maps in the folder above (or named in {INDEX}),\n"
    "# made again when missing: safe to delete (torchspec/view/cache.py).\n"
)


class Stopped(Exception):
    """The pass or the cache's write was asked to stop (the server is closing)."""


def sources(folder: Path) -> list[list]:
    """``[name, bytes, mtime_ns, ctime_ns]`` of the map folder's ``.exr`` and ``.json`` files, by
    name. The change time too: a file rewritten in place with its size and modification time kept
    (``cp -p``, ``touch -d``) has a new one (it cannot be set back)."""
    found = []
    for path in sorted(Path(folder).iterdir()):
        if path.suffix.lower() in (".exr", ".json") and path.is_file():
            stat = path.stat()
            found.append([path.name, stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns])
    return found


def user_folder(maps: Path) -> Path:
    """The cache folder of ``maps`` in the user's cache: ``$XDG_CACHE_HOME`` (when absolute) or
    ``~/.cache``, then ``torchspec/view/`` and 16 hex digits of the SHA-256 of the resolved path."""
    base = os.environ.get("XDG_CACHE_HOME", "")
    root = Path(base) if os.path.isabs(base) else Path.home() / ".cache"
    return root / "torchspec" / "view" / hashlib.sha256(str(Path(maps).resolve()).encode()).hexdigest()[:16]


def _ours(folder: Path) -> bool:
    """Whether ``folder`` is marked as torchspec's cache (its ``CACHEDIR.TAG`` is ours)."""
    try:
        text = (folder / TAG).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    return text.startswith(_SIGNATURE) and "torchspec view" in text


def _claim(folder: Path) -> None:
    """Make ``folder`` a cache folder of torchspec's: created (or, empty, taken) with its tag.

    Raises:
        OSError: it cannot be written, or it holds files without torchspec's tag (not ours).
    """
    folder.mkdir(parents=True, exist_ok=True)
    if _ours(folder):
        return
    if any(folder.iterdir()):
        raise FileExistsError(errno.EEXIST, f"it holds files and no {TAG} of torchspec's: not replaced", str(folder))
    with atomic_path(folder / TAG) as tmp:
        tmp.write_text(_TAG_TEXT, encoding="utf-8")


def _note(text: str) -> None:
    print(f"torchspec view: {text}", file=sys.stderr, flush=True)


class LevelCache:
    """The held levels of one map folder's pyramid on disk (the module's layout and rules).

    Args:
        maps: the map folder.
        textures: the tile's ``(name, dtype, planes)``: a level is ``(P, h, w)`` float32, its
            planes in this order.
        shapes: ``{level: (h, w)}`` of the levels cached.
        pyramid: what else the levels depend on (JSON values: tile size, image size, ...).
    """

    def __init__(self, maps: Path, textures, shapes: dict[int, tuple[int, int]], pyramid: dict):
        self.maps = Path(maps)
        self.dtypes = [np.dtype(dtype).newbyteorder("<") for _, dtype, planes in textures for _ in planes]
        self.shapes = dict(shapes)
        key = {"format": "torchspec.view.levels", "version": VERSION, "torchspec": __version__, **pyramid,
               "textures": [[name, dtype, list(planes)] for name, dtype, planes in textures],
               "levels": {str(level): list(shape) for level, shape in self.shapes.items()}}  # fmt: skip
        self.key = json.loads(json.dumps(key))  # as read back
        self.sources = sources(self.maps)
        self.folders = [self.maps / FOLDER, user_folder(self.maps)]
        self.found: tuple[Path, dict] | None = None

    def _bytes(self, level: int) -> int:
        height, width = self.shapes[level]
        return sum(height * width * dtype.itemsize for dtype in self.dtypes)

    def find(self) -> bool:
        """Whether a cache folder holds levels of these maps as they are now (then :meth:`load`
        reads from it)."""
        for folder in self.folders:
            try:
                if not _ours(folder):
                    continue
                index = json.loads((folder / INDEX).read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue
            if isinstance(index, dict) and index.get("sources") == self.sources and _matches(index, self.key):
                self.found = folder, index
                return True
        return False

    def load(self, level: int) -> torch.Tensor | None:
        """Level ``level`` ``(P, h, w)`` float32 from the folder :meth:`find` found; ``None``
        (and a line on stderr) when its file is missing, of other bytes or CRC than the index says."""
        folder, index = self.found
        path, (height, width) = folder / f"level_{level}.bin", self.shapes[level]
        out = torch.empty(len(self.dtypes), height, width)  # CPU on purpose: read from the cache's file
        try:
            entry, crc = index["files"][str(level)], 0
            with open(path, "rb") as handle:
                size = os.fstat(handle.fileno()).st_size
                if not size == entry["bytes"] == self._bytes(level):
                    raise ValueError(f"{size} bytes, not {self._bytes(level)}")
                for plane, dtype in enumerate(self.dtypes):
                    data = handle.read(height * width * dtype.itemsize)
                    crc = zlib.crc32(data, crc)
                    out[plane] = torch.from_numpy(np.frombuffer(data, dtype).reshape(height, width).astype(np.float32))
            if crc != entry["crc32"]:
                raise ValueError("its CRC-32 differs from the one written")
        except (OSError, ValueError, KeyError, TypeError) as error:
            _note(f"the cached level {level} ({path}) cannot be used ({error}): the levels are made again.")
            return None
        return out

    def save(self, levels: dict[int, torch.Tensor], pause: Callable[[], None] | None = None) -> Path | None:
        """Write ``levels`` (``{level: (P, h, w)}``) to the first folder that can take them; the
        folder, or ``None`` (and a line on stderr when no folder could) when not written: also when
        a map file changed since the levels were read (they may mix its old and new rows).
        ``pause`` is called before each plane is written: it may wait (for tile requests), or stop.

        Raises:
            Stopped: raised by ``pause`` (the file being written is removed).
        """
        if sources(self.maps) != self.sources:
            return None
        why = []
        for folder in self.folders:
            try:
                _claim(folder)
                files = {str(level): self._write(folder / f"level_{level}.bin", planes, pause)
                         for level, planes in levels.items()}  # fmt: skip
                index = {**self.key, "maps": str(self.maps.resolve()), "sources": self.sources, "files": files}
                write_json(folder / INDEX, index)
            except OSError as error:
                why.append(f"{folder}: {error.strerror or error}")
                continue
            for stale in folder.glob("level_*.bin"):  # of other levels, written for other settings
                if stale.name not in {f"level_{level}.bin" for level in levels}:
                    stale.unlink(missing_ok=True)
            return folder
        _note(f"the coarse levels of {self.maps} are not cached ({'; '.join(why)}): they are made again at every view.")
        return None

    def _write(self, path: Path, planes: torch.Tensor, pause: Callable[[], None] | None) -> dict:
        """One level's file; its bytes and CRC-32."""
        crc, size = 0, 0
        with atomic_path(path) as tmp, open(tmp, "wb") as handle:
            for plane, dtype in zip(planes, self.dtypes, strict=True):
                if pause is not None:
                    pause()
                with np.errstate(over="ignore"):  # float16: beyond 65504 is Inf, as in the tile
                    data = np.ascontiguousarray(plane.cpu().numpy().astype(dtype))
                crc, size = zlib.crc32(data, crc), size + data.nbytes
                handle.write(data.data)
        return {"bytes": size, "crc32": crc}


def _matches(index: dict, key: dict) -> bool:
    """Whether ``index`` was written for ``key``."""
    return all(index.get(name) == value for name, value in key.items())
