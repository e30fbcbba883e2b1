"""The checks stage: each pixel's flags (:mod:`torchspec.pipeline.flags`), the peak checks behind two of
them (:class:`Checks`) and its quality.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..lm import CONVERGED, DIVERGED
from ..model.brdf import SVBRDF
from ..model.registry import get_model, render_chosen
from .flags import WEAK_LOBE_SNR, bit, peak_checks, untrusted
from .samples import TileSamples
from .selection import Choice
from .settings import MODEL_CODES, FitConfig

__all__ = ["Checks", "check_choice", "overshoot", "solver_flags", "quality_of", "with_flags"]


@dataclass(frozen=True)
class Checks:
    """The values behind the ``peak_misfit`` and ``astray`` flags, ``(n,)`` each
    (:func:`torchspec.pipeline.flags.peak_checks`; NaN where not computed: no lobe, a weak one, or no noise
    estimate)."""

    peak_misfit: Tensor
    astray: Tensor


def with_flags(flags: Tensor, *marks: tuple[str, Tensor]) -> Tensor:
    """``flags`` (int16) with bit ``name`` set where ``where`` holds, for each ``(name, where)``."""
    for name, where in marks:
        flags = flags | torch.where(where, bit(name), 0).to(torch.int16)
    return flags


def solver_flags(status: Tensor, few: Tensor) -> Tensor:
    """The flags a fit gets from its solver and its samples alone: ``diverged``, ``few_samples`` and
    ``not_converged``."""
    flags = torch.zeros(status.shape, dtype=torch.int16, device=status.device)
    return with_flags(
        flags,
        ("diverged", status == DIVERGED),
        ("few_samples", few),
        ("not_converged", (status != CONVERGED) & (status != DIVERGED)),
    )


def quality_of(base: Tensor, status: Tensor, flags: Tensor) -> Tensor:
    """A pixel's quality: ``base``, halved where the solver did not converge, 0 where untrusted."""
    quality = torch.where(status == CONVERGED, base, 0.5 * base)
    return torch.where(untrusted(flags), torch.zeros_like(quality), quality)


def check_choice(choice: Choice, data: TileSamples, few: Tensor, config: FitConfig) -> tuple[Tensor, Checks]:
    """The flags ``(n,)`` int16 and :class:`Checks` of a tile's chosen fits; ``few (n,)``: the pixels
    with fewer than 3 valid samples. Without a noise estimate, the solver's flags only."""
    like = choice.criterion
    peak_misfit, astray = like.new_full(like.shape, math.nan), like.new_full(like.shape, math.nan)
    flags = solver_flags(choice.status, few)
    if not config.noise_known:  # the checks need the sensor's noise
        return flags, Checks(peak_misfit, astray)
    lobed = torch.tensor([get_model(name).lobe is not None for name in MODEL_CODES], device=like.device)
    lobed = lobed[choice.code.long()]
    weak = lobed & (choice.peak.lobe_snr < WEAK_LOBE_SNR)
    flags = with_flags(flags, ("weak_lobe", weak))
    index = (lobed & ~few & ~weak).nonzero()[:, 0]
    if index.numel():
        peak_misfit[index], astray[index] = peak_checks(
            choice.svbrdf[index],
            choice.peak.z2[index],
            choice.peak.excess[index],
            data.valid[index],
            data.lights,
            data.view,
            reach=config.flags.reach,
        )
    flags = with_flags(
        flags,
        ("undetermined", ~choice.deviation["normal"].isfinite() & ~few & ~weak),
        ("peak_misfit", peak_misfit > config.flags.peak_misfit),
        ("astray", astray > config.flags.astray),
        ("misfit", choice.misfit),
        ("poor_fit", ~lobed & choice.misfit & (data.relative_rms(choice.cost) > config.flags.trust_rms)),
    )
    return flags, Checks(peak_misfit, astray)


def overshoot(svbrdf: SVBRDF, y: Tensor, data: TileSamples, config: FitConfig, code: Tensor | None = None) -> Tensor:
    """``(n,)``: the brightest value the fitted maps ``svbrdf`` render at the tile's frames (the
    physical model, at every frame the fit read: its clipped and masked samples too) over the
    brightest value the pixel recorded, ``y (n, K, C)`` (any finite sample: a clipped one shows its
    clipping level), floored at 1 % of a white Lambertian surface's value under the brightest light
    (a dark pixel's ratio means nothing).

    Near 1 where the model explains the photographs. Far above (``FitConfig.flags.overshoot``: the
    ``implausible`` flag) where a lobe grew without bound on samples the fit did not use: a clipped
    highlight (censored, so any height above the clipping level fits it), a masked frame.

    ``code (n,)``: each pixel's model (:class:`~torchspec.pipeline.selection.Choice`), rendered with
    its lobe (:func:`torchspec.model.registry.render_chosen`); ``None``: Ward's lobe for all."""
    rule = replace(config.rule, compile=False)  # one forward render: not worth compiling
    predicted = render_chosen(svbrdf, code, data.lights, data.view, quadrature=rule).amax((1, 2))
    recorded = torch.where(y.isfinite(), y, torch.zeros_like(y)).amax((1, 2))
    floor = 0.01 * data.scale.amax() / math.pi
    return predicted / torch.maximum(recorded, floor)
