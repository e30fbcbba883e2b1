"""Synthetic ground truth: procedural SVBRDF maps of a painting and of a near-mirror, and a
sensor model that turns rendered radiance into what an HDR camera records.

A fit can only be scored against known maps, and the development captures are few; these
generators make as many test objects as needed, with the structure that makes paintings hard:
pigment patches and brush strokes in ``k_d``, canvas weave and impasto in the normals, matte
and varnished areas side by side, and an anisotropic coloured gilding. The settings match those
of the independently rendered ``painting-dev`` and ``mirror-dev-1d`` captures
(``truth/scene.json``), so ``PaintingConfig()`` and ``MirrorConfig()`` are look-alikes of them.

Maps follow ``docs/capture-format.md``: leading dims ``(H, W)`` with row 0 the top of the image,
surface ``x`` along the columns and ``y`` up (towards row 0). Normals come from the gradient of
a height field, so they are integrable like a real surface's, and every random draw is made on
the CPU in float64 from generators seeded by ``config.seed``: a seed gives the same maps on any
device and in any dtype, up to the final rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..config import ConfigError
from ..model.brdf import SVBRDF

__all__ = [
    "GildedConfig",
    "PaintingConfig",
    "MirrorConfig",
    "SensorConfig",
    "MATTE",
    "VARNISHED",
    "GILDED",
    "DUAL",
    "DualConfig",
    "painting",
    "mirror",
    "sense",
]

MATTE, VARNISHED, GILDED, DUAL = 0, 1, 2, 3
"""The labels of the region map (as in ``truth/regions.exr``)."""

_F64 = torch.float64

# Independent random streams, so that changing one setting (say the number of strokes) leaves
# the other layers of a painting unchanged.
_PIGMENT_FIELDS, _PIGMENT_COLOURS, _WEAVE, _STROKES, _VARNISH, _GILDED = range(6)

# Above this mean photon count the Poisson law is replaced by its Gaussian limit: the skew left
# out is below 3 %, and the Gaussian costs the same for any count.
_POISSON_LIMIT = 1000.0


@dataclass(frozen=True)
class GildedConfig:
    """A gilded rectangle: gold leaf, a coloured anisotropic lobe over a dark diffuse base.

    Attributes:
        box: ``(x0, y0, x1, y1)`` in fractions of the image width and height, ``x`` to the
            right and ``y`` down the rows (as in ``scene.json``); a pixel is gilded when its
            centre is inside.
        ks: per-channel ``k_s`` (the colour of the metal).
        kd: per-channel ``k_d``.
        alpha: ``(alpha_x, alpha_y)``, the burnishing direction along the surface ``x`` axis.
        max_tilt_deg: the largest normal tilt inside the box, degrees.
    """

    box: tuple[float, float, float, float] = (0.1, 0.55, 0.35, 0.85)
    ks: tuple[float, ...] = (0.7, 0.5, 0.2)
    kd: tuple[float, ...] = (0.03, 0.02, 0.01)
    alpha: tuple[float, float] = (0.18, 0.05)
    max_tilt_deg: float = 3.0


@dataclass(frozen=True)
class DualConfig:
    """A rectangle of two-lobed gloss: a sharp varnish over a glossy layer with a broad lobe of
    its own (both grey and isotropic, on one normal: the ``ward-dual`` model). It replaces the
    varnish (and the matte) inside it; gilding stays on top.

    Attributes:
        box: ``(x0, y0, x1, y1)`` as :attr:`GildedConfig.box`.
        ks, alpha: the sharp lobe's ``k_s`` and ``alpha``.
        ks2, alpha2: the broad lobe's.
    """

    box: tuple[float, float, float, float] = (0.55, 0.1, 0.9, 0.4)
    ks: float = 0.08
    alpha: float = 0.04
    ks2: float = 0.25
    alpha2: float = 0.25


@dataclass(frozen=True)
class PaintingConfig:
    """Settings of :func:`painting`; lengths are in pixels.

    Attributes:
        width, height: the image size ``W``, ``H``.
        seed: the seed of every random draw.
        pigments: the number of pigment colours.
        pigment_scale: the typical size of a pigment patch.
        pigment_sharpness: how abruptly neighbouring pigments meet (0 blends them all evenly).
        kd_range: ``(lo, hi)`` of every ``k_d`` channel outside the gilding.
        weave_period: the canvas thread period.
        weave_amp: the weave's largest slope as a fraction of ``tan(max_tilt_deg)`` (0.25 makes
            the weave a quarter of the steepest stroke, as in ``painting-dev``).
        strokes: the number of brush strokes.
        stroke_width, stroke_length: ``(lo, hi)`` of the uniform draws of each stroke's size.
        max_tilt_deg: the cap on the normal tilt, degrees.
        varnish_fraction: the fraction of the non-gilded area that is varnished.
        varnish_scale: the typical size of a varnish blob and of its ``k_s``, ``alpha`` variations.
        ks_range, alpha_range: ``(lo, hi)`` of the grey ``k_s`` and the isotropic ``alpha`` of
            the varnish.
        gilded: the gilded box, or ``None`` for none.
        dual: a box of two-lobed gloss (:class:`DualConfig`), or ``None`` for none: the maps
            then have a second lobe (``SVBRDF.specular2``).
    """

    width: int = 48
    height: int = 48
    seed: int = 777
    pigments: int = 5
    pigment_scale: float = 7.0
    pigment_sharpness: float = 6.0
    kd_range: tuple[float, float] = (0.05, 0.75)
    weave_period: float = 4.3
    weave_amp: float = 0.25
    strokes: int = 20
    stroke_width: tuple[float, float] = (3.0, 7.0)
    stroke_length: tuple[float, float] = (10.0, 30.0)
    max_tilt_deg: float = 12.0
    varnish_fraction: float = 0.55
    varnish_scale: float = 8.0
    ks_range: tuple[float, float] = (0.05, 0.3)
    alpha_range: tuple[float, float] = (0.03, 0.2)
    gilded: GildedConfig | None = field(default_factory=GildedConfig)
    dual: DualConfig | None = None


@dataclass(frozen=True)
class MirrorConfig:
    """Settings of :func:`mirror`: a uniform near-mirror with a tilted normal.

    Attributes:
        width, height: the image size ``W``, ``H``.
        kd: per-channel ``k_d`` (its length is the number of channels ``C``).
        ks: per-channel ``k_s`` (length ``C``, or 1 for grey).
        alpha: ``(alpha_x, alpha_y)``.
        tilt_deg: the normal's angle from the surface ``z`` axis, degrees.
        tilt_azimuth_deg: the direction it leans to, from the surface ``x`` axis counter-clockwise
            towards ``y``, degrees.
    """

    width: int = 16
    height: int = 16
    kd: tuple[float, ...] = (0.02, 0.02, 0.02)
    ks: tuple[float, ...] = (0.8, 0.8, 0.8)
    alpha: tuple[float, float] = (0.005, 0.005)
    tilt_deg: float = 3.0
    tilt_azimuth_deg: float = -20.0


@dataclass(frozen=True)
class SensorConfig:
    """Settings of :func:`sense`.

    Attributes:
        exposure: the factor from radiance to recorded value.
        photons_per_unit: photons collected per unit of exposed value; 0 turns shot noise off.
        read_noise: std of the additive Gaussian noise, in value units.
        saturation: the largest value the sensor records (``inf`` for none).
        seed: the seed of the noise when :func:`sense` is given no generator.
    """

    exposure: float = 1.0
    photons_per_unit: float = 0.0
    read_noise: float = 0.0
    saturation: float = math.inf
    seed: int = 0


def _require(checks: list[tuple[bool, str]]) -> None:
    """Raises :class:`~torchspec.config.ConfigError` with the message of the first failed ``(ok, message)``
    check."""
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)


def _size_checks(config: PaintingConfig | MirrorConfig) -> list[tuple[bool, str]]:
    return [(config.width >= 1 and config.height >= 1,
             f"width and height must be >= 1; got {config.width}, {config.height}.")]


def _range_check(name: str, value: tuple[float, float], *, positive: bool = False) -> tuple[bool, str]:
    ok = len(value) == 2 and (value[0] > 0 if positive else value[0] >= 0) and value[0] <= value[1]
    return ok, f"{name} must be (lo, hi) with {'0 <' if positive else '0 <='} lo <= hi; got {value!r}."


def _box_check(name: str, box: tuple) -> tuple[bool, str]:
    x0, y0, x1, y1 = box if len(box) == 4 else (1, 1, 0, 0)
    return (
        0 <= x0 <= x1 <= 1 and 0 <= y0 <= y1 <= 1,
        f"{name}.box must be (x0, y0, x1, y1) with 0 <= x0 <= x1 <= 1, 0 <= y0 <= y1 <= 1; got {box!r}.",
    )


def _check_painting(config: PaintingConfig) -> None:
    checks = _size_checks(config) + [
        (config.pigments >= 1, f"pigments must be >= 1; got {config.pigments}."),
        (config.strokes >= 0, f"strokes must be >= 0; got {config.strokes}."),
        (config.pigment_scale > 0, f"pigment_scale must be > 0; got {config.pigment_scale!r}."),
        (config.varnish_scale > 0, f"varnish_scale must be > 0; got {config.varnish_scale!r}."),
        (config.weave_period > 0, f"weave_period must be > 0; got {config.weave_period!r}."),
        (config.pigment_sharpness >= 0, f"pigment_sharpness must be >= 0; got {config.pigment_sharpness!r}."),
        (config.weave_amp >= 0, f"weave_amp must be >= 0; got {config.weave_amp!r}."),
        (0 <= config.max_tilt_deg < 90, f"max_tilt_deg must be in [0, 90); got {config.max_tilt_deg!r}."),
        (0 <= config.varnish_fraction <= 1, f"varnish_fraction must be in [0, 1]; got {config.varnish_fraction!r}."),
        _range_check("kd_range", config.kd_range),
        _range_check("ks_range", config.ks_range),
        _range_check("stroke_width", config.stroke_width, positive=True),
        _range_check("stroke_length", config.stroke_length, positive=True),
        _range_check("alpha_range", config.alpha_range, positive=True),
    ]
    gilded = config.gilded
    if gilded is not None:
        checks += [
            _box_check("gilded", gilded.box),
            (len(gilded.kd) == 3 and len(gilded.ks) == 3,
             f"gilded.kd and gilded.ks must have 3 values (R, G, B); got {gilded.kd!r}, {gilded.ks!r}."),
            (len(gilded.alpha) == 2 and min(gilded.alpha) > 0,
             f"gilded.alpha must be 2 values > 0; got {gilded.alpha!r}."),
            (0 <= gilded.max_tilt_deg < 90, f"gilded.max_tilt_deg must be in [0, 90); got {gilded.max_tilt_deg!r}."),
        ]
    dual = config.dual
    if dual is not None:
        checks += [
            _box_check("dual", dual.box),
            (dual.ks >= 0 and dual.ks2 >= 0, f"dual.ks and dual.ks2 must be >= 0; got {dual.ks!r}, {dual.ks2!r}."),
            (dual.alpha > 0 and dual.alpha2 > 0,
             f"dual.alpha and dual.alpha2 must be > 0; got {dual.alpha!r}, {dual.alpha2!r}."),
        ]
    _require(checks)


def _generator(seed: int, stream: int) -> torch.Generator:
    # A seed per (config seed, layer): the streams stay independent of one another.
    return torch.Generator().manual_seed((seed * 1_000_003 + stream * 7_919) % (2**63))


def _smooth_field(shape: tuple[int, ...], scale: float, generator: torch.Generator) -> Tensor:
    """Stationary Gaussian random fields ``(*shape[:-2], H, W)`` of unit variance with the
    correlation ``exp(-d^2 / (2 scale^2))`` at a distance of ``d`` pixels: white noise under a
    Gaussian blur, computed past the border so the edges are as random as the middle."""
    *batch, height, width = shape
    # Blurring twice (the noise is white) doubles the variance of the kernel.
    sigma = scale / math.sqrt(2.0)
    pad = math.ceil(3.0 * sigma)
    # CPU on purpose: the seeded draw is the same on every device (the maps are cast at the end)
    noise = torch.randn(*batch, height + 2 * pad, width + 2 * pad, generator=generator, dtype=_F64)
    # The blur by FFT costs the same for any scale; the kernel spans at most 2 pad + 1 pixels,
    # so the cropped output never sees the wrap-around of the circular convolution.
    spectrum = torch.fft.rfft2(noise)
    for axis, length in ((-2, height + 2 * pad), (-1, width + 2 * pad)):
        taps = torch.arange(length, dtype=_F64, device=noise.device)
        taps = torch.minimum(taps, length - taps)  # circular distance to tap 0
        kernel = torch.where(taps <= pad, torch.exp(-0.5 * (taps / sigma) ** 2), 0.0)
        kernel = kernel / torch.linalg.vector_norm(kernel)  # unit variance after each 1D pass
        transfer = torch.fft.rfft(kernel) if axis == -1 else torch.fft.fft(kernel)
        spectrum = spectrum * (transfer if axis == -1 else transfer[:, None])
    blurred = torch.fft.irfft2(spectrum, s=noise.shape[-2:])
    return blurred[..., pad : pad + height, pad : pad + width]


def _bump(s: Tensor) -> tuple[Tensor, Tensor]:
    """``(1 - s^2)^2`` on ``|s| < 1`` and 0 outside, with its derivative: C1, so stroke edges
    do not crease the normals."""
    inside = s.abs() < 1
    one_minus = torch.where(inside, 1 - s * s, torch.zeros_like(s))
    return one_minus**2, -4 * s * one_minus


def _pigments(config: PaintingConfig) -> tuple[Tensor, Tensor]:
    """Pigment colours ``(P, 3)`` and the patchwork ``k_d (H, W, 3)`` they make."""
    lo, hi = config.kd_range
    g = _generator(config.seed, _PIGMENT_COLOURS)
    # Stratified lightness puts dark and light pigments on every canvas, and a tint around it keeps
    # the colours earthy rather than saturated primaries.
    # CPU on purpose (the next three draws): seeded, they are the same on every device
    strata = torch.randperm(config.pigments, generator=g).to(_F64)[:, None]
    lightness = (strata + torch.rand(config.pigments, 1, generator=g, dtype=_F64)) / config.pigments  # CPU: seeded
    tint = torch.rand(config.pigments, 3, generator=g, dtype=_F64) - 0.5  # CPU: seeded
    colours = lo + (hi - lo) * (lightness + 0.4 * tint).clamp(0.0, 1.0)
    fields = _smooth_field(
        (config.pigments, config.height, config.width), config.pigment_scale, _generator(config.seed, _PIGMENT_FIELDS)
    )
    weights = torch.softmax(config.pigment_sharpness * fields, dim=0)
    return colours, torch.einsum("phw,pc->hwc", weights, colours)


def _weave(config: PaintingConfig, rows: Tensor, cols: Tensor) -> tuple[Tensor, Tensor]:
    """Height gradient ``(d/dcol, d/drow)`` of a plain weave: threads along both image axes
    passing over and under each other, an egg-crate ``sin(k col) sin(k row)``."""
    g = _generator(config.seed, _WEAVE)
    phase = 2 * math.pi * torch.rand(2, generator=g, dtype=_F64)  # CPU on purpose: the seeded draw
    k = 2 * math.pi / config.weave_period
    slope = config.weave_amp * math.tan(math.radians(config.max_tilt_deg))
    a, b = k * cols + phase[0], k * rows + phase[1]
    return slope * torch.cos(a) * torch.sin(b), slope * torch.sin(a) * torch.cos(b)


def _strokes(config: PaintingConfig, kd: Tensor, colours: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The height gradient ``(d/dcol, d/drow)`` of the brush strokes and ``kd (H, W, 3)`` with
    them painted over it: ridges of paint, highest along the middle and tapering at both ends,
    each carrying one of the pigments."""
    g = _generator(config.seed, _STROKES)
    size = (config.height, config.width)
    grad_c = torch.zeros(size, dtype=_F64, device=kd.device)
    grad_r, kd = torch.zeros_like(grad_c), kd.clone()
    tan_max = math.tan(math.radians(config.max_tilt_deg))
    max_profile_slope = 8.0 / (3.0 * math.sqrt(3.0))  # max |d/ds (1 - s^2)^2|, at s = 1/sqrt(3)
    for _ in range(config.strokes):
        draw = torch.rand(8, generator=g, dtype=_F64).tolist()  # CPU on purpose: a seeded draw
        centre_c, centre_r = draw[0] * config.width, draw[1] * config.height
        angle = math.pi * draw[2]
        width = config.stroke_width[0] + (config.stroke_width[1] - config.stroke_width[0]) * draw[3]
        length = config.stroke_length[0] + (config.stroke_length[1] - config.stroke_length[0]) * draw[4]
        # The steepest flank of a stroke is between 30 % and 100 % of the cap.
        height = (0.3 + 0.7 * draw[5]) * tan_max * width / (2.0 * max_profile_slope)
        colour = colours[min(int(draw[6] * config.pigments), config.pigments - 1)]
        # Thin paint lets the layer below show through.
        opacity = 0.3 + 0.7 * draw[7]
        # Only the stroke's bounding square is computed: a large canvas has many small strokes.
        reach = 0.5 * math.hypot(length, width)
        r0, r1 = max(0, math.floor(centre_r - reach)), min(config.height, math.ceil(centre_r + reach) + 1)
        c0, c1 = max(0, math.floor(centre_c - reach)), min(config.width, math.ceil(centre_c + reach) + 1)
        dr = torch.arange(r0, r1, dtype=_F64, device=kd.device)[:, None] - centre_r
        dc = torch.arange(c0, c1, dtype=_F64, device=kd.device)[None, :] - centre_c
        c, s = math.cos(angle), math.sin(angle)
        along, across = (dc * c + dr * s) * (2.0 / length), (dr * c - dc * s) * (2.0 / width)
        # A flat-topped envelope along the stroke: (1 - t^4)^2 = bump(t^2).
        envelope, d_envelope = _bump(along * along)
        d_envelope = d_envelope * 2 * along
        profile, d_profile = _bump(across)
        d_along = height * profile * d_envelope * (2.0 / length)
        d_across = height * d_profile * envelope * (2.0 / width)
        grad_c[r0:r1, c0:c1] += d_along * c - d_across * s
        grad_r[r0:r1, c0:c1] += d_along * s + d_across * c
        cover = opacity * (2.0 * profile * envelope).clamp(max=1.0)[..., None]
        kd[r0:r1, c0:c1] = kd[r0:r1, c0:c1] * (1 - cover) + cover * colour
    return grad_c, grad_r, kd


def _normals(grad_c: Tensor, grad_r: Tensor, max_tilt_deg: float) -> Tensor:
    """Unit normals ``(H, W, 3)`` of a height field with gradient ``(d/dcol, d/drow)``, the
    slope clipped to ``tan(max_tilt_deg)`` keeping its direction."""
    # Surface y runs up the rows: dh/dy = -dh/drow.
    slope = torch.stack([grad_c, -grad_r], dim=-1)
    magnitude = torch.linalg.vector_norm(slope, dim=-1, keepdim=True)
    cap = math.tan(math.radians(max_tilt_deg))
    slope = slope * torch.where(magnitude > cap, cap / magnitude.clamp(min=1e-300), torch.ones_like(magnitude))
    v = torch.cat([-slope, torch.ones_like(magnitude)], dim=-1)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _gilded_mask(box: tuple[float, float, float, float], rows: Tensor, cols: Tensor, size: tuple[int, int]) -> Tensor:
    height, width = size
    x, y = (cols + 0.5) / width, (rows + 0.5) / height
    return (x >= box[0]) & (x < box[2]) & (y >= box[1]) & (y < box[3])


def _gilded_normals(config: PaintingConfig, gilded: GildedConfig) -> Tensor:
    """Normals ``(H, W, 3)`` of the gold leaf: one overall lean plus gentle undulations."""
    g = _generator(config.seed, _GILDED)
    tan_max = math.tan(math.radians(gilded.max_tilt_deg))
    lean, azimuth = torch.rand(2, generator=g, dtype=_F64).tolist()  # CPU on purpose: a seeded draw
    waves = 0.3 * tan_max * _smooth_field((2, config.height, config.width), config.pigment_scale, g)
    grad_c = waves[0] - 0.7 * tan_max * lean * math.cos(2 * math.pi * azimuth)
    grad_r = waves[1] + 0.7 * tan_max * lean * math.sin(2 * math.pi * azimuth)
    return _normals(grad_c, grad_r, gilded.max_tilt_deg)


def _varnish(config: PaintingConfig, eligible: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The varnished mask ``(H, W)`` (the top ``varnish_fraction`` of a smooth field among the
    ``eligible`` pixels) and smooth ``k_s``, ``alpha`` fields ``(H, W)`` inside their ranges."""
    g = _generator(config.seed, _VARNISH)
    blob, ks_field, alpha_field = _smooth_field((3, config.height, config.width), config.varnish_scale, g)
    count = round(config.varnish_fraction * int(eligible.sum()))
    order = torch.argsort(torch.where(eligible, blob, torch.full_like(blob, -math.inf)).flatten(), descending=True)
    mask = torch.zeros(blob.numel(), dtype=torch.bool, device=blob.device)
    mask[order[:count]] = True
    # The normal CDF maps a unit Gaussian field to an evenly spread one in (0, 1).
    ks_lo, ks_hi = config.ks_range
    ks = ks_lo + (ks_hi - ks_lo) * torch.special.ndtr(ks_field)
    # Roughness spreads evenly in log: 0.03 and 0.06 differ as much as 0.1 and 0.2 do.
    a_lo, a_hi = config.alpha_range
    alpha = a_lo * (a_hi / a_lo) ** torch.special.ndtr(alpha_field)
    return mask.view(config.height, config.width), ks, alpha


def painting(
    config: PaintingConfig, *, dtype: torch.dtype, device: torch.device | str | None = None
) -> tuple[SVBRDF, Tensor]:
    """A procedural painting's SVBRDF maps and region map.

    Layers, each from its own random stream of ``config.seed``: pigment patches (a sharpened
    softmax over ``pigments`` smooth fields) give ``k_d``; brush strokes add ridges of one
    pigment each; the canvas weave and the strokes make a height field whose gradient, capped at
    ``max_tilt_deg``, gives the normals; smooth blobs of varnish cover ``varnish_fraction`` of the
    non-gilded area with a grey isotropic lobe; the dual box (if any) gives two grey lobes inside
    it; the gilded box replaces everything inside it.

    Args:
        config: the settings.
        dtype: the floating dtype of the maps.
        device: the device of the maps (the CPU by default).

    Returns:
        ``(svbrdf, regions)``: maps with leading dims ``(H, W)`` (normal ``(H, W, 3)``, diffuse
        and specular ``(H, W, 3)``, roughness ``(H, W, 2)``, no rotation) and an int64
        ``(H, W)`` map of :data:`MATTE` (``k_s = 0``, roughness 0), :data:`VARNISHED`,
        :data:`GILDED` and :data:`DUAL` pixels. With ``config.dual`` the maps have a second lobe
        (``specular2 (H, W, 1)``, ``roughness2 (H, W, 2)``, 0 outside the dual box).

    Raises:
        ConfigError: a setting is out of its domain (the message names it).

    Example:
        >>> svbrdf, regions = painting(PaintingConfig(width=32, height=24), dtype=torch.float32)
        >>> tuple(svbrdf.normal.shape), regions.dtype
        ((24, 32, 3), torch.int64)
    """
    _check_painting(config)
    size = (config.height, config.width)
    # The maps are built in float64 where the seeded fields are drawn, and cast to dtype and device
    # at the end: CPU on purpose, so that a seed gives the same maps on every device.
    rows = torch.arange(config.height, dtype=_F64)[:, None].expand(size)
    cols = torch.arange(config.width, dtype=_F64)[None, :].expand(size)  # CPU on purpose: as rows

    colours, kd = _pigments(config)
    weave_c, weave_r = _weave(config, rows, cols)
    stroke_c, stroke_r, kd = _strokes(config, kd, colours)
    normal = _normals(weave_c + stroke_c, weave_r + stroke_r, config.max_tilt_deg)

    gilded = config.gilded
    box = (
        _gilded_mask(gilded.box, rows, cols, size)
        if gilded is not None
        else torch.zeros(size, dtype=torch.bool, device=rows.device)
    )
    varnished, ks_grey, alpha_iso = _varnish(config, ~box)
    regions = torch.full(size, MATTE, dtype=torch.int64, device=rows.device)
    regions[varnished] = VARNISHED
    ks = torch.where(varnished, ks_grey, 0.0)[..., None].expand(*size, 3).clone()
    roughness = torch.where(varnished, alpha_iso, 0.0)[..., None].expand(*size, 2).clone()
    second = {}
    if config.dual is not None:
        dual = _gilded_mask(config.dual.box, rows, cols, size) & ~box
        regions[dual] = DUAL
        ks = torch.where(dual[..., None], config.dual.ks, ks)
        roughness = torch.where(dual[..., None], config.dual.alpha, roughness)
        second = {
            "specular2": torch.where(dual, config.dual.ks2, 0.0)[..., None],
            "roughness2": torch.where(dual, config.dual.alpha2, 0.0)[..., None].expand(*size, 2),
        }
    if gilded is not None:
        regions[box] = GILDED
        inside = box[..., None]
        normal = torch.where(inside, _gilded_normals(config, gilded), normal)
        kd = torch.where(inside, torch.tensor(gilded.kd, dtype=_F64, device=kd.device), kd)
        ks = torch.where(inside, torch.tensor(gilded.ks, dtype=_F64, device=ks.device), ks)
        roughness = torch.where(inside, torch.tensor(gilded.alpha, dtype=_F64, device=roughness.device), roughness)

    def cast(t: Tensor) -> Tensor:
        return t.to(device=device, dtype=dtype)

    svbrdf = SVBRDF(
        normal=cast(normal),
        diffuse=cast(kd),
        specular=cast(ks),
        roughness=cast(roughness),
        **{name: cast(value) for name, value in second.items()},
    )
    return svbrdf, regions.to(device=device)


def mirror(
    config: MirrorConfig, *, dtype: torch.dtype, device: torch.device | str | None = None
) -> tuple[SVBRDF, Tensor]:
    """A uniform near-mirror whose normal leans ``tilt_deg`` towards ``tilt_azimuth_deg``.

    Args:
        config: the settings.
        dtype: the floating dtype of the maps.
        device: the device of the maps (the CPU by default).

    Returns:
        ``(svbrdf, regions)``: constant maps with leading dims ``(H, W)`` (diffuse ``(H, W, C)``,
        specular ``(H, W, C)`` or ``(H, W, 1)``) and an int64 ``(H, W)`` map, all
        :data:`VARNISHED` (1: a single isotropic or anisotropic lobe, no gilding).

    Raises:
        ConfigError: a setting is out of its domain (the message names it).

    Example:
        >>> svbrdf, _ = mirror(MirrorConfig(), dtype=torch.float64)
        >>> round(math.degrees(math.acos(float(svbrdf.normal[0, 0, 2]))), 6)
        3.0
    """
    _require(_size_checks(config) + [
        (len(config.kd) >= 1 and len(config.ks) in (1, len(config.kd)),
         f"ks must have 1 value or one per kd channel ({len(config.kd)}); got {config.ks!r}."),
        (len(config.alpha) == 2 and min(config.alpha) > 0, f"alpha must be 2 values > 0; got {config.alpha!r}."),
        (0 <= config.tilt_deg < 90, f"tilt_deg must be in [0, 90); got {config.tilt_deg!r}."),
    ])
    tilt, azimuth = math.radians(config.tilt_deg), math.radians(config.tilt_azimuth_deg)
    normal = (math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt))
    size = (config.height, config.width)

    def constant(values: tuple[float, ...]) -> Tensor:
        return torch.tensor(values, dtype=_F64, device=device).expand(*size, len(values)).to(dtype=dtype).contiguous()

    svbrdf = SVBRDF(
        normal=constant(normal),
        diffuse=constant(config.kd),
        specular=constant(config.ks),
        roughness=constant(config.alpha),
    )
    return svbrdf, torch.full(size, VARNISHED, dtype=torch.int64, device=device)


def sense(
    values: Tensor, config: SensorConfig, *, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """What a linear HDR camera records of ``values``: exposure, shot noise, read noise, clipping.

    The exposed value ``v = exposure * values`` collects ``Poisson(v * photons_per_unit)``
    photons (Gaussian above 1000 expected photons; negative ``v`` pass without shot noise),
    read back as ``photons / photons_per_unit``; Gaussian read noise of std ``read_noise`` is
    added and not clipped at 0 (an HDR merge gives slightly negative values in the dark); values
    at or above ``saturation`` are clipped to it and flagged, since a reading at the clip level
    cannot be told from one above it.

    Args:
        values: ``(*)`` radiance, any floating dtype and device.
        config: the sensor settings.
        generator: the source of the noise, on any device; by default a CPU generator seeded
            with ``config.seed``, which gives the same noise on every device and dtype.

    Returns:
        ``(recorded, saturated)``: ``(*)`` values in the dtype and on the device of ``values``,
        and a ``(*)`` bool mask of the clipped ones.

    Raises:
        ConfigError: a setting is negative.

    Example:
        >>> recorded, saturated = sense(torch.tensor([0.5, 3.0]), SensorConfig(exposure=2.0, saturation=4.0))
        >>> recorded.tolist(), saturated.tolist()
        ([1.0, 4.0], [False, True])
    """
    _require([
        (getattr(config, name) >= 0, f"SensorConfig.{name} must be >= 0; got {getattr(config, name)!r}.")
        for name in ("exposure", "photons_per_unit", "read_noise", "saturation")
    ])
    if generator is None:
        generator = torch.Generator().manual_seed(config.seed)
    # Noise is drawn in float64 where the generator lives, so it does not depend on the dtype of
    # the values and, with the default generator, not on their device either.
    noise_device = generator.device

    def draw_normal() -> Tensor:
        z = torch.randn(values.shape, generator=generator, dtype=_F64, device=noise_device)
        return z.to(device=values.device, dtype=values.dtype)

    exposed = values * config.exposure
    if config.photons_per_unit > 0:
        ppu = config.photons_per_unit
        mean = (exposed.detach().to(device=noise_device, dtype=_F64).clamp(min=0.0)) * ppu
        small = mean <= _POISSON_LIMIT
        photons = torch.poisson(torch.where(small, mean, 0.0), generator=generator)
        gaussian = mean + mean.sqrt() * torch.randn(mean.shape, generator=generator, dtype=_F64, device=noise_device)
        shot = (torch.where(small, photons, gaussian) - mean) / ppu
        exposed = exposed + shot.to(device=values.device, dtype=values.dtype)
    if config.read_noise > 0:
        exposed = exposed + config.read_noise * draw_normal()
    saturated = exposed >= config.saturation
    return exposed.clamp(max=config.saturation), saturated
