"""The groups of :class:`~torchspec.pipeline.settings.FitConfig` that name no model: what is read and
masked (:class:`MasksConfig`), the residual term (:class:`TermConfig`), the flags of trust
(:class:`FlagsConfig`), the model's quadrature (:class:`QuadratureConfig`) and the computation
(:class:`ComputeConfig`). The groups of the start and of ``auto``'s ladder, which name the models,
are in :mod:`~torchspec.pipeline.settings`.

Each group is a frozen dataclass that checks its own values; a message names the full key
(``FitConfig.term.z must be ...``), as ``configs/fit.yaml`` writes it (``term: {z: ...}``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from ..config import ConfigError
from ..io.scale import Scale
from ..model.quadrature import QUADRATURES, Quadrature
from ..model.residual_term import TERMS

__all__ = ["ComputeConfig", "FlagsConfig", "MasksConfig", "QuadratureConfig", "TermConfig"]


def positive(group: str, config, names: tuple[str, ...]) -> None:
    """Refuse a value of ``names`` (fields of ``config``, the group ``FitConfig.<group>``) that is not > 0."""
    for name in names:
        if not getattr(config, name) > 0:
            raise ConfigError(f"FitConfig.{group}.{name} must be > 0; got {getattr(config, name)!r}.")


@dataclass(frozen=True)
class MasksConfig:
    """What of the capture is read, and which samples are masked (``FitConfig.masks``).

    Attributes:
        saturation: the sensor's clipping level; ``None``: the level the capture records
            (:attr:`torchspec.io.Capture.saturation`, an imported capture's), else a clipped plateau detected.
        grow: saturated regions are grown by this many pixels (of the image fitted: of the
            reduced one with ``downsample``).
        shadow: samples below this fraction of the pixel's median are shadows.
        downsample: fit boxes of ``N x N`` pixels, averaged as the frames are read
            (:class:`torchspec.io.scale.Scale`): a quick look at a large capture, in about ``1 / N^2``
            of the memory and time. A box holding a clipped sample is clipped; the maps record the
            scale (``svbrdf.json``'s ``fit.scale``).
        crop: ``(X, Y, W, H)``: fit only these pixels of the capture's frames (``X, Y`` the
            top-left corner), before ``downsample``; ``None``: all of them.
    """

    saturation: float | None = None
    grow: int = 1
    shadow: float = 0.02
    downsample: int = 1
    crop: tuple[int, int, int, int] | None = None

    def __post_init__(self):
        Scale(self.downsample, self.crop)  # ScaleError (a TorchspecError) naming --downsample or --crop


@dataclass(frozen=True)
class TermConfig:
    """The smooth per-pixel residual term (``FitConfig.term``; :mod:`torchspec.model.residual_term`).

    Attributes:
        order: ``auto`` (the default: ``3`` for a capture imported from photographs, whose
            manifest has a ``source`` block; ``0`` for others, e.g. simulated ones), ``0`` (off),
            ``2`` or ``3``: the order of a smooth per-pixel residual term (hemispherical harmonics
            of the light direction, 4 or 9 coefficients per channel, in the sRGB-encoded domain)
            fitted on top of the chosen model and kept only where it predicts left-out frames
            better (``ladder.folds``). It carries what the physical model cannot (cast shadows,
            interreflections) for relighting, in maps of its own (``residual_term.exr``): the
            physical maps are unchanged by it.
        z: the residual term is kept where its left-out prediction beats the physical model's by
            more than ``z`` standard deviations of the noise's share (the margin of
            ``ladder.predict_z``; lower, because the noise estimate of photographs includes what no
            model of the ladder explains).
    """

    order: int | str = "auto"
    z: float = 1.0

    def __post_init__(self):
        if self.order not in ("auto", 0, *TERMS):
            raise ConfigError(
                f"FitConfig.term.order must be auto, 0 (off) or an order in {sorted(TERMS)}; got {self.order!r}."
            )
        if not (self.z >= 0 and math.isfinite(self.z)):
            raise ConfigError(f"FitConfig.term.z must be >= 0 and finite; got {self.z!r}.")


@dataclass(frozen=True)
class FlagsConfig:
    """The thresholds of the flags that take a pixel's trust away (``FitConfig.flags``;
    :mod:`torchspec.pipeline.flags`). ``experiments/stability.py`` chose the defaults.

    Attributes:
        trust_rms: a pixel whose chosen model leaves a misfit (a residual above the noise) with a
            relative RMS above ``trust_rms`` of its level is flagged ``poor_fit``, untrusted
            (quality 0): no model of the ladder explains it (a shadow, an interreflection, a
            material of another kind), and its maps are not to be used.
        peak_misfit, astray, reach: the thresholds of the ``peak_misfit`` and ``astray`` flags and
            the neighbourhood of the peak (they need the noise: ``uncertainty`` or ``auto``).
        overshoot: a pixel whose fitted maps render, at some frame of the fit, more than this many
            times the brightest value its photographs recorded is flagged ``implausible``,
            untrusted (:func:`~torchspec.pipeline.checks.overshoot`: a lobe grown without bound where
            its samples were clipped or masked; the photographs show nothing of the kind).
    """

    trust_rms: float = 0.05
    peak_misfit: float = 3.0
    astray: float = 2.0
    overshoot: float = 10.0
    reach: float = 1.5

    def __post_init__(self):
        positive("flags", self, ("trust_rms", "peak_misfit", "astray", "overshoot", "reach"))


@dataclass(frozen=True)
class QuadratureConfig:
    """How the model's integrals are taken in a fit (``FitConfig.quadrature``; :attr:`rule`).

    Attributes:
        preset: ``fit`` (the default): 3 x 3 nodes per frame for the lobe (8 radii where the
            reference rule takes over) and the clamp's fast rule (:data:`torchspec.model.quadrature.CLAMPS`):
            within 1e-3 of a pixel's largest value; ``render``: the renderer's own rules (1e-6).
        path: the quadrature path of the model (:func:`torchspec.model.rendering.render`).
        compile: fuse the model's integrations with ``torch.compile`` (faster solver steps after
            a one-off compilation). A failed compilation warns and fits without. ``None``: when
            the fit has at least ``COMPILE_PIXELS`` pixels.
    """

    preset: str = "fit"
    path: str = "auto"
    compile: bool | None = None

    def __post_init__(self):
        if self.preset not in QUADRATURES:
            raise ConfigError(
                f"FitConfig.quadrature.preset must be one of {sorted(QUADRATURES)}; got {self.preset!r}."
            )

    @property
    def rule(self) -> Quadrature:
        """The preset ``preset`` names (:data:`torchspec.model.quadrature.QUADRATURES`) on ``path``,
        compiled when ``compile``."""
        return replace(QUADRATURES[self.preset], path=self.path, compile=bool(self.compile))


@dataclass(frozen=True)
class ComputeConfig:
    """Where and in what pieces a fit runs (``FitConfig.compute``): none of these changes the maps
    but ``dtype`` (and ``device``, by rounding).

    Attributes:
        tile: pixels per tile; 0 sizes tiles to ``memory_gib``, and cuts an image into at least 16
            tiles of at least 1024 pixels (:func:`torchspec.pipeline.plan.plan`).
        memory_gib: the memory budget of the whole fit: the frame stack, its masks, the torch
            runtime and a tile (tiles are sized to what is left, at least 256 pixels).
        dtype: ``float32`` or ``float64``.
        device: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ...
        threads: torch's CPU threads for each tile: ``auto`` (the default): torch's own count
            (``torch.set_num_threads``, ``OMP_NUM_THREADS``) when its threads sleep at a barrier
            (``import torchspec`` sets ``OMP_WAIT_POLICY=passive``), else the cores other processes
            leave free, measured before each tile; or a number, used as it is
            (:mod:`torchspec.threads`). A cluster's tasks run on one thread each.
    """

    tile: int = 0
    memory_gib: float = 2.0
    dtype: str = "float32"
    device: str = "auto"
    threads: int | str = "auto"

    def __post_init__(self):
        if self.tile < 0:
            raise ConfigError(f"FitConfig.compute.tile must be >= 0 (0: from memory_gib); got {self.tile}.")
        positive("compute", self, ("memory_gib",))
        if self.dtype not in ("float32", "float64"):
            raise ConfigError(f"FitConfig.compute.dtype must be 'float32' or 'float64'; got {self.dtype!r}.")
        if self.threads != "auto" and (
            isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1
        ):
            raise ConfigError(f"FitConfig.compute.threads must be 'auto' or a number >= 1; got {self.threads!r}.")
