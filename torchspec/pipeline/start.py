"""The stages before the solver, per batch of ``n`` pixels: robust photometric stereo (normal and
``k_d``), the lobe test (a residual peak above the noise) and the specular start of
``FitConfig.start.init`` (:mod:`torchspec.start.specular`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..model.brdf import SVBRDF
from ..model.layout import Layout, kernel_variance, layout_of
from ..model.lights import Lights, diffuse_directions
from ..start.photometric import Diffuse, photometric_stereo
from ..start.specular import LobeStart, grid_search, locate_peak, naive_start, specular_residual
from .settings import FitConfig

__all__ = ["LightContext", "StartingPoint", "light_context", "starting_point"]


@dataclass(frozen=True)
class LightContext:
    """What the stages need of a fit's lights, computed once per fit (:func:`light_context`).

    Attributes:
        directions: ``(K, 3)`` the directions photometric stereo takes (the kernels' effective
            diffuse directions; the centres for point lights).
        layout: the l-plane layout of the frames' centres.
        kernel_variance: the kernel's per-axis variance at the first frame (0 for point lights).
    """

    directions: Tensor
    layout: Layout
    kernel_variance: float


def light_context(lights: Lights) -> LightContext:
    """The :class:`LightContext` of ``lights``."""
    point = lights.kernel.kind == "point"
    return LightContext(
        directions=lights.directions if point else diffuse_directions(lights),
        layout=layout_of(lights.directions[:, :2]),
        kernel_variance=kernel_variance(lights, frames="first"),
    )


@dataclass(frozen=True)
class StartingPoint:
    """What the stages before the solver give a batch of ``n`` pixels (:func:`starting_point`).

    Attributes:
        diffuse: the photometric-stereo fit (:class:`torchspec.start.photometric.Diffuse`).
        specular: the specular start (:class:`torchspec.start.specular.LobeStart`).
        lobe: ``(n,)`` bool, the pixels whose residual peaks above the noise: fitted with a lobe.
        level: ``(n,)`` the pixels' mean value (divided by exposure and irradiance).
        times: seconds per stage (``photometric``, ``specular_start``).
    """

    diffuse: Diffuse
    specular: LobeStart
    lobe: Tensor
    level: Tensor
    times: dict

    def svbrdf(self, channels: tuple[str, ...]) -> SVBRDF:
        """The solver's starting point for a lobe, ``(n,)`` pixels: the peak's normal, the
        photometric ``k_d``, a grey ``k_s`` (at least 1e-3 of the pixel's level, so the solver's
        softplus starts off its flat end) and an isotropic ``alpha``."""
        peak = self.specular
        ks = peak.specular.clamp(min=1e-3 * self.level)[:, None]
        return SVBRDF(peak.normal, self.diffuse.diffuse, ks, peak.alpha[:, None].expand(-1, 2), None, channels)


def starting_point(
    y: Tensor, valid: Tensor, lights: Lights, view: Tensor, *, config: FitConfig, context: LightContext | None = None
) -> StartingPoint:
    """The fit's stages before the solver, for ``n`` pixels: photometric stereo, the lobe test and
    the specular start of ``config.start.init`` (``naive`` for ``model: diffuse``, whose pixels get no lobe).

    Args:
        y: ``(n, K, C)`` recorded values.
        valid: ``(n, K)`` samples to use.
        lights, view: the frames' lights and the view ``(3,)``.
        config: the fit's settings.
        context: :func:`light_context` of ``lights`` when the caller has it.
    """
    ctx = context if context is not None else light_context(lights)
    samples = y / lights.scale.to(y.dtype)
    times = {}
    t0 = time.perf_counter()
    ps = photometric_stereo(samples, ctx.directions, valid=valid, cut=config.start.cut, trim=config.start.trim)
    times["photometric"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    clean = torch.where(valid[..., None], samples, torch.zeros_like(samples))
    count = valid.sum(-1).clamp(min=1).to(y.dtype)
    level = clean.mean(-1).sum(-1) / count  # mean value per pixel
    residual = specular_residual(clean, ps.normal, ps.diffuse, ctx.directions)
    residual = torch.where(valid, residual, torch.zeros_like(residual))
    noise = torch.maximum(ps.noise, config.start.noise_floor * level)
    lobe = residual.amax(-1) > config.start.detect * noise
    prior = dict(prior_normal=ps.normal, kernel_variance=ctx.kernel_variance)
    # A fit without lobes uses no specular start: the cheapest, which needs no layout for a peak.
    init = config.start.init if config.lobes else "naive"
    if init == "fri":
        found = locate_peak(
            residual,
            ctx.layout,
            view,
            method=config.start.fri_method,
            num_coefficients=config.start.fri_coefficients,
            kernel="pooled" if config.start.fri_kernel == "pooled" else None,
            **prior,
        )
    elif init == "grid":
        found = grid_search(residual, ctx.layout, view, **prior)
    else:
        found = naive_start(residual, ctx.layout, view, prior_normal=ps.normal, alpha=config.start.naive_alpha)
    times["specular_start"] = time.perf_counter() - t0
    return StartingPoint(diffuse=ps, specular=found, lobe=lobe, level=level, times=times)
