"""A synthetic relief: a known height field (Gaussian bumps and a ridge, in pixels) and its exact
normals, the ground truth of cast shadows (:mod:`torchspec.model.visibility`) and of the height
integration (:mod:`torchspec.model.height`). ``torchspec simulate`` puts it under a scene with
``scene.relief``.

Conventions of ``docs/capture-format.md``: rows down, columns right, surface ``y`` up, so a height
``h`` has the normal ``(-dh/dcol, +dh/drow, 1)`` normalised. Every random draw is made on the CPU in
float64 from ``config.seed``: a seed gives the same relief on every device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import TorchspecError

__all__ = ["ReliefConfig", "Relief", "relief"]


@dataclass(frozen=True)
class ReliefConfig:
    """Settings of :func:`relief`; lengths and heights in pixels.

    Attributes:
        bumps: the number of Gaussian bumps, centres uniform over the image.
        bump_height: ``(lo, hi)`` of their heights (uniform draws).
        bump_radius: ``(lo, hi)`` of their standard deviations.
        ridge_height: the height of a straight Gaussian ridge through the image's centre (0: none),
            at an angle drawn from the seed.
        ridge_width: its standard deviation across.
        seed: the seed of every draw.
        shadows: ``torchspec simulate`` casts the relief's shadows (else the normals alone change).
        softness_deg: the penumbra's width in elevation, degrees (:func:`torchspec.model.visibility.visibility`).
        indirect: with ``shadows``, the indirect share (:mod:`torchspec.model.indirect`) of a pixel
            that sees none of the sky: each pixel's is ``indirect (1 - sky)``, ``sky`` its
            cosine-weighted visible share of the hemisphere
            (:func:`torchspec.model.visibility.sky_view`); 0: no indirect light.
    """

    bumps: int = 5
    bump_height: tuple[float, float] = (3.0, 8.0)
    bump_radius: tuple[float, float] = (3.0, 8.0)
    ridge_height: float = 4.0
    ridge_width: float = 2.0
    seed: int = 0
    shadows: bool = True
    softness_deg: float = 1.0
    indirect: float = 0.0

    def __post_init__(self):
        if self.bumps < 0:
            raise TorchspecError(f"ReliefConfig.bumps must be >= 0; got {self.bumps}.")
        for name in ("bump_height", "bump_radius"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise TorchspecError(f"ReliefConfig.{name} must be (lo, hi) with lo <= hi; got {(lo, hi)}.")
        if not min(self.bump_radius[0], self.ridge_width) > 0:
            raise TorchspecError(
                f"ReliefConfig.bump_radius and ridge_width must be > 0; got {self.bump_radius}, {self.ridge_width}."
            )
        if not 0.0 <= self.indirect <= 1.0:
            raise TorchspecError(f"ReliefConfig.indirect must be in [0, 1]; got {self.indirect}.")
        if not self.softness_deg > 0:
            raise TorchspecError(f"ReliefConfig.softness_deg must be > 0; got {self.softness_deg}.")


@dataclass(frozen=True)
class Relief:
    """A relief's height ``(H, W)`` (pixels, mean 0), its exact slopes ``dh/dcol``, ``dh/drow``
    ``(H, W)`` and unit normals ``(H, W, 3)``."""

    height: Tensor
    slope_col: Tensor
    slope_row: Tensor
    normal: Tensor


def relief(config: ReliefConfig, height: int, width: int, *, dtype: torch.dtype = torch.float64, device=None) -> Relief:
    """The relief of ``config`` over an ``height x width`` image (drawn in float64 on the CPU, cast to
    ``dtype`` and moved to ``device`` at the end).

    Example:
        >>> r = relief(ReliefConfig(), 16, 24)
        >>> tuple(r.height.shape), tuple(r.normal.shape), abs(float(r.height.mean())) < 1e-12
        ((16, 24), (16, 24, 3), True)
    """
    if height < 1 or width < 1:
        raise TorchspecError(f"a relief needs height and width >= 1; got {height}, {width}.")
    f64 = torch.float64
    g = torch.Generator().manual_seed(config.seed)  # CPU on purpose: the seeded draw
    rows = torch.arange(height, dtype=f64)[:, None].expand(height, width)  # CPU on purpose: as the draw
    cols = torch.arange(width, dtype=f64)[None, :].expand(height, width)  # CPU on purpose: as the draw
    h = torch.zeros(height, width, dtype=f64)  # CPU on purpose: as the draw
    gc, gr = torch.zeros_like(h), torch.zeros_like(h)
    draws = torch.rand(config.bumps, 4, generator=g, dtype=f64)  # CPU on purpose: the seeded draw
    for r0, c0, a, s in draws.tolist():
        r0, c0 = r0 * height, c0 * width
        amp = config.bump_height[0] + (config.bump_height[1] - config.bump_height[0]) * a
        sigma = config.bump_radius[0] + (config.bump_radius[1] - config.bump_radius[0]) * s
        bump = amp * torch.exp(-((rows - r0) ** 2 + (cols - c0) ** 2) / (2 * sigma**2))
        h, gc, gr = h + bump, gc - bump * (cols - c0) / sigma**2, gr - bump * (rows - r0) / sigma**2
    angle = math.pi * float(torch.rand(1, generator=g, dtype=f64))  # CPU on purpose: the seeded draw
    if config.ridge_height != 0:
        # Signed distance across a line through the centre at ``angle`` from the columns.
        nr, nc = math.cos(angle), -math.sin(angle)
        d = (rows - (height - 1) / 2) * nr + (cols - (width - 1) / 2) * nc
        ridge = config.ridge_height * torch.exp(-(d**2) / (2 * config.ridge_width**2))
        slope = -ridge * d / config.ridge_width**2
        h, gc, gr = h + ridge, gc + slope * nc, gr + slope * nr
    v = torch.stack([-gc, gr, torch.ones_like(h)], -1)
    normal = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)

    def cast(t: Tensor) -> Tensor:
        return t.to(device=device, dtype=dtype)

    return Relief(cast(h - h.mean()), cast(gc), cast(gr), cast(normal))
