"""The per-tile engine: every stage of the fit on one tile of pixels (:func:`fit_pixels`), as
every driver runs it (:func:`fit_tile`: in-process and on a cluster), giving a :class:`TileResult`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path

import torch
from torch import Tensor

from ..model.lights import Lights
from ..model.registry import get_model, render_chosen
from ..model.residual_term import ResidualTerm, TermDomain, blend, fit_term
from ..start.photometric import Masks
from ..threads import fit_threads
from .checkpoint import save_tile
from .checks import check_choice, overshoot, quality_of, with_flags
from .prediction import held_out_refit, light_folds
from .records import PlainFit, TileResult  # re-exported: the records live in records
from .samples import TileSamples
from .selection import select_models
from .settings import MODEL_CODES, FitConfig
from .smoothing import plain_alternative
from .start import LightContext, starting_point

__all__ = [
    "EXPLAINED",
    "MASK_KINDS",
    "TERM_REFIT",
    "VISIBLE",
    "FitInputs",
    "TileInputs",
    "TilePixels",
    "TileResult",
    "fit_pixels",
    "fit_tile",
    "seen_through",
]

MASK_KINDS = tuple(f.name for f in fields(Masks))
"""The masks of :class:`torchspec.start.photometric.Masks` that :func:`fit_tile` takes and counts."""
TERM_REFIT = 2
"""Solver steps of each fold's refit that judges the residual term (:func:`held_out_values`). The
refits were most of the term's time; on ``experiments/rti_relight.py``'s captures (4 x 4 reduced)
2 steps predicted the left-out photographs as 5 did (item3 30.62 against 30.60 dB, item7 32.94 and
32.94, item9 25.11 and 25.12, SynthRTI m1 52.09 and 52.09, m8 38.90 and 38.87), in 0.6 of the time
on item3 (2.5 s against 4.2 s)."""


@dataclass(frozen=True)
class TilePixels:
    """The ``n`` pixels of a tile as the stages take them (:func:`fit_pixels`).

    Attributes:
        y: ``(n, K, C)`` the recorded values.
        valid: ``(n, K)`` bool, the samples the fit uses.
        kept: ``(n, K)`` bool, the samples the residual term (``FitConfig.term.order``) is
            fitted on: the fit's masks leave out shadowed samples, which the term is to carry.
        visibility: ``(n, K)`` the lights' fixed visibility (cast shadows), else ``None``: ``y``
            then holds the recorded values over it (:func:`seen_through`), and the stages fit the
            maps without shadows to them, each sample's weight times its visibility
            (:class:`~torchspec.pipeline.samples.TileSamples`).
        recorded: ``(n, K, C)`` with a visibility, the recorded values themselves: the residual
            term is fitted on them against the maps' rendering times the visibility, the hidden
            samples too (:func:`residual_term`); else ``None`` (``y`` holds them).
    """

    y: Tensor
    valid: Tensor
    kept: Tensor
    visibility: Tensor | None = None
    recorded: Tensor | None = None

    @classmethod
    def of(cls, tile: TileInputs) -> TilePixels:
        """``tile``'s pixels, its samples of every kind of :data:`MASK_KINDS` left out of ``valid``,
        the non-finite ones of ``kept``."""
        masks = tile.masks
        y = tile.values.permute(2, 0, 1)  # (n, K, C)
        if tile.visibility is None:
            return cls(y=y, valid=~masks.invalid.T, kept=~masks.nonfinite.T)
        seen = tile.visibility.T.to(y)  # (n, K)
        over, valid, kept = seen_through(y, masks, seen)
        return cls(y=over, valid=valid, kept=kept, visibility=seen, recorded=y)


def fit_pixels(pixels: TilePixels, lights: Lights, ctx: LightContext, shared: FitInputs) -> TileResult:
    """All stages for ``n`` ``pixels`` under ``lights`` (``ctx``: their
    :class:`~torchspec.pipeline.start.LightContext`), with what every tile of the fit shares:
    ``shared.gains (K, C)``, the lights' calibrated gains (in ``lights``), which the residual term
    leaves out (:func:`residual_term`), fitted in ``shared.domain`` (the photographs' encoding)
    on the samples ``pixels.kept``. ``shared.folder`` is :func:`fit_tile`'s (not used here).

    The stages: :func:`~torchspec.pipeline.start.starting_point`, then
    :func:`~torchspec.pipeline.selection.select_models`, then
    :func:`~torchspec.pipeline.checks.check_choice`, and with ``FitConfig.ladder.smooth`` the fits without a
    lobe (:func:`~torchspec.pipeline.smoothing.plain_alternative`)."""
    y, valid, view, config = pixels.y, pixels.valid, shared.view, shared.config
    begun = starting_point(y, valid, lights, view, config=config, context=ctx)
    times = dict(begun.times)
    lobe = begun.lobe if config.lobes else torch.zeros_like(begun.lobe)
    data = TileSamples.of(y, valid, begun.level, lights, view, shared.channels, visibility=pixels.visibility)
    t0 = time.perf_counter()
    choice, sensor, found_quality = select_models(begun, lobe, data, config)
    times["lm"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    few = valid.sum(-1) < 3
    flags, checks = check_choice(choice, data, few, config)
    implausible = overshoot(choice.svbrdf, y, data, config, choice.code) > config.flags.overshoot
    flags = with_flags(flags, ("implausible", implausible))
    times["checks"] = time.perf_counter() - t0

    term = None
    if config.term.order:
        t0 = time.perf_counter()
        term = residual_term(choice, sensor, pixels, data, shared)
        times["residual_term"] = time.perf_counter() - t0
    rms = data.relative_rms(choice.cost)
    quality = quality_of(begun.diffuse.quality * found_quality, choice.status, flags)
    plain = None
    if config.ladder.smooth > 0:  # the alternative of each lobed pixel, for the image's choice (smoothing)
        chosen = PlainFit(
            normal=choice.svbrdf.normal.clone(),
            diffuse=choice.svbrdf.diffuse.clone(),
            criterion=choice.criterion,
            status=choice.status.clone(),
            iterations=choice.iterations.clone(),
            residual=rms.clone(),
            quality=quality.clone(),
            flags=flags.clone(),
            std_normal=choice.deviation["normal"].clone(),
            std_diffuse=choice.deviation["diffuse"].clone(),
        )
        plain = plain_alternative(begun, chosen, choice.code, sensor, few, data, config, choice.tried)
    return TileResult(
        svbrdf=choice.svbrdf,
        flags=flags,
        checks=checks,
        residual=torch.nan_to_num(rms, nan=math.inf),
        quality=quality,
        status=choice.status,
        iterations=choice.iterations,
        lobe=choice.code > 0,
        model=choice.code,
        criterion=choice.criterion,
        std=choice.deviation,
        tried=choice.tried,
        noise=sensor,
        times=times,
        plain=plain,
        term=term,
    )


def residual_term(choice, sensor: Tensor, pixels: TilePixels, data: TileSamples, shared: FitInputs) -> ResidualTerm:
    """The residual term (:func:`torchspec.model.residual_term.fit_term`) of a tile's chosen models
    (``choice``, :func:`~torchspec.pipeline.selection.select_models`) on the samples ``pixels.kept``
    of ``pixels.y``, judged on the folds of ``auto``'s choice.

    The term is fitted on two bases: the chosen model, judged by its prediction of each fold from
    a refit without it (:func:`~torchspec.pipeline.prediction.held_out_refit`), and nothing (the term
    alone, an HSH of the photographs); each pixel keeps the blend of the two that predicts the
    left-out frames best (:func:`torchspec.model.residual_term.blend`: the model's weight
    ``ResidualTerm.weight``; the maps are unchanged).

    With calibrated ``shared.gains (K, C)`` the term is fitted under the lights as written (the gains
    divided out of the model's prediction): it then carries how the photographs' brightness
    varies with the light's direction, which a render under lights as written (new or left-out
    ones, whose gain no photograph gave) needs. ``shared.domain``: the encoding it is fitted and
    judged in (:class:`torchspec.model.residual_term.TermDomain`; default sRGB)."""
    config, gains, domain = shared.config, shared.gains, shared.domain
    y = pixels.y if pixels.recorded is None else pixels.recorded
    kept = pixels.kept & y.isfinite().all(-1)
    values = torch.where(kept[..., None], y, torch.zeros_like(y))
    folds = light_folds(data.lights.directions, config.ladder.folds, config.ladder.fold_regions)
    model = render_chosen(choice.svbrdf, choice.code, data.lights, data.view, quadrature=config.rule)
    predicted = held_out_values(choice, model, sensor, folds, data, config)
    if pixels.visibility is not None:  # the prediction with its shadows
        seen = pixels.visibility.to(model)[..., None]  # (n, K, 1)
        model, predicted = model * seen, predicted * seen[:, None]
    lights = data.lights
    if gains is not None:  # the model under the lights as written
        gains = gains.to(model)
        model, predicted = model / gains, predicted / gains[None]
        lights = Lights(lights.directions, lights.kernel, lights.irradiance / gains, lights.exposure)
    order = config.term.order
    z = config.term.z
    with_model = fit_term(values, kept, model, lights, folds, order=order, z=z, held_out=predicted, domain=domain)
    alone = fit_term(values, kept, torch.zeros_like(model), lights, folds, order=order, z=z, domain=domain)
    blended = blend(with_model, alone, z)
    return ResidualTerm(
        coefficients=blended.coefficients, chosen=blended.chosen, weight=blended.weight, domain=blended.domain
    )


def held_out_values(
    choice, model: Tensor, sensor: Tensor, folds: Tensor, data: TileSamples, config: FitConfig
) -> Tensor:
    """``(n, S, K, C)`` each pixel's chosen model's prediction of each valid sample from a fit
    without its fold, refitted by :data:`TERM_REFIT` (or ``FitConfig.ladder.refit``) solver steps
    (:func:`~torchspec.pipeline.prediction.held_out_refit`: the one-step linear prediction of
    :func:`~torchspec.pipeline.prediction.held_out`, good enough to rank models, can be far off
    where a fold holds a lobe's peak, and the term would then give up a model that predicts well);
    ``model (n, K, C)``, the fit
    on every frame, at samples the fit did not use."""
    out = model[:, None].expand(-1, folds.shape[0], -1, -1).clone()
    for code, name in enumerate(MODEL_CODES):
        index = (choice.code == code).nonzero().squeeze(1)
        if index.numel() == 0:
            continue
        inverse = data.inverse_noise(sensor, index, config.start.noise_floor)  # (m, K, C)
        # held_out_refit's residuals: (render - observed) in noise units
        refit = replace(config, ladder=replace(config.ladder, refit=config.ladder.refit or TERM_REFIT))
        residual = held_out_refit(get_model(name), choice.svbrdf[index], index, data, inverse, folds, refit)
        valid = inverse[:, None] > 0
        fitted = data.observed[index, None] + residual / torch.where(valid, inverse[:, None], torch.ones_like(residual))
        out[index] = torch.where(valid, fitted, out[index])
    return out


@dataclass(frozen=True)
class FitInputs:
    """What every tile of one fit shares, built once by each driver (:func:`fit_tile`).

    Attributes:
        view: ``(3,)`` the unit direction towards the camera, in the fit's dtype and on its device.
        channels: the capture's channel names (``C``).
        config: the fit's settings, as planned (:func:`~torchspec.pipeline.plan.plan`).
        folder: the checkpoint folder each finished tile is saved in, or ``None``.
        gains: ``(K, C)`` the lights' calibrated gains (:func:`fit_pixels`'s), or ``None``.
        domain: the residual term's encoding (:func:`fit_pixels`'s), or ``None`` (sRGB).
    """

    view: Tensor
    channels: tuple[str, ...]
    config: FitConfig
    folder: Path | None = None
    gains: Tensor | None = None
    domain: TermDomain | None = None


@dataclass(frozen=True)
class TileInputs:
    """One tile of ``n`` pixels of the image, ``first .. first + n - 1`` in the fit's pixel order
    (:func:`fit_tile`).

    Attributes:
        first: the tile's first pixel (its key in the checkpoint).
        values: ``(K, C, n)`` the pixels' recorded values.
        masks: the pixels' samples to leave out, each kind ``(K, n)``
            (:meth:`torchspec.start.photometric.Masks.of_pixels`).
        lights: the ``K`` lights as this tile sees them (under near lights, from its centre).
        ctx: ``lights``'s :class:`~torchspec.pipeline.start.LightContext`.
        visibility: ``(K, n)`` the lights' fixed visibility at the pixels (cast shadows), or ``None``.
    """

    first: int
    values: Tensor
    masks: Masks
    lights: Lights
    ctx: LightContext
    visibility: Tensor | None = None


VISIBLE = 0.8
"""A sample whose light's visibility is below this is left out (as a shadowed one is without a
visibility): ``y / V`` would amplify its noise and the shadow's edge, which the height places only
roughly (a pixel's visibility is averaged over its footprint and a penumbra, so an edge spans a
range of ``V``; on a simulated relief, 0.2 let the edges pull the normals further from the truth
than a fit without shadows)."""
EXPLAINED = 0.5
"""A sample masked as a shadow (too dark) is used again where the visibility is below this: the
visibility explains its darkness."""


def seen_through(y: Tensor, masks: Masks, visibility: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """A tile's ``y (n, K, C)`` over the lights' visibility ``(n, K)``, the samples to fit and the
    residual term's (:func:`fit_tile`), ``(y / V, valid, kept)``: a sample is left out of the fit
    where ``V < VISIBLE``, non-finite, saturated, or masked as a shadow that ``V`` does not explain
    (``V >= EXPLAINED``); out of the term's only where non-finite (the term is fitted on ``y``
    against the prediction times ``V``: :func:`residual_term`). With ``V = 1`` everywhere, ``y``
    itself and the masks' samples, exactly."""
    v = visibility.to(y)
    seen = v >= VISIBLE
    unexplained = masks.shadowed.T & (v >= EXPLAINED)
    valid = ~(masks.nonfinite.T | masks.saturated.T | unexplained) & seen
    kept = ~masks.nonfinite.T
    values = torch.where(seen[..., None], y / torch.where(seen, v, torch.ones_like(v))[..., None], y)
    return values, valid, kept


def fit_tile(tile: TileInputs, shared: FitInputs) -> TileResult:
    """One tile, as every driver fits it: :func:`fit_pixels` on ``tile``'s pixels, its samples of
    every kind of :data:`MASK_KINDS` left out (the non-finite ones also from the residual term's);
    saved in the checkpoint ``shared.folder`` when given; on ``config.compute.threads`` torch threads
    (:func:`torchspec.threads.fit_threads`). Returns :func:`fit_pixels`'s result with the count of
    masked samples of each kind (``TileResult.masked``)."""
    config = shared.config
    with fit_threads(config.compute.threads):  # auto: the cores free now (other processes share them)
        out = fit_pixels(TilePixels.of(tile), tile.lights, tile.ctx, shared)
    out = replace(out, masked=tile.masks.counts())
    if shared.folder is not None:
        save_tile(shared.folder, tile.first, out)
    return out
