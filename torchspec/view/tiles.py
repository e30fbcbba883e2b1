"""The viewer's data: SVBRDF maps (and a capture's photographs) as a pyramid of square binary
tiles that the page (``torchspec/view/static/viewer.js``) uploads as WebGL2 textures.

A tile is ``TILE x TILE`` texels of level ``l`` (level 0 the maps themselves, level ``l + 1``
half of level ``l``, down to a level that fits in one tile; edge tiles padded with zeros).
Its file is the textures of :data:`TEXTURES`, one after the other, each ``TILE * TILE * 4``
values (RGBA interleaved, rows top to bottom) little-endian in the texture's dtype: float32 for
what a highlight is sensitive to (the normal, the rotation, the roughness), float16 for the rest
(relative error 2^-11, below an 8-bit display's step). Level ``l`` averages ``2^l x 2^l`` texels
of level 0 (normals renormalised); the model code, the flags and the rotation take the top-left
texel. The coarser levels are made in the background (:class:`Pyramid`).

Maps with a residual term (``residual_term.exr``, :mod:`torchspec.model.residual_term`) add the
textures of :func:`term_textures`: its weight ``w`` and its coefficients per basis function and
channel (RGB, grey replicated), float16, packed four planes a texture (:func:`term_planes`).
Maps with a height (``height.exr``) add the cast shadows' textures last: the horizon maps and
the indirect share (:mod:`torchspec.view.shadows`), float16.

A photograph's pyramid holds the frame divided by its exposure and irradiance (the value under a
unit light, comparable with the relit maps at the same exposure); its tiles are JPEGs of their own
size (an edge tile is cut, not padded), :func:`photo_jpeg`: 8-bit sRGB codes of the value over the
tile's largest, that scale in the JPEG's comment (``torchspec scale=S``), a few times the size of
the photographs' own JPEGs where float16 tiles were a few hundred times.
"""

from __future__ import annotations

import io
import math
import re
import threading
import time
from collections import OrderedDict

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from ..errors import TorchspecError
from ..io import Maps, read_svbrdf
from ..model.residual_term import MAP_NAME, WEIGHT_MAP, ResidualTerm, decode, encode
from .cache import LevelCache, Stopped
from .shadows import SHADOW_TEXTURES, read_height, shadow_planes, view_reach

__all__ = [
    "TILE",
    "TEXTURES",
    "Pyramid",
    "frame_pyramid",
    "levels_for",
    "photo_jpeg",
    "photo_pyramid",
    "photo_tile",
    "read_photo_jpeg",
    "term_textures",
    "term_planes",
    "textures_of",
]

TILE = 256
"""Texels on a tile's side."""

TEXTURES = (
    ("geometry", "float32", ("normal_x", "normal_y", "normal_z", "rotation")),
    ("roughness", "float32", ("alpha_x", "alpha_y", "alpha2_x", "alpha2_y")),
    ("diffuse", "float16", ("kd_r", "kd_g", "kd_b", "quality")),
    ("specular", "float16", ("ks_r", "ks_g", "ks_b", "model")),
    ("specular2", "float16", ("ks2_r", "ks2_g", "ks2_b", "flags")),
    ("std", "float16", ("std_normal_deg", "std_diffuse", "std_specular", "std_roughness")),
)
"""The textures of a map tile: name, dtype, the four planes (RGBA)."""

EXTRA_MAPS = ("quality", "model", "flags", "std_normal_deg", "std_diffuse", "std_specular", "std_roughness",
              MAP_NAME, WEIGHT_MAP, "height", "indirect")  # fmt: skip
"""The extra maps of a fit that the tiles hold (the others are not read)."""

NEAREST = ("rotation", "model", "flags")
"""Planes a coarser level takes from the top-left texel instead of the average."""


def levels_for(height: int, width: int, tile: int = TILE) -> int:
    """How many levels a ``height x width`` image takes: down to one that fits in one tile."""
    return 1 + max(0, math.ceil(math.log2(max(height, width, 1) / tile)))


def _rgb(value: torch.Tensor) -> torch.Tensor:
    """``(H, W, C)`` as three planes ``(H, W, 3)``: grey replicated, more than 3 channels cut to 3."""
    if value.shape[-1] == 1:
        return value.expand(*value.shape[:-1], 3)
    return value[..., :3]


def _planes(maps: Maps) -> dict[str, torch.Tensor]:
    """Every plane of :data:`TEXTURES` at level 0, ``(H, W)`` float32 (0 where the maps lack it)."""
    svbrdf, extra = maps.svbrdf, maps.extra
    height, width = svbrdf.shape
    device = svbrdf.normal.device
    zero = torch.zeros(1, 1, device=device).expand(height, width)
    planes = {}
    for axis, name in enumerate("xyz"):
        planes[f"normal_{name}"] = svbrdf.normal[..., axis]
    planes["rotation"] = zero if svbrdf.rotation is None else svbrdf.rotation
    planes["alpha_x"], planes["alpha_y"] = svbrdf.roughness[..., 0], svbrdf.roughness[..., 1]
    second = svbrdf.roughness2 if svbrdf.roughness2 is not None else zero[..., None].expand(height, width, 2)
    planes["alpha2_x"], planes["alpha2_y"] = second[..., 0], second[..., 1]
    for prefix, value in (("kd", svbrdf.diffuse), ("ks", svbrdf.specular), ("ks2", svbrdf.specular2)):
        value = zero[..., None].expand(height, width, 3) if value is None else _rgb(value)
        for c, name in enumerate("rgb"):
            planes[f"{prefix}_{name}"] = value[..., c]
    for name in ("quality", "model", "flags", "std_normal_deg"):
        planes[name] = extra.get(name, zero)
    for name in ("std_diffuse", "std_specular"):
        value = extra.get(name)
        planes[name] = zero if value is None else (value.mean(-1) if value.dim() == 3 else value)
    rough = extra.get("std_roughness")
    planes["std_roughness"] = zero if rough is None else (rough[..., 0] if rough.dim() == 3 else rough)
    return {name: value.float() for name, value in planes.items()}


def term_textures(terms: int) -> tuple:
    """The textures of a residual term of ``terms`` basis functions (4 or 9): planes
    ``term_weight``, then ``term_{j}_{r,g,b}`` for each function ``j``, then zero planes
    ``term_pad_{k}`` up to a multiple of four."""
    names = ["term_weight"] + [f"term_{j}_{c}" for j in range(terms) for c in "rgb"]
    names += [f"term_pad_{k}" for k in range(-len(names) % 4)]
    return tuple((f"term{i}", "float16", tuple(names[4 * i : 4 * i + 4])) for i in range(len(names) // 4))


def term_planes(maps: Maps) -> dict[str, torch.Tensor]:
    """The planes of :func:`term_textures` of the maps' residual term ``(H, W)`` float32 each (none
    without a term).

    Raises:
        TorchspecError: the term's map does not fit the maps' channels, or its weight is outside
            ``[0, 1]`` (:meth:`ResidualTerm.from_map`, naming ``residual_term.exr``).
    """
    if MAP_NAME not in maps.extra:
        return {}
    channels = len(maps.svbrdf.channels)
    value = maps.extra[MAP_NAME]
    value = value[..., None] if value.dim() == 2 else value
    term = ResidualTerm.from_map(value, channels, f"{MAP_NAME}.exr", maps.extra.get(WEIGHT_MAP))
    coefficients = _rgb(term.coefficients)  # (H, W, J, 3)
    weight = torch.ones(coefficients.shape[:2], device=coefficients.device) if term.weight is None else term.weight
    planes = {"term_weight": weight}
    for j in range(coefficients.shape[2]):
        planes.update({f"term_{j}_{c}": coefficients[:, :, j, i] for i, c in enumerate("rgb")})
    zero = torch.zeros(1, 1, device=coefficients.device).expand(*coefficients.shape[:2])
    for _, _, names in term_textures(coefficients.shape[2]):
        planes.update({name: zero for name in names if name.startswith("term_pad")})
    return {name: plane.float() for name, plane in planes.items()}


def textures_of(maps: Maps) -> tuple:
    """A tile's textures for ``maps``: :data:`TEXTURES`, the term's when the maps have one, and
    the cast shadows' (:data:`torchspec.view.shadows.SHADOW_TEXTURES`) when they have a height."""
    textures = TEXTURES
    if MAP_NAME in maps.extra:
        value = maps.extra[MAP_NAME]
        count = value.shape[-1] if value.dim() == 3 else 1
        textures = textures + term_textures(max(1, count // max(1, len(maps.svbrdf.channels))))
    return textures + (SHADOW_TEXTURES if "height" in maps.extra else ())


def _reduce(planes, names: tuple[str, ...]) -> torch.Tensor:
    """The next level of ``planes`` (``(h, w)`` each, or ``(P, h, w)``), stacked ``(P, h', w')``:
    ``2 x 2`` averages (odd sizes: the last row or column repeated), normals renormalised,
    :data:`NEAREST` planes from the top-left texel. One plane at a time: no copy of the whole."""
    out = []
    for plane, name in zip(planes, names, strict=True):
        if name in NEAREST:
            out.append(plane[::2, ::2])
            continue
        height, width = plane.shape
        if height % 2 or width % 2:
            plane = F.pad(plane[None, None], (0, width % 2, 0, height % 2), mode="replicate")[0, 0]
        out.append((plane[0::2, 0::2] + plane[1::2, 0::2] + plane[0::2, 1::2] + plane[1::2, 1::2]) * 0.25)
    out = torch.stack(out)
    index = {name: i for i, name in enumerate(names)}
    if "normal_x" in index:
        rows = [index[f"normal_{a}"] for a in "xyz"]
        out[rows] = out[rows] / out[rows].norm(dim=0).clamp(min=1e-12)
    return out


KEEP_TEXELS = 1 << 23
"""A lazily read pyramid holds in memory the levels of at most this many texels (8 megapixels: 768
MB of planes); the finer ones are made on demand from level 0's rows."""
CACHE_BYTES = 1 << 30
"""The bands of level-0 rows a lazily read pyramid keeps (the last ones read), in bytes of planes."""


class Pyramid:
    """Tiled levels of an image with named planes; :meth:`tile` encodes one tile.

    In memory (``planes``): level 0 is the image; a background thread, started at construction,
    halves it level after level (each a ``2 x 2`` reduction of the one before), and a tile of a
    level not yet made waits for it: the server starts at once, and the coarsest level (the page's
    first image) follows after one pass over the image and a third of one.

    Read lazily (``read``: level 0's rows from files, :func:`~torchspec.io.read_svbrdf`'s
    ``rows``): the levels of at most ``keep_texels`` texels are held in memory, the finest of them
    (level ``kept``) made by a background pass that reads level 0 in bands and reduces each band
    (memory: one band), the coarser ones reduced from it; a tile of a finer level is made on demand
    from the level-0 rows under it (a level-``l`` tile: ``tile 2^l`` rows), read in bands of
    ``tile`` rows of which the last read are kept (``cache_bytes``), as is a level-0 tile asked for
    before the pass has read level 0 when that is the level held. Both give the same tiles, bit
    for bit: the bands and tiles are aligned on the ``2 x 2`` blocks of every level.

    With ``cache`` (the map folder, when read lazily): the held levels other than level 0 are read
    from the cache of :mod:`torchspec.view.cache` when it holds them for the folder's files as they
    are now, coarsest first (each served as soon as it is read: the whole painting at once), and
    there is no pass (level 0's tiles are then read on demand even when it is the level held); else
    the pass makes them and writes them there after. The tiles are the same, bit for bit.

    Attributes:
        textures: ``(name, dtype, planes)`` of a tile's textures, in file order.
        size: level 0's ``(H, W)``.
        tile_size: texels on a tile's side.
        kept: the finest level held in memory (0 in memory).
        store: the levels' :class:`~torchspec.view.cache.LevelCache` (``None``: none).
        worker: the background thread (it ends once the levels are made, and written to the cache).
        shadow_reach: of maps with a height, the reach of their horizon maps (pixels,
            :func:`torchspec.view.shadows.view_reach`); else ``None``.
    """

    def __init__(self, textures, size, planes=None, read=None, *, tile=TILE, keep_texels=KEEP_TEXELS,
                 cache_bytes=CACHE_BYTES, cache=None):  # fmt: skip
        self.textures, self.size, self.tile_size = tuple(textures), tuple(size), tile
        self.shadow_reach: float | None = None  # maps with a height: how far their horizons look (pixels)
        self.names = tuple(name for _, _, names in self.textures for name in names)
        self.read = read if planes is None else (lambda a, b: torch.stack([p[a:b] for p in planes]))
        sizes = self.levels
        held = [i for i, (h, w) in enumerate(sizes) if h * w <= keep_texels] + [len(sizes) - 1]
        self.kept = 0 if planes is not None else held[0]
        self.reduced = [planes] + [None] * (len(sizes) - 1)
        self.made = [threading.Event() for _ in sizes]
        for level in range(self.kept + (planes is not None)):
            self.made[level].set()
        self.error: BaseException | None = None
        self.bands: OrderedDict = OrderedDict()
        self.band_count = max(2, cache_bytes // max(1, 4 * len(self.names) * tile * size[1]))
        self.lock = threading.Lock()  # the band cache
        # EXR reads one at a time: each decodes its blocks on OpenEXR's threads, one a core (torchspec.io.exr
        # is safe from several threads, but two reads at once would only share the cores)
        self.io = threading.Lock()
        self.urgent = 0  # tile requests waiting to read: the background pass lets them go first
        self.store = None
        if cache is not None and planes is None and len(sizes) > 1:  # level 0 never: read on demand
            shapes = {level: sizes[level] for level in range(max(1, self.kept), len(sizes))}
            self.store = LevelCache(cache, self.textures, shapes, {"tile": tile, "size": list(self.size)})
        self.closing = threading.Event()
        self.worker = threading.Thread(target=self._make_all, name="torchspec-view-pyramid", daemon=True)
        self.worker.start()

    def close(self, timeout: float = 10.0) -> None:
        """Stop the background pass and the cache's write (its temporary file removed); wait up to
        ``timeout`` seconds for them. Tiles of levels not made are then never made."""
        self.closing.set()
        self.worker.join(timeout)

    def _make_all(self) -> None:
        try:
            if self.store is not None and self._load():
                return
            if self.reduced[self.kept] is None:
                self.reduced[self.kept] = self._stream(self.kept)
                self.made[self.kept].set()
            for level in range(self.kept + 1, len(self.made)):
                self.reduced[level] = _reduce(self.reduced[level - 1], self.names)
                self.made[level].set()
        except BaseException as error:  # a tile of a level never made says why
            self.error = error
            for made in self.made:
                made.set()
            return
        if self.store is not None:
            try:
                self.store.save({level: self.reduced[level] for level in self.store.shapes}, self._pause)
            except Stopped:
                pass

    def _load(self) -> bool:
        """The held levels from the cache, coarsest first, each published once read; false when
        the cache has none for these maps or one is damaged (the pass then makes them all)."""
        if not self.store.find():
            return False
        for level in sorted(self.store.shapes, reverse=True):
            planes = self.store.load(level)
            if planes is None:
                return False
            self.reduced[level] = planes
            self.made[level].set()
        return True

    def _stream(self, level: int) -> torch.Tensor:
        """Level ``level`` from level 0's rows, read in bands (a multiple of ``2^level`` rows)."""
        height, width = self.levels[level]
        out = torch.empty(len(self.names), height, width)  # on the CPU: its tiles are sent and cached as files
        band = 2**level * max(1, self.tile_size // 2**level)
        for start in range(0, self.size[0], band):
            self._pause()
            with self.io:
                block = self.read(start, min(self.size[0], start + band))
            for _ in range(level):
                block = _reduce(block, self.names)
            out[:, start // 2**level : start // 2**level + block.shape[1]] = block
        return out

    def _pause(self) -> None:
        """Between two steps of the background work: wait while tile requests wait to read; raise
        :class:`~torchspec.view.cache.Stopped` once :meth:`close` is called."""
        while self.urgent:
            time.sleep(0.005)
        if self.closing.is_set():
            raise Stopped("the pyramid is closed")

    def rows(self, start: int, stop: int) -> torch.Tensor:
        """Level 0's rows ``start`` to ``stop - 1``, ``(P, stop - start, W)``, from the bands of
        ``tile_size`` rows read last (or read now)."""
        n, parts = self.tile_size, []
        for index in range(start // n, -(-stop // n)):
            with self.lock:
                if index not in self.bands:
                    self.urgent += 1
                    try:
                        with self.io:
                            self.bands[index] = self.read(index * n, min(self.size[0], (index + 1) * n))
                    finally:
                        self.urgent -= 1
                    while len(self.bands) > self.band_count:
                        self.bands.popitem(last=False)
                self.bands.move_to_end(index)
                band = self.bands[index]
            parts.append(band[:, max(start - index * n, 0) : stop - index * n])
        return torch.cat(parts, 1) if len(parts) > 1 else parts[0]

    @classmethod
    def build(cls, planes: dict[str, torch.Tensor], textures=TEXTURES, tile: int = TILE) -> Pyramid:
        """The pyramid of ``planes`` (each ``(H, W)``) packed into ``textures``."""
        names = [name for _, _, names in textures for name in names]
        return cls(textures, planes[names[0]].shape, tuple(planes[name].float() for name in names), tile=tile)

    @classmethod
    def of_maps(cls, maps: Maps, tile: int = TILE) -> Pyramid:
        """The pyramid of a fit's maps (:data:`TEXTURES`, the residual term's, the cast shadows')."""
        planes = {**_planes(maps), **term_planes(maps)}
        height = maps.extra.get("height")
        reach = None if height is None else view_reach(height.float())
        if height is not None:
            planes.update(shadow_planes(height.float(), maps.extra.get("indirect"), 0, height.shape[0], reach))
        pyramid = cls.build(planes, textures_of(maps), tile)
        pyramid.shadow_reach = reach
        return pyramid

    @classmethod
    def of_folder(cls, folder, head: Maps, size: tuple[int, int], cache: bool = False, **options) -> Pyramid:
        """The pyramid of the map folder ``folder`` of ``size`` ``(H, W)``, read lazily (``head``:
        a band of its rows, for the textures; ``options``: ``tile``, ``keep_texels``,
        ``cache_bytes``; ``cache=True``: its held levels cached, :mod:`torchspec.view.cache`)."""
        textures = textures_of(head)
        names = [name for _, _, names in textures for name in names]
        height = read_height(folder) if "height" in head.extra else None  # whole: a ray looks beyond a band
        reach = None if height is None else view_reach(height)
        band_maps = tuple(name for name in EXTRA_MAPS if name != "height")  # read whole above, not again a band

        def read(start: int, stop: int) -> torch.Tensor:
            band = read_svbrdf(folder, rows=(start, stop), extra_maps=band_maps)
            planes = {**_planes(band), **term_planes(band)}
            if height is not None:
                planes.update(shadow_planes(height, band.extra.get("indirect"), start, stop, reach))
            return torch.stack([planes[name] for name in names])

        pyramid = cls(textures, size, read=read, cache=folder if cache else None, **options)
        pyramid.shadow_reach = reach
        return pyramid

    @property
    def height(self) -> int:
        return self.size[0]

    @property
    def width(self) -> int:
        return self.size[1]

    @property
    def levels(self) -> list[tuple[int, int]]:
        """``(h, w)`` of every level, 0 first."""
        count = levels_for(self.height, self.width, self.tile_size)
        return [(-(-self.height // 2**level), -(-self.width // 2**level)) for level in range(count)]

    def grid(self, level: int) -> tuple[int, int]:
        """``(rows, columns)`` of tiles at ``level``."""
        h, w = self.levels[level]
        return -(-h // self.tile_size), -(-w // self.tile_size)

    def ready(self, level: int, timeout: float = 0.0) -> bool:
        """Whether a tile of ``level`` can be made now (its level made, or made on demand), after
        waiting up to ``timeout`` seconds for its level."""
        return not 0 <= level < len(self.made) or level < self.kept or level == 0 or self.made[level].wait(timeout)

    def block(self, level: int, row: int, column: int) -> torch.Tensor:
        """A tile's planes ``(P, h, w)`` (``h, w <= tile_size``: an edge tile is cut).

        Raises:
            IndexError: no such level or tile.
        """
        if not 0 <= level < len(self.levels):
            raise IndexError(f"no level {level}")
        rows, columns = self.grid(level)
        if not (0 <= row < rows and 0 <= column < columns):
            raise IndexError(f"no tile {row}, {column} at level {level}")
        n = self.tile_size
        if level < self.kept or not self.made[level].is_set() and level == 0:  # on demand from level 0's rows
            span = n * 2**level
            block = self.rows(row * span, min(self.height, (row + 1) * span))[:, :, column * span : (column + 1) * span]
            for _ in range(level):
                block = _reduce(block, self.names)
            return block
        self.made[level].wait()
        if self.error is not None:
            raise self.error
        return torch.stack(
            [plane[row * n : (row + 1) * n, column * n : (column + 1) * n] for plane in self.reduced[level]]
        )

    def tile(self, level: int, row: int, column: int) -> bytes:
        """The file of a tile: each texture's ``tile_size^2 x 4`` values, padded with zeros.

        Raises:
            IndexError: no such level or tile.
        """
        block = self.block(level, row, column).permute(1, 2, 0)
        n, parts, first = self.tile_size, [], 0
        for _, dtype, planes in self.textures:
            padded = np.zeros((n, n, 4), dtype=np.dtype(dtype).newbyteorder("<"))
            with np.errstate(over="ignore"):  # float16: beyond 65504 is Inf (an undetermined deviation's)
                padded[: block.shape[0], : block.shape[1]] = block[..., first : first + len(planes)].cpu().numpy()
            parts.append(padded.tobytes())
            first += len(planes)
        return b"".join(parts)

    def describe(self) -> dict:
        """The pyramid's part of the page's ``manifest.json``."""
        return {
            "tile": self.tile_size,
            "levels": [list(size) for size in self.levels],
            "textures": [{"name": n, "dtype": d, "planes": list(p)} for n, d, p in self.textures],
        }


PHOTO_TEXTURES = (("photo", "float16", ("r", "g", "b", "a")),)
"""The planes of a photograph's pyramid (float32 in memory); its tiles are served as JPEGs
(:func:`photo_tile`), :meth:`Pyramid.tile`'s float16 bytes only compare two pyramids."""
PHOTO_BYTES = CACHE_BYTES // 4
"""The bands of level-0 rows a lazily read photograph's pyramid keeps, in bytes of planes (the
server keeps a few photographs: ``torchspec.view.site.PHOTO_CACHE``)."""


def _photo_planes(frame: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The planes ``r, g, b, a`` ``(4, H, W)`` float32 of ``frame (C, H, W)`` divided by ``scale (C,)``
    (grey replicated, more than 3 channels cut to 3; ``a`` is 1)."""
    value = _rgb((frame / scale.to(frame)[:, None, None]).permute(1, 2, 0)).float()
    return torch.stack([value[..., 0], value[..., 1], value[..., 2], torch.ones_like(value[..., 0])])


def photo_pyramid(frame: torch.Tensor, scale: torch.Tensor, tile: int = TILE) -> Pyramid:
    """The pyramid of a photograph ``frame (C, H, W)`` divided by ``scale (C,)`` (its exposure
    times irradiance, per channel), in memory."""
    planes = _photo_planes(frame, scale)
    return Pyramid(PHOTO_TEXTURES, planes.shape[1:], tuple(planes), tile=tile)


def frame_pyramid(capture, k: int, *, tile: int = TILE, keep_texels: int = KEEP_TEXELS,
                  cache_bytes: int = PHOTO_BYTES) -> Pyramid:  # fmt: skip
    """The pyramid of frame ``k`` of ``capture`` (a :class:`~torchspec.io.Capture`) as
    :func:`photo_pyramid` makes it: divided by its exposure times irradiance, NaN and Inf made 0.

    A frame of at most ``keep_texels`` pixels is read whole (NaN, Inf and negative values kept,
    with a warning: :meth:`~torchspec.io.Capture.read_frames`), as the pyramid of a map folder
    holds its level 0 whole. A larger one is read lazily as a map folder is
    (:meth:`Pyramid.of_folder`): bands of its EXR's rows, read when a tile of a fine level asks
    for them (``cache_bytes`` of them kept) and by the background pass that makes the coarse
    levels (without the warning). The tiles are the same, bit for bit.

    Raises:
        CaptureError: the frame (read whole) is unreadable or not of the capture's size; read
            lazily, the tile whose rows are asked for raises it.
    """
    scale = capture.exposure()[k] * capture.irradiance()[k]
    size = (capture.height, capture.width)
    if size[0] * size[1] <= keep_texels:
        frame = capture.read_frames([k], nonfinite="keep")[0]
        return photo_pyramid(torch.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0), scale, tile)

    def read(start: int, stop: int) -> torch.Tensor:
        frame = capture.read_frames([k], rows=(start, stop), nonfinite="ignore")[0]
        return _photo_planes(torch.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0), scale)

    return Pyramid(PHOTO_TEXTURES, size, read=read, tile=tile, keep_texels=keep_texels, cache_bytes=cache_bytes)


PHOTO_QUALITY = 90
"""The JPEG quality of a photograph's tiles (chroma at full resolution): on realrti-item7 their
codes are off by 1.0 on average from the tile's 8-bit sRGB codes (0.6 at the zenith), and the 48
photographs' tiles take 2.2 times their JPEGs (float16 tiles: 280 times)."""
_SCALE = re.compile(rb"torchspec scale=([0-9.eE+-]+)")


def photo_jpeg(block: torch.Tensor, quality: int = PHOTO_QUALITY) -> bytes:
    """A photograph's tile, its planes ``r, g, b (, a)`` ``(P, h, w)`` (:func:`photo_pyramid`), as a
    ``w x h`` JPEG: the 8-bit sRGB codes of ``value / S``, ``S`` the tile's largest value (1 where
    that is not positive), clipped to ``[0, 1]`` (a negative value shows as 0), ``S`` in the JPEG's
    comment as ``torchspec scale=S`` (:func:`read_photo_jpeg`)."""
    rgb = block[:3].double()
    top = float(rgb.max()) if rgb.numel() else 0.0
    scale = top if math.isfinite(top) and top > 0 else 1.0
    codes = (encode((rgb / scale).clamp(0, 1)) * 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    out = io.BytesIO()
    comment = f"torchspec scale={scale!r}".encode()
    Image.fromarray(codes, "RGB").save(out, "JPEG", quality=quality, subsampling=0, optimize=True, comment=comment)
    return out.getvalue()


def read_photo_jpeg(data: bytes) -> tuple[np.ndarray, float]:
    """A tile of :func:`photo_jpeg` as the page reads it: ``(h, w, 3)`` float64 values (the codes
    sRGB-decoded, times the scale) and the scale.

    Raises:
        TorchspecError: not a JPEG with a ``torchspec scale=`` comment."""
    found = _SCALE.search(data[: data.find(b"\xff\xda")] if b"\xff\xda" in data else data)
    if found is None:
        raise TorchspecError("not a photograph's tile: a JPEG whose comment holds 'torchspec scale='.")
    scale = float(found[1])
    codes = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"), dtype=np.float64) / 255
    return decode(torch.from_numpy(codes)).numpy() * scale, scale


def photo_tile(pyramid: Pyramid, level: int, row: int, column: int, quality: int = PHOTO_QUALITY) -> bytes:
    """The JPEG (:func:`photo_jpeg`) of a photograph's tile at ``level``, ``row``, ``column``.

    Raises:
        IndexError: no such level or tile."""
    return photo_jpeg(pyramid.block(level, row, column), quality)
