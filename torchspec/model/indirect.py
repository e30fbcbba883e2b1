"""Indirect light in a relief's shadows: light that reaches a pixel after one bounce off its lit
surroundings (interreflection).

A groove or the foot of a carved figure is not black in the shadow its neighbour casts: the lit
surface around it reflects light into it. With cast shadows (:mod:`torchspec.model.visibility`)
the model of a pixel's recorded value under light ``k`` is

    y_k = V_k r_k + b D_k,

``r_k`` the maps' rendering without shadows, ``V_k`` the light's visibility, and ``D_k`` the
pixel's *flat diffuse*: its diffuse albedo rendered under light ``k`` with the mean plane's normal
``(0, 0, 1)``, no lobe and no shadow (:func:`flat_maps`), so ``D_k`` follows the light's
irradiance on the surroundings (``l_z`` for a distant light, the falloff of a near one, the
frame's exposure and gain) and the pixel's own albedo. ``b >= 0`` (the *indirect share*, one per
pixel, shared by the channels) is the indirect irradiance over the direct irradiance of the mean
plane: 0 on an open surface, up to a few tenths in a deep groove. It is a first-order model of the
bounce (the irradiance of the surroundings does not follow each light's own shadows), so it adds
one number per pixel, not a per-light residual.

Given the maps and the visibility, ``b`` is linear: :func:`indirect_share` is its closed-form
least-squares solution, clamped to ``[0, (1 - sky)]`` (:func:`bound`: the light comes back from
the part of the hemisphere the relief hides).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .brdf import SVBRDF

__all__ = ["MAX_SHARE", "bound", "flat_maps", "indirect_share"]

MAX_SHARE = 1.0
"""The largest indirect share (indirect irradiance over the direct irradiance of the mean plane):
the surroundings of a pixel reflect at most what they receive."""


def flat_maps(svbrdf: SVBRDF) -> SVBRDF:
    """``svbrdf``'s diffuse albedo on the mean plane: normal ``(0, 0, 1)``, no lobe, no rotation;
    rendered (:func:`torchspec.model.rendering.render`) it gives the flat diffuse ``D`` of the module's
    docstring."""
    lead = svbrdf.shape
    normal = torch.zeros_like(svbrdf.normal)
    normal[..., 2] = 1.0
    zero = svbrdf.diffuse.new_zeros((*lead, 1))
    return SVBRDF(normal, svbrdf.diffuse, zero, svbrdf.diffuse.new_zeros((*lead, 2)), channels=svbrdf.channels)


def indirect_share(
    residual: Tensor, flat: Tensor, weight: Tensor, maximum: float | Tensor = MAX_SHARE
) -> Tensor:
    """The least-squares indirect share ``b`` of each pixel: ``argmin_b sum_k,c w (residual - b
    flat)^2`` clamped to ``[0, maximum]``, with ``residual = y - V r`` and ``flat = D`` ``(K, C, *)``
    and ``weight`` ``(K, *)`` or ``(K, C, *)`` (0: a sample left out); ``maximum`` a number or one
    per pixel ``(*)`` (:func:`bound`). Returns ``(*)``; 0 where a pixel has no weighted flat diffuse."""
    if weight.dim() == residual.dim() - 1:
        weight = weight[:, None]
    weight = weight.to(residual).expand_as(residual)
    flat = flat.to(residual)
    top = (weight * residual * flat).sum((0, 1))
    bottom = (weight * flat.square()).sum((0, 1))
    share = top / bottom.clamp(min=torch.finfo(residual.dtype).tiny)
    share = torch.where(bottom > 0, share, torch.zeros_like(share)).clamp(min=0.0)
    return share.minimum(torch.as_tensor(maximum, dtype=share.dtype, device=share.device))


def bound(sky: Tensor) -> Tensor:
    """The largest indirect share of pixels that see ``sky`` ``(*)`` of the sky (cosine-weighted,
    :func:`torchspec.model.visibility.sky_view`): ``MAX_SHARE (1 - sky)``. Light comes back only from
    the part of the hemisphere the relief hides, and the surface there reflects at most the
    mean plane's irradiance; a pixel open to the sky gets none, so the share cannot stand in for a
    misfit of an open surface."""
    return MAX_SHARE * (1.0 - sky).clamp(0.0, 1.0)

