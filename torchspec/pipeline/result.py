"""The result of a fit (:class:`Fit`) and its SVBRDF folder (:func:`write_fit`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..io import write_svbrdf
from ..lm import STATUS
from ..model.brdf import SVBRDF
from ..model.residual_term import MAP_NAME, WEIGHT_MAP, ResidualTerm
from ..outputs import check_apart, check_output
from .checkpoint import CHECKPOINT
from .flags import FLAGS, UNTRUSTED, bit
from .settings import MODEL_CODES

__all__ = ["Fit", "write_fit"]


@dataclass(frozen=True)
class Fit:
    """The result of :func:`torchspec.pipeline.fit` (and of :func:`torchspec.pipeline.fit_on_cluster`).

    Attributes:
        svbrdf: the maps, leading dims ``(H, W)``; with a second lobe (``specular2``,
            ``roughness2``) where some pixel got ``ward-dual``.
        residual: ``(H, W)`` RMS of the fit's residual over the valid samples, relative to the
            pixel's mean value.
        quality: ``(H, W)`` in ``[0, 1]``: photometric-stereo quality, times the peak location's
            quality for lobed pixels, halved where the solver did not converge; 0 where ``flags``
            holds a flag of :data:`torchspec.pipeline.flags.UNTRUSTED` (diverged, fewer than 3 valid
            samples, an undetermined normal, a misfit around the peak, a peak astray).
        status: ``(H, W)`` int8 solver status (:data:`torchspec.lm.STATUS`).
        iterations: ``(H, W)`` solver steps taken.
        lobe: ``(H, W)`` bool, the pixels fitted with a lobe.
        model: ``(H, W)`` int8, each pixel's model: an index into :data:`MODEL_CODES`.
        criterion: ``(H, W)`` the Bayesian information criterion of each pixel's fit,
            ``chi^2 + P ln(n)`` with the pixel's noise level (``inf`` where no sample was valid).
        std: standard deviations of the fitted parameters from the Fisher information at the
            solution with the estimated noise (the Cramer-Rao bound at the estimate):
            ``normal (H, W)`` (the angle, radians), ``diffuse (H, W, C)``, ``specular (H, W, C_s)``,
            ``roughness (H, W, 2)``, and ``specular2 (H, W, 1)``, ``roughness2 (H, W, 2)`` with a
            second lobe; NaN for a parameter the pixel's model does not have, ``inf`` where the data
            leave it undetermined.
        stats: settings, timings and per-stage statistics (JSON-ready); ``smoothed``: the lobes
            that ``FitConfig.ladder.smooth`` took away (``None`` without it).
        flags: ``(H, W)`` int16 bits of :data:`torchspec.pipeline.flags.FLAGS`: why not to trust a pixel
            (the :data:`torchspec.pipeline.flags.UNTRUSTED` ones; ``quality`` is then 0) or what to know
            of it (its solver stopped early, its model leaves a residual above the noise, its
            lobe is too weak to place a peak).
        checks: ``peak_misfit`` and ``astray`` ``(H, W)``: the values behind those flags
            (:func:`torchspec.pipeline.flags.peak_checks`; NaN where not computed: no lobe, a weak one, or
            no noise estimate with a forced model and ``uncertainty`` off).
        term: the residual term, ``coefficients (H, W, J, C)`` and ``chosen (H, W)``
            (:class:`torchspec.model.residual_term.ResidualTerm`; ``FitConfig.term.order``, else ``None``).
        height: ``(H, W)`` the height field (pixels) whose cast shadows the maps were fitted with
            (``FitConfig.shadows``, :mod:`torchspec.pipeline.shadows`), else ``None``.
        indirect: ``(H, W)`` with ``height``, each pixel's indirect share: the light its lit
            surroundings reflect into its shadows, over the mean plane's direct light
            (:mod:`torchspec.model.indirect`), else ``None``.
    """

    svbrdf: SVBRDF
    residual: Tensor
    quality: Tensor
    status: Tensor
    iterations: Tensor
    lobe: Tensor
    model: Tensor
    criterion: Tensor
    std: dict[str, Tensor]
    stats: dict
    flags: Tensor
    checks: dict[str, Tensor]
    term: ResidualTerm | None = None
    height: Tensor | None = None
    indirect: Tensor | None = None


def write_fit(path: str | Path, result: Fit, *, overwrite: bool = False) -> None:
    """Write a :class:`Fit` as an SVBRDF folder: the maps, ``residual.exr``, ``quality.exr``,
    ``status.exr``, ``iterations.exr``, ``model.exr`` (codes of ``model_codes``),
    ``criterion.exr``, ``flags.exr`` (bits of ``flag_bits``), ``check_peak_misfit.exr``,
    ``check_astray.exr``, ``residual_term.exr`` and ``residual_term_base.exr`` (with
    ``FitConfig.term.order``: its coefficients and bases, described under ``residual_term`` in
    ``svbrdf.json``), the standard deviations ``std_normal_deg.exr``, ``std_diffuse.exr``,
    ``std_specular.exr``, ``std_roughness.exr`` (and ``std_specular2.exr``, ``std_roughness2.exr``
    with a second lobe, whose maps are ``specular2.exr`` and ``roughness2.exr``) and ``svbrdf.json``
    (model, settings, timings, statistics).

    A folder that holds other files is refused (:class:`~torchspec.outputs.OutputError`) unless
    ``overwrite``; one that holds the fit's own checkpoint (:data:`~torchspec.pipeline.checkpoint.CHECKPOINT`)
    is this fit's. The capture's folder (``stats["capture"]``), a folder inside it or one holding it is
    refused whatever ``overwrite`` says (:func:`~torchspec.outputs.check_apart`)."""
    if result.stats.get("capture"):
        check_apart(path, result.stats["capture"], "the capture")
    check_output(path, overwrite=overwrite, job=CHECKPOINT)
    meta = {
        "model": "ward",
        "fit": result.stats,
        "status_codes": list(STATUS),
        "model_codes": list(MODEL_CODES),
        "flag_bits": {name: bit(name) for name in FLAGS},
        "untrusted_flags": list(UNTRUSTED),
    }
    extra = {
        "residual": result.residual.float(),
        "quality": result.quality.float(),
        "status": result.status.float(),
        "iterations": result.iterations.float(),
        "model": result.model.float(),
        "criterion": result.criterion.float(),
        "flags": result.flags.float(),
        "check_peak_misfit": result.checks["peak_misfit"].float(),
        "check_astray": result.checks["astray"].float(),
        "std_normal_deg": torch.rad2deg(result.std["normal"]).float(),
        "std_diffuse": result.std["diffuse"].float(),
        "std_specular": result.std["specular"].float(),
        "std_roughness": result.std["roughness"].float(),
    }
    if "specular2" in result.std:  # ward-dual's second lobe
        extra.update(std_specular2=result.std["specular2"].float(), std_roughness2=result.std["roughness2"].float())
    if result.term is not None:  # FitConfig.term.order: its own maps, the physical ones unchanged
        extra[MAP_NAME] = result.term.to_map().float()
        extra[WEIGHT_MAP] = result.term.weight.float()
        meta[MAP_NAME] = result.term.description()
    if result.height is not None:  # cast shadows: the height their visibility came from
        extra["height"] = result.height.float()
        meta["height"] = result.stats.get("height") or {"unit": "pixel", "pitch": 1.0}
    if result.indirect is not None:  # cast shadows' indirect light: y = V r + b D
        extra["indirect"] = result.indirect.float()
    write_svbrdf(path, result.svbrdf.to(torch.float32), meta=meta, extra=extra, overwrite=True)
