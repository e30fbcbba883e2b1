"""The settings of a fit (:class:`FitConfig`, ``configs/fit.yaml``) and the choices they name.

:data:`LADDER` is the order in which ``auto`` tries the lobed models, :attr:`FitConfig.rule` the
rules of the model's integrations, :func:`select_frames` the frames a SPEC picks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import ClassVar

from ..config import ConfigError, from_mapping
from ..lm import LMConfig
from ..model.layout import resolvable_roughness
from ..model.lights import Lights
from ..model.quadrature import Quadrature
from ..model.registry import ALPHA_BOUNDS, MODEL_CODES, MODELS, get_model
from .config_groups import ComputeConfig, FlagsConfig, MasksConfig, QuadratureConfig, TermConfig, positive

__all__ = [
    "AUTO",
    "SHADOWS",
    "COMPILE_PIXELS",
    "FRI_KERNELS",
    "GROUPS",
    "INITS",
    "LADDER",
    "MODEL_CODES",
    "MOVED",
    "ComputeConfig",
    "FitConfig",
    "FlagsConfig",
    "LadderConfig",
    "MasksConfig",
    "QuadratureConfig",
    "StartConfig",
    "TermConfig",
    "nested_settings",
    "flat_settings",
    "select_frames",
]

INITS = ("fri", "naive", "grid")
"""The specular starts of ``FitConfig.start.init``."""
FRI_KERNELS = ("pixel", "pooled")
"""The lobe spectra of ``FitConfig.start.fri_kernel``."""
AUTO = "auto"
"""``FitConfig.model`` that picks each pixel's model."""
LADDER = tuple(name for name, model in MODELS.items() if model.ladder)
"""The lobed models ``auto`` tries, in order: each on the pixels the previous left unexplained (the
built-in models declared ``ladder``, :mod:`torchspec.model.registry`; a model registered later joins
``auto`` through ``FitConfig.ladder``)."""
CALIBRATE = ("auto", "none", "gains", "positions", "dome")
"""The values of ``FitConfig.calibrate``."""
SHADOWS = ("auto", "on", "off")
"""The choices of ``FitConfig.shadows``."""
COMPILE_PIXELS = 1 << 17
"""``FitConfig.quadrature.compile=None`` compiles the model for fits of at least this many pixels (the
one-off compilation pays for itself on large fits only)."""


@dataclass(frozen=True)
class StartConfig:
    """The starting point of the solver (``FitConfig.start``): robust photometric stereo, then a
    specular start where a pixel's residual shows a peak (:mod:`torchspec.pipeline.start`).

    Attributes:
        init: the specular start: ``fri`` (FRI peak location), ``naive`` (photometric-stereo
            normal, ``alpha = naive_alpha``) or ``grid`` (dense search).
        detect: a pixel gets a lobe when its residual peaks above ``detect`` times its noise
            level (the larger of the photometric-stereo noise and ``noise_floor`` times the
            pixel's mean value).
        noise_floor: see ``detect``; also the smallest noise of a sample, relative to its
            pixel's level, in the criterion and the deviations (the model's own error: the
            quadrature, a lobe shape the data's material does not follow).
        naive_alpha: the roughness of the naive start.
        trim, cut: of the robust photometric stereo.
        fri_method, fri_coefficients: of the peak location (``None``: the defaults).
        fri_kernel: the lobe's spectrum the peak location weighs coefficients by: ``pixel``
            (fitted to each pixel, the default) or ``pooled`` (one spectrum pooled over the
            tile's pixels, :func:`torchspec.start.fri.estimate_kernel`: nearer the Cramer-Rao bound
            for broad lobes at low SNR when the tile's lobes share a width; needs the
            ``coherent`` method).
        broad_alpha: the roughness of the broad-lobe start of ``auto``'s pixels that show no peak
            but whose fit without a lobe leaves a misfit (a broad lobe is absorbed by a tilted
            normal and leaves no peak to detect).
    """

    init: str = "fri"
    detect: float = 5.0
    noise_floor: float = 0.002
    naive_alpha: float = 0.1
    trim: float = 0.25
    cut: float = 3.0
    fri_method: str | None = None
    fri_coefficients: int | None = None
    fri_kernel: str = "pixel"
    broad_alpha: float = 0.25

    def __post_init__(self):
        if self.init not in INITS:
            raise ConfigError(f"FitConfig.start.init must be one of {INITS}; got {self.init!r}.")
        if self.fri_kernel not in FRI_KERNELS:
            raise ConfigError(f"FitConfig.start.fri_kernel must be one of {FRI_KERNELS}; got {self.fri_kernel!r}.")
        if self.fri_kernel == "pooled" and self.fri_method not in (None, "coherent"):
            raise ConfigError(
                f"FitConfig.start.fri_kernel 'pooled' weighs the 'coherent' method; got fri_method={self.fri_method!r}."
            )
        positive("start", self, ("detect", "noise_floor", "naive_alpha"))
        if not 0 < self.broad_alpha <= 1:
            raise ConfigError(f"FitConfig.start.broad_alpha must be in (0, 1]; got {self.broad_alpha!r}.")


@dataclass(frozen=True)
class LadderConfig:
    """How ``auto`` chooses each pixel's model (``FitConfig.ladder``; :mod:`torchspec.pipeline.selection`,
    :mod:`torchspec.pipeline.prediction`).

    Attributes:
        models: the models ``auto`` climbs, in order, each tried from the previous one's solution
            on the pixels it leaves unexplained (:data:`LADDER` by default). Leave ``ward-dual`` out
            to spend no time on two lobes: a pixel no single Ward lobe explains (a lobe of another
            shape, such as the development captures' Beckmann lobes) climbs to the last model.
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
            prediction (and the residual term's); fold_regions: also leave out whole regions of
            the light domain (sectors), besides folds scattered over it.
        refit: ``0``: each fold's refit is one Gauss-Newton step from the solution (one Jacobian
            per model and pixel); ``N``: ``N`` steps of the solver per fold (all folds of all pixels
            in one batch: about ``folds`` times the cost of the fits).
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
        lobe_resolution: with point lights, no lobe narrower than ``lobe_resolution`` times the
            half vectors' spacing (:func:`torchspec.model.layout.resolvable_roughness`): a narrower one
            falls between the frames, fits one frame's sample and predicts nothing between them
            (relighting between lights explodes). ``0``: only :data:`torchspec.model.registry.ALPHA_BOUNDS`.
            An extended kernel's blur resolves narrower lobes: no bound from the sampling.
        lobe_support: with point lights, ``auto`` keeps a lobe only where some frame of the fit
            sees at least ``lobe_support`` of its peak (:func:`torchspec.model.layout.lobe_support`; 1/2:
            a light within the lobe's half maximum): a lobe peaking between the lights, farther
            from each than its width, has a height no photograph determines, and a light at its
            peak sees it at any height. ``0``: no such test.
    """

    models: tuple[str, ...] = LADDER
    smooth: float = 0.0
    select_z: float = 3.0
    predict_z: float = 3.0
    folds: int = 5
    fold_regions: bool = False
    refit: int = 0
    resolve: float = 0.5
    dual_rms: float = 0.03
    dual_gate: float | None = 0.0
    lobe_resolution: float = 0.5
    lobe_support: float = 0.5

    def __post_init__(self):
        ladder = tuple(self.models)
        object.__setattr__(self, "models", ladder)
        unknown = [name for name in ladder if name not in MODELS]
        if unknown:
            raise ConfigError(f"FitConfig.ladder.models: each model must be one of {sorted(MODELS)}; got {unknown!r}.")
        if not ladder or len(set(ladder)) != len(ladder) or any(get_model(name).lobe is None for name in ladder):
            raise ConfigError(
                f"FitConfig.ladder.models must name one or more models with a lobe, each once "
                f"(of {[name for name, model in MODELS.items() if model.lobe is not None]}); got {list(ladder)!r}."
            )
        for name in ("smooth", "select_z", "predict_z", "lobe_resolution"):
            if not (getattr(self, name) >= 0 and math.isfinite(getattr(self, name))):
                raise ConfigError(f"FitConfig.ladder.{name} must be >= 0 and finite; got {getattr(self, name)!r}.")
        if self.folds < 2:
            raise ConfigError(f"FitConfig.ladder.folds must be >= 2; got {self.folds!r}.")
        if self.refit < 0:
            raise ConfigError(f"FitConfig.ladder.refit must be >= 0; got {self.refit!r}.")
        positive("ladder", self, ("resolve",))
        if not self.dual_rms >= 0:
            raise ConfigError(f"FitConfig.ladder.dual_rms must be >= 0; got {self.dual_rms!r}.")
        if self.dual_gate is not None and not (
            isinstance(self.dual_gate, (int, float)) and math.isfinite(self.dual_gate)
        ):
            raise ConfigError(f"FitConfig.ladder.dual_gate must be a finite number or None; got {self.dual_gate!r}.")
        if not 0 <= self.lobe_support <= 1:
            raise ConfigError(f"FitConfig.ladder.lobe_support must be in [0, 1]; got {self.lobe_support!r}.")


GROUPS = {
    "masks": MasksConfig,
    "start": StartConfig,
    "ladder": LadderConfig,
    "term": TermConfig,
    "flags": FlagsConfig,
    "quadrature": QuadratureConfig,
    "compute": ComputeConfig,
}
"""``FitConfig``'s groups of settings, by key (``configs/fit.yaml``'s blocks), in stage order."""
RENAMED = {
    "ladder": "ladder.models",
    "residual_term": "term.order",
    "term_z": "term.z",
    "flag_peak_misfit": "flags.peak_misfit",
    "flag_astray": "flags.astray",
    "flag_overshoot": "flags.overshoot",
    "flag_reach": "flags.reach",
    "quadrature": "quadrature.preset",
}
"""The keys of the flat settings (before the groups) whose name changed in their group."""
MOVED = {
    **{
        name: f"{group}.{name}"
        for group, kind in GROUPS.items()
        for name in (f.name for f in fields(kind))
        if f"{group}.{name}" not in RENAMED.values()
    },
    **RENAMED,
}
"""Each key of the flat settings (one level, before the groups) and its place now (``group.key``);
``FitConfig.from_dict`` and ``configs/fit.yaml`` refuse a flat key with a message naming it."""


def nested_settings(settings: dict) -> dict:
    """``settings`` (a mapping of ``FitConfig``'s keys, e.g. a record written before the groups,
    one level: ``{"smooth": 10, "tile": 700}``) with each flat key moved into its group
    (``{"ladder": {"smooth": 10}, "compute": {"tile": 700}}``); nested keys are kept as they are.

    Example:
        >>> nested_settings({"model": "auto", "smooth": 10.0, "quadrature": "render", "lm": {}})
        {'model': 'auto', 'lm': {}, 'ladder': {'smooth': 10.0}, 'quadrature': {'preset': 'render'}}
    """
    nested = {key: value for key, value in settings.items() if key not in MOVED or isinstance(value, dict)}
    for key, value in settings.items():
        if key in MOVED and not isinstance(value, dict):
            group, name = MOVED[key].split(".")
            nested[group] = {**nested.get(group, {}), name: value}
    return nested


def flat_settings(settings: dict) -> dict:
    """The inverse of :func:`nested_settings`: a nested settings record (``asdict(FitConfig())``, a
    fit's ``svbrdf.json`` settings) in the flat keys of before the groups (``lm`` stays nested, as
    it was), so that records of the two layouts compare key by key.

    Example:
        >>> flat_settings({"model": "auto", "ladder": {"smooth": 10.0}, "quadrature": {"preset": "render"}, "lm": {}})
        {'model': 'auto', 'smooth': 10.0, 'quadrature': 'render', 'lm': {}}
    """
    flat_key = {place: key for key, place in MOVED.items()}
    flat = {}
    for key, value in settings.items():
        if isinstance(value, dict) and key != "lm":
            flat.update({flat_key[f"{key}.{name}"]: item for name, item in value.items()})
        else:
            flat[key] = value
    return flat


@dataclass(frozen=True)
class FitConfig:
    """Settings of :func:`torchspec.pipeline.fit` (``configs/fit*.yaml``), grouped by stage:
    :class:`MasksConfig` (what is read and masked), :class:`StartConfig` (the solver's start),
    :class:`LadderConfig` (``auto``'s choice of a model), :class:`TermConfig` (the residual term),
    :class:`FlagsConfig` (trust), :class:`QuadratureConfig` (the model's integrals),
    :class:`ComputeConfig` (tiles, memory, device) and :class:`~torchspec.lm.LMConfig` (the solver).

    Built from a nested mapping (a YAML file's) with :meth:`from_dict`, or in Python, e.g.
    ``FitConfig(model="auto", ladder=LadderConfig(smooth=10.0))``.

    Attributes:
        model: ``auto`` picks each pixel's model by what it predicts of frames left out of its
            fit (:mod:`torchspec.pipeline.prediction`), trying the larger ones only where the
            smaller leave a residual above the noise (``ladder``); or one model forced on every
            pixel that shows a peak (:data:`torchspec.model.registry.MODELS`): ``ward-iso`` (grey ``k_s``),
            ``ward-iso-colour``, ``ward-aniso`` or ``ward-dual`` (two grey isotropic lobes), or
            ``diffuse`` on every pixel. Where some pixel gets ``ward-dual``, the maps have a second
            lobe (``SVBRDF.specular2``, 0 where another model was chosen; ``std`` has its deviations).
        calibrate: the lights estimated from the photographs with the maps
            (:func:`torchspec.pipeline.calibration.calibrated`): ``auto`` (what the capture's manifest
            lists as ``unknown``: its irradiance, a gain per frame and channel, with a dome radius
            for lights written as directions, kept where the gains are refused; its lights'
            positions), ``gains``, ``positions`` (near lights' positions and gains), ``dome`` (gains
            and one dome radius for every light, or distant lights where none explains the
            photographs better: :func:`torchspec.calibration.lights.dome_radius`) or ``none``.
        uncertainty: compute each pixel's criterion and standard deviations (one more evaluation
            of the model per pixel, at the solution), with each sample's noise from the sensor's
            ``a y + b`` fitted to the residuals of the pixels without a peak
            (:func:`torchspec.model.noise.affine_noise`; ``stats["sensor_noise"]``), floored at
            ``start.noise_floor`` times the pixel's level. ``auto`` needs them; a forced model
            without them leaves ``criterion`` and ``std`` NaN.
        shadows: cast shadows in the model (:mod:`torchspec.pipeline.shadows`): ``on`` fits the
            maps with each light's visibility over a height field integrated from the normals,
            alternating with the height, and keeps it where it predicts left-out frames better;
            ``auto`` (the default) tries it on captures imported from photographs and where the
            frames hold shadows (a share of samples masked as shadows of at least
            ``torchspec.pipeline.shadows.SHADOW_SHARE``); ``off``: never.
        masks, start, ladder, term, flags, quadrature, compute: the groups above.
        lm: the solver's settings.
    """

    model: str = "auto"
    calibrate: str = "auto"
    uncertainty: bool = True
    shadows: str = AUTO
    masks: MasksConfig = field(default_factory=MasksConfig)
    start: StartConfig = field(default_factory=StartConfig)
    ladder: LadderConfig = field(default_factory=LadderConfig)
    term: TermConfig = field(default_factory=TermConfig)
    flags: FlagsConfig = field(default_factory=FlagsConfig)
    quadrature: QuadratureConfig = field(default_factory=QuadratureConfig)
    compute: ComputeConfig = field(default_factory=ComputeConfig)
    lm: LMConfig = field(default_factory=LMConfig)
    MOVED: ClassVar[dict[str, str]] = MOVED
    """The keys of the flat settings and their places now (:data:`MOVED`): ``from_dict`` refuses them."""

    def __post_init__(self):
        if self.model != AUTO and self.model not in MODELS:
            raise ConfigError(f"FitConfig.model must be one of {[AUTO, *sorted(MODELS)]}; got {self.model!r}.")
        if self.calibrate not in CALIBRATE:
            raise ConfigError(f"FitConfig.calibrate must be one of {list(CALIBRATE)}; got {self.calibrate!r}.")
        if self.shadows not in SHADOWS:
            raise ConfigError(f"FitConfig.shadows must be one of {list(SHADOWS)}; got {self.shadows!r}.")
        for name, kind in (*GROUPS.items(), ("lm", LMConfig)):
            if not isinstance(getattr(self, name), kind):
                raise ConfigError(
                    f"FitConfig.{name} must be a {kind.__name__}; got {getattr(self, name)!r} "
                    f"(FitConfig.from_dict builds the groups from mappings)."
                )
        if self.ladder.smooth > 0 and self.model != AUTO:
            raise ConfigError(
                f"FitConfig.ladder.smooth regularises auto's choice of a lobe; a forced model ({self.model!r}) has "
                "none to regularise: set ladder.smooth to 0, or model to 'auto'."
            )

    @classmethod
    def from_dict(cls, data: dict, where: str = "FitConfig") -> FitConfig:
        """The settings of a nested mapping (``configs/fit.yaml``'s layout: ``{"model": "auto",
        "ladder": {"smooth": 10.0}}``), its groups and values checked as a YAML file's.

        Raises:
            ConfigError: an unknown key, a key of the flat settings (naming its place now: :data:`MOVED`),
                a value of the wrong type or out of its domain; the message names ``where`` and the key.

        Example:
            >>> FitConfig.from_dict({"ladder": {"smooth": 10.0}}).ladder.smooth
            10.0
            >>> FitConfig.from_dict({"smooth": 10.0})
            Traceback (most recent call last):
            ...
            torchspec.config.ConfigError: FitConfig: key 'smooth' has moved: write it as ladder: {smooth: ...}.
        """
        return from_mapping(data, cls, where)

    @property
    def ladder_climbed(self) -> tuple[str, ...]:
        """The lobed models fitted, in order: the ladder (``auto``), the forced model, or none."""
        if self.model == AUTO:
            return self.ladder.models
        return (self.model,) if self.lobes else ()

    @property
    def lobes(self) -> bool:
        """Whether the fit may give a pixel a lobe: ``auto``, or a forced model with one (its
        :attr:`torchspec.model.registry.Model.lobe`)."""
        return self.model == AUTO or get_model(self.model).lobe is not None

    @property
    def noise_known(self) -> bool:
        """Whether the fit estimates the sensor's noise: the criterion, deviations and peak checks need it."""
        return self.uncertainty or self.model == AUTO

    def least_roughness(self, lights: Lights) -> float:
        """The smallest roughness of a fit under ``lights`` (``ladder.lobe_resolution``)."""
        return resolvable_roughness(lights, self.ladder.lobe_resolution, ALPHA_BOUNDS[0])

    @property
    def rule(self) -> Quadrature:
        """The model's quadrature in a fit (:attr:`QuadratureConfig.rule`)."""
        return self.quadrature.rule


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
