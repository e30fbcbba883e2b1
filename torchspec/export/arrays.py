"""What every export format shares: its errors and warning, the maps as float64 numpy arrays
(:class:`MapArrays`, checked by :func:`map_arrays`), and the encodings of their values
(grey to RGB, sRGB, 8-bit codes, PNG files)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import TorchspecError
from ..io import Maps, read_svbrdf
from ..model.brdf import SVBRDF

__all__ = [
    "ExportError",
    "ExportWarning",
    "MapArrays",
    "checked_svbrdf",
    "map_arrays",
    "height_array",
    "relief_mesh",
    "ReliefMesh",
    "rgb",
    "srgb",
    "code8",
    "write_png",
    "ISOTROPIC",
]

ISOTROPIC = 1e-3
"""Relative difference of ``alpha_x`` and ``alpha_y`` below which a lobe counts as isotropic."""


class ExportError(TorchspecError):
    """Maps or options that cannot be exported as asked; the message names what and why."""


class ExportWarning(UserWarning):
    """An export that had to change values its target cannot hold (clipped, rounded)."""


@dataclass(frozen=True)
class MapArrays:
    """The maps as float64 numpy arrays, ``(H, W, ...)``; ``specular`` broadcast to ``C``."""

    normal: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    rotation: np.ndarray | None
    channels: tuple[str, ...]

    @property
    def size(self) -> tuple[int, int]:
        return self.normal.shape[0], self.normal.shape[1]

    @property
    def lobe(self) -> np.ndarray:
        """``(H, W)``: the pixels with a specular lobe (``k_s > 0`` on some channel)."""
        return (self.specular > 0).any(axis=-1)


def checked_svbrdf(maps) -> SVBRDF:
    """The :class:`~torchspec.SVBRDF` of ``maps`` (a folder, :class:`~torchspec.io.Maps` or an
    SVBRDF), checked: leading dims ``(H, W)``, channels ``R, G, B`` or ``Y``."""
    if isinstance(maps, (str, Path)):
        maps = read_svbrdf(maps)
    svbrdf = maps.svbrdf if isinstance(maps, Maps) else maps
    if not isinstance(svbrdf, SVBRDF):
        raise ExportError(f"maps must be a map folder, Maps or an SVBRDF; got {type(maps).__name__}.")
    if len(svbrdf.shape) != 2:
        raise ExportError(
            f"the SVBRDF must have leading dims (H, W); got {tuple(svbrdf.shape)}. Reshape it: svbrdf.reshape(H, W)."
        )
    channels = tuple(svbrdf.channels)
    if channels not in (("R", "G", "B"), ("Y",)):
        raise ExportError(
            f"the maps must have channels R, G, B or Y to export; got {list(channels)}. "
            "Other channel sets have no colour meaning in Mitsuba, glTF or PNG."
        )
    return svbrdf


def map_arrays(maps) -> MapArrays:
    """The maps (a folder, :class:`~torchspec.io.Maps` or an :class:`~torchspec.SVBRDF` of leading
    dims ``(H, W)``) as :class:`MapArrays`, checked (:func:`checked_svbrdf`; finite values,
    ``k_d``, ``k_s`` and ``alpha >= 0``); warns that a second lobe is dropped."""
    svbrdf = checked_svbrdf(maps)
    channels = tuple(svbrdf.channels)

    def array(value):
        return value.detach().cpu().double().numpy()

    diffuse = array(svbrdf.diffuse)
    values = {
        "normal": array(svbrdf.normal),
        "diffuse": diffuse,
        "specular": np.broadcast_to(array(svbrdf.specular), diffuse.shape),
        "roughness": array(svbrdf.roughness),
        "rotation": None if svbrdf.rotation is None else array(svbrdf.rotation),
    }
    for name, value in values.items():
        if value is not None and not np.isfinite(value).all():
            raise ExportError(
                f"SVBRDF.{name} must be finite; got {int((~np.isfinite(value)).sum())} NaN or Inf value(s)."
            )
    for name in ("diffuse", "specular", "roughness"):
        if (values[name] < 0).any():
            raise ExportError(f"SVBRDF.{name} must be >= 0; got a minimum of {values[name].min():.3g}.")
    if svbrdf.specular2 is not None and bool((svbrdf.specular2 > 0).any()):
        count = int((svbrdf.specular2 > 0).any(-1).sum())
        warnings.warn(
            f"{count} pixel(s) have a second lobe (ward-dual: specular2.exr, roughness2.exr), which no export "
            "carries: they are exported with their first (sharper) lobe only (docs/export.md).",
            ExportWarning,
            stacklevel=3,
        )
    return MapArrays(channels=channels, **values)


def rgb(value: np.ndarray) -> np.ndarray:
    """``(..., 3)``: a single channel replicated (grey)."""
    return np.repeat(value, 3, axis=-1) if value.shape[-1] == 1 else value


def srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of values clipped to ``[0, 1]``."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def code8(value: np.ndarray) -> np.ndarray:
    """8-bit codes ``(uint8)`` of values clipped to ``[0, 1]``."""
    return np.round(np.clip(value, 0.0, 1.0) * 255).astype(np.uint8)


def write_png(path: Path, image: np.ndarray, bitdepth: int) -> None:
    """An ``(H, W)`` or ``(H, W, C)`` (C = 1 to 4) integer image as PNG, atomically."""
    import png

    image = image[..., None] if image.ndim == 2 else image
    height, width, count = image.shape
    writer = png.Writer(width, height, greyscale=count <= 2, alpha=count in (2, 4), bitdepth=bitdepth, compression=9)
    with atomic_path(path) as tmp, open(tmp, "wb") as file:
        writer.write(file, image.reshape(height, width * count).tolist())


def height_array(maps: Maps | SVBRDF, size: tuple[int, int], height=None) -> np.ndarray | None:
    """The height field ``(H, W)`` (pixel pitches) an export gives its shape: ``height`` (an array
    or tensor) where given, else the height (``height.exr``) of ``maps`` (a
    :class:`~torchspec.io.Maps` fitted with cast shadows; an export reads a folder once, for the
    maps and their height), else ``None`` (a flat rectangle).
    Raises :class:`ExportError` for a height of another size than the maps' ``size`` or not finite."""
    if height is None:
        height = maps.extra.get("height") if isinstance(maps, Maps) else None
        if height is None:
            return None
    values = np.asarray(height.detach().cpu() if hasattr(height, "detach") else height, dtype=np.float64)
    if values.shape != tuple(size):
        raise ExportError(f"the height must be (H, W) = {tuple(size)} like the maps; got {values.shape}.")
    if not np.isfinite(values).all():
        raise ExportError(f"the height must be finite; got {int((~np.isfinite(values)).sum())} NaN or Inf value(s).")
    return values


@dataclass(frozen=True)
class ReliefMesh:
    """A height field as a triangle mesh over the exports' rectangle (the longer side 1, centred).

    Attributes:
        position: ``(V, 3)`` float32, ``V = (H + 1)(W + 1)`` vertices at the texel corners, row by
            row from the top; ``z`` the mean height of the (up to four) texels around each corner,
            over ``max(H, W)`` (one pixel pitch in the rectangle's units).
        texel: ``(V, 2)`` float32, each vertex's column and row over ``W`` and ``H`` (``(0, 0)``: the
            maps' top-left corner).
        triangles: ``(2 H W, 3)`` int64, two per texel, counter-clockwise seen from ``+z``.
    """

    position: np.ndarray
    texel: np.ndarray
    triangles: np.ndarray


def relief_mesh(height: np.ndarray) -> ReliefMesh:
    """The :class:`ReliefMesh` of ``height (H, W)`` (pixel pitches)."""
    rows, cols = height.shape
    side = max(rows, cols)
    padded = np.pad(height, 1, mode="edge")
    corner = 0.25 * (padded[:-1, :-1] + padded[:-1, 1:] + padded[1:, :-1] + padded[1:, 1:])  # (H + 1, W + 1)
    i, j = np.meshgrid(np.arange(rows + 1), np.arange(cols + 1), indexing="ij")
    u, v = j / cols, i / rows
    x, y = (u - 0.5) * cols / side, (0.5 - v) * rows / side
    position = np.stack([x, y, corner / side], -1).reshape(-1, 3).astype(np.float32)
    at = (i * (cols + 1) + j)[:-1, :-1].reshape(-1)  # each texel's top-left corner
    a, b, c, d = at, at + 1, at + cols + 1, at + cols + 2  # top-left, top-right, bottom-left, bottom-right
    triangles = np.stack([np.stack([c, d, b], -1), np.stack([c, b, a], -1)], 1).reshape(-1, 3)
    return ReliefMesh(position, np.stack([u, v], -1).reshape(-1, 2).astype(np.float32), triangles)
