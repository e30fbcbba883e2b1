"""The specular stage: from what the diffuse fit leaves over, a starting point for the full fit.

Per pixel, the residual ``r_k = y_k - k_d / pi <n, d_k>`` (mean over channels) is the specular
lobe blurred by the light kernel, sampled at the frames' l-plane positions ``l_k``. Its peak sits
where the lobe's mirror direction points, ``w_peak``, and the normal is the half vector
``n = normalize(w_peak + view)``. Three ways to find it, one per function:

- :func:`locate_peak`: finite-rate-of-innovation location (:func:`torchspec.start.fri.locate`) of the
  blurred peak, in 2D for a planar layout and along the line for a line of lights (the other
  coordinate then comes from the photometric-stereo normal). Exact for any symmetric blur.
- :func:`grid_search`: a dense search over peak positions and widths of a Gaussian surrogate
  of the blurred lobe, ``k_s`` solved in closed form at every node: the brute-force baseline.
- :func:`naive_start`: the photometric-stereo normal and a fixed roughness.

``k_s`` and ``alpha`` come from the residual's energy and spread: near the mirror direction the
Ward lobe is a Gaussian in the l-plane of variance ``2 alpha^2 (n.v)^2``-ish that integrates to
``k_s``, and the light kernel adds its own variance; so ``k_s ~ sum_k r_k A_k`` (``A_k`` the
l-plane area per sample) and ``alpha^2 ~ (var(r) - var(kernel)) / 2`` per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..model.geometry import from_plane, normalize
from ..model.layout import Layout, mirror_point
from . import fri

__all__ = ["LobeStart", "specular_residual", "locate_peak", "grid_search", "naive_start"]

ALPHA_RANGE = (0.005, 0.5)
"""Starting roughness is clamped into this range."""


def specular_residual(samples: Tensor, normal: Tensor, diffuse: Tensor, directions: Tensor) -> Tensor:
    """``r (N, K)``: the mean over channels of ``samples - k_d / pi <n, d_k>^+``.

    Args:
        samples: ``(N, K, C)`` divided by exposure and irradiance.
        normal, diffuse: ``(N, 3)``, ``(N, C)`` from photometric stereo.
        directions: ``(K, 3)`` effective diffuse directions.
    """
    shading = (normal @ directions.to(normal.dtype).T).clamp(min=0.0)
    return (samples - diffuse[:, None, :] / math.pi * shading[..., None]).mean(-1)


@dataclass(frozen=True)
class LobeStart:
    """A starting point of the specular fit for ``N`` pixels.

    Attributes:
        normal: ``(N, 3)`` the half vector of the peak.
        peak: ``(N, 2)`` the peak's position in the l-plane.
        specular: ``(N,)`` ``k_s`` from the residual's energy.
        alpha: ``(N,)`` isotropic roughness from its spread.
        quality: ``(N,)`` in ``[0, 1]``: the location's quality (1 for searches without one).
    """

    normal: Tensor
    peak: Tensor
    specular: Tensor
    alpha: Tensor
    quality: Tensor


def _half_vector(peak: Tensor, view: Tensor) -> Tensor:
    """``normalize(w + view)`` for the direction ``w`` at ``peak (N, 2)``, pulled inside the unit disk."""
    length = peak.norm(dim=-1, keepdim=True)
    peak = peak * ((1.0 - 1e-6) / length.clamp(min=torch.finfo(peak.dtype).tiny)).clamp(max=1.0)
    return normalize(from_plane(peak) + view.to(peak.dtype))


def _moments(residual: Tensor, layout: Layout, peak: Tensor, kernel_variance: float, window: float) -> tuple:
    """``k_s`` and ``alpha`` from the positive residual near the peak: its mass and second moment
    within a window grown from the sampling's own resolution to three of their standard
    deviations (at most ``window``): noise far from a narrow peak then never enters, and a broad
    peak widens the window at each pass."""
    offset = layout.l[None] - peak[:, None, :]  # (N, K, 2)
    d2 = offset.pow(2).sum(-1)
    if layout.dims == 1:
        d2 = (offset @ layout.axis).pow(2)
    tiny = torch.finfo(residual.dtype).tiny
    floor = (1.5 * layout.spacing) ** 2 + 9.0 * kernel_variance  # never narrower than the sampling
    reach = torch.full_like(residual[:, 0], min(floor, window**2))
    for _ in range(6):
        positive = residual.clamp(min=0.0) * (d2 <= reach[:, None]).to(residual.dtype)
        mass = (positive * layout.area).sum(-1)
        spread = (positive * layout.area * d2).sum(-1) / mass.clamp(min=tiny)  # E|l - peak|^2
        reach = (9.0 * spread).clamp(min=floor, max=window**2)
    variance = spread / layout.dims - kernel_variance  # per axis
    alpha = (variance.clamp(min=0.0) / 2.0).sqrt().clamp(*ALPHA_RANGE)
    if layout.dims == 1:  # a line through a 2D Gaussian of std s holds 1 / (sqrt(2 pi) s) of its mass
        mass = mass * math.sqrt(2.0 * math.pi) * (2.0 * alpha**2 + kernel_variance).sqrt()
    return mass.clamp(min=0.0), alpha


def locate_peak(
    residual: Tensor,
    layout: Layout,
    view: Tensor,
    *,
    prior_normal: Tensor,
    kernel_variance: float,
    method: str | None = None,
    num_coefficients: int | None = None,
    kernel: str | None = None,
) -> LobeStart:
    """FRI location of the specular peak and the start it gives.

    Args:
        residual: ``(N, K)`` from :func:`specular_residual`.
        layout: :func:`torchspec.model.layout.layout_of` the frames' positions.
        view: ``(3,)``.
        prior_normal: ``(N, 3)`` the photometric-stereo normal, for the coordinate a line of
            lights cannot see.
        kernel_variance: the light kernel's variance per axis in the l-plane.
        method, num_coefficients, kernel: for :func:`torchspec.start.fri.locate` (``kernel="pooled"``:
            one lobe spectrum pooled over the ``N`` pixels).

    Returns:
        :class:`LobeStart`.
    """
    start = layout.start.to(residual.dtype)
    if layout.grid is not None:
        # A (clipped) grid: the lattice's empty cells lie outside the lit disk, where the lobe has
        # died out, so they are zeros, and the samples are uniform: the periodised peak stays
        # symmetric about its centre however much of it aliases. Scattered least squares on the
        # disk alone would alias it asymmetrically.
        row, col, ny, nx = layout.grid.row, layout.grid.col, layout.grid.rows, layout.grid.columns
        image = residual.new_zeros((residual.shape[0], ny, nx))
        image[:, row, col] = residual
        found = fri.locate(
            image, period=layout.period[::-1], method=method, num_coefficients=num_coefficients, kernel=kernel
        )
        position = found.position.flip(-1)  # (y, x) -> (x, y)
        like = {"dtype": residual.dtype, "device": residual.device}
        spacing = torch.tensor([p / n for p, n in zip(layout.period, (nx, ny), strict=True)], **like)
        period = torch.tensor(layout.period, **like)
        # Positions past the last cell by more than half a cell belong before the first one.
        position = torch.where(position > period - 0.5 * spacing, position - period, position)
        peak = position + start
    else:
        coords = layout.coordinates().to(residual.dtype)
        period = layout.period if layout.dims == 2 else layout.period[0]
        positions = coords if layout.dims == 2 else coords[:, 0]
        if num_coefficients is None and layout.dims == 2:
            per_axis = max(1, round(math.sqrt(layout.l.shape[0])))
            num_coefficients = max(1, min((per_axis - 1) // 2 - 1, 4))
        found = fri.locate(
            residual,
            period=period,
            method=method,
            num_coefficients=num_coefficients,
            positions=positions,
            kernel=kernel,
        )
        if layout.dims == 2:
            peak = found.position + start
        else:  # along the line; across it, where the photometric-stereo normal mirrors the view
            seen = mirror_point(prior_normal, view)
            across = seen - ((seen - layout.origin) @ layout.axis)[:, None] * layout.axis
            peak = across + (found.position + start)[:, None] * layout.axis
    finite = torch.isfinite(peak).all(-1, keepdim=True)
    peak = torch.where(finite, peak, mirror_point(prior_normal, view))
    # A location far from every bright sample is an aliased one (too few samples for the lobe's
    # width on a scattered layout): fall back on the centroid around the brightest sample.
    spacing = layout.spacing
    brightest = layout.l.to(residual.dtype)[residual.argmax(-1)]  # (N, 2)
    near = layout.l[None] - brightest[:, None, :]
    near = (near.pow(2).sum(-1) if layout.dims == 2 else (near @ layout.axis).pow(2)) <= (1.5 * spacing) ** 2
    weight = residual.clamp(min=0.0) * near.to(residual.dtype)
    centroid = (weight[..., None] * layout.l[None]).sum(1) / weight.sum(1, keepdim=True).clamp(
        min=torch.finfo(residual.dtype).tiny
    )
    if layout.dims == 1:  # keep the line's crossing of the prior
        centroid = peak + ((centroid - peak) @ layout.axis)[:, None] * layout.axis
    astray = (peak - brightest).norm(dim=-1) > 1.5 * spacing
    peak = torch.where(astray[:, None], centroid, peak)
    quality = torch.where(astray, 0.25 * found.quality, found.quality)
    window = 3.0 * math.sqrt(2.0 * ALPHA_RANGE[1] ** 2 * 0.25 + kernel_variance)
    specular, alpha = _moments(residual, layout, peak, kernel_variance, window)
    # A lobe started narrower than the samples resolve has no gradient towards them; too wide is safe.
    alpha = alpha.clamp(min=layout.spacing / (2.0 * math.sqrt(2.0)))
    return LobeStart(_half_vector(peak, view), peak, specular, alpha, quality)


def grid_search(
    residual: Tensor,
    layout: Layout,
    view: Tensor,
    *,
    prior_normal: Tensor,
    kernel_variance: float,
    step: float = 0.01,
    radius: float = 0.3,
    alphas: int = 12,
) -> LobeStart:
    """Brute force: the best peak position (within ``radius`` of the photometric-stereo mirror
    point, every ``step``) and roughness (``alphas`` log-spaced values) of a Gaussian surrogate of
    the blurred lobe, ``r_k ~ k_s g(l_k; peak, 2 alpha^2 + kernel variance)``, with ``k_s`` by
    least squares at every node. Memory and time grow as ``(radius / step)^2 alphas K`` per pixel."""
    dtype = residual.dtype
    centre = mirror_point(prior_normal, view)
    ticks = torch.arange(-radius, radius + 0.5 * step, step, dtype=dtype, device=residual.device)
    if layout.dims == 2:
        offsets = torch.stack(torch.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2)
    else:
        offsets = ticks[:, None] * layout.axis.to(dtype)
    alpha = torch.logspace(
        math.log10(ALPHA_RANGE[0]), math.log10(ALPHA_RANGE[1]), alphas, dtype=dtype, device=residual.device
    )
    variance = 2.0 * alpha**2 + kernel_variance  # (A,)
    best = torch.full_like(residual[:, 0], math.inf)
    best_peak, best_alpha, best_ks = centre.clone(), torch.full_like(best, alpha[0]), torch.zeros_like(best)
    l = layout.l.to(dtype)
    for offset in offsets:  # the search nodes: a per-pixel batch at each
        peak = centre + offset
        d2 = (l[None] - peak[:, None, :]).pow(2).sum(-1)  # (N, K)
        if layout.dims == 1:
            d2 = ((l[None] - peak[:, None, :]) @ layout.axis.to(dtype)).pow(2)
        shape = torch.exp(-0.5 * d2[..., None] / variance) / (2.0 * math.pi * variance) ** (
            layout.dims / 2.0
        )  # (N, K, A)
        ks = ((shape * residual[..., None]).sum(1) / shape.pow(2).sum(1).clamp(min=torch.finfo(dtype).tiny)).clamp(
            min=0.0
        )
        cost = (residual[..., None] - ks[:, None, :] * shape).pow(2).sum(1)  # (N, A)
        value, index = cost.min(-1)
        better = value < best
        best = torch.where(better, value, best)
        best_peak = torch.where(better[:, None], peak, best_peak)
        best_alpha = torch.where(better, alpha[index], best_alpha)
        best_ks = torch.where(better, ks.gather(-1, index[:, None])[:, 0], best_ks)
    if layout.dims == 1:  # the surrogate's mass along the line -> the lobe's full mass
        best_ks = best_ks * (2.0 * math.pi * (2.0 * best_alpha**2 + kernel_variance)).sqrt()
    return LobeStart(_half_vector(best_peak, view), best_peak, best_ks, best_alpha, torch.ones_like(best))


def naive_start(
    residual: Tensor, layout: Layout, view: Tensor, *, prior_normal: Tensor, alpha: float = 0.1
) -> LobeStart:
    """The photometric-stereo normal, ``alpha`` and ``k_s`` from the residual's energy."""
    peak = mirror_point(prior_normal, view)
    mass = (residual.clamp(min=0.0) * layout.area).sum(-1)
    if layout.dims == 1:
        mass = mass * math.sqrt(2.0 * math.pi) * math.sqrt(2.0) * alpha
    return LobeStart(prior_normal, peak, mass, torch.full_like(mass, alpha), torch.ones_like(mass))
