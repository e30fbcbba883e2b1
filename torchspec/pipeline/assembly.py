"""Assembly: an image's :class:`~torchspec.pipeline.result.Fit` from its tiles' results
(:func:`assemble`), its statistics built alike by every driver (:func:`run_stats`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, fields, replace
from pathlib import Path

import torch
from torch import Tensor

from ..io import Capture
from ..io.scale import ScaledCapture
from ..lm import STATUS
from ..model.brdf import SVBRDF
from ..model.residual_term import ResidualTerm
from .checks import Checks
from .flags import describe, untrusted
from .plan import FitWarning, frame_warnings
from .records import PlainFit, TileResult
from .result import Fit
from .settings import MODEL_CODES, FitConfig
from .smoothing import smooth
from .tiling import sum_counts
from .verdict import LOW_QUALITY, trust_warnings

__all__ = ["STALLED_SHARE", "assemble", "run_stats", "scene_record", "stalled_warning"]


def run_stats(
    *,
    capture: Capture,
    picked: list[int],
    config: FitConfig,
    device: torch.device,
    pixels: int,
    tile: int,
    resumed: int,
    seconds: dict[str, float],
    masked: dict[str, int] | None,
    lights: dict | None,
    cluster: dict | None = None,
) -> dict:
    """The statistics a driver knows of its fit before the tiles' (JSON-ready): the capture, the
    frames, the scale it was read at (:class:`~torchspec.io.scale.ScaledCapture`; ``None``: full
    size), its lights and view (:func:`scene_record`), the settings, the device, the pixels and
    tiling, the tiles resumed, ``seconds`` per stage so far, the masked samples per kind, ``lights``
    (the record of :func:`torchspec.pipeline.calibration.calibrated`; ``None``: the lights as written) and,
    on a cluster, ``cluster`` (``stats["distributed"]``). Every driver builds the ``fit`` block of
    ``svbrdf.json`` here (then :func:`assemble`): the same keys, in the same order, from either."""
    stats = {
        "capture": str(Path(capture.root).resolve()),  # absolute: the maps find it from anywhere
        "frames": picked,
        "scale": capture.record() if isinstance(capture, ScaledCapture) else None,
        "scene": scene_record(capture, picked),
        "warnings": frame_warnings(capture, picked),
        "settings": asdict(config),
        "device": str(device),
        "pixels": pixels,
        "tile_pixels": tile,
        "resumed_tiles": resumed,
        "seconds": seconds,
        "masked_samples": masked,
        "lights": lights,
    }
    if cluster is not None:
        stats["distributed"] = cluster
    return stats


def scene_record(capture: Capture, picked: list[int]) -> dict:
    """What rendering the maps under new lights needs of the capture (``svbrdf.json``'s
    ``fit.scene``; :mod:`torchspec.relight.lights`): ``view``, the ``light`` block (its kernel),
    the fitted frames' ``irradiance`` (per channel) and ``exposure``, the near lights' median
    ``distance`` from the image's centre (``None``: distant lights), whether the capture came
    from ``photographs`` (its manifest's ``source``) and the ``transfer`` they were decoded with
    (``source``'s ``transfer`` and ``response``; ``None``: not photographs)."""
    positions = capture.positions()
    source = capture.extra.get("source")
    photographs = isinstance(source, dict)
    index = torch.tensor(picked, dtype=torch.long)  # CPU on purpose: indexes the manifest's table
    return {
        "view": list(capture.view),
        "light": {key: value for key, value in asdict(capture.light).items() if value is not None},
        "irradiance": [list(capture.frames[k].irradiance) for k in picked],
        "exposure": [capture.frames[k].exposure for k in picked],
        "distance": None if positions is None else float(positions[index].norm(dim=-1).median()),
        "photographs": photographs,
        "transfer": {key: source.get(key) for key in ("transfer", "response")} if photographs else None,
    }


def _join(values: list[Tensor], h: int, w: int) -> Tensor:
    return torch.cat(values).reshape(h, w, *values[0].shape[1:])


def _join_svbrdf(pieces: list[SVBRDF], h: int, w: int, channels: tuple[str, ...]) -> SVBRDF:
    def glue(name, tail):
        if getattr(pieces[0], name) is None:
            return None
        return torch.cat([getattr(p, name) for p in pieces]).reshape(h, w, *tail)

    return SVBRDF(
        glue("normal", (3,)),
        glue("diffuse", (len(channels),)),
        glue("specular", (-1,)),
        glue("roughness", (2,)),
        glue("rotation", ()),
        channels,
        glue("specular2", (-1,)),
        glue("roughness2", (2,)),
    )


def assemble(
    parts: list[TileResult], *, height: int, width: int, channels: tuple[str, ...], stats: dict, started: float
) -> Fit:
    """The :class:`~torchspec.pipeline.result.Fit` of an image from its tiles' results (in pixel
    order), smoothed with ``stats["settings"]["ladder"]["smooth"]`` when the tiles hold the fits without a
    lobe, ``stats`` (:func:`run_stats`) completed with the tiles' statistics and the time since
    ``started`` (``time.perf_counter``)."""
    h, w = height, width
    joined = Fit(
        svbrdf=_join_svbrdf([p.svbrdf for p in parts], h, w, channels),
        **{
            name: _join([getattr(p, name) for p in parts], h, w)
            for name in ("residual", "quality", "status", "iterations", "lobe", "model", "criterion", "flags")
        },
        std={name: _join([p.std[name] for p in parts], h, w) for name in parts[0].std},
        stats={},
        checks={f.name: _join([getattr(p.checks, f.name) for p in parts], h, w) for f in fields(Checks)},
    )
    if parts[0].term is not None:
        term = ResidualTerm(
            coefficients=_join([p.term.coefficients for p in parts], h, w),
            chosen=_join([p.term.chosen for p in parts], h, w),
            weight=_join([p.term.weight for p in parts], h, w),
            domain=parts[0].term.domain,
        )
        joined = replace(joined, term=term)
    smoothed = None
    if parts[0].plain is not None:  # FitConfig.ladder.smooth: the choice of a lobe over the whole image
        plain = PlainFit(**{f.name: _join([getattr(p.plain, f.name) for p in parts], h, w) for f in fields(PlainFit)})
        before = joined.model
        joined, smoothed = smooth(joined, plain, stats["settings"]["ladder"]["smooth"])
        if joined.term is not None:  # a term fitted on top of a lobe that smoothing took away: none
            kept = joined.term.chosen & (joined.model == before)
            coefficients = torch.where(kept[..., None, None], joined.term.coefficients, 0.0)
            weight = torch.where(joined.model == before, joined.term.weight, torch.ones_like(joined.term.weight))
            term = replace(joined.term, coefficients=coefficients, chosen=kept, weight=weight)
            joined = replace(joined, term=term)
    svbrdf = joined.svbrdf
    if svbrdf.specular2 is not None and not bool((svbrdf.specular2 > 0).any()):
        # A ladder with ward-dual that no pixel took: no second lobe's maps or deviations.
        std = {name: value for name, value in joined.std.items() if name not in ("specular2", "roughness2")}
        joined = replace(joined, svbrdf=replace(svbrdf, specular2=None, roughness2=None), std=std)
    stats = _tile_stats(joined, parts, stats, smoothed, time.perf_counter() - started)
    stalled = stalled_warning(stats)
    if stalled is not None:
        stats["warnings"] = [*stats.get("warnings", []), stalled]
        warnings.warn(stalled, FitWarning, stacklevel=3)
    stats["warnings"] = [*stats.get("warnings", []), *trust_warnings(stats)]  # in words a user can act on
    return replace(joined, stats=stats)


STALLED_SHARE = 0.1
"""The share of pixels stopped at the solver's iteration limit above which a fit warns."""


def stalled_warning(stats: dict) -> str | None:
    """The warning of a fit (its ``stats``) whose pixels stopped at the solver's iteration limit
    (``max iterations``) in a share above :data:`STALLED_SHARE`; ``None`` otherwise."""
    stalled, pixels = stats["status"].get("max iterations", 0), stats["pixels"]
    if pixels == 0 or stalled <= STALLED_SHARE * pixels:
        return None
    limit = stats["settings"]["lm"]["max_iterations"]
    return (
        f"{stalled} of {pixels} pixels ({100 * stalled / pixels:.0f} %) stopped at the solver's iteration limit "
        f"({limit}) without converging: their maps are unreliable (flags.exr marks them not_converged). The "
        f"{len(stats['frames'])} frames may not resolve their lobes: fit more frames, or raise lm.max_iterations in "
        "a --config file."
    )


def _tile_stats(fit: Fit, parts: list[TileResult], stats: dict, smoothed: int | None, total: float) -> dict:
    """``stats`` completed with the tiles' times and counts and the image's statistics."""
    times, tried = sum_counts([part.times for part in parts]), sum_counts([part.tried for part in parts])
    status, iterations, lobe, model, criterion = fit.status, fit.iterations, fit.lobe, fit.model, fit.criterion
    finite = criterion.isfinite()
    pixels = status.numel()
    return {
        **stats,
        "seconds": {**stats["seconds"], **times, "total": total},
        "pixels_per_second": pixels / total if total > 0 else None,
        "lobe_pixels": int(lobe.sum()),
        "models": {name: int((model == code).sum()) for code, name in enumerate(MODEL_CODES)},
        "models_tried": tried,
        "criterion": float(criterion[finite].double().sum()) if bool(finite.any()) else None,
        # The sensor's noise variance a y + b per tile (y in recorded units; 0 when not estimated).
        "sensor_noise": {key: [float(p.noise[i]) for p in parts] for i, key in enumerate("ab")},
        "status": {name: int((status == code).sum()) for code, name in enumerate(STATUS)},
        "iterations": {
            "mean": float(iterations.float().mean()),
            "median": float(iterations.float().median()),
            "max": int(iterations.max()),
            "mean_lobe": float(iterations[lobe].float().mean()) if bool(lobe.any()) else None,
        },
        "median_residual": float(fit.residual.median()),
        "flags": describe(fit.flags),
        "untrusted": int(untrusted(fit.flags).sum()),
        "low_quality": int((fit.quality < LOW_QUALITY).sum()),
        # FitConfig.ladder.smooth: the pixels whose lobe the neighbours' term took away (None: not smoothed).
        "smoothed": smoothed,
        # FitConfig.term.order: the pixels that carry one (None: not fitted).
        "residual_term_pixels": None if fit.term is None else int(fit.term.chosen.sum()),
    }
