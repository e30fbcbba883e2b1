"""What the page's relit image should be: :func:`torchspec.render` of the same maps under the same
light (a point or an extended kernel about the same centre; a near light as
:func:`torchspec.relight.render_near` renders it, or at each pixel), encoded as the page encodes it (sRGB,
8 bits); the width of each pixel's lobe, to tell where an extended light's fixed nodes fall too far
apart; and small maps of each model type to compare on (the tests, ``experiments/view.py``).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import TorchspecError
from ..io import Maps
from ..model.brdf import SVBRDF
from ..model.geometry import from_plane, normal_from_angles, spiral_plane
from ..model.lights import Kernel, Lights
from ..model.lobe import lobe_frame, lobe_moments
from ..model.near_lights import image_points, near_light
from ..model.rendering import render, render_image
from ..model.residual_term import MAP_NAME, TERMS, WEIGHT_MAP, ResidualTerm, encode
from ..model.visibility import frame_visibility
from ..pipeline.flags import FLAGS, UNTRUSTED, bit
from ..pipeline.settings import MODEL_CODES
from ..relight import indirect_light, render_near

__all__ = [
    "MODEL_TYPES",
    "model_maps",
    "with_term",
    "with_height",
    "reference_srgb",
    "render_each_pixel",
    "hemisphere_lights",
    "lobe_width",
]

MODEL_TYPES = ("diffuse", "ward-iso", "ward-aniso", "ward-dual")
"""The model types the page shades (``ward-iso-colour`` is ``ward-iso`` with a coloured ``k_s``)."""


def model_maps(
    model: str, height: int = 48, width: int = 64, seed: int = 0, alpha: tuple[float, float] | None = None
) -> Maps:
    """Random maps of one model type, with the fit's extra maps (model, quality, flags, standard
    deviations) and ``svbrdf.json`` keys: normals tilted up to 25 degrees, ``k_d`` in
    ``[0.1, 0.9]``, ``k_s`` in ``[0.02, 0.5]``, ``alpha`` in ``[0.05, 0.45]`` or the range
    ``alpha`` (anisotropic: each axis, and a rotation), the dual model's second lobe
    (``alpha`` in ``[0.2, 0.5]``) broader than its first (``[0.05, 0.15]`` by default)."""
    if model not in MODEL_TYPES:
        raise TorchspecError(f"model must be one of {MODEL_TYPES}; got {model!r}.")
    g = torch.Generator().manual_seed(seed)  # on the CPU: a seeded generator, the maps reproducible

    def uniform(low, high, *shape):
        return low + (high - low) * torch.rand(height, width, *shape, generator=g, dtype=torch.float64)

    normal = normal_from_angles(uniform(-math.radians(25), math.radians(25), 2))
    kd = uniform(0.1, 0.9, 3)
    ks = uniform(0.02, 0.5, 3) * (model != "diffuse")
    low, high = (0.05, 0.45) if alpha is None else alpha
    rotation, ks2, alpha2 = None, None, None
    if model == "ward-aniso":
        alpha, rotation = uniform(low, high, 2), uniform(-math.pi, math.pi)
    else:
        low, high = (0.05, 0.15) if model == "ward-dual" and alpha is None else (low, high)
        alpha = uniform(low, high, 1).expand(height, width, 2).clone()
    if model == "ward-dual":
        ks2, alpha2 = uniform(0.02, 0.3, 1), uniform(0.2, 0.5, 1).expand(height, width, 2).clone()
    if model == "diffuse":
        alpha = torch.zeros_like(alpha)
    svbrdf = SVBRDF(normal, kd, ks, alpha, rotation, specular2=ks2, roughness2=alpha2).to(torch.float32)
    flags = torch.where(torch.rand(height, width, generator=g) < 0.1, float(bit(UNTRUSTED[0])), 0.0)
    extra = {
        "model": torch.full((height, width), float(MODEL_CODES.index(model))),  # on the CPU, with the maps
        "quality": torch.rand(height, width, generator=g),
        "flags": flags,
        "std_normal_deg": torch.rand(height, width, generator=g),
        "std_diffuse": 0.01 * torch.rand(height, width, 3, generator=g),
    }
    meta = {
        "model_codes": list(MODEL_CODES),
        "flag_bits": {name: bit(name) for name in FLAGS},
        "untrusted_flags": list(UNTRUSTED),
    }
    return Maps(svbrdf, meta, extra)


def with_term(maps: Maps, order: int = 3, seed: int = 0, size: float = 0.1, encoding: dict | None = None) -> Maps:
    """``maps`` with a random residual term (as a fit writes it: ``residual_term`` channel-major,
    ``residual_term_weight``): coefficients uniform in ``[-size, size]`` on three pixels of four
    (the others none), the weight 1 on half of those and uniform in ``[0, 1]`` on the rest; in the
    domain of ``encoding`` (:meth:`~torchspec.model.residual_term.TermDomain.to_json`, recorded in the
    maps' ``meta`` as a fit records it; ``None``: sRGB, nothing recorded)."""
    height, width = maps.svbrdf.shape
    channels = len(maps.svbrdf.channels)
    g = torch.Generator().manual_seed(seed)  # on the CPU: a seeded generator, the term reproducible
    coefficients = size * (2 * torch.rand(height, width, TERMS[order], channels, generator=g) - 1)
    chosen = torch.rand(height, width, generator=g) < 0.75
    blended = chosen & (torch.rand(height, width, generator=g) < 0.5)
    weight = torch.where(blended, torch.rand(height, width, generator=g), torch.ones(height, width))  # CPU: as g
    term = ResidualTerm(coefficients * chosen[..., None, None], chosen, weight)
    meta = maps.meta if encoding is None else {**maps.meta, MAP_NAME: {"encoding": encoding}}
    return Maps(maps.svbrdf, meta, {**maps.extra, MAP_NAME: term.to_map(), WEIGHT_MAP: weight})


def with_height(maps: Maps, seed: int = 0, softness_deg: float = 2.0, peak: float = 8.0) -> Maps:
    """``maps`` with a smooth relief as a fit with cast shadows writes it: ``height`` (pixels), a
    sum of four Gaussian bumps (one ``peak`` pixels high, the others lower, widths 3 to 6 pixels,
    seeded), ``indirect`` uniform in ``[0, 0.3]`` and ``svbrdf.json``'s ``height`` block with the
    penumbra ``softness_deg``."""
    height, width = maps.svbrdf.shape
    g = torch.Generator().manual_seed(seed)  # on the CPU: a seeded generator, the relief reproducible
    like = dict(dtype=torch.float64, device="cpu")  # as the generator
    rows, cols = torch.meshgrid(torch.arange(height, **like), torch.arange(width, **like), indexing="ij")
    relief = torch.zeros(height, width, **like)
    for k in range(4):
        centre = torch.rand(2, generator=g, **like) * torch.tensor([height, width], **like)
        size = 3.0 + 3.0 * float(torch.rand(1, generator=g))
        top = peak * (1.0 if k == 0 else 0.3 + 0.5 * float(torch.rand(1, generator=g)))
        relief += top * torch.exp(-((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2) / (2.0 * size**2))
    share = 0.3 * torch.rand(height, width, generator=g)
    meta = {**maps.meta, "height": {"unit": "pixel", "pitch": 1.0, "depth": 1.0, "softness_deg": softness_deg}}
    return Maps(maps.svbrdf, meta, {**maps.extra, "height": relief.float(), "indirect": share})


def reference_srgb(
    svbrdf: SVBRDF,
    light,
    view=(0.0, 0.0, 1.0),
    *,
    exposure: float = 1.0,
    dtype: torch.dtype = torch.float64,
    kernel: Kernel | None = None,
    term: ResidualTerm | None = None,
    position=None,
    each_pixel: bool = False,
    shadows: tuple | None = None,
    footprint: int = 1,
) -> np.ndarray:
    """``(H, W, 3)`` uint8: :func:`torchspec.model.rendering.render_image` of ``svbrdf`` under a light
    centred at ``light (3,)`` of unit irradiance (a point, or ``kernel``), with the residual
    ``term`` applied as ``torchspec render`` applies it (:meth:`ResidualTerm.apply`), times ``exposure``,
    sRGB-encoded (clipped to ``[0, 1]``) and rounded to 8 bits as the page shows it (grey
    replicated to 3 channels). With ``position (3,)`` (image widths; ``light`` is then unused), a
    near light of unit irradiance at the image's centre, rendered as ``torchspec render`` renders
    it (:func:`torchspec.relight.render_near`: block by block) or, ``each_pixel``, at each pixel
    (:func:`render_each_pixel`). ``shadows``: ``(height, share, softness)``, the cast shadows of
    maps with a height (``(H, W)`` pixels), an indirect share (``(H, W)`` or ``None``) and the
    penumbra (radians), as :func:`torchspec.relight.shaded_render` adds them, the visibility at
    the pixels' centres (:func:`torchspec.model.visibility.frame_visibility`, ``footprint=1``, as
    the page takes it; ``footprint=2``: as ``torchspec render`` does)."""
    device = svbrdf.normal.device
    one = torch.ones(1, 1, dtype=dtype, device=device)
    view = torch.tensor(view, dtype=dtype, device=device)
    at = None if position is None else torch.tensor([position], dtype=dtype, device=device)
    centre = torch.tensor([light], dtype=dtype, device=device) if position is None else at / at.norm()
    lights = Lights(centre, kernel or Kernel("point"), one, one[0])
    seen = bounce = None
    if shadows is not None:
        height, share, softness = shadows
        seen = frame_visibility(height.to(device, dtype), lights, at, footprint=footprint, softness=softness)[..., None]
        if share is not None:
            bounce = indirect_light(svbrdf.to(dtype), share.to(device, dtype), lights, view, at)
    if position is None:
        value = render_image(svbrdf.to(dtype), lights, view)
        value = value if seen is None else value * seen
        value = value if term is None else term.apply(value, lights)
    elif each_pixel:
        if seen is not None:
            raise TorchspecError("reference_srgb: each_pixel takes no shadows.")
        value = render_each_pixel(svbrdf.to(dtype), lights, at, view, term=term)
    else:
        value = render_near(svbrdf.to(dtype), lights, at, view, term=term, seen=seen)
    value = value if bounce is None else value + bounce
    value = (value[:, :, 0] * exposure).clamp(0.0, 1.0)
    value = value.expand(*value.shape[:2], 3) if value.shape[-1] == 1 else value[..., :3]
    return torch.round(encode(value) * 255.0).to(torch.uint8).cpu().numpy()


def render_each_pixel(
    svbrdf: SVBRDF, lights: Lights, positions: torch.Tensor, view: torch.Tensor, *, term: ResidualTerm | None = None
) -> torch.Tensor:
    """``(H, W, K, C)``: :func:`torchspec.relight.render_near` with every pixel under the lights as
    seen from its own centre (not its block's): by brute force, a chunk of ``n`` pixels rendered
    under the ``n K`` lights of its pixels and each pixel's own ``K`` kept (``n`` times the work)."""
    height, width = svbrdf.shape
    flat, k = svbrdf.flatten(), positions.shape[0]
    positions = positions.to(svbrdf.normal)
    points = image_points(height, width, dtype=positions.dtype, device=positions.device)
    coefficients = None if term is None else term.coefficients.reshape(height * width, *term.coefficients.shape[-2:])
    parts, step = [], 64
    for first in range(0, height * width, step):  # chunks of pixels: a batched render each
        index = torch.arange(first, min(first + step, height * width), device=points.device)
        n = index.numel()
        directions, falloff = near_light(positions, points[index])  # (n, K, 3), (n, K)
        irradiance = (lights.irradiance.to(falloff)[None] * falloff[..., None]).reshape(n * k, -1)
        near = Lights(directions.reshape(n * k, 3), lights.kernel, irradiance, lights.exposure.to(falloff).repeat(n))
        values = render(flat[index], near, view)  # (n, n K, C)
        if term is not None:
            weight = None if term.weight is None else term.weight.reshape(-1)[index]
            part = ResidualTerm(coefficients[index], term.chosen.reshape(-1)[index], weight=weight, domain=term.domain)
            values = part.apply(values, near)
        own = torch.arange(n, device=values.device)
        parts.append(values.reshape(n, n, k, -1)[own, own])  # each pixel's own lights
    return torch.cat(parts).reshape(height, width, k, -1)


def hemisphere_lights(count: int = 20, max_zenith_deg: float = 80.0) -> np.ndarray:
    """``(count, 3)`` unit directions spread over the hemisphere (a Fibonacci spiral in the
    l-plane, out to ``max_zenith_deg`` from the zenith: :func:`torchspec.model.geometry.spiral_plane`)."""
    plane = spiral_plane(count, math.sin(math.radians(max_zenith_deg)))  # CPU on purpose: returned as numpy
    return from_plane(plane).numpy()


def lobe_width(svbrdf: SVBRDF, view=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``(H, W)``: the full width at half maximum, in the l-plane and along its narrowest axis, of
    the narrower of each pixel's lobes (Ward's, linearised about the mirror direction:
    :func:`torchspec.model.lobe.lobe_moments`); ``inf`` where a pixel has no lobe."""
    flat = svbrdf.to(torch.float64).flatten()
    view = torch.tensor(view, dtype=torch.float64, device=flat.normal.device)
    width = torch.full(flat.shape, math.inf, dtype=torch.float64, device=flat.normal.device)
    for lobe in (flat, flat.second()):
        if lobe is None:
            continue
        _, (xx, xy, yy) = lobe_moments(lobe_frame(lobe, view))
        smallest = 0.5 * (xx + yy) - torch.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)
        fwhm = math.sqrt(8.0 * math.log(2.0)) * smallest.clamp(min=0.0).sqrt().reshape(-1)
        has = (lobe.specular.amax(-1) > 0) & (lobe.roughness.amin(-1) > 0)
        width = torch.where(has, torch.minimum(width, fwhm), width)
    return width.reshape(svbrdf.shape).cpu().numpy()
