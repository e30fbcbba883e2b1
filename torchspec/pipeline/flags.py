"""Per-pixel flags: which fitted pixels not to trust, and why.

A fit's residual and deviations describe a pixel whose model is right; they do not say when the
estimate is wrong altogether (a peak placed far from the truth). Two checks against the samples
around the fitted peak tell (``experiments/stability.py`` compares them with the solver's status
and the photometric-stereo quality):

- ``peak_misfit``: the mean square of the residual, in units of each sample's noise, over the
  frames whose light lies within ``reach`` blurred widths of the fitted peak (the lobe's l-plane
  spread ``alpha_x^2 + alpha_y^2`` and the kernel's variance). Noise alone gives ~1; a second
  lobe merged with the first, or a peak caught beside the lobe, leaves more. A misfit *beyond*
  the peak (a resolved second lobe, the model's tails) does not move the peak and is not counted.
- ``astray``: the distance from the fitted peak to the light of the brightest specular sample (the
  samples less the fitted diffuse part), in blurred widths (at least the lights' spacing): a fit
  caught in a local minimum away from the lobe, or a peak placed outside the lights' range.

Both need a lobe: a pixel whose fitted lobe adds less than :data:`WEAK_LOBE_SNR` to its values
(the norm of the lobe's part in units of the noise: a peak detected in the noise of a matte pixel
and fitted with ``k_s ~ 0``, or a lobe drowned in the noise) is flagged ``weak_lobe`` instead, and
not checked: its lobe's peak and width mean nothing, its normal and ``k_d`` are the diffuse part's.

:data:`FLAGS` lists the bits of a pixel's ``flags``; those in :data:`UNTRUSTED` mean "do not use
this pixel's lobe or normal" (its ``quality`` is then 0), the others are information.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..model.brdf import SVBRDF
from ..model.layout import kernel_variance, light_spacing, mirror_point
from ..model.least_squares import sandwich_terms
from ..model.lights import Lights
from ..model.quadrature import Quadrature

__all__ = [
    "FLAGS",
    "UNTRUSTED",
    "WEAK_LOBE_SNR",
    "bit",
    "untrusted",
    "describe",
    "peak_checks",
    "residual_samples",
]

FLAGS = (
    "diverged",  # the solver diverged
    "few_samples",  # fewer than 3 valid samples
    "undetermined",  # the normal's standard deviation is infinite: the data leave it undetermined
    "peak_misfit",  # the samples around the fitted peak are not explained (peak_checks)
    "astray",  # the fitted peak lies far from the brightest specular sample (peak_checks)
    "not_converged",  # the solver stopped at its iteration limit
    "misfit",  # the chosen model leaves a residual above the noise (chi^2 test)
    "weak_lobe",  # the lobe's part of the values is below WEAK_LOBE_SNR noise units: no lobe established
    "poor_fit",  # the chosen model leaves a misfit far above the noise: no model of the ladder explains the pixel
    "implausible",  # the maps render far above anything the pixel's photographs recorded (FitConfig.flags.overshoot)
)
"""The bits of ``flags``: bit ``i`` is ``1 << i`` for ``FLAGS[i]``."""

WEAK_LOBE_SNR = 4.0
"""A lobe whose part of a pixel's values has a norm below this many noise standard deviations is
``weak_lobe`` (a lobe fitted to pure noise reaches ~2-3: its three parameters absorb that much)."""

UNTRUSTED = ("diverged", "few_samples", "undetermined", "peak_misfit", "astray", "poor_fit", "implausible")
"""The flags that mark a pixel's estimate as unusable (``quality`` 0)."""


def bit(name: str) -> int:
    """The bit of flag ``name``."""
    if name not in FLAGS:
        raise TorchspecError(f"unknown flag {name!r}; the flags are {FLAGS}.")
    return 1 << FLAGS.index(name)


def untrusted(flags: Tensor) -> Tensor:
    """Bool, same shape: the pixels with any flag of :data:`UNTRUSTED`."""
    mask = sum(bit(name) for name in UNTRUSTED)
    return (flags.to(torch.int32) & mask) != 0


def describe(flags: Tensor) -> dict[str, int]:
    """The number of pixels carrying each flag."""
    values = flags.to(torch.int32)
    return {name: int(((values & bit(name)) != 0).sum()) for name in FLAGS}


def residual_samples(
    svbrdf: SVBRDF,
    observed: Tensor,
    inverse_noise: Tensor,
    lights: Lights,
    view: Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
) -> tuple[Tensor, Tensor, Tensor]:
    """What :func:`peak_checks` takes, per sample ``(n, K)``: the squared residual in units of the
    noise summed over channels, and the samples less the fitted diffuse part (mean over channels);
    and the lobe's signal-to-noise ratio ``(n,)`` (``weak_lobe`` below :data:`WEAK_LOBE_SNR`).
    A fit has them from its deviations' pass (:func:`torchspec.model.least_squares.sandwich_terms`); this
    computes them alone.

    Args:
        svbrdf: the fitted maps ``(n,)``; observed: ``(n, K, C)``; inverse_noise: ``(n, K, C)`` one
            over each sample's noise, 0 for invalid samples.
        quadrature: the model's evaluation (:class:`torchspec.model.quadrature.Quadrature`).
    """
    c = svbrdf.diffuse.shape[-1]
    size = 5 + c + svbrdf.specular.shape[-1]
    select = torch.eye(size, dtype=observed.dtype, device=observed.device)
    out = sandwich_terms(
        svbrdf, lights, view, observed, inverse_noise, inverse_noise, select, quadrature=quadrature, samples=True
    )
    return out[3], out[4], out[5]


def peak_checks(
    svbrdf: SVBRDF,
    z2: Tensor,
    excess: Tensor,
    valid: Tensor,
    lights: Lights,
    view: Tensor,
    *,
    reach: float = 1.5,
) -> tuple[Tensor, Tensor]:
    """The ``peak_misfit`` and ``astray`` checks (module docstring) of ``n`` fitted pixels.

    Args:
        svbrdf: the fitted maps ``(n,)`` (with a lobe: ``k_s > 0``).
        z2, excess: ``(n, K)`` from :func:`residual_samples` (or the fit's deviations pass).
        valid: ``(n, K)`` the samples used.
        lights, view: as for :func:`torchspec.model.rendering.render`.
        reach: the frames within ``reach`` blurred widths of the peak are its neighbourhood.

    Returns:
        ``(peak_misfit (n,), astray (n,))``: the mean squared noise-normalised residual near the
        peak (0 where no valid sample is near it), and the peak's distance to the brightest
        specular sample in blurred widths (at least the lights' spacing; NaN where no sample is
        valid).
    """
    like = dict(dtype=z2.dtype, device=z2.device)
    centres = lights.directions[:, :2].to(**like) + lights.kernel.offset(z2)
    kernel = kernel_variance(lights, frames="all")
    spacing = float(light_spacing(centres))
    c = svbrdf.diffuse.shape[-1]
    peak = mirror_point(svbrdf.normal.to(**like), view.to(**like))
    width = (svbrdf.roughness.to(**like).pow(2).sum(-1) + kernel).sqrt()
    near = (torch.cdist(peak, centres) < reach * width[:, None]) & valid
    local = (z2 / c * near).sum(-1) / near.sum(-1).clamp(min=1)
    bright = torch.where(valid, excess, torch.full_like(excess, -math.inf))
    brightest = centres[bright.argmax(-1)]
    unit = width.clamp(min=spacing) if math.isfinite(spacing) else width
    astray = (brightest - peak).norm(dim=-1) / unit
    return local, torch.where(valid.any(-1), astray, torch.full_like(astray, math.nan))
