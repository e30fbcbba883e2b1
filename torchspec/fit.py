"""The pipeline: SVBRDF maps from a capture (``torchspec fit``).

Stages, per tile of pixels (all frames of a tile at once, so memory is bounded by the tile):

1. masks of non-finite, saturated (grown in the image) and shadowed samples
   (:func:`torchspec.photometric.sample_masks`, on the whole stack);
2. robust photometric stereo: normal and ``k_d`` from the non-specular samples;
3. the specular stage: pixels whose residual peaks above the noise get a starting point from
   the FRI location of the peak (:func:`torchspec.specular.locate_peak`; or a naive start, or a
   dense grid search, for comparison);
4. batched Levenberg-Marquardt (:func:`torchspec.lm.solve`) of every parameter jointly on every
   valid sample: the lobed pixels with the configured Ward model, the others diffuse only; with
   ``auto``, each pixel's model by the information criterion, climbing ``FitConfig.ladder``
   (one grey lobe, coloured, anisotropic, two lobes) only where the smaller model leaves a
   residual above the noise.

Then, over the whole image (with ``FitConfig.smooth``), the choice between a lobe and none is
regularised across neighbouring pixels (:func:`smooth_choice`).

The result holds the maps, a per-pixel relative RMS residual, quality and flags
(:mod:`torchspec.flags`: which pixels not to trust, and why), the solver's status and iteration
counts, and statistics per stage; :func:`write_fit` writes them as an SVBRDF folder.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor
from tqdm.auto import tqdm

from .atomic import atomic_path, read_json, write_json
from ._version import __version__
from .brdf import SVBRDF
from .flags import FLAGS, UNTRUSTED, WEAK_LOBE_SNR, bit, describe, peak_checks, untrusted
from .geometry import normal_derivative
from .io import Capture, read_capture, write_svbrdf
from .jacobian import sandwich_terms
from .lights import Lights, diffuse_directions
from .lm import CONVERGED, DIVERGED, STATUS, LMConfig, bounded, solve
from .models import MODELS, get_model
from .noise import affine_noise
from .photometric import Diffuse, photometric_stereo, sample_masks
from .relight import lights_of
from .specular import Start as SpecularStart
from .specular import grid_search, layout_of, locate_peak, naive_start, specular_residual

__all__ = [
    "FitConfig",
    "Fit",
    "FitInterrupted",
    "Start",
    "fit",
    "start",
    "write_fit",
    "select_frames",
    "smooth_choice",
    "INITS",
]

INITS = ("fri", "naive", "grid")
AUTO = "auto"
LADDER = ("ward-iso", "ward-iso-colour", "ward-aniso", "ward-dual")
"""The lobed models ``auto`` tries, in order: each on the pixels the previous left unexplained."""
MODEL_CODES = tuple(MODELS)
"""``model.exr``'s codes: the index of each pixel's model in this tuple."""
# torch.compile's one-off cost (~50 s; ~10 s from its on-disk cache) against the ~0.2 ms it saves
# per pixel of a 144-frame fit (0.33 ms with a lobe, 0.07 ms without): it pays from 50k-250k pixels.
COMPILE_PIXELS = 1 << 17
QUADRATURES = {
    # name: the lobe's Gauss-Hermite nodes per axis (fast rule) and radii (reference rule), and the
    # rule of the diffuse clamp (torchspec.jacobian.jacobian's order, reference_order and clamp)
    "fit": {"order": 3, "reference_order": 8, "clamp": "fast"},
    "render": {"order": None, "reference_order": None, "clamp": "exact"},
}


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`fit` (``configs/fit*.yaml``).

    Attributes:
        model: ``auto`` picks each pixel's model by the Bayesian information criterion, trying
            the larger ones only where the smaller leave a residual above the noise
            (``ladder``); or one model forced on every pixel that shows a peak
            (:data:`torchspec.models.MODELS`): ``ward-iso`` (grey ``k_s``), ``ward-iso-colour``,
            ``ward-aniso`` or ``ward-dual`` (two grey isotropic lobes), or ``diffuse`` on every
            pixel. Where some pixel gets ``ward-dual``, the maps have a second lobe
            (``SVBRDF.specular2``, 0 where another model was chosen; ``std`` has its deviations).
        ladder: the models ``auto`` climbs, in order, each tried from the previous one's solution on
            the pixels it leaves unexplained (:data:`LADDER` by default). Leave ``ward-dual`` out to
            spend no time on two lobes: a pixel no single Ward lobe explains (a lobe of another
            shape, such as the development captures' Beckmann lobes) climbs to the last model.
        uncertainty: compute each pixel's criterion and standard deviations (one more evaluation
            of the model per pixel, at the solution), with each sample's noise from the sensor's
            ``a y + b`` fitted to the residuals of the pixels without a peak
            (:func:`torchspec.noise.affine_noise`; ``stats["sensor_noise"]``), floored at
            ``noise_floor`` times the pixel's level. ``auto`` needs them; a forced model without
            them leaves ``criterion`` and ``std`` NaN.
        flag_peak_misfit, flag_astray, flag_reach: the thresholds of the ``peak_misfit`` and
            ``astray`` flags and the neighbourhood of the peak (:mod:`torchspec.flags`; they need
            the noise: ``uncertainty`` or ``auto``). Set by the stability study: they catch most
            peaks placed more than 10 Cramer-Rao deviations away while flagging few good ones.
        smooth: spatial regularisation of ``auto``'s choice between a lobe and none (a matte region
            of a painting is contiguous): the criterion of a pixel gains ``smooth`` for each of its
            four neighbours on the other side of that choice, and the image's total is lowered pixel
            by pixel (:func:`smooth_choice`). Every pixel given a lobe is then also fitted without one
            (its ``diffuse`` fit is the alternative). ``0`` (the default): each pixel on its own, and a
            pixel whose samples show a peak always gets a lobe. In units of the criterion: the BIC
            charges ``ln n`` (~5 for a few hundred samples) per parameter, so ``smooth = 10`` lets
            four matte neighbours outweigh about eight parameters' worth of improvement.
        select_z: ``auto`` tries the next larger model where the fit's chi-square exceeds its
            degrees of freedom by more than ``select_z`` of its standard deviations
            (``dof + select_z sqrt(2 dof)``): the residual is not noise.
        init: the specular start: ``fri`` (FRI peak location), ``naive`` (photometric-stereo
            normal, ``alpha = naive_alpha``) or ``grid`` (dense search).
        detect: a pixel gets a lobe when its residual peaks above ``detect`` times its noise
            level (the larger of the photometric-stereo noise and ``noise_floor`` times the
            pixel's mean value).
        noise_floor: see ``detect``; also the smallest noise of a sample, relative to its
            pixel's level, in the criterion and the deviations (the model's own error: the
            quadrature, a lobe shape the data's material does not follow).
        naive_alpha: the roughness of the naive start.
        saturation: the sensor's clipping level; ``None`` detects a clipped plateau.
        grow: saturated regions are grown by this many pixels.
        shadow: samples below this fraction of the pixel's median are shadows.
        trim, cut: of the robust photometric stereo.
        fri_method, fri_coefficients: of the peak location (``None``: the defaults).
        path: the quadrature path of the model (:func:`torchspec.render.render`).
        quadrature: ``fit`` (the default): 3 x 3 nodes per frame for the lobe (8 radii where
            the reference rule takes over) and the clamp's fast rule
            (:data:`torchspec.render.CLAMPS`): within 1e-3 of a pixel's largest value, 2.7x faster;
            ``render``: the renderer's own rules (1e-6).
        compile: fuse the model's integrations with ``torch.compile``: 3-4x faster solver steps
            on the CPU, after a one-off compilation of ~50 s (~10 s once torch has cached it on
            disk). A failed compilation warns and fits without. ``None``: when the fit has at
            least ``COMPILE_PIXELS`` pixels.
        tile: pixels per tile; 0 sizes tiles to ``memory_gib``.
        memory_gib: the memory budget of the whole fit: the frame stack, its masks, the torch
            runtime and a tile (tiles are sized to what is left, at least 256 pixels).
        dtype: ``float32`` or ``float64``.
        device: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ...
        lm: the solver's settings.
    """

    model: str = "auto"
    ladder: tuple[str, ...] = LADDER
    smooth: float = 0.0
    select_z: float = 3.0
    uncertainty: bool = True
    flag_peak_misfit: float = 3.0
    flag_astray: float = 2.0
    flag_reach: float = 1.5
    init: str = "fri"
    detect: float = 5.0
    noise_floor: float = 0.002
    naive_alpha: float = 0.1
    saturation: float | None = None
    grow: int = 1
    shadow: float = 0.02
    trim: float = 0.25
    cut: float = 3.0
    fri_method: str | None = None
    fri_coefficients: int | None = None
    path: str = "auto"
    quadrature: str = "fit"
    compile: bool | None = None
    tile: int = 0
    memory_gib: float = 2.0
    dtype: str = "float32"
    device: str = "auto"
    lm: LMConfig = field(default_factory=LMConfig)

    def __post_init__(self):
        if self.model != AUTO:
            get_model(self.model)
        ladder = tuple(self.ladder)
        object.__setattr__(self, "ladder", ladder)
        if not ladder or len(set(ladder)) != len(ladder) or not all(get_model(name).lobe for name in ladder):
            raise ValueError(
                f"FitConfig.ladder must name one or more models with a lobe, each once "
                f"(of {[name for name in MODELS if get_model(name).lobe]}); got {list(ladder)!r}."
            )
        if not self.select_z >= 0:
            raise ValueError(f"FitConfig.select_z must be >= 0; got {self.select_z!r}.")
        if not (self.smooth >= 0 and math.isfinite(self.smooth)):
            raise ValueError(f"FitConfig.smooth must be >= 0 and finite; got {self.smooth!r}.")
        if self.smooth > 0 and self.model != AUTO:
            raise ValueError(
                f"FitConfig.smooth regularises auto's choice of a lobe; a forced model ({self.model!r}) has none "
                "to regularise: set smooth to 0, or model to 'auto'."
            )
        if self.init not in INITS:
            raise ValueError(f"FitConfig.init must be one of {INITS}; got {self.init!r}.")
        if self.quadrature not in QUADRATURES:
            raise ValueError(f"FitConfig.quadrature must be one of {sorted(QUADRATURES)}; got {self.quadrature!r}.")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"FitConfig.dtype must be 'float32' or 'float64'; got {self.dtype!r}.")
        for name in (
            "detect",
            "noise_floor",
            "naive_alpha",
            "memory_gib",
            "flag_peak_misfit",
            "flag_astray",
            "flag_reach",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"FitConfig.{name} must be > 0; got {getattr(self, name)!r}.")
        if self.tile < 0:
            raise ValueError(f"FitConfig.tile must be >= 0 (0: from memory_gib); got {self.tile}.")


@dataclass(frozen=True)
class Fit:
    """The result of :func:`fit`.

    Attributes:
        svbrdf: the maps, leading dims ``(H, W)``; with a second lobe (``specular2``,
            ``roughness2``) where some pixel got ``ward-dual``.
        residual: ``(H, W)`` RMS of the fit's residual over the valid samples, relative to the
            pixel's mean value.
        quality: ``(H, W)`` in ``[0, 1]``: photometric-stereo quality, times the peak location's
            quality for lobed pixels, halved where the solver did not converge; 0 where ``flags``
            holds a flag of :data:`torchspec.flags.UNTRUSTED` (diverged, fewer than 3 valid
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
            that ``FitConfig.smooth`` took away (``None`` without it).
        flags: ``(H, W)`` int16 bits of :data:`torchspec.flags.FLAGS`: why not to trust a pixel
            (the :data:`torchspec.flags.UNTRUSTED` ones; ``quality`` is then 0) or what to know
            of it (its solver stopped early, its model leaves a residual above the noise, its
            lobe is too weak to place a peak).
        checks: ``peak_misfit`` and ``astray`` ``(H, W)``: the values behind those flags
            (:func:`torchspec.flags.peak_checks`; NaN where not computed: no lobe, a weak one, or
            no noise estimate with a forced model and ``uncertainty`` off).
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


def select_frames(spec: str | None, count: int) -> list[int]:
    """Frame indices from a SPEC: ``None`` or ``all``; a Python slice ``start:stop:step``
    (``::2`` every second frame, ``1::2`` the others); or a comma list of indices and ranges
    ``0,3,10-19`` (inclusive).

    Raises:
        ValueError: a malformed SPEC, an index out of ``[0, count)``, a repeated frame or an
            empty selection.
    """
    if spec is None or spec.strip() in ("", "all"):
        return list(range(count))
    text = spec.strip()
    try:
        if ":" in text:
            parts = [int(p) if p.strip() else None for p in text.split(":")]
            if len(parts) > 3 or (len(parts) == 3 and parts[2] == 0):
                raise ValueError
            picked = list(range(count))[slice(*parts)]
        else:
            picked = []
            for item in text.split(","):
                if "-" in item.strip()[1:]:
                    low, high = item.split("-", 1)
                    picked += list(range(int(low), int(high) + 1))
                else:
                    picked.append(int(item))
    except ValueError:
        raise ValueError(
            f"frames SPEC must be 'all', a slice 'start:stop:step' or a list '0,3,10-19'; got {spec!r}."
        ) from None
    bad = [k for k in picked if not 0 <= k < count]
    if bad:
        raise ValueError(f"frames SPEC {spec!r} names frame(s) {bad[:5]} outside 0..{count - 1}.")
    if len(set(picked)) != len(picked):
        raise ValueError(f"frames SPEC {spec!r} names a frame twice.")
    if not picked:
        raise ValueError(f"frames SPEC {spec!r} selects no frame of {count}.")
    return picked


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


RUNTIME_BYTES = 768 * 2**20
"""What a fit holds besides its stack and tiles: the torch runtime and fixed work arrays (measured:
~250 MB after importing torch, ~450 MB more at the first tile whatever its size)."""


def _tile_size(config: FitConfig, frames: int, channels: int, itemsize: int, reserved: int) -> int:
    """Pixels per tile: ``config.tile``, or what fits in ``memory_gib`` after ``reserved`` bytes
    (the stack and its masks) and :data:`RUNTIME_BYTES`."""
    if config.tile:
        return config.tile
    p = max(get_model(name).size(channels) for name in (config.ladder if config.model == AUTO else (config.model,)))
    # Per pixel: observations, weights, values, residuals and the Jacobian twice (the full columns and
    # the model's), J^T J, plus the photometric and specular stages' (N, K) work arrays; twice that
    # for transients (~20 kB per pixel was measured at K = 144, C = 3, float32, when the solver held
    # the Jacobian; it now takes normal equations, the Jacobian living in chunks: a conservative bound).
    per_pixel = itemsize * frames * (channels * (2 * p + 8) + 16) + itemsize * 4 * p * p
    available = config.memory_gib * 2**30 - reserved - RUNTIME_BYTES
    return int(max(256, min(1 << 17, available / (2 * per_pixel))))


_COMPILE_FAILED = []  # a compilation that failed once in this process is not tried again


def _lm_stage(model, start: SVBRDF, observed, weight, lights, view, channels, config):
    bounds = model.bounds(len(channels))
    quadrature = QUADRATURES[config.quadrature]
    params = bounds.to_free(model.pack(start))

    def run(compile: bool):
        fn = model.residuals(
            observed, weight, lights, view, channels, path=config.path, compile=compile, normal=True, **quadrature
        )
        return solve(bounded(fn, bounds), params, config=config.lm)

    if config.compile and not _COMPILE_FAILED:
        try:
            result = run(True)
        except Exception as error:  # no C++ compiler, an unsupported device, ...: the same fit without
            _COMPILE_FAILED.append(error)
            warnings.warn(f"torch.compile failed ({type(error).__name__}: {error}); fitting without it.", stacklevel=2)
            result = run(False)
    else:
        result = run(False)
    return model.unpack(bounds.from_free(result.params)[0], channels, order=True), result


@dataclass(frozen=True)
class Start:
    """What the stages before the solver give a batch of ``n`` pixels (:func:`start`).

    Attributes:
        diffuse: the photometric-stereo fit (:class:`torchspec.photometric.Diffuse`).
        specular: the specular start (:class:`torchspec.specular.Start`).
        lobe: ``(n,)`` bool, the pixels whose residual peaks above the noise: fitted with a lobe.
        level: ``(n,)`` the pixels' mean value (divided by exposure and irradiance).
        times: seconds per stage.
    """

    diffuse: Diffuse
    specular: SpecularStart
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


def _context(lights: Lights) -> dict:
    """What the stages need of the lights, computed once per fit."""
    point = lights.kernel.kind == "point"
    return {
        "directions": lights.directions if point else diffuse_directions(lights),
        "layout": layout_of(lights.directions[:, :2]),
        "kernel_variance": 0.0
        if point
        else float(lights.kernel.covariance(lights.directions[:1])[0].diagonal().mean()),
    }


def start(
    y: Tensor, valid: Tensor, lights: Lights, view: Tensor, *, config: FitConfig, context: dict | None = None
) -> Start:
    """The fit's stages before the solver, for ``n`` pixels: photometric stereo, the lobe test and
    the specular start of ``config.init``.

    Args:
        y: ``(n, K, C)`` recorded values.
        valid: ``(n, K)`` samples to use.
        lights, view: the frames' lights and the view.
        config: the fit's settings.
        context: :func:`_context` of ``lights`` when the caller has it.
    """
    ctx = context if context is not None else _context(lights)
    samples = y / lights.scale.to(y.dtype)
    times = {}
    t0 = time.perf_counter()
    ps = photometric_stereo(samples, ctx["directions"], valid=valid, cut=config.cut, trim=config.trim)
    times["photometric"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    clean = torch.where(valid[..., None], samples, torch.zeros_like(samples))
    count = valid.sum(-1).clamp(min=1).to(y.dtype)
    level = clean.mean(-1).sum(-1) / count  # mean value per pixel
    residual = specular_residual(clean, ps.normal, ps.diffuse, ctx["directions"])
    residual = torch.where(valid, residual, torch.zeros_like(residual))
    noise = torch.maximum(ps.noise, config.noise_floor * level)
    lobe = residual.amax(-1) > config.detect * noise
    start_args = dict(prior_normal=ps.normal, kernel_variance=ctx["kernel_variance"])
    if config.init == "fri":
        found = locate_peak(
            residual,
            ctx["layout"],
            view,
            method=config.fri_method,
            num_coefficients=config.fri_coefficients,
            **start_args,
        )
    elif config.init == "grid":
        found = grid_search(residual, ctx["layout"], view, **start_args)
    else:
        found = naive_start(residual, ctx["layout"], view, prior_normal=ps.normal, alpha=config.naive_alpha)
    times["specular_start"] = time.perf_counter() - t0
    return Start(ps, found, lobe, level, times)


def _tile(y: Tensor, valid: Tensor, lights: Lights, view: Tensor, channels, config: FitConfig, ctx: dict) -> dict:
    """All stages for one tile: ``y (n, K, C)`` recorded values, ``valid (n, K)``."""
    begun = start(y, valid, lights, view, config=config, context=ctx)
    ps, level, times = begun.diffuse, begun.level, dict(begun.times)
    lobe = begun.lobe if config.model != "diffuse" else torch.zeros_like(begun.lobe)
    count = valid.sum(-1).clamp(min=1).to(y.dtype)
    t0 = time.perf_counter()
    ladder = config.ladder if config.model == AUTO else (() if config.model == "diffuse" else (config.model,))
    n, c = y.shape[0], y.shape[-1]
    safe_level = torch.where(level > 0, level, torch.ones_like(level))
    weight = valid.to(y.dtype) / safe_level[:, None]
    observed = torch.where(valid[..., None], y, torch.zeros_like(y))
    scale = lights.scale.to(y.dtype)[None]  # (1, K, C or 1)
    # The noise of each sample, for the criterion and the deviations: the sensor's variance
    # a y + b (noise.affine_noise, fitted below to the first models' residuals), floored at
    # noise_floor times the pixel's level (model error: the quadrature, a lobe's shape).
    sensor = y.new_zeros(2)

    def chi_weight(index: Tensor) -> Tensor:
        """One over each sample's noise ``(m, K, C)`` (0 for invalid samples)."""
        variance = sensor[0] * observed[index].clamp(min=0.0) + sensor[1]
        floor = config.noise_floor * safe_level[index, None, None] * scale
        sigma = torch.maximum(variance.sqrt(), floor).clamp(min=torch.finfo(y.dtype).tiny)
        return valid[index, :, None].to(y.dtype) / sigma

    samples = valid.sum(-1).to(y.dtype) * c
    quadrature = QUADRATURES[config.quadrature]

    grey = len(ladder) == 1 and get_model(ladder[0]).grey
    normal, diffuse = ps.normal.clone(), ps.diffuse.clone()
    specular = y.new_zeros((n, 1 if grey else c))
    roughness = y.new_zeros((n, 2))
    rotation = y.new_zeros(n) if any(get_model(name).anisotropic for name in ladder) else None
    dual = any(get_model(name).dual for name in ladder)  # a second lobe's maps, 0 where not fitted
    specular2, roughness2 = (y.new_zeros((n, 1)), y.new_zeros((n, 2))) if dual else (None, None)
    status = torch.zeros(n, dtype=torch.int8, device=y.device)
    iterations = torch.zeros(n, dtype=torch.int32, device=y.device)
    cost = y.new_zeros(n)
    code = torch.zeros(n, dtype=torch.int8, device=y.device)
    criterion = torch.full((n,), math.inf, dtype=y.dtype, device=y.device)
    found_quality = torch.ones_like(level)
    misfit = torch.zeros(n, dtype=torch.bool, device=y.device)
    # At each pixel's chosen fit, for the flags (torchspec.flags): per sample, the squared residual in
    # noise units and the samples less the diffuse part; per pixel, the lobe's signal-to-noise ratio.
    z2, excess, lobe_snr = y.new_zeros((n, y.shape[1])), y.new_zeros((n, y.shape[1])), y.new_zeros(n)
    tried: dict[str, int] = {}
    deviation = {
        "normal": y.new_full((n,), math.nan),
        "diffuse": y.new_full((n, c), math.nan),
        "specular": y.new_full((n, specular.shape[-1]), math.nan),
        "roughness": y.new_full((n, 2), math.nan),
    }
    if dual:
        deviation.update(specular2=y.new_full((n, 1), math.nan), roughness2=y.new_full((n, 2), math.nan))

    def assess(model, index, fitted, result):
        """The fit's chi-square, deviations and flag inputs (:func:`_uncertainty`), its criterion (NaN
        without the noise, inf where it diverged) and whether its residual is above the noise."""
        if config.uncertainty or config.model == AUTO:
            chi2, std, samples_at = _uncertainty(
                model,
                fitted,
                observed[index],
                chi_weight(index),
                weight[index, :, None].expand(-1, -1, c),
                lights,
                view,
                config.path,
                quadrature,
                config.compile,
            )
        else:  # one model, nothing to compare: keep it, with neither criterion nor deviations
            chi2, std, samples_at = torch.full_like(result.cost, -math.inf), {}, None
        dof = (samples[index] - model.size(c)).clamp(min=1.0)
        bic = chi2 + model.size(c) * torch.log(samples[index].clamp(min=1.0))
        bic = torch.where(result.status == DIVERGED, torch.full_like(bic, math.inf), bic)
        unexplained = chi2 > dof + config.select_z * (2.0 * dof).sqrt()
        return chi2, std, samples_at, bic, unexplained

    def keep(name, index, fitted, result) -> Tensor:
        """Take the fit of model ``name`` where its criterion is the lowest so far; returns the
        pixels (of ``index``) whose residual it leaves above the noise."""
        model = get_model(name)
        chi2, std, samples_at, bic, unexplained = assess(model, index, fitted, result)
        better = (bic < criterion[index]) | (chi2 == -math.inf)
        bic = torch.where(chi2 == -math.inf, torch.full_like(bic, math.nan), bic)
        pick = index[better]
        fit = fitted[better]
        normal[pick], diffuse[pick] = fit.normal, fit.diffuse
        specular[pick] = fit.specular.expand(-1, specular.shape[-1])
        roughness[pick] = fit.roughness
        if rotation is not None:
            rotation[pick] = fit.rotation if fit.rotation is not None else torch.zeros_like(fit.roughness[:, 0])
        if dual:
            specular2[pick] = fit.specular2 if model.dual else 0.0
            roughness2[pick] = fit.roughness2 if model.dual else 0.0
        status[pick], iterations[pick] = result.status[better], result.iterations[better]
        cost[pick], criterion[pick] = result.cost[better], bic[better]
        code[pick] = MODEL_CODES.index(name)
        for key, value in std.items():
            if key not in deviation:  # a second lobe's, where no model has one
                continue
            chosen = value[better]
            deviation[key][pick] = chosen.expand(-1, deviation[key].shape[-1]) if chosen.dim() > 1 else chosen
        tried[name] = tried.get(name, 0) + index.numel()
        misfit[pick] = unexplained[better]
        if samples_at is not None:
            z2[pick], excess[pick], lobe_snr[pick] = (value[better] for value in samples_at)
        return unexplained

    # Pixels without a peak: normal and k_d only; pixels with a peak: the first model of the ladder
    # from the specular start. Their residuals give the sensor's noise, then the criterion of each.
    first = []
    zero = y.new_zeros((n, 1))
    plain_start = SVBRDF(ps.normal, ps.diffuse, zero, zero.expand(-1, 2), None, channels)  # without a lobe
    index = (~lobe).nonzero()[:, 0]
    if index.numel():
        first.append(
            (
                "diffuse",
                index,
                *_lm_stage(
                    get_model("diffuse"),
                    plain_start[index],
                    observed[index],
                    weight[index],
                    lights,
                    view,
                    channels,
                    config,
                ),
            )
        )
    index = lobe.nonzero()[:, 0]
    found_quality[index] = begun.specular.quality[index]
    if index.numel() and ladder:
        init = begun.svbrdf(channels)[index]
        first.append(
            (
                ladder[0],
                index,
                *_lm_stage(get_model(ladder[0]), init, observed[index], weight[index], lights, view, channels, config),
            )
        )
    if first and (config.uncertainty or config.model == AUTO):
        sensor = torch.stack(_sensor_noise(first, begun.lobe, observed, valid, safe_level, c))
    index = y.new_zeros(0, dtype=torch.long)
    for name, at, fitted, result in first:
        unexplained = keep(name, at, fitted, result)
        if name != "diffuse":
            index, init = at[unexplained], fitted[unexplained]
    # The larger models of the ladder, each from the previous one's solution, on the pixels it
    # leaves unexplained.
    for name in ladder[1:]:
        if index.numel() == 0:
            break
        model = get_model(name)
        fitted, result = _lm_stage(model, init, observed[index], weight[index], lights, view, channels, config)
        unexplained = keep(name, index, fitted, result)
        index, init = index[unexplained], fitted[unexplained]
    times["lm"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    svbrdf = SVBRDF(normal, diffuse, specular, roughness, rotation, channels, specular2, roughness2)
    checked = config.uncertainty or config.model == AUTO  # the checks need the sensor's noise
    checks = {name: y.new_full((n,), math.nan) for name in ("peak_misfit", "astray")}
    few = valid.sum(-1) < 3
    flags = _solver_flags(status, few)
    if checked:
        lobed = torch.tensor([get_model(name).lobe for name in MODEL_CODES], device=y.device)[code.long()]
        weak = lobed & (lobe_snr < WEAK_LOBE_SNR)
        flags = flags | torch.where(weak, bit("weak_lobe"), 0).to(torch.int16)
        index = (lobed & ~few & ~weak).nonzero()[:, 0]
        if index.numel():
            local, astray = peak_checks(
                svbrdf[index], z2[index], excess[index], valid[index], lights, view, reach=config.flag_reach
            )
            checks["peak_misfit"][index], checks["astray"][index] = local, astray
        for name, where in (
            ("undetermined", ~deviation["normal"].isfinite() & ~few & ~weak),
            ("peak_misfit", checks["peak_misfit"] > config.flag_peak_misfit),
            ("astray", checks["astray"] > config.flag_astray),
            ("misfit", misfit),
        ):
            flags = flags | torch.where(where, bit(name), 0).to(torch.int16)
    times["checks"] = time.perf_counter() - t0

    rms = (2.0 * cost / (count * c)).sqrt()
    quality = _quality(ps.quality * found_quality, status, flags)

    plain = None
    if config.smooth > 0:
        # Every pixel without a lobe, for the neighbours' term of the choice (_smooth_choice, over the
        # whole image in _result): the pixels given a lobe are fitted without one too.
        plain = {
            "normal": normal.clone(),
            "diffuse": diffuse.clone(),
            "criterion": torch.where(code == 0, criterion, torch.full_like(criterion, math.inf)),
            "status": status.clone(),
            "iterations": iterations.clone(),
            "residual": rms.clone(),
            "quality": quality.clone(),
            "flags": flags.clone(),
            "std_normal": deviation["normal"].clone(),
            "std_diffuse": deviation["diffuse"].clone(),
        }
        index = (code > 0).nonzero()[:, 0]
        if index.numel():
            model = get_model("diffuse")
            fitted, result = _lm_stage(
                model, plain_start[index], observed[index], weight[index], lights, view, channels, config
            )
            _, std, _, bic, unexplained = assess(model, index, fitted, result)
            tried["diffuse"] = tried.get("diffuse", 0) + index.numel()
            few_at = few[index]
            alone = _solver_flags(result.status, few_at)
            for name, where in (("undetermined", ~std["normal"].isfinite() & ~few_at), ("misfit", unexplained)):
                alone = alone | torch.where(where, bit(name), 0).to(torch.int16)
            for key, value in (
                ("normal", fitted.normal),
                ("diffuse", fitted.diffuse),
                ("criterion", bic),
                ("status", result.status),
                ("iterations", result.iterations),
                ("residual", torch.nan_to_num((2.0 * result.cost / (count[index] * c)).sqrt(), nan=math.inf)),
                ("quality", _quality(ps.quality[index], result.status, alone)),
                ("flags", alone),
                ("std_normal", std["normal"]),
                ("std_diffuse", std["diffuse"]),
            ):
                plain[key][index] = value
    return {
        "svbrdf": svbrdf,
        "flags": flags,
        **{f"check_{name}": value for name, value in checks.items()},
        "residual": torch.nan_to_num(rms, nan=math.inf),
        "quality": quality,
        "status": status,
        "iterations": iterations,
        "lobe": lobe,
        "model": code,
        "criterion": criterion,
        "std": deviation,
        "tried": tried,
        "noise": sensor,
        "times": times,
        "plain": plain,
    }


def _quality(base: Tensor, status: Tensor, flags: Tensor) -> Tensor:
    """A pixel's quality: ``base``, halved where the solver did not converge, 0 where untrusted."""
    quality = torch.where(status == CONVERGED, base, 0.5 * base)
    return torch.where(untrusted(flags), torch.zeros_like(quality), quality)


def _solver_flags(status: Tensor, few: Tensor) -> Tensor:
    """The flags a fit gets from its solver and its samples alone: ``diverged``, ``few_samples`` and
    ``not_converged``."""
    flags = torch.zeros(status.shape, dtype=torch.int16, device=status.device)
    for name, where in (
        ("diverged", status == DIVERGED),
        ("few_samples", few),
        ("not_converged", (status != CONVERGED) & (status != DIVERGED)),
    ):
        flags = flags | torch.where(where, bit(name), 0).to(torch.int16)
    return flags


NOISE_PIXELS = 64
"""The fewest pixels without a lobe that set the sensor's noise on their own (:func:`_sensor_noise`)."""


def _sensor_noise(
    first: list, peaked: Tensor, observed: Tensor, valid: Tensor, level: Tensor, channels: int
) -> tuple[Tensor, Tensor]:
    """The sensor's ``(a, b)`` (:func:`torchspec.noise.affine_noise`) from the first fitted models'
    costs ``0.5 sum (r / level)^2`` over each pixel's valid samples (diverged fits left out).

    The pixels without a peak (``peaked (n,)`` false), fitted without a lobe, are used when there
    are ``NOISE_PIXELS`` of them: an unweighted fit of a lobe absorbs more than its share of the
    noise at the peak, where the shot noise is largest (its samples' leverage), and its residual
    understates the noise by ~5 %; a lobe forced away (``--model diffuse``) leaves a misfit. So the
    noise, and the criterion with it, is the same whichever model is fitted or forced."""
    parts = []
    for name, index, _, result in first:
        keep = result.status != DIVERGED
        parts.append((name, index[keep], result.cost[keep], ~peaked[index[keep]]))
    plain = [(name, at[m], cost[m]) for name, at, cost, m in parts if name == "diffuse"]
    if sum(at.numel() for _, at, _ in plain) < NOISE_PIXELS:
        plain = [(name, at, cost) for name, at, cost, _ in parts]
    squares, values, counts, params = [], [], [], []
    for name, at, cost in plain:
        squares.append(2.0 * cost * level[at] ** 2)
        values.append((observed[at].clamp(min=0.0) * valid[at, :, None]).sum((1, 2)))
        counts.append(valid[at].sum(-1) * channels)
        params.append(torch.full_like(squares[-1], get_model(name).size(channels)))
    return affine_noise(torch.cat(squares), torch.cat(values), torch.cat(counts), torch.cat(params))


def _uncertainty(
    model,
    svbrdf: SVBRDF,
    observed: Tensor,
    weight: Tensor,
    fit_weight: Tensor,
    lights: Lights,
    view: Tensor,
    path,
    quadrature,
    compile,
) -> tuple[Tensor, dict[str, Tensor], tuple[Tensor, Tensor, Tensor]]:
    """The fit's ``chi^2 = sum ((render - observed) weight)^2`` per pixel ``(n,)``, ``weight``
    being one over each sample's noise, what :mod:`torchspec.flags` takes (``z2`` and ``excess``,
    each ``(n, K)``, and ``lobe_snr (n,)``), and the standard deviations of its parameters there:
    ``normal`` (radians, the angle), ``diffuse (n, C)``, ``specular (n, C_s)``, ``roughness (n, 2)``,
    ``specular2 (n, 1)`` and ``roughness2 (n, 2)`` (``ward-dual``'s second lobe); NaN for the
    parameters the model does not have, ``inf`` for those the data leave undetermined.

    The estimate minimised ``|fit_weight (render - observed)|^2``, not the noise-weighted residual
    (it is fitted before the noise is known): its covariance is the sandwich ``A^-1 B A^-1``
    (:func:`torchspec.jacobian.sandwich_terms`), larger than the inverse Fisher information
    ``J^T S^-1 J`` (the Cramer-Rao bound) wherever the samples' noise differs within a pixel (shot
    noise at a specular peak)."""
    n, c = svbrdf.diffuse.shape
    like = dict(dtype=weight.dtype, device=weight.device)
    select = model.selection(c, weight)
    if n == 0:
        empty = weight.new_zeros(0, weight.shape[1])
        return weight.new_zeros(0), {}, (empty, empty, weight.new_zeros(0))

    def run(fused: bool):
        return sandwich_terms(
            svbrdf,
            lights,
            view,
            observed,
            weight,
            fit_weight,
            select,
            path=path,
            diffuse_only=not model.lobe,
            compile=fused,
            samples=True,
            **quadrature,
        )

    if compile and not _COMPILE_FAILED:
        try:
            cost, bread, meat, z2, excess, lobe_snr = run(True)
        except Exception as error:  # as in _lm_stage: the same evaluation without torch.compile
            _COMPILE_FAILED.append(error)
            warnings.warn(f"torch.compile failed ({type(error).__name__}: {error}); fitting without it.", stacklevel=2)
            cost, bread, meat, z2, excess, lobe_snr = run(False)
    else:
        cost, bread, meat, z2, excess, lobe_snr = run(False)
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
    nan = math.nan
    out = {"normal": normal, "diffuse": std[:, 2 : 2 + c]}
    if model.lobe:
        at = 2 + c + (1 if model.grey else c)
        out["specular"] = std[:, 2 + c : at]
        out["roughness"] = std[:, at : at + 2] if model.anisotropic else std[:, at : at + 1].expand(-1, 2)
    else:
        out["specular"] = torch.full((n, 1), nan, **like)
        out["roughness"] = torch.full((n, 2), nan, **like)
    if model.dual:  # after the first lobe's alpha: k_s2, alpha2
        out["specular2"], out["roughness2"] = std[:, at + 1 : at + 2], std[:, at + 2 : at + 3].expand(-1, 2)
    else:
        out["specular2"], out["roughness2"] = torch.full((n, 1), nan, **like), torch.full((n, 2), nan, **like)
    return 2.0 * cost, out, (z2, excess, lobe_snr)


class FitInterrupted(KeyboardInterrupt):
    """A fit stopped by Ctrl-C (or another ``KeyboardInterrupt``) with a checkpoint: its finished
    tiles are saved and ``fit(..., checkpoint=..., resume=True)`` continues it."""

    def __init__(self, done: int, total: int, checkpoint: Path):
        super().__init__(f"the fit was interrupted after {done} of {total} tiles; they are saved in {checkpoint}.")
        self.done, self.total, self.checkpoint = done, total, checkpoint


STATE = "state.json"
"""The checkpoint's record of the job it belongs to (:func:`_job`)."""


def _job(capture: Capture, picked: list[int], config: FitConfig, tile: int, pixels: int) -> dict:
    """What a checkpoint's tiles depend on: the manifest, each frame file's size and time, the
    frames, the settings and the tiling (a resumed fit must be the same job to give the same maps); as
    JSON gives it back (tuples as lists), to compare with a saved one."""
    files = [capture.root / capture.frames[k].file for k in picked]
    job = {
        "torchspec": __version__,
        "capture": str(capture.root.resolve()),
        "manifest": _stamp(capture.manifest) if capture.manifest.is_file() else None,
        "files": [_stamp(f) if f.is_file() else None for f in files],
        "frames": picked,
        "settings": asdict(config),
        "tile_pixels": tile,
        "pixels": pixels,
    }
    return json.loads(json.dumps(job))


def _stamp(path: Path) -> list:
    info = path.stat()
    return [path.name, info.st_size, info.st_mtime_ns]


def _checkpoint(folder: Path, job: dict, resume: bool) -> dict[int, dict]:
    """Open the checkpoint folder: its finished tiles ``{first pixel: tile}`` when resuming the
    same job, none for a new one. Raises ``ValueError`` (naming what differs) for another job,
    and for an unfinished one that is not to be resumed (its work is never silently dropped)."""
    state = folder / STATE
    if not state.is_file():
        if resume and folder.exists() and any(folder.glob("tile-*.pt")):
            raise ValueError(f"{folder} holds tiles but no {STATE}; remove {folder} to start over.")
        folder.mkdir(parents=True, exist_ok=True)
        write_json(state, job)
        return {}
    saved = read_json(state, ValueError, "")
    finished = sorted(folder.glob("tile-*.pt"))
    if not resume:
        raise ValueError(
            f"{folder} holds an unfinished fit ({len(finished)} tile(s) done): continue it with --resume "
            f"(resume=True), or remove {folder} to start over."
        )
    differ = [key for key in job if saved.get(key) != job[key]]
    if differ:
        raise ValueError(
            f"{folder} holds a fit of another job (its {', '.join(differ)} differ from this one's), so resuming "
            f"it would mix two fits; run the same command as before, or remove {folder} to start over."
        )
    tiles = {}
    for path in finished:
        try:
            tile = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as error:  # a tile is written atomically: this is damage from outside
            raise ValueError(f"{path} is not a readable tile ({type(error).__name__}: {error}); remove it.") from error
        tiles[int(tile["first"])] = tile
    for stale in folder.glob(".tile-*"):  # temporaries of a write the interruption cut short
        stale.unlink(missing_ok=True)
    return tiles


def _save_tile(folder: Path, first: int, out: dict) -> None:
    def cpu(value):
        if isinstance(value, Tensor):
            return value.cpu()
        if isinstance(value, SVBRDF):
            return value.to(device="cpu")
        if isinstance(value, dict):
            return {name: cpu(item) for name, item in value.items()}
        return value

    with atomic_path(folder / f"tile-{first:012d}.pt") as tmp:
        torch.save({"first": first, **{name: cpu(value) for name, value in out.items()}}, tmp)


def _load_tile(tile: dict, device: torch.device) -> dict:
    def move(value):
        if isinstance(value, Tensor):
            return value.to(device)
        if isinstance(value, SVBRDF):
            return value.to(device=device)
        if isinstance(value, dict):
            return {name: move(item) for name, item in value.items()}
        return value

    return {name: move(value) for name, value in tile.items() if name != "first"}


def _setup(
    capture: Capture | str | Path, config: FitConfig | None, frames: str | list[int] | None
) -> tuple[FitConfig, Capture, list[int], Lights, Tensor]:
    """What every engine of a fit starts from: the settings, the capture (its manifest read), the
    frames picked, their lights and the view (on the settings' device and dtype)."""
    config = config or FitConfig()
    capture = capture if isinstance(capture, Capture) else read_capture(capture)
    picked = frames if isinstance(frames, list) else select_frames(frames, len(capture.frames))
    if len(picked) < 4:
        raise ValueError(
            f"a fit needs at least 4 frames (3 for the normal and k_d, one more for a lobe); got {len(picked)}."
        )
    dtype = getattr(torch, config.dtype)
    device = _device(config.device)
    everything = lights_of(capture, dtype=dtype)
    index = torch.tensor(picked)
    lights = Lights(
        everything.directions[index], everything.kernel, everything.irradiance[index], everything.exposure[index]
    ).to(device=device)
    view = torch.tensor(capture.view, dtype=dtype, device=device)
    return config, capture, picked, lights, view


def _plan(config: FitConfig, k: int, c: int, h: int, w: int, itemsize: int) -> tuple[FitConfig, int]:
    """The settings with ``compile`` decided and the pixels per tile of a fit of a ``(K, C, H, W)``
    stack: from the capture's size and the settings only, so that every engine tiles a fit alike
    (the same maps, and either resumes the other's checkpoint)."""
    if config.compile is None:
        config = replace(config, compile=h * w >= COMPILE_PIXELS)
    reserved = (k * c * itemsize + 3 * k) * h * w  # the stack, three bool masks
    return config, _tile_size(config, k, c, itemsize, reserved)


MASK_KINDS = ("nonfinite", "saturated", "shadowed")
"""The masks of :class:`torchspec.photometric.Masks` that :func:`_fit_tile` takes and counts."""


def _fit_tile(
    first: int,
    values: Tensor,
    masks: list[Tensor],
    lights: Lights,
    view: Tensor,
    channels: tuple[str, ...],
    config: FitConfig,
    ctx: dict,
    folder: Path | None,
) -> dict:
    """One tile, as every engine fits it (in-process, :mod:`torchspec.distributed`): the pixels
    ``first .. first + n - 1`` of the image from their values ``(K, C, n)`` and their masks of
    :data:`MASK_KINDS` (each ``(K, n)``); saved in ``folder`` when given. Returns :func:`_tile`'s
    output with the count of masked samples of each kind."""
    y = values.permute(2, 0, 1)  # (n, K, C)
    valid = ~(masks[0] | masks[1] | masks[2]).T
    out = _tile(y, valid, lights, view, channels, config, ctx)
    out["masked"] = {name: int(m.sum()) for name, m in zip(MASK_KINDS, masks, strict=True)}
    if folder is not None:
        _save_tile(folder, first, out)
    return out


def fit(
    capture: Capture | str | Path,
    *,
    config: FitConfig | None = None,
    frames: str | list[int] | None = None,
    progress: bool = False,
    checkpoint: str | Path | None = None,
    resume: bool = False,
) -> Fit:
    """Fit SVBRDF maps to a capture.

    Args:
        capture: a :class:`~torchspec.io.Capture` or its folder.
        config: :class:`FitConfig` (the defaults otherwise).
        frames: the frames to fit: a SPEC of :func:`select_frames` or a list of indices.
        progress: show a tqdm bar over the pixels.
        checkpoint: a folder where each finished tile is saved (atomically), so that an
            interrupted fit can be continued; a ``KeyboardInterrupt`` then becomes
            :class:`FitInterrupted`. The caller removes the folder once the maps are written.
        resume: continue the fit whose tiles ``checkpoint`` holds (the same capture, frames,
            settings and tiling, else ``ValueError``): the maps are identical to an
            uninterrupted fit's. Without it, a checkpoint holding tiles is an error (never
            silently dropped).

    Returns:
        :class:`Fit`.

    Raises:
        CaptureError: an unreadable capture or frame, or a light whose shape is unknown. (NaN
            or Inf pixels are not an error: they are masked, with a warning naming the frame, and
            counted in ``stats["masked_samples"]``.)
        ValueError: a bad SPEC or setting.

    Example:
        >>> result = fit("painting-dev", frames="::2")  # doctest: +SKIP
        >>> write_fit("maps", result)  # doctest: +SKIP
    """
    clock = time.perf_counter()
    config, capture, picked, lights, view = _setup(capture, config, frames)
    dtype, device = view.dtype, view.device
    # NaN or Inf pixels (a failed HDR merge) are masked like saturated ones, with a warning per frame.
    stack = capture.read_frames(picked, dtype=dtype, device=device, nonfinite="keep")  # (K, C, H, W)
    read_seconds = time.perf_counter() - clock

    clock = time.perf_counter()
    masks = sample_masks(stack, saturation=config.saturation, grow=config.grow, shadow=config.shadow)
    kinds = [m.flatten(1) for m in (masks.nonfinite, masks.saturated, masks.shadowed)]  # (K, H W) views
    ctx = _context(lights)
    mask_seconds = time.perf_counter() - clock

    k, c, h, w = stack.shape
    pixels = h * w
    config, tile = _plan(config, k, c, h, w, stack.element_size())
    flat = stack.flatten(2)  # (K, C, H W), a view
    folder = Path(checkpoint) if checkpoint is not None else None
    done = _checkpoint(folder, _job(capture, picked, config, tile, pixels), resume) if folder is not None else {}
    firsts = range(0, pixels, tile)
    parts = []
    with tqdm(total=pixels, unit="px", disable=not progress, desc="fit") as bar:
        try:
            for first in firsts:
                stop = min(first + tile, pixels)
                if first in done:  # resumed: the tile as it was computed (its times are that run's)
                    out = _load_tile(done[first], device)
                else:
                    at = slice(first, stop)
                    values, tile_masks = flat[:, :, at], [m[:, at] for m in kinds]
                    out = _fit_tile(first, values, tile_masks, lights, view, capture.channels, config, ctx, folder)
                parts.append(out)
                bar.update(stop - first)
        except KeyboardInterrupt as interrupt:
            if folder is None:
                raise
            raise FitInterrupted(len(parts), len(firsts), folder) from interrupt
    stats = {
        "capture": str(capture.root),
        "frames": picked,
        "settings": asdict(config),
        "device": str(device),
        "pixels": pixels,
        "tile_pixels": tile,
        "resumed_tiles": len(done),
        "seconds": {"read": read_seconds, "masks": mask_seconds},
        "masked_samples": masks.counts(),
    }
    return _result(parts, h, w, capture.channels, stats, started=clock - read_seconds)  # clock: the masks began


SMOOTH_SWEEPS = 50
"""The most sweeps of :func:`smooth_choice` (each lowers the total; it stops at the first that changes nothing)."""


def smooth_choice(lobed: Tensor, plain: Tensor, weight: float, sweeps: int = SMOOTH_SWEEPS) -> Tensor:
    """Per pixel of an image, a lobe or none: ``(H, W)`` bool, from the criterion of each pixel's
    fit with a lobe ``lobed (H, W)`` and without ``plain (H, W)`` (``inf`` where there is none), a
    local minimum of

        E = sum_p criterion(p) + weight * (pairs of 4-neighbours on different sides)

    by iterated conditional modes: from each pixel's own choice, each pixel takes the side that
    lowers ``E`` given its neighbours, the two colours of a checkerboard in turn (a pixel's
    neighbours are all of the other colour, so each update lowers ``E`` and the sweeps end). A tie
    keeps the pixel's side; a pixel with one of the two fits only keeps it."""
    if lobed.shape != plain.shape or lobed.dim() != 2:
        raise ValueError(f"lobed and plain must be (H, W) alike; got {tuple(lobed.shape)} and {tuple(plain.shape)}.")
    choice = lobed < plain
    h, w = choice.shape

    def neighbours(x: Tensor) -> Tensor:  # the sum over each pixel's 4-neighbours (0 beyond the border)
        padded = torch.nn.functional.pad(x[None, None], (1, 1, 1, 1))[0, 0]
        return padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]

    count = neighbours(torch.ones_like(lobed))
    rows = torch.arange(h, device=lobed.device)[:, None]
    colour = (rows + torch.arange(w, device=lobed.device)[None, :]) % 2
    for _ in range(sweeps):
        before = choice
        for turn in (0, 1):
            with_lobe = neighbours(choice.to(lobed.dtype))
            e_lobed = lobed + weight * (count - with_lobe)
            e_plain = plain + weight * with_lobe
            side = torch.where(e_lobed < e_plain, True, torch.where(e_plain < e_lobed, False, choice))
            choice = torch.where(colour == turn, side, choice)
        if torch.equal(choice, before):
            break
    return choice


def _smooth(joined: dict, plain: dict, weight: float) -> int:
    """:func:`smooth_choice` on a joined fit: the pixels it leaves without a lobe take their fit without
    one (``plain``) in every output of ``joined`` (maps, criterion, deviations, flags, ...), in place;
    returns how many pixels changed side."""
    model, criterion = joined["model"], joined["criterion"]
    lobed = torch.where(model > 0, criterion, torch.full_like(criterion, math.inf))
    choice = smooth_choice(lobed, plain["criterion"], weight)
    drop = (model > 0) & ~choice  # the pixels that lose their lobe; the others keep the fit they have
    if not bool(drop.any()):
        return 0
    svbrdf = joined["svbrdf"]
    zero = {
        name: torch.where(drop[..., None] if value.dim() == 3 else drop, torch.zeros_like(value), value)
        for name in ("specular", "roughness", "rotation", "specular2", "roughness2")
        if (value := getattr(svbrdf, name)) is not None
    }
    joined["svbrdf"] = replace(
        svbrdf,
        normal=torch.where(drop[..., None], plain["normal"], svbrdf.normal),
        diffuse=torch.where(drop[..., None], plain["diffuse"], svbrdf.diffuse),
        **zero,
    )
    for key in ("criterion", "status", "iterations", "residual", "quality", "flags"):
        joined[key] = torch.where(drop, plain[key], joined[key])
    joined["model"] = torch.where(drop, torch.zeros_like(model), model)
    joined["lobe"] = joined["lobe"] & ~drop
    for key in joined["checks"]:
        joined["checks"][key] = torch.where(
            drop, torch.full_like(joined["checks"][key], math.nan), joined["checks"][key]
        )
    std = joined["std"]
    std["normal"] = torch.where(drop, plain["std_normal"], std["normal"])
    std["diffuse"] = torch.where(drop[..., None], plain["std_diffuse"], std["diffuse"])
    for key in std:
        if key not in ("normal", "diffuse"):  # the lobe's: none
            std[key] = torch.where(drop[..., None], torch.full_like(std[key], math.nan), std[key])
    return int(drop.sum())


def _result(parts: list[dict], h: int, w: int, channels: tuple[str, ...], stats: dict, started: float) -> Fit:
    """The :class:`Fit` of an image from its tiles' outputs (in pixel order), ``stats`` completed
    with the tiles' statistics and the time since ``started`` (``time.perf_counter``)."""
    times: dict[str, float] = {}
    tried: dict[str, int] = {}
    for out in parts:
        for name, seconds in out["times"].items():
            times[name] = times.get(name, 0.0) + seconds
        for name, pixels_tried in out["tried"].items():
            tried[name] = tried.get(name, 0) + pixels_tried
    c, pixels = len(channels), h * w

    def join(name):
        return torch.cat([p[name] for p in parts]).reshape(h, w, *parts[0][name].shape[1:])

    pieces = [p["svbrdf"] for p in parts]

    def glue(name, tail):
        return (
            None
            if getattr(pieces[0], name) is None
            else torch.cat([getattr(p, name) for p in pieces]).reshape(h, w, *tail)
        )

    svbrdf = SVBRDF(
        glue("normal", (3,)),
        glue("diffuse", (c,)),
        glue("specular", (-1,)),
        glue("roughness", (2,)),
        glue("rotation", ()),
        channels,
        glue("specular2", (-1,)),
        glue("roughness2", (2,)),
    )
    joined = {
        "svbrdf": svbrdf,
        **{name: join(name) for name in ("status", "iterations", "lobe", "model", "criterion", "flags")},
        **{name: join(name) for name in ("residual", "quality")},
        "std": {
            name: torch.cat([p["std"][name] for p in parts]).reshape(h, w, *parts[0]["std"][name].shape[1:])
            for name in parts[0]["std"]
        },
        "checks": {name: join(f"check_{name}") for name in ("peak_misfit", "astray")},
    }
    smoothed = None
    if parts[0].get("plain") is not None:  # FitConfig.smooth: the choice of a lobe over the whole image
        plain = {
            name: torch.cat([p["plain"][name] for p in parts]).reshape(h, w, *parts[0]["plain"][name].shape[1:])
            for name in parts[0]["plain"]
        }
        smoothed = _smooth(joined, plain, stats["settings"]["smooth"])
    svbrdf = joined["svbrdf"]
    if svbrdf.specular2 is not None and not bool((svbrdf.specular2 > 0).any()):
        # A ladder with ward-dual that no pixel took: no second lobe's maps or deviations.
        svbrdf = replace(svbrdf, specular2=None, roughness2=None)
        joined["std"] = {
            name: value for name, value in joined["std"].items() if name not in ("specular2", "roughness2")
        }
    status, iterations, lobe = joined["status"], joined["iterations"], joined["lobe"]
    model, criterion, flags = joined["model"], joined["criterion"], joined["flags"]
    std, checks = joined["std"], joined["checks"]
    finite = criterion.isfinite()
    total = time.perf_counter() - started
    stats = {
        **stats,
        "seconds": {**stats["seconds"], **times, "total": total},
        "pixels_per_second": pixels / total if total > 0 else None,
        "lobe_pixels": int(lobe.sum()),
        "models": {name: int((model == code).sum()) for code, name in enumerate(MODEL_CODES)},
        "models_tried": tried,
        "criterion": float(criterion[finite].double().sum()) if bool(finite.any()) else None,
        # The sensor's noise variance a y + b per tile (y in recorded units; 0 when not estimated).
        "sensor_noise": {key: [float(p["noise"][i]) for p in parts] for i, key in enumerate("ab")},
        "status": {name: int((status == code).sum()) for code, name in enumerate(STATUS)},
        "iterations": {
            "mean": float(iterations.float().mean()),
            "median": float(iterations.float().median()),
            "max": int(iterations.max()),
            "mean_lobe": float(iterations[lobe].float().mean()) if bool(lobe.any()) else None,
        },
        "median_residual": float(joined["residual"].median()),
        "flags": describe(flags),
        "untrusted": int(untrusted(flags).sum()),
        # FitConfig.smooth: the pixels whose lobe the neighbours' term took away (None: not smoothed).
        "smoothed": smoothed,
    }
    residual, quality = joined["residual"], joined["quality"]
    return Fit(svbrdf, residual, quality, status, iterations, lobe, model, criterion, std, stats, flags, checks)


def write_fit(path: str | Path, result: Fit) -> None:
    """Write a :class:`Fit` as an SVBRDF folder: the maps, ``residual.exr``, ``quality.exr``,
    ``status.exr``, ``iterations.exr``, ``model.exr`` (codes of ``model_codes``),
    ``criterion.exr``, ``flags.exr`` (bits of ``flag_bits``), ``check_peak_misfit.exr``,
    ``check_astray.exr``, the standard deviations ``std_normal_deg.exr``, ``std_diffuse.exr``,
    ``std_specular.exr``, ``std_roughness.exr`` (and ``std_specular2.exr``, ``std_roughness2.exr``
    with a second lobe, whose maps are ``specular2.exr`` and ``roughness2.exr``) and ``svbrdf.json``
    (model, settings, timings, statistics)."""
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
    write_svbrdf(path, result.svbrdf.to(torch.float32), meta=meta, extra=extra)
