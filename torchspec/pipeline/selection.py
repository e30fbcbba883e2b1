"""Model selection: each pixel's model by what it predicts of frames left out of its fit.

The pixels without a peak are fitted without a lobe, those with one with the first model of the
ladder from the specular start; their residuals give the sensor's noise, then each fit is assessed
(:func:`assess`: a :class:`ModelFit`: chi-square, deviations, criterion, misfit). A forced model
keeps its one fit per pixel. ``auto`` climbs the ladder (:func:`select_models`): a larger model is
tried, from the previous one's solution, where that leaves a misfit, and kept (:class:`Choice`)
where it predicts the frames left out of its fit better than the model kept so far by more than
the noise (:mod:`torchspec.pipeline.prediction`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

from ..lm import DIVERGED, LMResult
from ..model.brdf import SVBRDF
from ..model.layout import lobe_support
from ..model.registry import ALPHA_BOUNDS, get_model
from ..statistics import predicts_better
from .prediction import held_out, held_out_refit, light_folds, second_lobe_held_out
from .samples import TileSamples
from .settings import AUTO, MODEL_CODES, FitConfig
from .solver import Solved, solve_pixels
from .start import StartingPoint
from .uncertainty import PeakSamples, sensor_noise, uncertainty

__all__ = ["GATE_ROUGHNESS", "ModelFit", "Choice", "assess", "resolved", "supported", "select_models"]

GATE_ROUGHNESS = 6
"""Second lobes' roughnesses ``auto``'s gate of ``ward-dual`` tries (``FitConfig.ladder.dual_gate``)."""


@dataclass(frozen=True)
class ModelFit:
    """A candidate model's fit of pixels ``index (m,)`` of a tile, assessed.

    Attributes:
        name, index, svbrdf, result: the solution (:class:`~torchspec.pipeline.solver.Solved`).
        chi2: ``(m,)`` noise-weighted chi-square (``-inf`` without a noise estimate).
        std: the parameters' deviations (:class:`~torchspec.pipeline.uncertainty.Uncertainty`).
        peak: what the peak checks take (``None`` without a noise estimate).
        criterion: ``(m,)`` ``chi^2 + P ln(n)`` (``inf`` where the solver diverged).
        unexplained: ``(m,)`` bool, the residual is above the noise (``FitConfig.ladder.select_z``).
    """

    name: str
    index: Tensor
    svbrdf: SVBRDF
    result: LMResult
    chi2: Tensor
    std: dict[str, Tensor]
    peak: PeakSamples | None
    criterion: Tensor
    unexplained: Tensor


def assess(solved: Solved, data: TileSamples, sensor: Tensor, config: FitConfig) -> ModelFit:
    """The fit's chi-square, deviations and peak samples (with the noise ``sensor = (a, b)``), its
    criterion and whether its residual is above the noise. A forced model without
    ``config.uncertainty`` is kept as is: neither criterion nor deviations."""
    model, index, result = get_model(solved.name), solved.index, solved.result
    c = len(data.channels)
    if config.noise_known:
        found = uncertainty(
            model,
            solved.svbrdf,
            data.observed[index],
            data.inverse_noise(sensor, index, config.start.noise_floor),
            data.weight[index, :, None].expand(-1, -1, c),
            data.lights,
            data.view,
            quadrature=config.rule,
        )
        chi2, std, peak = found.chi2, found.std, found.peak
    else:
        chi2, std, peak = torch.full_like(result.cost, -math.inf), {}, None
    samples = data.samples[index]
    dof = (samples - model.size(c)).clamp(min=1.0)
    bic = chi2 + model.size(c) * torch.log(samples.clamp(min=1.0))
    bic = torch.where(result.status == DIVERGED, torch.full_like(bic, math.inf), bic)
    unexplained = chi2 > dof + config.ladder.select_z * (2.0 * dof).sqrt()
    return ModelFit(solved.name, index, solved.svbrdf, result, chi2, std, peak, bic, unexplained)


@dataclass
class Choice:
    """The accumulator of a tile's chosen fits, ``n`` pixels: each pixel holds the fit with the
    lowest criterion so far (:meth:`take`). Built by :meth:`empty` from the models to be tried.

    Attributes:
        svbrdf: the chosen maps ``(n,)`` (``rotation`` with an anisotropic model in the ladder,
            ``specular2``, ``roughness2`` with a model of a second lobe in it, ``ward-dual``; 0 where
            the chosen model lacks them: the maps each model's parameters fill, :meth:`Model.fills`).
        status, iterations, cost: the solver's, ``(n,)``.
        code: ``(n,)`` int8 index of the chosen model in :data:`MODEL_CODES`.
        criterion: ``(n,)`` (``inf`` where none was chosen, NaN without a noise estimate).
        misfit: ``(n,)`` bool, the chosen fit leaves a residual above the noise.
        peak: the chosen fits' :class:`PeakSamples` (zeros where not computed).
        deviation: standard deviations as :class:`~torchspec.pipeline.uncertainty.Uncertainty`'s
            (NaN where not computed).
        tried: pixels fitted per model.
    """

    svbrdf: SVBRDF
    status: Tensor
    iterations: Tensor
    cost: Tensor
    code: Tensor
    criterion: Tensor
    misfit: Tensor
    peak: PeakSamples
    deviation: dict[str, Tensor]
    tried: dict[str, int] = field(default_factory=dict)

    @staticmethod
    def empty(start: StartingPoint, ladder: tuple[str, ...], frames: int, channels: tuple[str, ...]) -> Choice:
        """No fit chosen yet: photometric stereo's normal and ``k_d``, no lobe."""
        ps = start.diffuse
        n, c = ps.diffuse.shape
        models = [get_model(name) for name in ladder]
        grey = len(models) == 1 and models[0].grey
        zeros = ps.diffuse.new_zeros
        rotation = zeros(n) if any(model.fills("rotation") for model in models) else None
        dual = any(model.fills("specular2") for model in models)  # a second lobe's maps, 0 where not fitted
        second = (zeros((n, 1)), zeros((n, 2))) if dual else (None, None)
        specular = zeros((n, 1 if grey else c))
        svbrdf = SVBRDF(ps.normal.clone(), ps.diffuse.clone(), specular, zeros((n, 2)), rotation, channels, *second)
        nan = math.nan
        deviation = {
            "normal": ps.diffuse.new_full((n,), nan),
            "diffuse": ps.diffuse.new_full((n, c), nan),
            "specular": ps.diffuse.new_full((n, svbrdf.specular.shape[-1]), nan),
            "roughness": ps.diffuse.new_full((n, 2), nan),
        }
        if dual:
            deviation.update(specular2=ps.diffuse.new_full((n, 1), nan), roughness2=ps.diffuse.new_full((n, 2), nan))
        device = ps.diffuse.device
        return Choice(
            svbrdf=svbrdf,
            status=torch.zeros(n, dtype=torch.int8, device=device),
            iterations=torch.zeros(n, dtype=torch.int32, device=device),
            cost=zeros(n),
            code=torch.zeros(n, dtype=torch.int8, device=device),
            criterion=torch.full((n,), math.inf, dtype=ps.diffuse.dtype, device=device),
            misfit=torch.zeros(n, dtype=torch.bool, device=device),
            peak=PeakSamples(zeros((n, frames)), zeros((n, frames)), zeros(n)),
            deviation=deviation,
        )

    def take(self, fit: ModelFit, better: Tensor | None = None) -> None:
        """Keep ``fit`` where ``better (m,)`` holds (by default: where its criterion is the lowest
        so far, or everywhere without a noise estimate), in place."""
        model, index, result = get_model(fit.name), fit.index, fit.result
        nothing = fit.chi2 == -math.inf
        if better is None:
            better = (fit.criterion < self.criterion[index]) | nothing
        bic = torch.where(nothing, torch.full_like(fit.criterion, math.nan), fit.criterion)
        pick, chosen, mine = index[better], fit.svbrdf[better], self.svbrdf
        mine.normal[pick], mine.diffuse[pick] = chosen.normal, chosen.diffuse
        mine.specular[pick] = chosen.specular.expand(-1, mine.specular.shape[-1])
        mine.roughness[pick] = chosen.roughness
        if mine.rotation is not None:
            rotation = chosen.rotation if chosen.rotation is not None else torch.zeros_like(chosen.roughness[:, 0])
            mine.rotation[pick] = rotation
        if mine.specular2 is not None:
            second = model.fills("specular2")
            mine.specular2[pick] = chosen.specular2 if second else 0.0
            mine.roughness2[pick] = chosen.roughness2 if second else 0.0
        self.status[pick], self.iterations[pick] = result.status[better], result.iterations[better]
        self.cost[pick], self.criterion[pick] = result.cost[better], bic[better]
        self.code[pick] = MODEL_CODES.index(fit.name)
        for key, value in fit.std.items():
            if key not in self.deviation:  # a second lobe's, where no model has one
                continue
            kept = value[better]
            self.deviation[key][pick] = kept.expand(-1, self.deviation[key].shape[-1]) if kept.dim() > 1 else kept
        self.tried[fit.name] = self.tried.get(fit.name, 0) + index.numel()
        self.misfit[pick] = fit.unexplained[better]
        if fit.peak is not None:
            self.peak.z2[pick], self.peak.excess[pick] = fit.peak.z2[better], fit.peak.excess[better]
            self.peak.lobe_snr[pick] = fit.peak.lobe_snr[better]


def select_models(
    start: StartingPoint, lobe: Tensor, data: TileSamples, config: FitConfig, folds: Tensor | None = None
) -> tuple[Choice, Tensor, Tensor]:
    """Fit and choose each pixel's model (module docstring) for pixels with a lobe ``lobe (n,)``;
    ``folds (S, K)``: the frames' folds of ``auto``'s choice (:func:`~torchspec.pipeline.prediction.light_folds`
    of the fit's lights by default).

    Returns:
        The :class:`Choice`, the sensor's noise ``(a, b)`` (zeros when not estimated) and the
        start's peak-location quality per pixel ``(n,)`` (1 for the pixels without a lobe).
    """
    ladder = config.ladder_climbed
    channels = data.channels
    choice = Choice.empty(start, ladder, data.observed.shape[1], channels)
    first = []
    index = (~lobe).nonzero()[:, 0]
    if index.numel():
        first.append(solve_pixels("diffuse", index, plain_start(start, channels)[index], data, config))
    index = lobe.nonzero()[:, 0]
    found_quality = torch.ones_like(start.level)
    found_quality[index] = start.specular.quality[index]
    if index.numel() and ladder:
        first.append(solve_pixels(ladder[0], index, start.svbrdf(channels)[index], data, config))
    sensor = data.observed.new_zeros(2)
    if first and config.noise_known:
        c = len(channels)
        sensor = torch.stack(sensor_noise(first, start.lobe, data.observed, data.valid, data.level, c))
    if config.model == AUTO:
        _climb(start, lobe, first, data, sensor, config, folds, choice)
        return choice, sensor, found_quality
    for solved in first:  # a forced model: each pixel's one fit
        choice.take(assess(solved, data, sensor, config))
    return choice, sensor, found_quality


def _climb(
    start: StartingPoint,
    lobe: Tensor,
    first: list[Solved],
    data: TileSamples,
    sensor: Tensor,
    config: FitConfig,
    folds: Tensor | None,
    choice: Choice,
) -> None:
    """``auto``'s ladder, in ``choice``, from the ``first`` fits (``diffuse`` where no peak was
    detected, the ladder's first model where one was: ``lobe``).

    A pixel without a detected peak whose fit leaves a misfit is fitted with the ladder's first
    model too (from the specular start and from a broad lobe about the photometric-stereo normal:
    a broad lobe leaves no peak to detect); each next model is tried, from the previous one's
    solution, where that leaves a misfit. A model is kept where it predicts the left-out frames
    better than the one kept so far (:func:`~torchspec.statistics.predicts_better`),
    the first lobe than the pixel's fit without one (for a detected peak, one step from the
    photometric-stereo fit; where the lobe is not kept, that fit is then made)."""
    ladder, channels = config.ladder.models, data.channels
    if folds is None:
        folds = light_folds(data.lights.directions, config.ladder.folds, config.ladder.fold_regions)
    fits = {solved.name: solved for solved in first}
    plain = plain_start(start, channels)  # each pixel's fit without a lobe, where made
    misfit = lobe.new_zeros(0, dtype=torch.long)
    if "diffuse" in fits:
        fit = assess(fits["diffuse"], data, sensor, config)
        choice.take(fit)
        plain = _placed(plain, fit.index, fit.svbrdf)
        misfit = fit.index[fit.unexplained]
    candidates = [fits[ladder[0]]] if ladder[0] in fits else []
    if misfit.numel():
        candidates.append(_broad_fit(start, misfit, data, config))
    if not candidates:
        return
    heldout = data.observed.new_zeros((lobe.shape[0], folds.shape[0], *data.observed.shape[1:]))
    diffuse = get_model("diffuse")

    def predicted(model, svbrdf: SVBRDF, index: Tensor) -> Tensor:
        inverse = data.inverse_noise(sensor, index, config.start.noise_floor)
        predict = held_out_refit if config.ladder.refit else held_out
        return predict(model, svbrdf, index, data, inverse, folds, config)

    def compare(fit: ModelFit) -> Tensor:
        # the left-out frames are predicted only where the fit could be kept at all
        eligible = resolved(fit, config.ladder.resolve) & supported(fit, data, config.ladder.lobe_support)
        eligible &= fit.criterion < math.inf
        at = eligible.nonzero()[:, 0]
        index = fit.index[at]
        mine = predicted(get_model(fit.name), fit.svbrdf[at], index)
        better = torch.zeros_like(eligible)
        better[at] = predicts_better(mine, heldout[index], config.ladder.predict_z)
        choice.take(fit, better)
        heldout[fit.index[better]] = mine[better[at]]
        return better

    fit = assess(_joined(candidates), data, sensor, config)
    heldout[fit.index] = predicted(diffuse, plain[fit.index], fit.index)
    kept = compare(fit)
    rejected = fit.index[~kept & lobe[fit.index]]
    if rejected.numel():  # a detected peak that no lobe predicts: the pixel's fit without one
        choice.take(assess(solve_pixels("diffuse", rejected, plain[rejected], data, config), data, sensor, config))
    index, init = fit.index[fit.unexplained], fit.svbrdf[fit.unexplained]
    for name in ladder[1:]:  # each from the previous one's solution, where it leaves a misfit
        if get_model(name).fills("specular2"):  # where one lobe leaves a misfit as large as a second lobe's
            keep = data.relative_rms(choice.cost[index], index) > config.ladder.dual_rms
            index, init = index[keep], init[keep]
            if config.ladder.dual_gate is not None and index.numel():  # and a second lobe would predict better
                keep = _second_lobe_gate(init, index, data, sensor, folds, heldout[index], config)
                index, init = index[keep], init[keep]
        if index.numel() == 0:
            break
        fit = assess(solve_pixels(name, index, init, data, config), data, sensor, config)
        compare(fit)
        index, init = index[fit.unexplained], fit.svbrdf[fit.unexplained]


def _second_lobe_gate(
    init: SVBRDF, index: Tensor, data: TileSamples, sensor: Tensor, folds: Tensor, current: Tensor, config: FitConfig
) -> Tensor:
    """``(m,)`` bool: a second lobe, linearised at the one-lobe fit ``init`` of pixels ``index``
    (:func:`~torchspec.pipeline.prediction.second_lobe_held_out`, at :data:`GATE_ROUGHNESS`
    roughnesses from twice the least the lights resolve to half the largest), predicts the left-out
    frames better than the model kept so far (``current``, its held-out residuals) by more than
    ``FitConfig.ladder.dual_gate`` noise deviations at one of them at least."""
    low, high = ALPHA_BOUNDS
    least = max(config.least_roughness(data.lights), low)
    roughness = torch.logspace(
        math.log10(2 * least), math.log10(high / 2), GATE_ROUGHNESS, dtype=data.observed.dtype, device=index.device
    )
    inverse = data.inverse_noise(sensor, index, config.start.noise_floor)
    linear = second_lobe_held_out(init, index, data, inverse, folds, config, roughness)  # (m, G, S, K, C)
    better = [predicts_better(linear[:, j], current, config.ladder.dual_gate) for j in range(roughness.shape[0])]
    return torch.stack(better, -1).any(-1)


def _placed(svbrdf: SVBRDF, index: Tensor, values: SVBRDF) -> SVBRDF:
    """``svbrdf`` (one lobe or none) with the pixels ``index`` set to ``values``."""
    out = svbrdf[torch.arange(svbrdf.shape[0], device=index.device)]  # a copy
    out.normal[index], out.diffuse[index] = values.normal, values.diffuse
    return out


def resolved(fit: ModelFit, bound: float) -> Tensor:
    """``(m,)`` bool: a ``ward-dual`` fit's two lobes each have a roughness the data determine (a
    standard deviation below ``bound`` times the roughness); True for the other models. Two lobes
    whose shapes the samples do not resolve (a lobe sharper than the light's kernel, whose samples
    show only its integral) predict the frames the fit saw, and nothing else: a light of another
    size (a point light) would see them at any height."""
    if not get_model(fit.name).fills("specular2") or not fit.std:
        return torch.ones_like(fit.unexplained)
    first = fit.std["roughness"][:, 0] < bound * fit.svbrdf.roughness[:, 0]
    second = fit.std["roughness2"][:, 0] < bound * fit.svbrdf.roughness2[:, 0]
    return first & second


def supported(fit: ModelFit, data: TileSamples, least: float) -> Tensor:
    """``(m,)`` bool: with point lights, a fit's lobe reaches at least ``least`` of its peak at
    one of the frames (:func:`torchspec.model.layout.lobe_support`); True without a lobe, with an
    extended kernel (whose blur sees the peak from the frames about it) or ``least = 0``."""
    if data.lights.kernel.kind != "point" or least <= 0 or get_model(fit.name).lobe is None:
        return torch.ones_like(fit.unexplained)
    return lobe_support(fit.svbrdf, data.lights, data.view) >= least


def _broad_fit(start: StartingPoint, index: Tensor, data: TileSamples, config: FitConfig) -> Solved:
    """The ladder's first model on pixels ``index`` without a detected peak, from two starts: the
    specular start (``FitConfig.start.init``) and a broad lobe (``alpha = FitConfig.start.broad_alpha``)
    about the photometric-stereo normal, each pixel keeping the solution of lower cost."""
    name, channels = config.ladder.models[0], data.channels
    peak = solve_pixels(name, index, start.svbrdf(channels)[index], data, config)
    ps = start.diffuse
    level = start.level[index, None]
    alpha = level.new_full((index.shape[0], 2), config.start.broad_alpha)
    broad_start = SVBRDF(ps.normal[index], 0.5 * ps.diffuse[index], level, alpha, None, channels)
    broad = solve_pixels(name, index, broad_start, data, config)
    lower = broad.result.cost < peak.result.cost
    return _where(lower, broad, peak)


def _where(mask: Tensor, chosen: Solved, other: Solved) -> Solved:
    """``chosen``'s solution where ``mask (m,)`` holds, ``other``'s elsewhere (one model, the same pixels)."""

    def pick(items):
        return torch.where(mask.view(-1, *[1] * (items[0].dim() - 1)), items[0], items[1])

    parts = [chosen, other]
    return Solved(chosen.name, chosen.index, _fields(parts, pick, "svbrdf"), _fields(parts, pick, "result"))


def _joined(parts: list[Solved]) -> Solved:
    """One :class:`Solved` of one model: the concatenation of ``parts``, sorted by pixel."""
    if len(parts) == 1:
        return parts[0]
    index = torch.cat([part.index for part in parts])
    order = torch.argsort(index)

    def join(items):
        return torch.cat(items)[order]

    return Solved(parts[0].name, index[order], _fields(parts, join, "svbrdf"), _fields(parts, join, "result"))


def _fields(parts: list[Solved], combine, name: str):
    """The dataclass ``name`` of ``parts`` with each tensor field ``combine(items)`` of theirs."""
    items = [getattr(part, name) for part in parts]
    values = {}
    for f in fields(items[0]):
        these = [getattr(item, f.name) for item in items]
        values[f.name] = combine(these) if isinstance(these[0], Tensor) else these[0]
    return type(items[0])(**values)


def plain_start(start: StartingPoint, channels: tuple[str, ...]) -> SVBRDF:
    """The solver's starting point without a lobe: photometric stereo's normal and ``k_d``."""
    zero = start.level.new_zeros((start.level.shape[0], 1))
    return SVBRDF(start.diffuse.normal, start.diffuse.diffuse, zero, zero.expand(-1, 2), None, channels)
