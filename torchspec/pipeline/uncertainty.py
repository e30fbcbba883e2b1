"""The uncertainty stage: the sensor's noise from a tile's first fits (:func:`sensor_noise`), then
per fit its chi-square, the standard deviations of its parameters and the per-sample residuals the
peak checks take (:func:`uncertainty`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..lm import DIVERGED
from ..model.brdf import SVBRDF
from ..model.forward_terms import forward_sandwich_terms
from ..model.geometry import normal_derivative
from ..model.least_squares import sandwich_terms
from ..model.lights import Lights
from ..model.noise import affine_noise
from ..model.quadrature import Quadrature
from ..model.registry import Model, get_model
from .solver import Solved, compiled_or_eager

__all__ = ["NOISE_PIXELS", "PeakSamples", "Uncertainty", "sensor_noise", "uncertainty"]

NOISE_PIXELS = 64
"""The fewest pixels without a lobe that set the sensor's noise on their own (:func:`sensor_noise`)."""


@dataclass(frozen=True)
class PeakSamples:
    """What the peak checks (:func:`torchspec.pipeline.flags.peak_checks`) take of a fit of ``m`` pixels.

    Attributes:
        z2: ``(m, K)`` the squared residual in noise units, summed over channels.
        excess: ``(m, K)`` the samples less the fitted diffuse part (mean over channels).
        lobe_snr: ``(m,)`` the norm of the lobe's part of the values in noise units.
    """

    z2: Tensor
    excess: Tensor
    lobe_snr: Tensor


@dataclass(frozen=True)
class Uncertainty:
    """A fit's chi-square ``(m,)``, its parameters' standard deviations (keys ``normal (m,)``, the
    angle in radians, ``diffuse (m, C)``, ``specular (m, C_s)``, ``roughness (m, 2)``,
    ``specular2 (m, 1)``, ``roughness2 (m, 2)``; NaN for a parameter the model lacks, ``inf`` where
    the data leave it undetermined; empty for no pixel) and its :class:`PeakSamples`."""

    chi2: Tensor
    std: dict[str, Tensor]
    peak: PeakSamples


def sensor_noise(
    first: list[Solved], peaked: Tensor, observed: Tensor, valid: Tensor, level: Tensor, channels: int
) -> tuple[Tensor, Tensor]:
    """The sensor's ``(a, b)`` (:func:`torchspec.model.noise.affine_noise`) from the first fitted models'
    costs ``0.5 sum (r / level)^2`` over each pixel's valid samples (diverged fits left out).

    The pixels without a peak (``peaked (n,)`` false), fitted without a lobe, are used when there
    are ``NOISE_PIXELS`` of them: an unweighted fit of a lobe absorbs more than its share of the
    noise at the peak, where the shot noise is largest (its samples' leverage), so its residual
    understates the noise; a lobe forced away (``model: diffuse``) leaves a misfit. So the noise,
    and the criterion with it, is the same whichever model is fitted or forced.

    Args:
        first: the tile's first fits; ``observed (n, K, C)``, ``valid (n, K)`` and ``level (n,)``
            the tile's samples, validity and levels; ``channels``: ``C``.
    """
    parts = []
    for solved in first:
        keep = solved.result.status != DIVERGED
        index = solved.index[keep]
        parts.append((solved.name, index, solved.result.cost[keep], ~peaked[index]))
    plain = [(name, at[m], cost[m]) for name, at, cost, m in parts if get_model(name).lobe is None]
    if sum(at.numel() for _, at, _ in plain) < NOISE_PIXELS:
        plain = [(name, at, cost) for name, at, cost, _ in parts]
    squares, values, counts, params = [], [], [], []
    for name, at, cost in plain:
        squares.append(2.0 * cost * level[at] ** 2)
        values.append((observed[at].clamp(min=0.0) * valid[at, :, None]).sum((1, 2)))
        counts.append(valid[at].sum(-1) * channels)
        params.append(torch.full_like(squares[-1], get_model(name).size(channels)))
    return affine_noise(torch.cat(squares), torch.cat(values), torch.cat(counts), torch.cat(params))


def uncertainty(
    model: Model,
    svbrdf: SVBRDF,
    observed: Tensor,
    weight: Tensor,
    fit_weight: Tensor,
    lights: Lights,
    view: Tensor,
    *,
    quadrature: Quadrature,
) -> Uncertainty:
    """The fit's ``chi^2 = sum ((render - observed) weight)^2`` per pixel, ``weight (m, K, C)``
    being one over each sample's noise, the standard deviations of its parameters there and its
    :class:`PeakSamples`.

    The estimate minimised ``|fit_weight (render - observed)|^2``, not the noise-weighted residual
    (it is fitted before the noise is known): its covariance is the sandwich ``A^-1 B A^-1``
    (:func:`torchspec.model.least_squares.sandwich_terms`; for a lobe without closed forms
    :func:`torchspec.model.forward_terms.forward_sandwich_terms`), larger than the inverse Fisher information
    ``J^T S^-1 J`` (the Cramer-Rao bound) wherever the samples' noise differs within a pixel (shot
    noise at a specular peak).

    Args:
        model: the fitted model; svbrdf: its solution ``(m,)``; observed: ``(m, K, C)``.
        quadrature: of the model's evaluation (:attr:`FitConfig.rule`), compiled when it says so.
    """
    n, c = svbrdf.diffuse.shape
    select = model.selection(c, weight)
    if n == 0:
        empty = weight.new_zeros(0, weight.shape[1])
        return Uncertainty(weight.new_zeros(0), {}, PeakSamples(empty, empty, weight.new_zeros(0)))

    def run(fused: bool):
        if model.lobe is not None and not model.lobe.analytic:  # no closed forms: the forward-mode Jacobian
            return forward_sandwich_terms(
                model, svbrdf, lights, view, observed, weight, fit_weight, quadrature=quadrature, samples=True
            )
        return sandwich_terms(
            svbrdf,
            lights,
            view,
            observed,
            weight,
            fit_weight,
            select,
            quadrature=replace(quadrature, compile=fused),
            diffuse_only=model.lobe is None,
            samples=True,
        )

    cost, bread, meat, z2, excess, lobe_snr = compiled_or_eager(run, quadrature.compile)
    return Uncertainty(2.0 * cost, _deviations(model, svbrdf, bread, meat, weight), PeakSamples(z2, excess, lobe_snr))


def _deviations(model: Model, svbrdf: SVBRDF, bread: Tensor, meat: Tensor, weight: Tensor) -> dict[str, Tensor]:
    """The standard deviations of :class:`Uncertainty` from the sandwich's terms ``(m, P, P)``
    (NaN parameters in ``weight``'s dtype and device)."""
    n, c = svbrdf.diffuse.shape
    like = dict(dtype=weight.dtype, device=weight.device)
    outer, info = torch.linalg.inv_ex(bread)
    inverse = outer @ meat @ outer
    variance = inverse.diagonal(dim1=-2, dim2=-1)
    solvable = (info == 0)[:, None] & (variance >= 0) & variance.isfinite()
    std = torch.where(solvable, variance.clamp(min=0.0).sqrt(), torch.full_like(variance, math.inf))
    # The normal's angle: the covariance of the two tilt angles mapped to n (its trace, n being unit).
    dn = normal_derivative(svbrdf.normal)
    block = inverse[:, :2, :2]
    cov_angles = torch.where((info == 0)[:, None, None], block, torch.full_like(block, math.inf))
    normal = torch.einsum("nij,njk,nik->n", dn, cov_angles, dn).clamp(min=0.0).sqrt()
    fields = model.fields(std, c, normal=False)  # the deviations of the fields the model fills
    out = {"normal": normal, "diffuse": fields["diffuse"]}
    for name, width in (("specular", 1), ("roughness", 2), ("specular2", 1), ("roughness2", 2)):
        out[name] = fields[name] if name in fields else torch.full((n, width), math.nan, **like)
    return out
