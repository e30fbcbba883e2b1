"""Checkpointing: a folder where each finished tile of a fit is saved atomically, so that an
interrupted fit continues where it stopped (either driver resumes the other's).

The folder holds :data:`STATE` (the job: :func:`job_record`) and one ``tile-<first pixel>.pt`` per
finished tile (:func:`save_tile`, :func:`read_tile`); :func:`open_checkpoint` opens it for a job.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import torch

from .._version import __version__
from ..atomic import atomic_path, read_json, write_json
from ..errors import TorchspecError
from ..io import Capture
from .records import TileResult
from .settings import FitConfig, nested_settings

__all__ = [
    "CHECKPOINT",
    "STATE",
    "FitInterrupted",
    "job_record",
    "open_checkpoint",
    "read_tile",
    "refuse_unfinished",
    "save_tile",
    "tile_name",
]

CHECKPOINT = ".torchspec-fit"
"""The folder, inside a fit's output, of its finished tiles until the maps are written (``torchspec fit``)."""
STATE = "state.json"
"""The checkpoint's record of the job it belongs to (:func:`job_record`)."""


class FitInterrupted(KeyboardInterrupt):
    """A fit stopped by Ctrl-C (or another ``KeyboardInterrupt``) with a checkpoint: its finished
    tiles are saved and ``fit(..., checkpoint=..., resume=True)`` continues it.

    Attributes:
        done: the tiles finished; total: the tiles of the fit; checkpoint: the folder.
    """

    def __init__(self, done: int, total: int, checkpoint: Path):
        super().__init__(f"the fit was interrupted after {done} of {total} tiles; they are saved in {checkpoint}.")
        self.done, self.total, self.checkpoint = done, total, checkpoint


def job_record(capture: Capture, picked: list[int], config: FitConfig, tile: int, pixels: int) -> dict:
    """What a checkpoint's tiles depend on: the manifest, each frame file's size and time, the
    frames, the settings and the tiling (a resumed fit must be the same job to give the same maps); as
    JSON gives it back (tuples as lists), to compare with a saved one."""
    files = [capture.root / capture.frames[k].file for k in picked]
    job = {
        "torchspec": __version__,
        "capture": str(capture.root.resolve()),
        "manifest": _stamp(capture.manifest) if capture.manifest.is_file() else None,
        "files": [_stamp(f) if f.is_file() else None for f in files],
        "frames": picked,
        "settings": _settings_record(config),
        "tile_pixels": tile,
        "pixels": pixels,
    }
    return json.loads(json.dumps(job))


def _settings_record(config: FitConfig) -> dict:
    """``config`` as a job's record: without ``compute.threads`` (tiles of any thread count resume)."""
    settings = asdict(config)
    settings["compute"].pop("threads")
    return settings


def _stamp(path: Path) -> list:
    info = path.stat()
    return [path.name, info.st_size, info.st_mtime_ns]


def tile_name(first: int) -> str:
    """The file of the tile whose first pixel is ``first``."""
    return f"tile-{first:012d}.pt"


def save_tile(folder: Path, first: int, tile: TileResult) -> None:
    """Save ``tile`` (moved to the CPU) atomically in ``folder``."""
    with atomic_path(folder / tile_name(first)) as tmp:
        torch.save({"first": first, "tile": tile.to("cpu")}, tmp)


def read_tile(path: Path) -> tuple[int, TileResult]:
    """The first pixel and the :class:`~torchspec.pipeline.records.TileResult` saved in ``path`` (on the CPU).

    Raises:
        TorchspecError: ``path`` is not a readable tile (written atomically: damage from outside).
    """
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        return int(saved["first"]), saved["tile"]
    except Exception as error:
        raise TorchspecError(f"{path} is not a readable tile ({type(error).__name__}: {error}); remove it.") from error


def refuse_unfinished(folder: Path | None, resume: bool) -> None:
    """Refuse a checkpoint folder that holds an unfinished fit (its :data:`STATE`) unless ``resume``:
    its work is never silently dropped (``None``: no checkpoint, nothing to refuse). Cheap (no pixel,
    no tile read): a driver calls it before any work.

    Raises:
        TorchspecError: naming the folder, the tiles done, and how to continue or start over.
    """
    if resume or folder is None or not (folder / STATE).is_file():
        return
    finished = len(list(folder.glob("tile-*.pt")))
    raise TorchspecError(
        f"{folder} holds an unfinished fit ({finished} tile(s) done): continue it with --resume, "
        f"or remove {folder} to start over."
    )


def open_checkpoint(folder: Path, job: dict, resume: bool) -> dict[int, TileResult]:
    """Open the checkpoint folder: its finished tiles ``{first pixel: tile}`` when resuming the
    same job, none for a new one.

    Raises:
        TorchspecError: the folder holds another job (naming what differs), or an unfinished one that
            is not to be resumed (its work is never silently dropped), or an unreadable tile.
    """
    state = folder / STATE
    if not state.is_file():
        if resume and folder.exists() and any(folder.glob("tile-*.pt")):
            raise TorchspecError(f"{folder} holds tiles but no {STATE}; remove {folder} to start over.")
        folder.mkdir(parents=True, exist_ok=True)
        write_json(state, job)
        return {}
    refuse_unfinished(folder, resume)
    saved = read_json(state, TorchspecError, "")
    if isinstance(saved.get("settings"), dict):  # a record of the flat settings (before their groups): alike
        saved["settings"] = nested_settings(saved["settings"])
    finished = sorted(folder.glob("tile-*.pt"))
    differ = [key for key in job if saved.get(key) != job[key]]
    if differ:
        raise TorchspecError(
            f"{folder} holds a fit of another job (its {', '.join(differ)} differ from this one's), so resuming "
            f"it would mix two fits; run the same command as before, or remove {folder} to start over."
        )
    tiles = dict(read_tile(path) for path in finished)
    for stale in folder.glob(".tile-*"):  # temporaries of a write the interruption cut short
        stale.unlink(missing_ok=True)
    return tiles
