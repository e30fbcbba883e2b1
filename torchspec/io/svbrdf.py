"""Folders of SVBRDF maps (``docs/capture-format.md``, "SVBRDF maps"): the output of a fit and the
``truth/`` of a synthetic capture.

    svbrdf.json     {"format": "torchspec.svbrdf", "version": 1, "model": "ward", ...}
    normal.exr      X, Y, Z          diffuse.exr, specular.exr   the capture's channels
    roughness.exr   X, Y (+ A)       any other *.exr             extra maps (model, regions, ...)
    specular2.exr, roughness2.exr    optional, together: a second lobe (``SVBRDF.specular2``)

The second lobe is this package's extension of the format (the ``ward-dual`` model): a reader that
does not know it ignores both files, as the format asks, and sees the first lobe alone.
``svbrdf.json`` then names them in ``second_lobe``.

Maps are ``(H, W, ...)`` tensors, row 0 at the top of the image. :func:`write_svbrdf` writes
``svbrdf.json`` last, so a folder with a manifest always has its maps.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..atomic import read_json, write_json
from ..errors import TorchspecError
from ..model.brdf import SVBRDF
from ..outputs import check_output
from .exr import ExrError, _read, _read_band, write_exr

__all__ = ["Maps", "SVBRDFError", "read_svbrdf", "write_svbrdf"]

FORMAT = "torchspec.svbrdf"
VERSIONS = (1,)
META = "svbrdf.json"
_MAPS = ("normal", "diffuse", "specular", "roughness")
_SECOND = ("specular2", "roughness2")
_KNOWN_EXTRA = ("model",)
"""Optional maps of the format: an unreadable one is an error, where an unknown one is skipped."""
_UNIT_TOLERANCE = 1e-3


class SVBRDFError(TorchspecError):
    """A folder of maps that does not follow ``docs/capture-format.md``; the message names the file
    and the key or map at fault."""


@dataclass(frozen=True, eq=False)
class Maps:
    """A folder of SVBRDF maps as read by :func:`read_svbrdf`.

    Attributes:
        svbrdf: the parameters, leading dims ``(H, W)``.
        meta: the content of ``svbrdf.json`` (``format``, ``version``, ``model`` and free keys).
        extra: the folder's other maps by file stem (``"model"``, ``"regions"``, ...): float32
            tensors ``(H, W)`` for a single channel, ``(H, W, C)`` otherwise.
    """

    svbrdf: SVBRDF
    meta: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)


def read_svbrdf(path: str | Path, *, rows: tuple[int, int] | None = None, extra_maps=None) -> Maps:
    """Read and validate a folder of SVBRDF maps, or (``rows``) a band of their rows.

    ``diffuse.exr`` defines the channels (``R, G, B`` in that order when present, otherwise the
    file's names sorted); ``specular.exr`` is read with the same channels. Normals within
    ``1e-3`` of unit length are renormalised. Unknown ``svbrdf.json`` keys are kept in ``meta``;
    other EXR files go to ``extra`` (an unreadable unknown one is skipped with a warning).

    Args:
        path: the folder, or its ``svbrdf.json``.
        rows: ``(start, stop)``: only rows ``start`` to ``stop - 1`` of every map, read from the
            files' blocks that hold them (:func:`~torchspec.io.read_exr`), validated as the whole
            maps are (an error names the row in the image); the sizes are checked from the
            headers.
        extra_maps: the stems of the extra maps to read (default: all; others are not opened).

    Returns:
        The maps: float32 tensors, leading dims ``(H, W)`` (``(stop - start, W)`` with ``rows``);
        ``svbrdf.rotation`` from channel ``A`` of ``roughness.exr`` when present, else ``None``;
        ``svbrdf.specular2`` and ``roughness2`` from ``specular2.exr`` and ``roughness2.exr`` when present.

    Raises:
        SVBRDFError: ``svbrdf.json`` is missing or invalid, a map is missing, unreadable, lacks
            a channel or has another size than ``normal.exr``, or a value is out of range: NaN
            or Inf anywhere, a normal far from unit length, negative roughness or ``k_s`` (the
            message names the file and the count of bad pixels).

    Example:
        >>> import shutil, tempfile
        >>> from torchspec.simulate.synth import PaintingConfig, painting
        >>> folder = Path(tempfile.mkdtemp())
        >>> svbrdf, regions = painting(PaintingConfig(width=8, height=6), dtype=torch.float32)
        >>> write_svbrdf(folder, svbrdf, extra={"regions": regions})
        >>> maps = read_svbrdf(folder)
        >>> maps.svbrdf.shape, sorted(maps.extra), maps.meta["model"]
        (torch.Size([6, 8]), ['regions'], 'ward')
        >>> shutil.rmtree(folder)
    """
    path = Path(path)
    folder = path.parent if path.suffix.lower() == ".json" or path.is_file() else path
    meta = _read_meta(folder / META)
    _, normal, size = _read_map(folder / "normal.exr", ["X", "Y", "Z"], rows=rows)
    channels, diffuse, _ = _read_map(folder / "diffuse.exr", None, size, rows)
    specular = _read_map(folder / "specular.exr", channels, size, rows)[1]
    names, roughness, _ = _read_map(folder / "roughness.exr", None, size, rows)
    for name in ("X", "Y"):
        if name not in names:
            raise SVBRDFError(
                f"{folder / 'roughness.exr'} must have channels X, Y (alpha_x, alpha_y) and optionally A; got {names}."
            )
    rotation = roughness[:, :, names.index("A")] if "A" in names else None
    roughness = roughness[:, :, [names.index("X"), names.index("Y")]]

    for name, value in (("normal", normal), ("diffuse", diffuse), ("specular", specular), ("roughness", roughness)):
        _check_finite(folder / f"{name}.exr", value)
    if rotation is not None:
        _check_finite(folder / "roughness.exr", rotation)
    normal = _unit(folder / "normal.exr", normal, first=0 if rows is None else rows[0])
    _check_non_negative(folder / "roughness.exr", "roughness (alpha)", roughness)
    _check_non_negative(folder / "specular.exr", "k_s", specular)
    second = _read_second(folder, channels, size, rows)

    extra = {}
    for file in sorted(folder.glob("*.exr")):
        if file.stem in _MAPS + _SECOND or file.name.startswith("."):  # .*.part.exr: a write in progress
            continue
        if extra_maps is not None and file.stem not in extra_maps:
            continue
        try:
            image = _read(file, None)[1] if rows is None else _read_band(file, None, rows)[1]
        except ExrError as error:
            if file.stem in _KNOWN_EXTRA:
                raise SVBRDFError(f"{file} must be a readable EXR; got: {error}") from error
            warnings.warn(f"skipping the unreadable extra map {file}: {error}", stacklevel=2)
            continue
        extra[file.stem] = torch.from_numpy(np.ascontiguousarray(image[:, :, 0]) if image.shape[2] == 1 else image)

    svbrdf = SVBRDF(
        normal=torch.from_numpy(np.ascontiguousarray(normal)),
        diffuse=torch.from_numpy(diffuse),
        specular=torch.from_numpy(specular),
        roughness=torch.from_numpy(np.ascontiguousarray(roughness)),
        rotation=None if rotation is None else torch.from_numpy(np.ascontiguousarray(rotation)),
        channels=tuple(channels),
        **second,
    )
    return Maps(svbrdf=svbrdf, meta=meta, extra=extra)


def _read_second(folder: Path, channels: list[str], size, rows=None) -> dict:
    """``specular2`` and ``roughness2`` (a second lobe) when the folder has them, else nothing."""
    present = [(folder / f"{name}.exr").exists() for name in _SECOND]
    if not any(present):
        return {}
    if not all(present):
        have, lack = (_SECOND[0], _SECOND[1]) if present[0] else (_SECOND[1], _SECOND[0])
        raise SVBRDFError(f"{folder / (have + '.exr')} (a second lobe) needs {folder / (lack + '.exr')} beside it.")
    specular = _read_map(folder / "specular2.exr", channels, size, rows)[1]
    roughness = _read_map(folder / "roughness2.exr", ["X", "Y"], size, rows)[1]
    for name, value in (("specular2", specular), ("roughness2", roughness)):
        _check_finite(folder / f"{name}.exr", value)
    _check_non_negative(folder / "specular2.exr", "k_s", specular)
    _check_non_negative(folder / "roughness2.exr", "roughness (alpha)", roughness)
    return {"specular2": torch.from_numpy(specular), "roughness2": torch.from_numpy(np.ascontiguousarray(roughness))}


def write_svbrdf(
    path: str | Path,
    maps_or_svbrdf: SVBRDF | Maps,
    *,
    meta: dict | None = None,
    extra: dict | None = None,
    overwrite: bool = False,
) -> None:
    """Write a folder of SVBRDF maps; ``svbrdf.json`` last.

    ``roughness.exr`` gets channel ``A`` only when ``rotation`` is not ``None``; a grey
    ``specular (H, W, 1)`` is written replicated to every channel; roughness (and rotation) is
    written as 0 where ``k_s = 0`` on every channel, as the format requires. A second lobe
    (``specular2``) is written as ``specular2.exr`` and ``roughness2.exr``, the same way. An existing
    ``svbrdf.json`` is removed first, so an interrupted write leaves no manifest; each file is
    written atomically.

    Args:
        path: the folder (created if needed).
        maps_or_svbrdf: an :class:`~torchspec.SVBRDF` with leading dims ``(H, W)``, or a
            :class:`Maps` whose ``meta`` and ``extra`` are written too.
        meta: keys for ``svbrdf.json``, over those of a :class:`Maps`. ``format`` and
            ``version`` are set; ``model`` defaults to ``"ward"``.
        extra: more maps by name, over those of a :class:`Maps`: ``(H, W)`` (written as
            channel ``Y``) or ``(H, W, C)``; e.g. ``{"model": index_map}``.
        overwrite: write into a folder that already holds files (those of the same names are
            replaced); without it such a folder is refused (:func:`torchspec.outputs.check_output`).

    Raises:
        OutputError: ``path`` holds files and ``overwrite`` is not set, or cannot be written.
        SVBRDFError: the SVBRDF is not ``(H, W)``, a value is NaN, Inf or out of range (normals
            not unit within ``1e-3``, negative roughness or ``k_s``), an extra map has another
            size or a reserved name, or ``meta`` is not JSON or contradicts the format.

    Example:
        :func:`read_svbrdf`'s example writes a folder of maps and reads it back.
    """
    folder = check_output(path, overwrite=overwrite)
    if isinstance(maps_or_svbrdf, Maps):
        svbrdf = maps_or_svbrdf.svbrdf
        meta = {**maps_or_svbrdf.meta, **(meta or {})}
        extra = {**maps_or_svbrdf.extra, **(extra or {})}
    elif isinstance(maps_or_svbrdf, SVBRDF):
        svbrdf, meta, extra = maps_or_svbrdf, dict(meta or {}), dict(extra or {})
    else:
        raise SVBRDFError(f"maps for {folder} must be an SVBRDF or Maps; got {type(maps_or_svbrdf).__name__}.")
    if len(svbrdf.shape) != 2:
        raise SVBRDFError(
            f"SVBRDF for {folder} must have leading dims (H, W); got {tuple(svbrdf.shape)}. "
            "Use svbrdf.reshape(H, W) for a flat batch of pixels."
        )
    size = tuple(svbrdf.shape)
    normal, diffuse, specular, roughness = (
        _numpy(value) for value in (svbrdf.normal, svbrdf.diffuse, svbrdf.specular, svbrdf.roughness)
    )
    rotation = None if svbrdf.rotation is None else _numpy(svbrdf.rotation)
    specular = np.broadcast_to(specular, diffuse.shape)
    # The format's "no lobe": roughness is 0 (never NaN) where k_s = 0 on every channel.
    lobe = (specular != 0).any(axis=-1)
    roughness = np.where(lobe[:, :, None], roughness, np.float32(0))
    if rotation is not None:
        rotation = np.where(lobe, rotation, np.float32(0))
    for name, value in (("normal", normal), ("diffuse", diffuse), ("specular", specular), ("roughness", roughness)):
        _check_finite(folder / f"{name}.exr", value, f"SVBRDF.{name} for ")
    if rotation is not None:
        _check_finite(folder / "roughness.exr", rotation, "SVBRDF.rotation for ")
    _unit(folder / "normal.exr", normal, "SVBRDF.normal for ")
    _check_non_negative(folder / "roughness.exr", "SVBRDF.roughness", roughness)
    _check_non_negative(folder / "specular.exr", "SVBRDF.specular", specular)
    second = {}
    if svbrdf.specular2 is not None:
        specular2 = np.broadcast_to(_numpy(svbrdf.specular2), diffuse.shape)
        roughness2 = np.where((specular2 != 0).any(axis=-1)[:, :, None], _numpy(svbrdf.roughness2), np.float32(0))
        second = {"specular2": (specular2, list(svbrdf.channels)), "roughness2": (roughness2, ["X", "Y"])}
        for name, (value, _) in second.items():
            _check_finite(folder / f"{name}.exr", value, f"SVBRDF.{name} for ")
            _check_non_negative(folder / f"{name}.exr", f"SVBRDF.{name}", value)
        meta = {**meta, "second_lobe": {"specular": "specular2.exr", "roughness": "roughness2.exr"}}
    else:
        meta = {key: value for key, value in meta.items() if key != "second_lobe"}
    document = _meta_to_write(folder / META, meta)
    extras = {name: _extra_to_write(folder, name, value, size) for name, value in extra.items()}

    folder.mkdir(parents=True, exist_ok=True)
    (folder / META).unlink(missing_ok=True)
    write_exr(folder / "normal.exr", normal, ["X", "Y", "Z"])
    write_exr(folder / "diffuse.exr", diffuse, svbrdf.channels)
    write_exr(folder / "specular.exr", specular, svbrdf.channels)
    if rotation is None:
        write_exr(folder / "roughness.exr", roughness, ["X", "Y"])
    else:
        write_exr(folder / "roughness.exr", np.concatenate([roughness, rotation[:, :, None]], axis=-1), ["X", "Y", "A"])
    for name in _SECOND:  # a second lobe, or none: a stale one from an earlier write must not stay
        if name in second:
            write_exr(folder / f"{name}.exr", *second[name])
        else:
            (folder / f"{name}.exr").unlink(missing_ok=True)
    for name, image in extras.items():
        write_exr(folder / f"{name}.exr", image, _extra_channels(image.shape[2]))
    write_json(folder / META, document)


def _read_meta(file: Path) -> dict:
    meta = read_json(file, SVBRDFError, f"Pass a folder of SVBRDF maps (holding {META}).")
    if not isinstance(meta, dict):
        raise SVBRDFError(f"{file} must hold a JSON object; got {type(meta).__name__}.")
    if meta.get("format") != FORMAT:
        raise SVBRDFError(f"{file}: format must be {FORMAT!r}; got {meta.get('format')!r}. Is this a map folder?")
    version = meta.get("version")
    if type(version) is not int or version not in VERSIONS:
        raise SVBRDFError(
            f"{file}: version must be a supported version ({', '.join(map(str, VERSIONS))}); got {version!r}. "
            "Convert the maps, or use a torchspec that reads this version."
        )
    if not isinstance(meta.get("model"), str) or not meta["model"]:
        raise SVBRDFError(f"{file}: model must be a model name such as 'ward'; got {meta.get('model')!r}.")
    return meta


def _read_map(file: Path, channels, size=None, rows=None) -> tuple[list[str], np.ndarray, tuple[int, int]]:
    """Channel names, ``(H, W, C)`` of a map (of its ``rows``) and its size, checked to be ``size``."""
    if not file.is_file():
        raise SVBRDFError(f"{file} must exist; got no such file. A map folder holds {', '.join(_MAPS)} (.exr).")
    try:
        names, image, found = (*_read(file, channels), None) if rows is None else _read_band(file, channels, rows)
    except ExrError as error:
        raise SVBRDFError(f"{file} must be a readable map; got: {error}") from error
    found = tuple(image.shape[:2]) if found is None else tuple(found)
    if size is not None and found != tuple(size):
        raise SVBRDFError(
            f"{file} must have the size of normal.exr, {size[0]}x{size[1]} (height x width); got {found[0]}x{found[1]}."
        )
    return names, image, found


def _check_finite(file: Path, value: np.ndarray, prefix: str = "") -> None:
    bad = ~np.isfinite(value)
    if bad.any():
        pixels = int((bad.reshape(*value.shape[:2], -1)).any(axis=-1).sum())
        raise SVBRDFError(f"{prefix}{file} must be finite; got {pixels} pixel(s) with NaN or Inf.")


def _unit(file: Path, normal: np.ndarray, prefix: str = "", first: int = 0) -> np.ndarray:
    norm = np.linalg.norm(normal.astype(np.float64), axis=-1, keepdims=True)
    far = np.abs(norm[:, :, 0] - 1) > _UNIT_TOLERANCE
    if far.any():
        row, col = np.argwhere(far)[0]
        raise SVBRDFError(
            f"{prefix}{file}: normals must be unit vectors (norm within {_UNIT_TOLERANCE:g} of 1); got "
            f"{int(far.sum())} pixel(s) that are not, the first at row {first + row}, column {col} with norm "
            f"{norm[row, col, 0]:.6g}. Normalise the normals."
        )
    return (normal / norm).astype(np.float32)


def _check_non_negative(file: Path, what: str, value: np.ndarray) -> None:
    negative = (value < 0).reshape(*value.shape[:2], -1).any(axis=-1)
    if negative.any():
        raise SVBRDFError(
            f"{file}: {what} must be >= 0; got {int(negative.sum())} pixel(s) with a negative value "
            f"(min {float(value.min()):.3g})."
        )


def _meta_to_write(file: Path, meta: dict) -> dict:
    header = {"format": FORMAT, "version": VERSIONS[-1], "model": meta.get("model", "ward")}
    for key in ("format", "version"):
        if key in meta and meta[key] != header[key]:
            raise SVBRDFError(f"meta for {file}: {key} must be {header[key]!r} (or left out); got {meta[key]!r}.")
    if not isinstance(header["model"], str) or not header["model"]:
        raise SVBRDFError(f"meta for {file}: model must be a model name such as 'ward'; got {header['model']!r}.")
    document = {**header, **{key: value for key, value in meta.items() if key not in header}}
    try:
        json.dumps(document)
    except (TypeError, ValueError) as error:
        raise SVBRDFError(f"meta for {file} must be JSON-serialisable; got {error}.") from error
    return document


def _extra_to_write(folder: Path, name: Any, value: Any, size: tuple[int, int]) -> np.ndarray:
    reserved = _MAPS + _SECOND + ("svbrdf",)
    if not isinstance(name, str) or not name or name.startswith(".") or any(c in name for c in "/\\:"):
        raise SVBRDFError(f"extra map names for {folder} must be plain file stems like 'model'; got {name!r}.")
    if name in reserved:
        raise SVBRDFError(f"extra map names for {folder} must not be one of {list(reserved)}; got {name!r}.")
    image = _numpy(value)
    shape = tuple(image.shape)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[:2] != size:
        raise SVBRDFError(
            f"extra map {name!r} for {folder} must have shape (H, W) or (H, W, C) with (H, W) = {size}; got {shape}."
        )
    return image


def _extra_channels(count: int) -> list[str]:
    """Names that :func:`~torchspec.io.read_exr` gives back in the same order."""
    names = {1: ["Y"], 2: ["X", "Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}
    width = max(2, len(str(count - 1)))
    return names.get(count, [f"C{c:0{width}d}" for c in range(count)])


def _numpy(value: Any) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float32)
