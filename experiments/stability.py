"""The stability study: where each way of locating a specular peak breaks, and whether its
quality flags say so.

Two families of methods locate the peak of a specular lobe seen through an extended light, in the
l-plane (errors in l units; near the zenith one l unit is ~28.6 degrees of the normal):

- *location*, batched 1D problems on a line of ``N`` lights (``trials`` per cell in one call): FRI
  (:func:`torchspec.start.fri.locate`: ``coherent``, the default, ``ls``, ``esprit``, ``cadzow``) on
  samples of a Gaussian lobe (std ``lobe_width``: a Ward lobe near the zenith) seen through the
  light's kernel, point-sampled and not periodised (a peak near an end of the line breaks FRI's
  periodicity); and the baseline FRI replaces, ``peak`` picking (argmax + parabola) on *point-light*
  samples at the same positions with the same noise. The grazing axis renders a Ward lobe with
  :func:`torchspec.model.rendering.render` instead.
- *pipeline*, :func:`torchspec.pipeline.fit` (``ward-iso``) on small simulated captures, a pixel per
  trial, an ``N x N`` grid of lights, with ``matte`` pixels from dark to light on which the fit
  measures its noise: ``fri+lm``, ``naive+lm``, ``grid+lm`` (``FitConfig.start.init``); the peak is the
  mirror direction of the fitted normal, the error its 2D distance to the truth.

Axes, each varied alone from the base setting: SNR; samples per axis; kernel width over lobe width;
the kernel's skewness (two Gaussians, the mean at the light's centre, :func:`kernel_components`;
the pipeline's capture declares a Gaussian of the same variance); the peak's position from the
centre (0) to the last light (1); a second lobe (``second_amplitude`` as strong) at a separation in
blurred widths; the view's angle from the zenith (the lights then centre on the mirror direction and
stop at the horizon). Plus SNR x samples maps of the location methods. SNR: the mean square of the
base setting's noise-free specular samples over the noise variance (Fig. 2's definition); along the
other axes the noise std stays the base's (a camera's noise does not follow the light or the peak).

Failure: ``|error| > failure * sqrt(CRB)``, the CRB per trial from the Fisher information at the
truth with the true noise and every parameter of the truth unknown but the kernel: location
family, the peak, amplitude, lobe width, an offset and a second lobe's peak and amplitude
(:func:`torchspec.model.crb.fisher_information`); peak picking is held to the extended-light samples'
bound, its point samples having none where they miss a narrow lobe; grazing and pipeline,
:func:`torchspec.model.jacobian.jacobian` at the true maps (tilt angles, ``k_d``, ``k_s``, ``alpha``,
a second facet's tilt and ``k_s``) mapped to the peak by ``d peak / d angles``. Flag rules
(:func:`flag_location`, :func:`flag_fit`) are scored by their catch rate (failures flagged) and
false alarms (good estimates flagged) over every trial of every cell; :func:`search_rules` lists
the best thresholds of a grid.

    python experiments/stability.py [--config experiments/configs/stability.yaml] [--output experiments/results]

Writes <stem>.json, <stem>.png (heat maps per axis), <stem>_maps.png (SNR x samples) and <stem>.md.
"""

from __future__ import annotations

import itertools
import math
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from _common import parse_args
from torch import Tensor

import torchspec as ts
from torchspec.atomic import atomic_path, save_figure, write_json
from torchspec.config import load_config
from torchspec.io import Capture, Frame, LightSpec, write_capture
from torchspec.lm import STATUS
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import angles_from_normal, from_plane, normal_from_angles, normalize
from torchspec.model.jacobian import jacobian
from torchspec.model.layout import mirror_point
from torchspec.model.lights import Kernel, Lights
from torchspec.model.registry import get_model
from torchspec.model.rendering import render
from torchspec.pipeline import MODEL_CODES, FitConfig, fit
from torchspec.pipeline.flags import bit, untrusted

F64 = torch.float64
AXES = ("snr_db", "samples", "width_ratio", "skew", "edge", "separation", "grazing_deg")
UNITS = {
    "snr_db": "dB",
    "samples": "",
    "width_ratio": "",
    "skew": "",
    "edge": "",
    "separation": "w",
    "grazing_deg": "deg",
}


@dataclass(frozen=True)
class Setting:
    """One cell: every knob of a trial (a field left at ``None`` is the base's uniform spread)."""

    snr_db: float = 20.0
    samples: int = 16  # lights along the line, over l in [-span / 2, span / 2]
    width_ratio: float = 2.0  # kernel std / lobe std (0: point lights)
    skew: float = 0.0  # the kernel's skewness along the line (kernel_components)
    edge: float | None = None  # the peak at this fraction of the half-span (1: the last light)
    separation: float | None = None  # a second lobe this many blurred widths away
    grazing_deg: float | None = None  # rendered Ward lobe, view this far from the zenith (None: the Gaussian lobe)


@dataclass(frozen=True)
class Axes:
    snr_db: tuple[float, ...] = ()
    samples: tuple[int, ...] = ()
    width_ratio: tuple[float, ...] = ()
    skew: tuple[float, ...] = ()
    edge: tuple[float, ...] = ()
    separation: tuple[float, ...] = ()
    grazing_deg: tuple[float, ...] = ()


@dataclass(frozen=True)
class Location:
    methods: tuple[str, ...]  # FRI methods and "peak"
    trials: int
    axes: Axes
    map_snr_db: tuple[float, ...] = ()
    map_samples: tuple[int, ...] = ()


@dataclass(frozen=True)
class Run:
    init: str  # FitConfig.start.init
    axes: Axes
    trials: int = 0  # pixels per cell (0: the pipeline's)
    matte: int = 0  # matte pixels per capture (0: the pipeline's)


@dataclass(frozen=True)
class Pipeline:
    runs: tuple[Run, ...]
    trials: int  # pixels per cell
    samples: int  # lights per side of the base grid
    matte: int = 256  # matte pixels per capture, dark to light: the fit measures its noise on them
    diffuse: float = 0.3  # k_d
    specular: float = 0.2  # k_s of the base setting
    fit: FitConfig = field(default_factory=lambda: FitConfig(model="ward-iso"))


@dataclass(frozen=True)
class LocationRule:
    """:func:`flag_location`'s thresholds."""

    quality: float  # Location.quality below this
    astray: float  # the peak farther than this many blurred widths (or spacings) from the brightest sample
    edge: float  # the peak within this many spacings of the line's ends, or beyond them
    std: float = math.inf  # Location.std above this many spacings
    asymmetry_z: float = math.inf  # asymmetry_z above this (needs the noise level)
    local: float = math.inf  # local_asymmetry above this (needs the noise level)


@dataclass(frozen=True)
class FitRule:
    """:func:`flag_fit`'s thresholds."""

    quality: float  # Fit.quality below this
    chi2_z: float  # chi^2 above dof + chi2_z sqrt(2 dof)
    status: bool = True  # a solver status other than converged
    no_lobe: bool = True  # no peak detected (the pixel fitted diffuse)
    std_deg: float = math.inf  # Fit.std["normal"] above this many degrees
    local: float = math.inf  # Fit.checks['peak_misfit'] above this (FitConfig.flags.peak_misfit)
    astray: float = math.inf  # Fit.checks['astray'] above this (FitConfig.flags.astray)


@dataclass(frozen=True)
class Rules:
    location: LocationRule
    fit: FitRule


@dataclass(frozen=True)
class Settings:
    seed: int
    span: float  # the line of lights covers l in [-span / 2, span / 2]
    lobe_width: float  # the lobe's l-plane std (~1.41 alpha for a Ward lobe at the zenith)
    spread: float  # base peaks lie uniformly within this fraction of the half-span
    second_amplitude: float  # the second lobe's amplitude over the first's
    failure: float  # a failure: |error| > failure sqrt(CRB)
    break_rate: float  # a cell "breaks" when more than this share of its trials fail
    base: Setting
    location: Location
    pipeline: Pipeline
    rules: Rules


# --- the flag rules (a package change would report them per pixel) --------------------------------


def flag_location(trial: dict, rule: LocationRule):
    """Flag FRI locations ``(T,)`` from what a user has: ``quality`` and ``std`` (:class:`torchspec.start.fri.
    Location`), the ``peak``, the ``brightest`` sample's position, the line's ends ``lo``, ``hi`` and
    ``spacing``, and with the noise level :func:`asymmetry_z` (``asymmetry``) and
    :func:`local_asymmetry` (``local``). Flagged: low quality, a large std, a peak far from the
    brightest sample (aliased or wrapped), at or past the line's ends (where the periodic model is
    violated), or that a symmetric pulse does not explain. All in l units."""
    spacing, peak = trial["spacing"], trial["peak"]
    near_end = (peak < trial["lo"] + rule.edge * spacing) | (peak > trial["hi"] - rule.edge * spacing)
    far = (peak - trial["brightest"]).abs() > rule.astray * torch.maximum(spacing, trial["width"])
    return (
        (trial["quality"] < rule.quality)
        | (trial["std"] > rule.std * spacing)
        | far
        | near_end
        | ~torch.isfinite(peak)
        | ~(trial["asymmetry"] <= rule.asymmetry_z)
        | ~(trial["local"] <= rule.local)
    )


def flag_fit(trial: dict, rule: FitRule):
    """Flag fitted pixels ``(T,)`` from :class:`torchspec.pipeline.Fit`: ``quality`` low, ``chi2_z`` (the
    criterion's chi^2 against its degrees of freedom, in standard deviations) high, a ``status``
    other than converged, no ``lobe`` detected, the normal's ``std_deg`` large, a misfit under the
    peak (``local``) or the peak far from the brightest sample (``astray``;
    :func:`torchspec.pipeline.flags.peak_checks`)."""
    flag = (
        (trial["quality"] < rule.quality)
        | (trial["chi2_z"] > rule.chi2_z)
        | (trial["std_deg"] > rule.std_deg)
        | ~torch.isfinite(trial["chi2_z"])
        | ~(trial["local"] <= rule.local)
        | ~(trial["astray"] <= rule.astray)
    )
    if rule.status:
        flag = flag | (trial["status"] != STATUS.index("converged"))
    if rule.no_lobe:
        flag = flag | ~trial["lobe"]
    return flag


def asymmetry_z(samples, peak, first, step, sigma):
    """The part of uniform ``samples (T, N)`` that a symmetric pulse at ``peak`` cannot explain, in
    units of the noise ``sigma``: the imaginary parts of the Fourier coefficients ``m = 1..M`` once
    rotated to the peak, ``chi^2 = sum Im^2 / (N sigma^2 / 2)`` on ``M - 1`` degrees of freedom, as
    ``(chi^2 - dof) / sqrt(2 dof)`` (0 when ``M < 2``: a lone coefficient's phase is the peak itself).
    A skewed kernel, a second lobe, aliasing and a lobe cut by the line's end all leave such a part;
    noise alone does not. ``first``: the first sample's position; l units throughout."""
    n = samples.shape[-1]
    bands = (n - 1) // 2
    if bands < 2:
        return torch.zeros_like(peak)
    m = torch.arange(1, bands + 1, dtype=samples.dtype)
    coefficients = torch.fft.fft(samples)[..., 1 : bands + 1]
    turn = torch.polar(torch.ones_like(m * peak[:, None]), 2.0 * math.pi * m * (peak[:, None] - first) / (n * step))
    chi2 = (coefficients * turn).imag.pow(2).sum(-1) / (0.5 * n * sigma**2)
    dof = bands - 1
    return (chi2 - dof) / math.sqrt(2.0 * dof)


def blurred_width(samples, step):
    """``(T,)`` the std of the blurred peak in uniform ``samples (T, N)``, from the ratio of its first
    two Fourier coefficients' magnitudes (exact for a Gaussian); within ``[step / 2, N step / 4]``."""
    n = samples.shape[-1]
    tau = n * step
    if n < 5:
        return torch.full_like(samples[:, 0], step)
    z = torch.fft.fft(samples)[..., 1:3].abs()
    ratio = (z[:, 0] / z[:, 1].clamp(min=torch.finfo(samples.dtype).tiny)).clamp(min=1.0 + 1e-6)
    return (tau**2 * ratio.log() / (6.0 * math.pi**2)).sqrt().clamp(0.5 * step, 0.25 * tau)


def local_asymmetry(samples, peak, first, step, sigma, *, reach: float = 1.5, points: int = 4):
    """Mean square, in noise units (~1 or less for noise alone: the fitted peak absorbs some), of the
    antisymmetric part of uniform ``samples (T, N)`` about ``peak``, at ``points`` offsets within
    ``reach`` blurred widths (:func:`blurred_width`) of it: what a symmetric pulse leaves unexplained
    *under the peak* (a merged second lobe), not beyond it (a resolved one, which does not move the
    peak). The antisymmetric part is the lowpass interpolant ``-(2 / N) sum_m Im(Z_m) sin(2 pi m u /
    tau)`` of the coefficients ``Z_m`` rotated to the peak. 0 when ``M < 2``."""
    n = samples.shape[-1]
    bands = (n - 1) // 2
    if bands < 2:
        return torch.zeros_like(peak)
    tau = n * step
    m = torch.arange(1, bands + 1, dtype=samples.dtype)
    turn = torch.polar(torch.ones_like(m * peak[:, None]), 2.0 * math.pi * m * (peak[:, None] - first) / tau)
    z = torch.fft.fft(samples)[..., 1 : bands + 1] * turn
    width = blurred_width(samples, step)
    u = reach * width[:, None] * torch.arange(1, points + 1, dtype=samples.dtype) / points  # (T, J)
    sines = torch.sin(2.0 * math.pi * m * u[..., None] / tau)  # (T, J, M)
    odd = -(2.0 / n) * (sines * z.imag[:, None, :]).sum(-1)
    variance = (2.0 * sigma**2 / n) * sines.pow(2).sum(-1)
    return (odd.pow(2) / variance.clamp(min=torch.finfo(samples.dtype).tiny)).mean(-1)


def _rates(flag, failed) -> dict:
    failures, good = int(failed.sum()), int((~failed).sum())
    return {
        "failures": failures,
        "good": good,
        "catch": float((flag & failed).sum() / failures) if failures else None,
        "false_alarms": float((flag & ~failed).sum() / good) if good else None,
    }


def search_rules(pool: dict, family: str, limit: float = 0.05) -> list[dict]:
    """The best thresholds of a family's rule on the pooled trials: every combination of a small
    grid, ranked by catch rate among those with false alarms <= ``limit`` (then the rest)."""
    failed = pool["failed"]
    if family == "location":
        grid = {
            "quality": (-math.inf, 0.05, 0.1),
            "astray": (1.5, 2.0, 3.0, math.inf),
            "edge": (-math.inf,),
            "asymmetry_z": (50.0, math.inf),
            "local": (5.0, 7.0, 10.0, 15.0, math.inf),
        }
    else:
        grid = {
            "quality": (-math.inf, 0.1, 0.3),
            "chi2_z": (30.0, math.inf),
            "status": (False, True),
            "no_lobe": (False, True),
            "std_deg": (1.0, math.inf),
            "local": (1.0, 2.0, 3.0, 5.0, math.inf),
            "astray": (1.5, 2.0, 3.0, math.inf),
        }
    rows = []
    for values in itertools.product(*grid.values()):
        rule = dict(zip(grid, values, strict=True))
        flag = _flag(pool, family, rule)
        rows.append({"rule": rule, **_rates(flag, failed)})
    rows.sort(key=lambda r: (-(r["false_alarms"] <= limit), -(r["catch"] or 0.0), r["false_alarms"]))
    return rows[:8]


def _flag(pool: dict, family: str, rule: dict):
    if family == "location":
        return flag_location(pool, LocationRule(**rule))
    return flag_fit(pool, FitRule(**rule))


# --- the location family: batched 1D problems -------------------------------------------------------


TAIL = 0.25  # the weight of a skewed kernel's second component


def kernel_components(sigma: float, skewness: float) -> list[tuple[float, float, float]]:
    """A light kernel along the line as ``(weight, offset, std)`` Gaussian components: one of std
    ``sigma`` (0: a point light), or for ``skewness > 0`` two of one std, weights ``1 - TAIL`` and
    ``TAIL``, with the mean at the light's centre (the centroid: ``torchspec.calibration.kernel``'s convention),
    variance ``sigma^2`` and that third standardised moment (at most ~1.1)."""
    if skewness == 0 or sigma == 0:
        return [(1.0, 0.0, sigma)]
    gap = sigma * (skewness / (TAIL * (1 - TAIL) * (1 - 2 * TAIL))) ** (1 / 3)
    inner = sigma**2 - TAIL * (1 - TAIL) * gap**2
    if inner <= 0:
        raise ValueError(f"skew must be below ~1.15 (two components of one width); got {skewness}.")
    return [(1 - TAIL, -TAIL * gap, math.sqrt(inner)), (TAIL, (1 - TAIL) * gap, math.sqrt(inner))]


def _profile(d, width, sigma, skew):
    """A unit-mass Gaussian lobe (std ``width``) seen by a light at offset ``d = t - peak`` through
    the kernel of :func:`kernel_components` (a frame collects the light from ``t + u``)."""
    out = torch.zeros_like(d)
    for weight, offset, std in kernel_components(sigma, skew):
        total = (std * std + width * width) ** 0.5
        out = out + weight / (math.sqrt(2.0 * math.pi) * total) * torch.exp(-0.5 * ((d + offset) / total) ** 2)
    return out


def _line(samples: int, span: float, like=F64):
    step = span / (samples - 1)
    return -0.5 * span + step * torch.arange(samples, dtype=like), step


def _peaks(settings: Settings, cell: Setting, count: int, step: float, generator):
    """``(T,)`` true peak positions: uniform within the base spread, or at ``edge`` (either end, jittered
    by half a spacing), and the second lobe's (NaN without one)."""
    half = 0.5 * settings.span
    u = torch.rand(count, dtype=F64, generator=generator) * 2.0 - 1.0
    sign = torch.where(torch.rand(count, dtype=F64, generator=generator) < 0.5, -1.0, 1.0).to(F64)
    if cell.edge is None:
        x = u * settings.spread * half
    else:
        x = sign * (cell.edge * half + 0.5 * u * step)
    second = torch.full_like(x, math.nan)
    if cell.separation is not None:
        sigma = cell.width_ratio * settings.lobe_width
        blurred = math.sqrt(settings.lobe_width**2 + sigma**2)
        away = torch.where(torch.rand(count, dtype=F64, generator=generator) < 0.5, -1.0, 1.0).to(F64)
        second = x + away * cell.separation * blurred
    return x, second


def _noise_sigma(settings: Settings, snr_db: float) -> float:
    """The noise std of the base setting at ``snr_db``, for a unit-mass lobe."""
    generator = torch.Generator().manual_seed(settings.seed)
    t, step = _line(settings.base.samples, settings.span)
    x, _ = _peaks(settings, settings.base, 4096, step, generator)
    sigma = settings.base.width_ratio * settings.lobe_width
    clean = _profile(t - x[:, None], settings.lobe_width, sigma, settings.base.skew)
    return math.sqrt(float(clean.pow(2).mean()) / 10 ** (snr_db / 10))


def _model_1d(t, cell: Setting, settings: Settings):
    """Noise-free samples ``(T, N)`` at ``t`` from ``(T, 6)`` parameters: the peak, amplitude, lobe
    width, offset, and the second lobe's peak (NaN: none) and amplitude; one lobe width for both."""
    sigma = cell.width_ratio * settings.lobe_width

    def forward(params):
        x, a, w, b, x2, a2 = params.unbind(-1)
        value = a[:, None] * _profile(t - x[:, None], w[:, None], sigma, cell.skew) + b[:, None]
        there = torch.isfinite(x2)[:, None]
        x2 = torch.where(torch.isfinite(x2), x2, torch.zeros_like(x2))
        extra = a2[:, None] * _profile(t - x2[:, None], w[:, None], sigma, cell.skew)
        return value + torch.where(there, extra, torch.zeros_like(extra))

    return forward


def _bound_1d(forward, truth, sigma):
    """The CRB of the peak with every parameter of the trial unknown (a missing second lobe's two
    are left out), and with the second lobe's known: ``J^T J / sigma^2`` with ``J (T, N, 6)`` by
    central differences (:func:`torchspec.model.crb.fisher_information`'s to 1e-8, without its slow
    forward-mode pass through the profile)."""
    columns = []
    for j in range(truth.shape[-1]):
        step = torch.zeros_like(truth)
        step[:, j] = 1e-6 * truth[:, j].abs().clamp(min=1e-2)
        step = torch.where(torch.isfinite(step), step, torch.zeros_like(step))
        spread = step[:, j : j + 1].clamp(min=torch.finfo(truth.dtype).tiny)
        columns.append((forward(truth + step) - forward(truth - step)) / (2.0 * spread))
    jac = torch.stack(columns, -1)
    fisher = jac.transpose(-1, -2) @ jac / sigma**2
    single = ts.model.crb.bound(fisher[:, :4, :4])[:, 0, 0]
    two = ts.model.crb.bound(fisher)[:, 0, 0]
    return torch.where(torch.isfinite(truth[:, 4]), two, single), single


def _parabola(y, t, step):
    """Argmax + parabola through the brightest sample and its neighbours (none at the line's ends)."""
    n = y.shape[-1]
    k = y.argmax(-1)
    rows = torch.arange(y.shape[0])
    left, mid, right = y[rows, (k - 1).clamp(min=0)], y[rows, k], y[rows, (k + 1).clamp(max=n - 1)]
    curv = left - 2 * mid + right
    inside = (k > 0) & (k < n - 1) & (curv < 0)
    offset = torch.where(inside, 0.5 * (left - right) / torch.where(inside, curv, -torch.ones_like(curv)), 0.0)
    return t[k] + step * offset.clamp(-0.5, 0.5)


def _fri_on_line(y, t, step, method):
    """FRI location on the line: period ``N`` spacings from the first light; a position past the last
    light by more than half a spacing belongs before the first one (as the fit's start does)."""
    period = step * y.shape[-1]
    found = ts.start.fri.locate(y, period=period, method=method)
    peak = t[0] + found.position
    peak = torch.where(peak > t[-1] + 0.5 * step, peak - period, peak)
    return peak, found.quality, found.std


def _grazing_samples(settings: Settings, cell: Setting, count: int, generator):
    """Rendered samples of a Ward lobe (``k_d = 0``) under the extended and the point lights of a line
    through the mirror direction of a view ``grazing_deg`` from the zenith, lights past the horizon
    reading 0; the true peaks and the Fisher information's pieces."""
    theta = math.radians(cell.grazing_deg)
    view = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=F64)
    t, step = _line(cell.samples, settings.span)
    t = t - math.sin(theta)
    lit = t.abs() < 0.99
    u = torch.rand(count, dtype=F64, generator=generator) * 2.0 - 1.0
    low = max(-settings.spread * 0.5 * settings.span, -0.98 + math.sin(theta))
    x = -math.sin(theta) + low + 0.5 * (u + 1.0) * (settings.spread * 0.5 * settings.span - low)
    a = 0.5 * (torch.asin(x) + theta)  # the normal's in-line angle that mirrors the view to x
    normal = torch.stack([torch.sin(a), torch.zeros_like(a), torch.cos(a)], -1)
    alpha = settings.lobe_width / math.sqrt(2.0)
    maps = SVBRDF(
        normal,
        torch.zeros(count, 1, dtype=F64),
        torch.ones(count, 1, dtype=F64),
        torch.full((count, 2), alpha, dtype=F64),
        None,
        ("Y",),
    )
    directions = from_plane(torch.stack([t[lit], torch.zeros_like(t[lit])], -1))
    ones = torch.ones(directions.shape[0], 1, dtype=F64)
    sigma = cell.width_ratio * settings.lobe_width
    extended = Kernel("gaussian", "projected", sigma) if sigma > 0 else Kernel("point")
    out = {}
    for name, kernel in (("extended", extended), ("point", Kernel("point"))):
        values = render(maps, Lights(directions, kernel, ones, ones[:, 0]), view)[..., 0]
        full = torch.zeros(count, cell.samples, dtype=F64)
        full[:, lit] = values
        out[name] = full
    _, jac = jacobian(maps, Lights(directions, extended, ones, ones[:, 0]), view)
    jac = jac[:, :, 0]  # (T, K, 8): a, b, k_d, k_s, alpha_x, alpha_y, rotation
    # The derivatives over every sample (0 where no light is): the unlit samples pin the offset.
    columns = torch.zeros(count, cell.samples, 4, dtype=F64)
    columns[:, lit] = torch.stack(
        [jac[..., 0], jac[..., 3], jac[..., 4] + jac[..., 5], torch.ones_like(jac[..., 0])], -1
    )
    columns[:, ~lit, 3] = 1.0
    slope = 2.0 * torch.cos(2.0 * a - theta)  # dl / da of the mirror direction
    return t, step, x, out, columns, slope


def _location_cell(settings: Settings, cell: Setting, sigma: float, generator) -> dict:
    """Every location method on one cell: per-trial errors, bounds and flag inputs."""
    count = settings.location.trials
    if cell.grazing_deg is not None:
        t, step, x, samples, columns, slope = _grazing_samples(settings, cell, count, generator)
        fisher = columns.transpose(-1, -2) @ columns / sigma**2
        bound = slope**2 * ts.model.crb.bound(fisher)[:, 0, 0]
        single = bound
        clean, point = samples["extended"], samples["point"]
    else:
        t, step = _line(cell.samples, settings.span)
        x, second = _peaks(settings, cell, count, step, generator)
        ones = torch.ones_like(x)
        truth = torch.stack([x, ones, settings.lobe_width * ones, 0 * x, second, settings.second_amplitude * ones], -1)
        forward = _model_1d(t, cell, settings)
        clean = forward(truth)
        point = _model_1d(t, replace(cell, width_ratio=0.0, skew=0.0), settings)(truth)
        bound, single = _bound_1d(forward, truth, sigma)
    noise = sigma * torch.randn(clean.shape, dtype=F64, generator=generator)
    y, y_point = clean + noise, point + noise
    out = {"bound": bound, "single": single, "x": x, "methods": {}}
    ends = (float(t[0]), float(t[-1]))
    width = blurred_width(y, step)
    for method in settings.location.methods:
        if method == "peak":
            peak = _parabola(y_point, t, step)
            quality, std, asymmetry = torch.ones_like(peak), torch.zeros_like(peak), torch.zeros_like(peak)
            local = asymmetry
            brightest = t[y_point.argmax(-1)]
        else:
            peak, quality, std = _fri_on_line(y, t, step, method)
            brightest = t[y.argmax(-1)]
            asymmetry = asymmetry_z(y, peak, float(t[0]), step, sigma)
            local = local_asymmetry(y, peak, float(t[0]), step, sigma)
        out["methods"][method] = {
            "peak": peak,
            "quality": quality,
            "std": std,
            "brightest": brightest,
            "asymmetry": asymmetry,
            "local": local,
            "lo": torch.full_like(peak, ends[0]),
            "hi": torch.full_like(peak, ends[1]),
            "spacing": torch.full_like(peak, step),
            "width": width,
        }
    return out


# --- the pipeline family: torchspec.pipeline.fit on small captures ---------------------------------------------


def _kernel(cell: Setting, settings: Settings) -> tuple[list[tuple[float, Tensor, Kernel]], LightSpec]:
    """The true light as ``(weight, l-plane offset, kernel)`` components, and what the capture declares:
    the same for a symmetric kernel; for a skewed one a Gaussian of its mean variance over both axes
    (what fitting a Gaussian to a calibration would give; a ``tabulated`` kernel is exact but its
    rendering path is too slow for this study: ~60 s for 10 pixels x 100 frames)."""
    sigma = cell.width_ratio * settings.lobe_width
    if sigma == 0:
        return [(1.0, torch.zeros(2, dtype=F64), Kernel("point"))], LightSpec(kernel="point")
    parts = kernel_components(sigma, cell.skew)
    out = [(w, torch.tensor([u, 0.0], dtype=F64), Kernel("gaussian", "projected", s)) for w, u, s in parts]
    declared = math.sqrt(0.5 * (sigma**2 + parts[0][2] ** 2))
    return out, LightSpec(kernel="gaussian", domain="projected", sigma=declared)


def _view(cell: Setting):
    theta = math.radians(cell.grazing_deg or 0.0)
    return torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=F64), theta


def _grid(settings: Settings, cell: Setting):
    """``(K, 2)`` light centres: an ``N x N`` grid over ``[-span / 2, span / 2]^2`` moved onto the flat
    surface's mirror direction, without those at or past the horizon."""
    t, step = _line(cell.samples, settings.span)
    gy, gx = torch.meshgrid(t.flip(0), t, indexing="ij")
    l = torch.stack([gx, gy], -1).reshape(-1, 2) - torch.tensor([math.sin(_view(cell)[1]), 0.0], dtype=F64)
    return l[l.norm(dim=-1) < 0.99], step


def _pixels(settings: Settings, cell: Setting, count: int, generator):
    """Truth maps of ``count`` pixels, the second facet's (a lobe alone) or None, and the true peaks
    ``(T, 2)``."""
    p = settings.pipeline
    view, theta = _view(cell)
    _, step = _line(cell.samples, settings.span)
    x, second = _peaks(settings, cell, count, step, generator)
    half = settings.spread * 0.5 * settings.span
    if theta:
        low = max(-half, -0.98 + math.sin(theta))
        x = -math.sin(theta) + low + torch.rand(count, dtype=F64, generator=generator) * (half - low)
    room = (0.98**2 - x * x).clamp(min=0.0).sqrt()
    y = (torch.rand(count, dtype=F64, generator=generator) * 2.0 - 1.0) * torch.minimum(room, torch.full_like(x, half))

    def facet(px, ks, kd):
        normal = normalize(from_plane(torch.stack([px, y], -1)) + view)
        return SVBRDF(
            normal,
            torch.full((count, 1), kd, dtype=F64),
            torch.full((count, 1), ks, dtype=F64),
            torch.full((count, 2), settings.lobe_width / math.sqrt(2.0), dtype=F64),
            None,
            ("Y",),
        )

    first = facet(x, p.specular, p.diffuse)
    other = None
    if cell.separation is not None:
        reach = (0.97**2 - y * y).sqrt()
        other = facet(torch.maximum(torch.minimum(second, reach), -reach), p.specular * settings.second_amplitude, 0.0)
    return first, other, torch.stack([x, y], -1)


def _slope(normal, view):
    """``d peak / d(a, b)`` ``(T, 2, 2)`` at the normal's tilt angles (central differences)."""
    angles = angles_from_normal(normal)
    h = 1e-6
    columns = []
    for j in range(2):
        step = torch.zeros_like(angles)
        step[:, j] = h
        plus, minus = normal_from_angles(angles + step), normal_from_angles(angles - step)
        columns.append((mirror_point(plus, view) - mirror_point(minus, view)) / (2 * h))
    return torch.stack(columns, -1)


def _bound_2d(first, other, truth, view, sigma):
    """The CRB ``trace(G C G^T)`` of the peak (``G`` = :func:`_slope`, ``C`` the tilt angles' block of
    the inverse Fisher information at the truth with every parameter unknown, a second facet's tilt
    and ``k_s`` too, one roughness for both), and the same with the second facet known. ``truth``:
    the light's ``(weight, Lights)`` components."""

    def jac(maps):
        return sum(w * jacobian(maps, lights, view)[1][:, :, 0] for w, lights in truth)  # (T, K, 8)

    one = jac(first)  # a, b, k_d, k_s, alpha_x, alpha_y, rotation
    columns = [one[..., 0], one[..., 1], one[..., 2], one[..., 3], one[..., 4] + one[..., 5]]
    single = torch.stack(columns, -1)
    full = single
    if other is not None:
        two = jac(other)
        columns[4] = columns[4] + two[..., 4] + two[..., 5]
        full = torch.stack([*columns, two[..., 0], two[..., 1], two[..., 3]], -1)
    slope = _slope(first.normal, view)
    out = []
    for j in (full, single):
        cov = ts.model.crb.bound(j.transpose(-1, -2) @ j / sigma**2)[:, :2, :2]
        out.append((slope @ cov @ slope.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).sum(-1))
    return out


def _capture_group(
    settings: Settings,
    lights_cell: Setting,
    cells: tuple[Setting, ...],
    sigma: float,
    sizes: tuple[int, int],
    folder: Path,
    generator,
) -> dict:
    """Render the cells sharing ``lights_cell``'s lights and view into one capture, ``sizes = (trials,
    matte)`` pixels per cell and of matte, with noise ``sigma``; each cell's true peaks and bounds."""
    view, _ = _view(lights_cell)
    l, step = _grid(settings, lights_cell)
    directions = from_plane(l)
    components, spec = _kernel(lights_cell, settings)
    k = directions.shape[0]
    ones = torch.ones(k, 1, dtype=F64)
    truth = [(w, Lights(from_plane(l + u), kernel, ones, ones[:, 0])) for w, u, kernel in components]
    values, truths = [], []
    for cell in cells:
        first, other, peak = _pixels(settings, cell, sizes[0], generator)
        value = sum(w * render(first, lights, view) for w, lights in truth)
        if other is not None:
            value = value + sum(w * render(other, lights, view) for w, lights in truth)
        bound, single = _bound_2d(first, other, truth, view, sigma)
        values.append(value)
        truths.append({"peak": peak, "bound": bound, "single": single})
    # Matte pixels from dark to light: the fit's noise model a y + b needs a range of values to tell a from b.
    count = sizes[1]
    tilt = torch.rand(count, 2, dtype=F64, generator=generator) * 0.2 - 0.1
    albedo = torch.logspace(math.log10(0.25), 0.0, count, dtype=F64)[:, None]
    matte = SVBRDF(
        normalize(from_plane(tilt)),
        albedo,
        torch.zeros(count, 1, dtype=F64),
        torch.full((count, 2), 0.1, dtype=F64),
        None,
        ("Y",),
    )
    values.append(sum(w * render(matte, lights, view) for w, lights in truth))
    stack = torch.cat(values)  # (pixels, K, 1)
    stack = stack + sigma * torch.randn(stack.shape, dtype=F64, generator=generator)
    width = 32
    rows = -(-stack.shape[0] // width)
    frames = torch.zeros(k, 1, rows * width, dtype=F64)
    frames[:, :, : stack.shape[0]] = stack.permute(1, 2, 0)
    capture = Capture(
        root=folder,
        width=width,
        height=rows,
        channels=("Y",),
        view=tuple(float(v) for v in view),
        light=spec,
        frames=tuple(
            Frame(f"frames/{i:04d}.exr", tuple(float(v) for v in directions[i]), (1.0,), 1.0) for i in range(k)
        ),
    )
    write_capture(folder, capture, frames.reshape(k, 1, rows, width).float())
    return {"truths": truths, "view": view, "frames": k, "step": step, "trials": sizes[0]}


def _fit_group(settings: Settings, folder: Path, group: dict, cells, init: str) -> list[dict]:
    """One fit of a group's capture; per cell, the per-trial peaks and flag inputs."""
    with warnings.catch_warnings():  # additive noise leaves negative samples: kept, as the fit does
        warnings.filterwarnings("ignore", message=r".*pixel\(s\) with a negative value")
        config = settings.pipeline.fit
        result = fit(folder, config=replace(config, start=replace(config.start, init=init)))
    local, astray = (result.checks[name].reshape(-1).double() for name in ("peak_misfit", "astray"))
    # The package's verdict on a peak: a flag of torchspec.pipeline.flags.UNTRUSTED, or no lobe established.
    flags = result.flags.reshape(-1)
    weak = (flags.to(torch.int32) & bit("weak_lobe")) != 0
    verdict = untrusted(flags) | ~result.lobe.reshape(-1) | weak
    normal = result.svbrdf.normal.reshape(-1, 3).double()
    peak = mirror_point(normal, group["view"])
    model = result.model.reshape(-1)
    size = torch.tensor([get_model(name).size(1) for name in MODEL_CODES], dtype=F64)[model.long()]
    n = torch.tensor(float(group["frames"]), dtype=F64)
    chi2 = result.criterion.reshape(-1).double() - size * torch.log(n)
    dof = (n - size).clamp(min=1.0)
    out, start = [], 0
    for _ in cells:
        rows = slice(start, start + group["trials"])
        start += group["trials"]
        out.append(
            {
                "peak": peak[rows],
                "quality": result.quality.reshape(-1)[rows].double(),
                "status": result.status.reshape(-1)[rows].long(),
                "lobe": result.lobe.reshape(-1)[rows],
                "chi2_z": ((chi2 - dof) / (2.0 * dof).sqrt())[rows],
                "std_deg": torch.rad2deg(result.std["normal"].reshape(-1)[rows].double()),
                "iterations": result.iterations.reshape(-1)[rows].double(),
                "local": local[rows],
                "astray": astray[rows],
                "package": verdict[rows],
            }
        )
    return out


def _pipeline_sigma(settings: Settings) -> float:
    """The noise std that gives the base setting its SNR on the specular part of its samples."""
    generator = torch.Generator().manual_seed(settings.seed)
    base = replace(settings.base, samples=settings.pipeline.samples)
    view, _ = _view(base)
    l, _ = _grid(settings, base)
    components, _ = _kernel(base, settings)
    ones = torch.ones(l.shape[0], 1, dtype=F64)
    first, _, _ = _pixels(settings, base, 256, generator)
    lobe = replace(first, diffuse=first.diffuse * 0)
    specular = sum(
        w * render(lobe, Lights(from_plane(l + u), kernel, ones, ones[:, 0]), view) for w, u, kernel in components
    )
    return math.sqrt(float(specular.pow(2).mean()) / 10 ** (base.snr_db / 10))


# --- cells, scoring and the run ---------------------------------------------------------------------


def _cells(settings: Settings, axes: Axes) -> list[tuple[str, float, Setting]]:
    """``(axis, value, setting)`` of every axis cell; the base setting once, under every axis it is on."""
    out = []
    for axis in AXES:
        for value in getattr(axes, axis):
            out.append((axis, value, replace(settings.base, **{axis: value})))
    return out


def _score(errors, bound, failure: float) -> dict:
    ratio = errors.abs() / bound.sqrt()
    failed = ~(ratio <= failure)  # NaN estimates fail
    return {
        "median_error": float(errors.abs().nanmedian()),
        "median_error_over_crb": float(ratio.nanmedian()),
        "median_crb_std": float(bound.sqrt().median()),
        "failure_rate": float(failed.double().mean()),
    }, failed


def run_location(settings: Settings, pool: dict) -> list[dict]:
    rows, memo = [], {}
    loc = settings.location
    cells = _cells(settings, loc.axes)
    cells += [
        ("map", (s, n), replace(settings.base, snr_db=s, samples=n)) for s in loc.map_snr_db for n in loc.map_samples
    ]
    sigmas, references = {}, {}
    for axis, value, cell in cells:
        noise_snr = cell.snr_db
        if noise_snr not in sigmas:
            sigmas[noise_snr] = _noise_sigma(settings, noise_snr)
        if cell not in memo:
            generator = torch.Generator().manual_seed(settings.seed + 7919 * len(memo))
            if cell.grazing_deg is not None:  # the rendered lobe has its own scale: the base is its zenith view
                key = replace(cell, grazing_deg=0.0)
                if key not in references:
                    references[key] = _grazing_reference(settings, cell)
                sigma = references[key] / math.sqrt(10 ** (cell.snr_db / 10))
            else:
                sigma = sigmas[noise_snr]
            memo[cell] = _location_cell(settings, cell, sigma, generator)
            fresh = True
        else:
            fresh = False
        data = memo[cell]
        row = {"family": "location", "axis": axis, "value": list(value) if axis == "map" else value, "methods": {}}
        for method, est in data["methods"].items():
            errors = est["peak"] - data["x"]
            score, failed = _score(errors, data["bound"], settings.failure)
            if axis == "separation":  # against the bound that knows the second lobe
                score["failure_rate_second_lobe_known"] = _score(errors, data["single"], settings.failure)[0][
                    "failure_rate"
                ]
            if method != "peak":
                score["median_quality"] = float(est["quality"].median())
                flag = flag_location(est, settings.rules.location)
                score.update(_rates(flag, failed))
                score["median_asymmetry_z"] = float(est["asymmetry"].nanmedian())
                score["median_local_asymmetry"] = float(est["local"].nanmedian())
                if fresh:  # every trial once in the pooled flag statistics
                    _append(
                        pool.setdefault("location", {}),
                        {
                            **est,
                            "error": errors.abs(),
                            "failed": failed,
                            "method": method,
                            "axis": axis,
                        },
                    )
            row["methods"][method] = score
        rows.append(row)
        print(_line_text(row), flush=True)
    return rows


def _grazing_reference(settings: Settings, cell: Setting) -> float:
    """RMS of the rendered, noise-free samples of the grazing family's base (its zenith view)."""
    generator = torch.Generator().manual_seed(settings.seed)
    _, _, _, samples, _, _ = _grazing_samples(settings, replace(cell, grazing_deg=0.0), 1024, generator)
    return float(samples["extended"].pow(2).mean().sqrt())


def _append(pool: dict, data: dict) -> None:
    for key, value in data.items():
        pool.setdefault(key, []).append(value)


def _line_text(row: dict) -> str:
    cells = " ".join(f"{m}={s['failure_rate']:.2f}/{s['median_error_over_crb']:.2g}" for m, s in row["methods"].items())
    return f"{row['family']:8s} {row['axis']:12s} {row['value']!s:>12s}  fail/med(err/crb): {cells}"


def run_pipeline(settings: Settings, pool: dict, workdir: Path) -> list[dict]:
    p = settings.pipeline
    sigma = _pipeline_sigma(settings) if p.runs else 0.0
    base = replace(settings.base, samples=p.samples)
    rows, captures, scored = [], {}, {}
    for run in p.runs:
        # A fit always renders the Ward lobe: the grazing axis' zenith view is the base setting.
        cells = [
            (a, v, replace(c, grazing_deg=None) if c.grazing_deg == 0 else c)
            for a, v, c in _cells(replace(settings, base=base), run.axes)
        ]
        # Cells that share lights, view and noise share a capture (the fit measures the noise per capture).
        groups: dict[Setting, list[Setting]] = {}
        for cell in dict.fromkeys(c for _, _, c in cells):
            key = replace(
                base, **{k: getattr(cell, k) for k in ("snr_db", "samples", "width_ratio", "skew", "grazing_deg")}
            )
            groups.setdefault(key, []).append(cell)
        results = {}
        for key, members in groups.items():
            members = tuple(members)
            sizes = (run.trials or p.trials, run.matte or p.matte)
            if (key, members, sizes) not in captures:
                generator = torch.Generator().manual_seed(settings.seed + 104729 * (len(captures) + 1))
                folder = workdir / f"capture-{len(captures)}"
                noise = sigma * 10 ** ((base.snr_db - key.snr_db) / 20)
                captures[(key, members, sizes)] = (
                    folder,
                    _capture_group(settings, key, members, noise, sizes, folder, generator),
                )
            folder, group = captures[(key, members, sizes)]
            started = time.perf_counter()
            fitted = _fit_group(settings, folder, group, members, run.init)
            seconds = time.perf_counter() - started
            for cell, truth, est in zip(members, group["truths"], fitted, strict=True):
                results[cell] = (truth, est, seconds / len(members))
        name = f"{run.init}+lm"
        for axis, value, cell in cells:
            truth, est, seconds = results[cell]
            errors = (est["peak"] - truth["peak"]).norm(dim=-1)
            score, failed = _score(errors, truth["bound"], settings.failure)
            if axis == "separation":
                score["failure_rate_second_lobe_known"] = _score(errors, truth["single"], settings.failure)[0][
                    "failure_rate"
                ]
            flag = flag_fit(est, settings.rules.fit)
            score.update(_rates(flag, failed))
            score.update(
                {
                    "median_quality": float(est["quality"].median()),
                    "lobe_detected": float(est["lobe"].double().mean()),
                    "converged": float((est["status"] == STATUS.index("converged")).double().mean()),
                    "median_chi2_z": float(est["chi2_z"].nanmedian()),
                    "median_local_residual": float(est["local"].nanmedian()),
                    "median_astray": float(est["astray"].nanmedian()),
                    "mean_iterations": float(est["iterations"].mean()),
                    "seconds_per_cell": seconds,
                }
            )
            if (name, cell) not in scored:  # every trial once in the pooled flag statistics
                scored[(name, cell)] = True
                _append(
                    pool.setdefault("fit", {}),
                    {**est, "error": errors, "failed": failed, "method": name, "axis": axis},
                )
            row = next((r for r in rows if r["axis"] == axis and r["value"] == value), None)
            if row is None:
                row = {"family": "pipeline", "axis": axis, "value": value, "methods": {}}
                rows.append(row)
            row["methods"][name] = score
        print(f"pipeline {name}: {len(groups)} fits, {sum(len(m) for m in groups.values())} cells", flush=True)
    for row in rows:
        print(_line_text(row), flush=True)
    return rows


# --- the summary: flags, where each method breaks, outputs ------------------------------------------


def summarise_flags(pool: dict, settings: Settings) -> dict:
    """Catch and false-alarm rates of the configured rules over every trial of every cell (and of
    each flag alone), per method, and the best thresholds of :func:`search_rules`."""
    out = {}
    for family, parts in pool.items():
        data = {key: torch.cat(value) for key, value in parts.items() if key not in ("method", "axis")}
        rule = asdict(settings.rules.location if family == "location" else settings.rules.fit)
        failed = data["failed"]
        flag = _flag(data, family, rule)
        summary = {"rule": rule, "all_cells": _rates(flag, failed), "per_method": {}, "per_axis": {}, "alone": {}}
        if family == "fit":  # the headline: what the package itself flags (Fit.flags), the rule beside it
            summary["rule_all_cells"] = summary["all_cells"]
            flag = data["package"]
            summary["all_cells"] = _rates(flag, failed)
        for label, key in (("per_method", "method"), ("per_axis", "axis")):
            tags = [t for t, part in zip(parts[key], parts["failed"], strict=True) for _ in range(part.numel())]
            names = list(dict.fromkeys(tags))
            index = torch.tensor([names.index(t) for t in tags])
            for k, name in enumerate(names):
                summary[label][name] = _rates(flag[index == k], failed[index == k])
        # A kernel declared symmetric that is not leaves data a shifted symmetric kernel explains too.
        skew = torch.tensor(
            [t == "skew" for t, part in zip(parts["axis"], parts["failed"], strict=True) for _ in range(part.numel())]
        )
        summary["without_skew_axis"] = _rates(flag[~skew], failed[~skew])
        off = (
            {
                "quality": -math.inf,
                "astray": math.inf,
                "edge": -math.inf,
                "std": math.inf,
                "asymmetry_z": math.inf,
                "local": math.inf,
            }
            if family == "location"
            else {
                "quality": -math.inf,
                "chi2_z": math.inf,
                "status": False,
                "no_lobe": False,
                "std_deg": math.inf,
                "local": math.inf,
                "astray": math.inf,
            }
        )
        for name in off:
            alone = {**off, name: rule[name]}
            summary["alone"][name] = _rates(_flag(data, family, alone), failed)
        good = ~failed & (data["std"] > 0 if family == "location" else data["std_deg"] > 0)
        if family == "location":
            z = data["error"] / data["std"]
        else:  # the normal's std in the peak's units: dl/da ~ 2 near the zenith
            z = data["error"] / (2.0 * torch.deg2rad(data["std_deg"]))
        summary["error_over_std_median_good"] = float(z[good].nanmedian()) if bool(good.any()) else None
        summary["search"] = search_rules(data, family)
        out[family] = summary
    return out


def _works(values: list, rates: list, threshold: float) -> str:
    """The values an axis can take before a method breaks: the longest run of cells failing at most
    ``threshold`` of their trials (``all``, ``none``)."""
    ok = [r is not None and r <= threshold for r in rates]
    if all(ok):
        return "all"
    if not any(ok):
        return "none"
    best, run = (0, -1), None
    for k, good in enumerate(ok + [False]):
        if good and run is None:
            run = k
        if not good and run is not None:
            if k - run > best[1] - best[0] + 1:
                best = (run, k - 1)
            run = None
    lo, hi = values[best[0]], values[best[1]]
    return f"{_fmt(lo)}" if lo == hi else f"{_fmt(lo)}..{_fmt(hi)}"


def _fmt(value) -> str:
    return f"{value:g}" if isinstance(value, (int, float)) else str(value)


def breakdown(rows: list[dict], settings: Settings) -> dict:
    """Per method and axis: the values (in config order) with their failure rates, and the run of
    values where it works (failure rate <= ``break_rate``)."""
    table: dict[str, dict[str, dict]] = {}
    for axis in AXES:
        for row in (r for r in rows if r["axis"] == axis):
            for method, score in row["methods"].items():
                entry = table.setdefault(method, {}).setdefault(
                    axis, {"values": [], "failure_rate": [], "median_error_over_crb": []}
                )
                entry["values"].append(row["value"])
                entry["failure_rate"].append(score["failure_rate"])
                entry["median_error_over_crb"].append(score["median_error_over_crb"])
    for axes in table.values():
        for entry in axes.values():
            entry["works"] = _works(entry["values"], entry["failure_rate"], settings.break_rate)
    return table


def _panel(fig, ax, data, columns, rows, title: str, error: bool) -> None:
    """One heat map: median |error| (l units, log colour) or failure rate (%), values written in."""
    from matplotlib.colors import LogNorm

    shown = data.clamp(1e-5, 1.0) if error else data
    image = ax.imshow(
        shown.numpy(),
        origin="lower",
        aspect="auto",
        cmap="viridis" if error else "magma_r",
        norm=LogNorm(1e-4, 0.3) if error else None,
        vmin=None if error else 0,
        vmax=None if error else 1,
    )
    for i in range(data.shape[0]):
        for j in range(data.shape[1]):
            v = float(data[i, j])
            if math.isfinite(v):
                text = f"{v:.1g}" if error else f"{100 * v:.0f}"
                ax.text(j, i, text, ha="center", va="center", fontsize=6.5, color="w" if error else "k")
    ax.set_xticks(range(len(columns)), columns, fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, fraction=0.03)


def _heatmaps(rows: list[dict], path: Path) -> None:
    """Per axis: methods x values, median |error| and failure rate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(dict.fromkeys(m for r in rows for m in r["methods"] if r["axis"] != "map"))[::-1]
    axes_used = [a for a in AXES if any(r["axis"] == a for r in rows)]
    fig, panels = plt.subplots(len(axes_used), 2, figsize=(16, 3.0 * len(axes_used)), squeeze=False)
    for (left, right), axis in zip(panels, axes_used, strict=True):
        values = list(dict.fromkeys(r["value"] for r in rows if r["axis"] == axis))
        error = torch.full((len(methods), len(values)), math.nan)
        fail = torch.full_like(error, math.nan)
        for r in (r for r in rows if r["axis"] == axis):
            for m, score in r["methods"].items():
                i, j = methods.index(m), values.index(r["value"])
                error[i, j], fail[i, j] = score["median_error"], score["failure_rate"]
        columns = [_fmt(v) for v in values]
        unit = f" ({UNITS[axis]})" if UNITS[axis] else ""
        _panel(fig, left, error, columns, methods, f"{axis}{unit}: median |error| (l units)", True)
        _panel(fig, right, fail, columns, methods, f"{axis}{unit}: failure rate (|error| > 10 CRB std), %", False)
    fig.tight_layout()
    save_figure(fig, path)


def _maps(rows: list[dict], path: Path) -> None:
    """SNR x samples maps of the location methods."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = [r for r in rows if r["axis"] == "map"]
    if not cells:
        return
    methods = list(cells[0]["methods"])
    snrs = sorted({r["value"][0] for r in cells})
    counts = sorted({r["value"][1] for r in cells})
    fig, panels = plt.subplots(len(methods), 2, figsize=(12, 3.2 * len(methods)), squeeze=False)
    for (left, right), method in zip(panels, methods, strict=True):
        error = torch.full((len(counts), len(snrs)), math.nan)
        fail = torch.full_like(error, math.nan)
        for r in cells:
            i, j = counts.index(r["value"][1]), snrs.index(r["value"][0])
            error[i, j] = r["methods"][method]["median_error"]
            fail[i, j] = r["methods"][method]["failure_rate"]
        for ax, data, title, kind in ((left, error, "median |error|", True), (right, fail, "failure rate, %", False)):
            _panel(fig, ax, data, [_fmt(v) for v in snrs], [str(v) for v in counts], f"{method}: {title}", kind)
            ax.set(xlabel="SNR (dB)", ylabel="samples")
    fig.tight_layout()
    save_figure(fig, path)


def _rate(r: dict) -> str:
    return f"{100 * (r['catch'] or 0):.0f} % / {100 * (r['false_alarms'] or 0):.1f} %"


def _markdown(result: dict, settings: Settings, command: str) -> str:
    table, flags = result["breakdown"], result["flags"]
    axes = [a for a in AXES if any(a in t for t in table.values())]
    base, pipe = settings.base, settings.pipeline
    lines = [
        "# Stability study (issue 6)",
        "",
        f"`{command}`: {result['seconds']:.0f} s on {result['threads']} threads, torch {result['torch']}. Error: the "
        "specular peak's location in l units (location family: along the line; pipeline: 2D distance of the "
        f"fitted normal's mirror direction). Failure: `|error| > {settings.failure:g} sqrt(CRB)`, the CRB per "
        "trial from the Fisher information at the truth with every parameter but the kernel unknown. A method "
        f"*works* where at most {100 * settings.break_rate:g} % of a cell's trials fail. Base: SNR "
        f"{base.snr_db:g} dB, kernel / lobe width {base.width_ratio:g} (lobe std {settings.lobe_width:g} l), "
        f"symmetric kernel, peaks within {settings.spread:g} of the half-span {settings.span / 2:g}, one lobe, "
        f"zenith view; {base.samples} lights on a line, {settings.location.trials} trials per cell (location); "
        f"a {pipe.samples} x {pipe.samples} grid, {pipe.trials} pixels per cell (pipeline).",
        "",
        "## Where each method works",
        "",
        "The run of axis values (in config order) around the base where the failure rate stays within the limit; "
        "outside it, the method breaks.",
        "",
        "| method | " + " | ".join(f"{a} ({UNITS[a]})" if UNITS[a] else a for a in axes) + " |",
        "| --- |" + " --- |" * len(axes),
    ]
    for method, entry in table.items():
        lines.append(f"| {method} | " + " | ".join(entry[a]["works"] if a in entry else "-" for a in axes) + " |")
    lines += ["", "Cells failing more than the limit (failure rate):", ""]
    for method, entry in table.items():
        parts = []
        for a in axes:
            if a not in entry:
                continue
            bad = [
                (v, r)
                for v, r in zip(entry[a]["values"], entry[a]["failure_rate"], strict=True)
                if r > settings.break_rate
            ]
            if bad:
                parts.append(f"{a} " + ", ".join(f"{_fmt(v)} ({100 * r:.0f} %)" for v, r in bad))
        lines.append(f"- **{method}**: " + ("; ".join(parts) if parts else "none") + ".")
    lines += [
        "",
        "## Quality flags",
        "",
        "Catch rate (failures flagged) / false alarms (good estimates flagged), "
        "over every trial of every cell; the target is >= 90 % / <= 5 %.",
        "",
    ]
    for family, summary in flags.items():
        rates = summary["all_cells"]
        rule = ", ".join(f"{k} {_fmt(v)}" for k, v in summary["rule"].items())
        verdict = "meets" if rates["catch"] >= 0.9 and rates["false_alarms"] <= 0.05 else "does not meet"
        best = summary["search"][0]
        if family == "fit":
            head = (
                "- **fit**: the package's own flags (`Fit.flags`: a flag of "
                f"`torchspec.pipeline.flags.UNTRUSTED`, or no lobe "
                f"fitted or established (`weak_lobe`); compare the rule {rule}: {_rate(summary['rule_all_cells'])})"
            )
        else:
            head = f"- **{family}** rule ({rule}; FRI alone: the package does not flag its start)"
        lines += [
            f"{head}: {_rate(rates)} of {rates['failures']} failures and {rates['good']} good "
            f"estimates: it {verdict} the target.",
            "  Per method: " + "; ".join(f"{m} {_rate(r)}" for m, r in summary["per_method"].items()) + ".",
            "  Per axis: " + "; ".join(f"{a} {_rate(r)}" for a, r in summary["per_axis"].items()) + ".",
            "  Each flag alone: " + "; ".join(f"{k} {_rate(r)}" for k, r in summary["alone"].items()) + ".",
            f"  All cells but the skew axis' (a mis-declared kernel): {_rate(summary['without_skew_axis'])}.",
            f"  Best of the search grid: {best['rule']}: {_rate(best)}. Median |error| / reported std of the good "
            f"estimates: {summary['error_over_std_median_good']:.2f}.",
        ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "stability.yaml", argv)
    settings = load_config(args.config, Settings)
    started = time.perf_counter()
    pool: dict = {}
    rows = run_location(settings, pool)
    location_seconds = time.perf_counter() - started
    with tempfile.TemporaryDirectory() as tmp:
        rows += run_pipeline(settings, pool, Path(tmp))
    result = {
        "settings": asdict(settings),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "rows": rows,
        "breakdown": breakdown(rows, settings),
        "flags": summarise_flags(pool, settings),
    }
    result["seconds"] = time.perf_counter() - started
    result["seconds_location"] = location_seconds
    stem = args.output / args.config.stem
    write_json(stem.with_suffix(".json"), result)
    _heatmaps(rows, stem.with_suffix(".png"))
    _maps(rows, stem.parent / f"{stem.name}_maps.png")
    command = f"python experiments/stability.py --config experiments/configs/{args.config.name}"
    with atomic_path(stem.with_suffix(".md")) as tmp:
        tmp.write_text(_markdown(result, settings, command), encoding="utf-8")
    for family, summary in result["flags"].items():
        rates = summary["all_cells"]
        print(
            f"{family} flags: catch {rates['catch']:.3f}, false alarms {rates['false_alarms']:.3f}; "
            f"best: {summary['search'][0]}"
        )
    print(f"wrote {stem}.json/.png/.md in {result['seconds']:.0f} s")
    return result


if __name__ == "__main__":
    main()
