"""How a fit cuts the image into tiles (:class:`Tiling`): runs of rows for distant lights, square
blocks under near lights, each block fitted under the lights as seen from its centre
(:mod:`torchspec.model.near_lights`), and the tiles' results put back in the image's order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, is_dataclass, replace

import torch
from torch import Tensor

from ..model.lights import Lights
from ..model.near_lights import block_order, block_sizes, image_points, lights_at
from ..model.rendering import TILE_PIXELS
from .records import TileResult
from .start import LightContext, light_context

__all__ = ["Tiling", "tiling_of", "near_block", "merge_tiles", "sum_counts"]

LEAST_BLOCK = 4
"""Under near lights a block is at least this many pixels wide ..."""
BLOCK_ANGLE = math.radians(0.6)
"""... and no wider than lets the nearest light's direction vary by more than this about the
block's centre along a side (:func:`near_block`; and at most a tile's pixels): 1/16 of the image's
width under lights 3 widths away. On a Lambertian relief of ``tests/test_near_lights.py``, 32 pixels
wide in blocks of 4, the normals' median error is 1.6 degrees against 12.8 with the lights taken as
distant; a farther dome takes larger blocks (fewer, larger batches) for the same error."""


def near_block(height: int, width: int, tile: int, positions: Tensor) -> int:
    """The side (pixels) of :func:`tiling_of`'s blocks under near lights at ``positions (K, 3)``:
    ``2 tan(BLOCK_ANGLE)`` times the least distance from a light to the image (image widths,
    :mod:`torchspec.model.near_lights`), at least :data:`LEAST_BLOCK` and at most ``sqrt(tile)`` pixels."""
    half = torch.tensor([0.5, 0.5 * height / width], dtype=positions.dtype, device=positions.device)
    nearest = torch.minimum(positions[:, :2].abs(), half)  # the image's point nearest each light, mirrored
    reach = float(torch.cat([positions[:, :2].abs() - nearest, positions[:, 2:]], 1).norm(dim=1).min())
    across = math.floor(2 * math.tan(BLOCK_ANGLE) * reach * width)
    return max(LEAST_BLOCK, min(math.isqrt(max(tile, 1)), across))


@dataclass(frozen=True)
class Tiling:
    """The tiles of an ``H x W`` image.

    Attributes:
        ranges: each tile's ``(first, stop)`` in the fit's pixel order.
        order: ``(H W,)`` the fit's pixel order (row-major indices), ``None`` for row-major itself.
        positions: ``(K, 3)`` the near lights' positions, ``None`` for distant lights.
        points: ``(H W, 3)`` the pixels' centres in object units (near lights only).
    """

    ranges: list[tuple[int, int]]
    order: Tensor | None = None
    positions: Tensor | None = None
    points: Tensor | None = None

    def pixels(self, flat: Tensor) -> Tensor:
        """``flat (..., H W)`` in the fit's pixel order."""
        return flat if self.order is None else flat[..., self.order.to(flat.device)]

    def lights(self, lights: Lights, ctx: LightContext, first: int, stop: int) -> tuple[Lights, LightContext]:
        """The lights of the tile ``first .. stop - 1`` and their context: ``lights`` and ``ctx``
        for distant lights; as seen from the block's centre under near ones."""
        if self.positions is None:
            return lights, ctx
        centre = self.points[self.order[first:stop]].mean(0)
        near = lights_at(lights, self.positions, centre)
        return near, light_context(near)

    def restore(self, parts: list[TileResult]) -> list[TileResult]:
        """The tiles' results in the image's row-major order (one merged result when reordered)."""
        if self.order is None:
            return parts
        inverse = torch.empty_like(self.order)
        inverse[self.order] = torch.arange(self.order.numel(), device=self.order.device)
        return [merge_tiles(parts, inverse)]


def tiling_of(height: int, width: int, tile: int, positions: Tensor | None) -> Tiling:
    """Tiles of ``tile`` pixels in row-major order for distant lights (``positions`` ``None``);
    square blocks under near lights (:func:`near_block`, of at most
    :data:`~torchspec.model.rendering.TILE_PIXELS` pixels whatever ``tile``): the blocks
    :func:`torchspec.relight.render_near` and the viewer render in, so that a render lights each
    pixel as the fit saw it (a fit cut into smaller blocks than its render saw other lights: on
    SynthRTI m1 at a dome radius of 25 image widths, 0.4 % apart, and a residual term fitted under
    them predicted left-out photographs 3 dB worse)."""
    pixels = height * width
    if positions is None:
        return Tiling(ranges=[(first, min(first + tile, pixels)) for first in range(0, pixels, tile)])
    block = near_block(height, width, TILE_PIXELS, positions)
    starts, ranges = 0, []
    for size in block_sizes(height, width, block):
        ranges.append((starts, starts + size))
        starts += size
    points = image_points(height, width, dtype=positions.dtype, device=positions.device)
    return Tiling(ranges=ranges, order=block_order(height, width, block), positions=positions, points=points)


def merge_tiles(parts: list[TileResult], inverse: Tensor) -> TileResult:
    """One :class:`TileResult` of ``parts`` concatenated and indexed by ``inverse`` (each pixel's
    place in the concatenation); per-tile statistics summed (``times``, ``tried``, ``masked``) and
    the sensor noise the median of the tiles'."""
    first = parts[0]

    def joined(values: list):
        head = values[0]
        if head is None:
            return None
        if isinstance(head, Tensor):
            return torch.cat(values)[inverse.to(head.device)]
        if isinstance(head, dict):
            return {key: joined([v[key] for v in values]) for key in head}
        if is_dataclass(head):  # SVBRDF, Checks, PlainFit, ResidualTerm: field by field
            return replace(head, **{f.name: joined([getattr(v, f.name) for v in values]) for f in fields(head)})
        return head  # the same in every tile (an SVBRDF's channel names)

    per_pixel = {
        f.name: joined([getattr(p, f.name) for p in parts])
        for f in fields(TileResult)
        if f.name not in ("tried", "noise", "times", "masked")
    }
    summed = {
        name: None if getattr(first, name) is None else sum_counts([getattr(p, name) for p in parts])
        for name in ("tried", "times", "masked")
    }
    noise = torch.stack([p.noise for p in parts]).median(0).values
    return TileResult(**per_pixel, **summed, noise=noise)


def sum_counts(values: list[dict]) -> dict:
    """The per-tile counts or seconds ``values`` summed key by key."""
    out: dict = {}
    for value in values:
        for key, number in value.items():
            out[key] = out.get(key, 0) + number
    return out
