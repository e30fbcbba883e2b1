"""The settings of a fit (:class:`FitConfig`, ``configs/fit.yaml``) and the choices they name.

:data:`LADDER` is the order in which ``auto`` tries the lobed models, :attr:`FitConfig.rule` the
rules of the model's integrations, :func:`select_frames` the frames a SPEC picks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from ..config import ConfigError
from ..io.scale import Scale
from ..layout import resolvable_roughness
from ..lights import Lights
from ..lm import LMConfig
from ..models import ALPHA_BOUNDS, MODELS, get_model
from ..quadrature import QUADRATURES, Quadrature
from ..residual_term import TERMS

__all__ = [
    "AUTO",
    "COMPILE_PIXELS",
    "FRI_KERNELS",
    "INITS",
    "LADDER",
    "MODEL_CODES",
    "SHADOWS",
    "FitConfig",
    "select_frames",
]

INITS = ("fri", "naive", "grid")
"""The specular starts of ``FitConfig.init``."""
FRI_KERNELS = ("pixel", "pooled")
"""The lobe spectra of ``FitConfig.fri_kernel``."""
SHADOWS = ("auto", "on", "off")
"""The choices of ``FitConfig.shadows``."""
AUTO = "auto"
"""``FitConfig.model`` that picks each pixel's model."""
LADDER = ("ward-iso", "ward-iso-colour", "ward-aniso", "ward-dual")
"""The lobed models ``auto`` tries, in order: each on the pixels the previous left unexplained."""
CALIBRATE = ("auto", "none", "gains", "positions", "dome")
"""The values of ``FitConfig.calibrate``."""
MODEL_CODES = tuple(MODELS)
"""``model.exr``'s codes: the index of each pixel's model in this tuple."""
COMPILE_PIXELS = 1 << 17
"""``FitConfig.compile=None`` compiles the model for fits of at least this many pixels (the
one-off compilation pays for itself on large fits only)."""


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`torchspec.pipeline.fit` (``configs/fit*.yaml``).

    Attributes:
        model: ``auto`` picks each pixel's model by what it predicts of frames left out of its
            fit (:mod:`torchspec.pipeline.prediction`), trying the larger ones only where the
            smaller leave a residual above the noise (``ladder``); or one model forced on every pixel that shows a peak
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
            the noise: ``uncertainty`` or ``auto``); ``experiments/stability.py`` chose the defaults.
        flag_overshoot: a pixel whose fitted maps render, at some frame of the fit, more than this
            many times the brightest value its photographs recorded is flagged ``implausible``,
            untrusted (:func:`~torchspec.pipeline.checks.overshoot`: a lobe grown without bound where
            its samples were clipped or masked; the photographs show nothing of the kind).
        smooth: spatial regularisation of ``auto``'s choice between a lobe and none (a matte region
            of a painting is contiguous): the criterion of a pixel gains ``smooth`` for each of its
            four neighbours on the other side of that choice, and the image's total is lowered pixel
            by pixel (:func:`torchspec.pipeline.smooth_choice`). Every pixel given a lobe is then
            also fitted without one (its ``diffuse`` fit is the alternative). ``0`` (the default):
            each pixel on its own, and a pixel whose samples show a peak always gets a lobe. In
            units of the criterion: the BIC charges ``ln n`` (~5 for a few hundred samples) per
            parameter, so ``smooth = 10`` lets four matte neighbours outweigh about eight
            parameters' worth of improvement.
        select_z: ``auto`` tries the next larger model where the fit's chi-square exceeds its
            degrees of freedom by more than ``select_z`` of its standard deviations
            (``dof + select_z sqrt(2 dof)``): the residual is not noise.
        predict_z: ``auto`` keeps a larger model where it predicts the frames left out of its fit
            better than the model kept so far by more than ``predict_z`` standard deviations of
            what the noise would make the difference (:mod:`torchspec.pipeline.prediction`).
        folds: the frames are split into this many folds, each left out in turn, for ``auto``'s
            prediction; fold_regions: also leave out whole regions of the light domain (sectors),
            besides folds scattered over it.
        resolve: ``auto`` keeps ``ward-dual`` only where each lobe's roughness is determined within
            ``resolve`` of its value (one standard deviation): two lobes the samples do not
            resolve predict nothing but the frames fitted.
        dual_rms: ``auto`` tries ``ward-dual`` only where the best fit of one lobe leaves a relative
            RMS residual above ``dual_rms`` (of the pixel's level): a second lobe is a large
            structure (two lobes fitted to what one lobe of another shape leaves, such as a
            Beckmann lobe's tails, cost the most of the ladder's time and predict nothing better).
        dual_gate: ``auto`` tries ``ward-dual`` only where a second lobe added to the one-lobe fit,
            to first order (:func:`~torchspec.pipeline.prediction.second_lobe_held_out`), predicts
            the left-out frames better than the model kept so far by more than ``dual_gate``
            deviations of the noise (:func:`~torchspec.statistics.predicts_better`) at one
            of a few roughnesses; ``None``: wherever ``dual_rms`` lets it.
        trust_rms: a pixel whose chosen model leaves a misfit (a residual above the noise) with a
            relative RMS above ``trust_rms`` of its level is flagged ``poor_fit``, untrusted
            (quality 0): no model of the ladder explains it (a shadow, an interreflection, a
            material of another kind), and its maps are not to be used.
        refit: ``0``: each fold's refit is one Gauss-Newton step from the solution (one Jacobian
            per model and pixel); ``N``: ``N`` steps of the solver per fold (all folds of all pixels
            in one batch: about ``folds`` times the cost of the fits).
        calibrate: the lights estimated from the photographs with the maps
            (:func:`torchspec.pipeline.calibration.calibrated`): ``auto`` (what the capture's manifest
            lists as ``unknown``: its irradiance, a gain per frame and channel, with a dome radius
            for lights written as directions, kept where the gains are refused; its lights'
            positions), ``gains``, ``positions`` (near lights' positions and gains), ``dome`` (gains
            and one dome radius for every light, or distant lights where none explains the
            photographs better: :func:`torchspec.lightcal.dome_radius`) or ``none``.
        lobe_resolution: with point lights, no lobe narrower than ``lobe_resolution`` times the
            half vectors' spacing (:func:`torchspec.layout.resolvable_roughness`): a narrower one
            falls between the frames, fits one frame's sample and predicts nothing between them
            (relighting between lights explodes). ``0``: only :data:`torchspec.models.ALPHA_BOUNDS`.
            An extended kernel's blur resolves narrower lobes: no bound from the sampling.
        lobe_support: with point lights, ``auto`` keeps a lobe only where some frame of the fit
            sees at least ``lobe_support`` of its peak (:func:`torchspec.layout.lobe_support`; 1/2:
            a light within the lobe's half maximum): a lobe peaking between the lights, farther
            from each than its width, has a height no photograph determines, and a light at its
            peak sees it at any height. ``0``: no such test.
        residual_term: ``auto`` (the default: ``3`` for a capture imported from photographs, whose
            manifest has a ``source`` block; ``0`` for others, e.g. simulated ones), ``0`` (off),
            ``2`` or ``3``: the order of a smooth per-pixel residual term
            (:mod:`torchspec.residual_term`: hemispherical harmonics of the light direction, 4 or 9
            coefficients per channel, in the sRGB-encoded domain) fitted on top of the chosen model
            and kept only where it predicts left-out frames better (``predict_z``, ``folds``). It
            carries what the physical model cannot (cast shadows, interreflections) for relighting,
            in maps of its own (``residual_term.exr``): the physical maps are unchanged by it.
        term_z: the residual term is kept where its left-out prediction beats the physical
            model's by more than ``term_z`` standard deviations of the noise's share (the margin of
            ``predict_z``; lower, because the noise estimate of photographs includes what no model
            of the ladder explains).
        broad_alpha: the roughness of the broad-lobe start of ``auto``'s pixels that show no peak
            but whose fit without a lobe leaves a misfit (a broad lobe is absorbed by a tilted
            normal and leaves no peak to detect).
        init: the specular start: ``fri`` (FRI peak location), ``naive`` (photometric-stereo
            normal, ``alpha = naive_alpha``) or ``grid`` (dense search).
        detect: a pixel gets a lobe when its residual peaks above ``detect`` times its noise
            level (the larger of the photometric-stereo noise and ``noise_floor`` times the
            pixel's mean value).
        noise_floor: see ``detect``; also the smallest noise of a sample, relative to its
            pixel's level, in the criterion and the deviations (the model's own error: the
            quadrature, a lobe shape the data's material does not follow).
        naive_alpha: the roughness of the naive start.
        saturation: the sensor's clipping level; ``None``: the level the capture records
            (:attr:`torchspec.io.Capture.saturation`, an imported capture's), else a clipped plateau detected.
        grow: saturated regions are grown by this many pixels (of the image fitted: of the
            reduced one with ``downsample``).
        shadow: samples below this fraction of the pixel's median are shadows.
        shadows: cast shadows in the model (:mod:`torchspec.pipeline.shadows`): ``on`` fits the
            maps with each light's visibility over a height field integrated from the normals,
            alternating with the height, and keeps it where it predicts left-out frames better;
            ``auto`` (the default) tries it on captures imported from photographs and where the
            frames hold shadows (a share of samples masked as shadows of at least
            ``torchspec.pipeline.shadows.SHADOW_SHARE``); ``off``: never.
        trim, cut: of the robust photometric stereo.
        fri_method, fri_coefficients: of the peak location (``None``: the defaults).
        fri_kernel: the lobe's spectrum the peak location weighs coefficients by: ``pixel``
            (fitted to each pixel, the default) or ``pooled`` (one spectrum pooled over the
            tile's pixels, :func:`torchspec.fri.estimate_kernel`: nearer the Cramer-Rao bound
            for broad lobes at low SNR when the tile's lobes share a width; needs the
            ``coherent`` method).
        path: the quadrature path of the model (:func:`torchspec.rendering.render`).
        quadrature: ``fit`` (the default): 3 x 3 nodes per frame for the lobe (8 radii where
            the reference rule takes over) and the clamp's fast rule
            (:data:`torchspec.quadrature.CLAMPS`): within 1e-3 of a pixel's largest value;
            ``render``: the renderer's own rules (1e-6).
        compile: fuse the model's integrations with ``torch.compile`` (faster solver steps after
            a one-off compilation). A failed compilation warns and fits without. ``None``: when
            the fit has at least ``COMPILE_PIXELS`` pixels.
        downsample: fit boxes of ``N x N`` pixels, averaged as the frames are read
            (:class:`torchspec.io.scale.Scale`): a quick look at a large capture, in about ``1 / N^2``
            of the memory and time. A box holding a clipped sample is clipped; the maps record the
            scale (``svbrdf.json``'s ``fit.scale``).
        crop: ``(X, Y, W, H)``: fit only these pixels of the capture's frames (``X, Y`` the
            top-left corner), before ``downsample``; ``None``: all of them.
        tile: pixels per tile; 0 sizes tiles to ``memory_gib``, and cuts an image into at least 16 tiles
            of at least 1024 pixels (:func:`torchspec.pipeline.plan.plan`).
        memory_gib: the memory budget of the whole fit: the frame stack, its masks, the torch
            runtime and a tile (tiles are sized to what is left, at least 256 pixels).
        dtype: ``float32`` or ``float64``.
        device: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ...
        threads: torch's CPU threads for each tile: ``auto`` (the default): torch's own count
            (``torch.set_num_threads``, ``OMP_NUM_THREADS``) when its threads sleep at a barrier
            (``import torchspec`` sets ``OMP_WAIT_POLICY=passive``), else the cores other processes
            leave free, measured before each tile; or a number, used as it is
            (:mod:`torchspec.threads`). A cluster's tasks run on one thread each.
        lm: the solver's settings.
    """

    model: str = "auto"
    ladder: tuple[str, ...] = LADDER
    smooth: float = 0.0
    select_z: float = 3.0
    predict_z: float = 3.0
    folds: int = 5
    fold_regions: bool = False
    refit: int = 0
    lobe_resolution: float = 0.5
    lobe_support: float = 0.5
    calibrate: str = "auto"
    residual_term: int | str = AUTO
    term_z: float = 1.0
    broad_alpha: float = 0.25
    resolve: float = 0.5
    dual_rms: float = 0.03
    dual_gate: float | None = 0.0
    trust_rms: float = 0.05
    uncertainty: bool = True
    flag_peak_misfit: float = 3.0
    flag_astray: float = 2.0
    flag_overshoot: float = 10.0
    flag_reach: float = 1.5
    init: str = "fri"
    detect: float = 5.0
    noise_floor: float = 0.002
    naive_alpha: float = 0.1
    saturation: float | None = None
    downsample: int = 1
    crop: tuple[int, int, int, int] | None = None
    grow: int = 1
    shadow: float = 0.02
    shadows: str = AUTO
    trim: float = 0.25
    cut: float = 3.0
    fri_method: str | None = None
    fri_coefficients: int | None = None
    fri_kernel: str = "pixel"
    path: str = "auto"
    quadrature: str = "fit"
    compile: bool | None = None
    tile: int = 0
    memory_gib: float = 2.0
    dtype: str = "float32"
    device: str = "auto"
    threads: int | str = "auto"
    lm: LMConfig = field(default_factory=LMConfig)

    def __post_init__(self):
        if self.model != AUTO and self.model not in MODELS:
            raise ConfigError(f"FitConfig.model must be one of {[AUTO, *sorted(MODELS)]}; got {self.model!r}.")
        ladder = tuple(self.ladder)
        object.__setattr__(self, "ladder", ladder)
        unknown = [name for name in ladder if name not in MODELS]
        if unknown:
            raise ConfigError(f"FitConfig.ladder: each model must be one of {sorted(MODELS)}; got {unknown!r}.")
        if not ladder or len(set(ladder)) != len(ladder) or not all(get_model(name).lobe for name in ladder):
            raise ConfigError(
                f"FitConfig.ladder must name one or more models with a lobe, each once "
                f"(of {[name for name in MODELS if get_model(name).lobe]}); got {list(ladder)!r}."
            )
        if not (self.predict_z >= 0 and math.isfinite(self.predict_z)):
            raise ConfigError(f"FitConfig.predict_z must be >= 0 and finite; got {self.predict_z!r}.")
        if self.residual_term not in (AUTO, 0, *TERMS):
            raise ConfigError(
                f"FitConfig.residual_term must be auto, 0 (off) or an order in {sorted(TERMS)}; got "
                f"{self.residual_term!r}."
            )
        if self.calibrate not in CALIBRATE:
            raise ConfigError(f"FitConfig.calibrate must be one of {list(CALIBRATE)}; got {self.calibrate!r}.")
        if not (self.lobe_resolution >= 0 and math.isfinite(self.lobe_resolution)):
            raise ConfigError(f"FitConfig.lobe_resolution must be >= 0 and finite; got {self.lobe_resolution!r}.")
        if not 0 <= self.lobe_support <= 1:
            raise ConfigError(f"FitConfig.lobe_support must be in [0, 1]; got {self.lobe_support!r}.")
        if not (self.term_z >= 0 and math.isfinite(self.term_z)):
            raise ConfigError(f"FitConfig.term_z must be >= 0 and finite; got {self.term_z!r}.")
        if not self.trust_rms > 0:
            raise ConfigError(f"FitConfig.trust_rms must be > 0; got {self.trust_rms!r}.")
        if not self.dual_rms >= 0:
            raise ConfigError(f"FitConfig.dual_rms must be >= 0; got {self.dual_rms!r}.")
        if self.dual_gate is not None and not (
            isinstance(self.dual_gate, (int, float)) and math.isfinite(self.dual_gate)
        ):
            raise ConfigError(f"FitConfig.dual_gate must be a finite number or None; got {self.dual_gate!r}.")
        if not self.resolve > 0:
            raise ConfigError(f"FitConfig.resolve must be > 0; got {self.resolve!r}.")
        if self.refit < 0:
            raise ConfigError(f"FitConfig.refit must be >= 0; got {self.refit!r}.")
        if self.folds < 2:
            raise ConfigError(f"FitConfig.folds must be >= 2; got {self.folds!r}.")
        if not 0 < self.broad_alpha <= 1:
            raise ConfigError(f"FitConfig.broad_alpha must be in (0, 1]; got {self.broad_alpha!r}.")
        if not self.select_z >= 0:
            raise ConfigError(f"FitConfig.select_z must be >= 0; got {self.select_z!r}.")
        if not (self.smooth >= 0 and math.isfinite(self.smooth)):
            raise ConfigError(f"FitConfig.smooth must be >= 0 and finite; got {self.smooth!r}.")
        if self.smooth > 0 and self.model != AUTO:
            raise ConfigError(
                f"FitConfig.smooth regularises auto's choice of a lobe; a forced model ({self.model!r}) has none "
                "to regularise: set smooth to 0, or model to 'auto'."
            )
        if self.shadows not in SHADOWS:
            raise ConfigError(f"FitConfig.shadows must be one of {list(SHADOWS)}; got {self.shadows!r}.")
        if self.init not in INITS:
            raise ConfigError(f"FitConfig.init must be one of {INITS}; got {self.init!r}.")
        if self.fri_kernel not in FRI_KERNELS:
            raise ConfigError(f"FitConfig.fri_kernel must be one of {FRI_KERNELS}; got {self.fri_kernel!r}.")
        if self.fri_kernel == "pooled" and self.fri_method not in (None, "coherent"):
            raise ConfigError(
                f"FitConfig.fri_kernel 'pooled' weighs the 'coherent' method; got fri_method={self.fri_method!r}."
            )
        if self.quadrature not in QUADRATURES:
            raise ConfigError(f"FitConfig.quadrature must be one of {sorted(QUADRATURES)}; got {self.quadrature!r}.")
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"FitConfig.dtype must be 'float32' or 'float64'; got {self.dtype!r}.")
        positive = ("detect", "noise_floor", "naive_alpha", "memory_gib")
        for name in (*positive, "flag_peak_misfit", "flag_astray", "flag_reach", "flag_overshoot"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"FitConfig.{name} must be > 0; got {getattr(self, name)!r}.")
        if self.threads != AUTO and (
            isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1
        ):
            raise ConfigError(f"FitConfig.threads must be 'auto' or a number >= 1; got {self.threads!r}.")
        Scale(self.downsample, self.crop)  # ScaleError (a TorchspecError) naming --downsample or --crop
        if self.tile < 0:
            raise ConfigError(f"FitConfig.tile must be >= 0 (0: from memory_gib); got {self.tile}.")

    @property
    def ladder_climbed(self) -> tuple[str, ...]:
        """The lobed models fitted, in order: the ladder (``auto``), the forced model, or none."""
        if self.model == AUTO:
            return self.ladder
        return () if self.model == "diffuse" else (self.model,)

    @property
    def noise_known(self) -> bool:
        """Whether the fit estimates the sensor's noise: the criterion, deviations and peak checks need it."""
        return self.uncertainty or self.model == AUTO

    def least_roughness(self, lights: Lights) -> float:
        """The smallest roughness of a fit under ``lights`` (``lobe_resolution``)."""
        return resolvable_roughness(lights, self.lobe_resolution, ALPHA_BOUNDS[0])

    @property
    def rule(self) -> Quadrature:
        """The model's quadrature in a fit: the preset ``quadrature`` names
        (:data:`torchspec.quadrature.QUADRATURES`) on ``path``, compiled when ``compile``."""
        return replace(QUADRATURES[self.quadrature], path=self.path, compile=bool(self.compile))


def select_frames(spec: str | None, count: int) -> list[int]:
    """Frame indices from a SPEC: ``None`` or ``all``; a Python slice ``start:stop:step``
    (``::2`` every second frame, ``1::2`` the others); or a comma list of indices and ranges
    ``0,3,10-19`` (inclusive).

    Example:
        >>> select_frames("0,3-5", 8), select_frames("1::3", 8)
        ([0, 3, 4, 5], [1, 4, 7])

    Raises:
        ConfigError: a malformed SPEC, an index out of ``[0, count)``, a repeated frame or an
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
        raise ConfigError(
            f"frames SPEC must be 'all', a slice 'start:stop:step' or a list '0,3,10-19'; got {spec!r}."
        ) from None
    bad = [k for k in picked if not 0 <= k < count]
    if bad:
        raise ConfigError(f"frames SPEC {spec!r} names frame(s) {bad[:5]} outside 0..{count - 1}.")
    if len(set(picked)) != len(picked):
        raise ConfigError(f"frames SPEC {spec!r} names a frame twice.")
    if not picked:
        raise ConfigError(f"frames SPEC {spec!r} selects no frame of {count}.")
    return picked
