"""Near lights: a light at a finite distance (a dome) lights each part of the image from its own
direction and with its own irradiance.

Geometry (the capture format's ``position``, docs/capture-format.md): the object plane is
``z = 0``, the origin at the image's centre, x right, y up, z towards the camera, the unit the
image's width. Pixel (row ``i``, column ``j``) of an ``H x W`` image lies at
``x = (j + 0.5) / W - 0.5``, ``y = (H / 2 - (i + 0.5)) / W``. A light at ``p`` lights a point
``x`` from the direction ``(p - x) / |p - x|`` with the irradiance the frame records times
``(|p| / |p - x|)^2``: the frame's irradiance is the one at the image's centre.

A fit of near lights fits the image in square blocks (:func:`block_order`), each under the
lights as seen from its centre (:func:`lights_at`): within a block of ``b`` pixels of an image
``W`` wide, under lights ``R`` widths away, the direction varies by about ``b / (W R)`` radians.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .lights import Lights

__all__ = ["image_points", "block_order", "block_sizes", "lights_at", "near_light"]


def image_points(height: int, width: int, *, dtype=torch.float64, device=None) -> Tensor:
    """``(H W, 3)`` the pixels' centres in object units, row-major."""
    rows = torch.arange(height, dtype=dtype, device=device)
    cols = torch.arange(width, dtype=dtype, device=device)
    y = (height / 2 - (rows + 0.5)) / width
    x = (cols + 0.5) / width - 0.5
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    return torch.stack([xx, yy, torch.zeros_like(xx)], -1).reshape(-1, 3)


def near_light(positions: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """Each point's light directions ``(N, K, 3)`` and falloff ``(N, K)`` (``(|p| / |p - x|)^2``,
    1 at the origin) under lights at ``positions (K, 3)``, for ``points (N, 3)``.

    Example:
        >>> d, s = near_light(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
        >>> d[0, 0].tolist(), round(float(s[0, 0]), 6)
        ([-0.4472135901451111, 0.0, 0.8944271802902222], 0.8)
    """
    offset = positions[None] - points[:, None]  # (N, K, 3)
    distance = offset.norm(dim=-1)
    falloff = (positions.norm(dim=-1)[None] / distance).square()
    return offset / distance[..., None], falloff


def block_order(height: int, width: int, block: int) -> Tensor:
    """A permutation of the ``H W`` pixels (row-major indices) that lists the image in square
    blocks of ``block x block`` pixels, block after block row by row (the last ones narrower)."""
    # on the CPU: an index table, which its users (Tiling, render_near) move to the pixels' device
    rows, cols = torch.arange(height), torch.arange(width)
    index = (rows[:, None] * width + cols[None, :]).reshape(height, width)
    key = (rows[:, None] // block) * math.ceil(width / block) + cols[None, :] // block  # each pixel's block
    # a stable sort by block keeps row-major order within each block
    return index.reshape(-1)[torch.sort(key.reshape(-1), stable=True).indices]


def block_sizes(height: int, width: int, block: int) -> list[int]:
    """The pixels of each block of :func:`block_order`, in its order."""
    sizes = []
    for top in range(0, height, block):
        for left in range(0, width, block):
            sizes.append(min(block, height - top) * min(block, width - left))
    return sizes


def lights_at(lights: Lights, positions: Tensor, point: Tensor) -> Lights:
    """``lights`` as seen from ``point (3,)``: each frame's direction towards its position and its
    irradiance times the falloff (:func:`near_light`); the kernel and exposure unchanged."""
    positions = positions.to(lights.directions)
    directions, falloff = near_light(positions, point.to(positions)[None])
    return Lights(directions[0], lights.kernel, lights.irradiance * falloff[0][:, None], lights.exposure)
