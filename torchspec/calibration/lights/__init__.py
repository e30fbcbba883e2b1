"""Light calibration: each frame's gain and, for a dome, each light's position, from the
photographs themselves.

A capture's light file gives one direction per frame; it knows neither the intensity of each
flash (which differs from frame to frame, and between colour channels) nor, in a dome, how near
the lights are (the direction to a near light and its irradiance vary across the image). This
stage estimates both jointly with Lambertian maps, on the pixels the Lambertian model explains
well.

Model. Frame ``k``, channel ``c``, pixel ``x``: ``I = g_kc s_k(x) <b_c(x), d_k(x)>`` where
``b_c = albedo_c * normal`` (per pixel and channel), ``g_kc`` the gain and, for a distant light,
``d_k`` the given direction and ``s_k = 1``; for a near light at ``p_k``,
:func:`torchspec.model.near_lights.near_light` gives ``d_k(x)`` and the falloff ``s_k(x)``.

Geometry (:mod:`torchspec.model.near_lights`, shared with the fit; points from
:func:`torchspec.model.near_lights.image_points`): the
object plane is ``z = 0``, the origin at the image centre, ``x`` right, ``y`` up, ``z`` towards
the camera; the unit is the image width. Pixel (row ``i``, column ``j``) of an ``H x W`` image
lies at ``x = (j + 0.5) / W - 0.5``, ``y = (H / 2 - (i + 0.5)) / W``. A near light at ``p_k``
gives the point ``x_p`` the direction ``(p_k - x_p) / |p_k - x_p|`` and the irradiance
``g_k (|p_k| / |p_k - x_p|)^2``: the gain is the irradiance at the image centre.

Method. Alternate (a) per-pixel photometric stereo, batched least squares with robust weights:
samples in attached shadow (``cos <= shadow``), invalid (saturated) samples, and samples whose
residual exceeds ``cut`` times the pixel's robust scale (1.4826 MAD: highlights, cast shadows) get
weight 0; a pixel is *explained* when its relative RMS on its inliers is within ``explain`` times
the median pixel's and most of its lit samples are inliers; and (b) a damped Gauss-Newton step on
the lights' parameters (``C`` gains and, when ``near``, 3 coordinates per light) by variable
projection: the maps are eliminated per pixel, so the step accounts for what the maps absorb;
a step is taken only when it lowers the sum of squares (Levenberg-Marquardt).

What is determined. Each channel's gains only up to one factor (the albedo takes the rest): they
are normalised to a geometric mean of 1. With distant lights the directions are not estimated
(with free normals, a rotation of all lights is a rotation of all normals). With near lights a
common rotation of all positions about the image centre is nearly invisible in the pixels (only
the object's extent breaks it): it is held at the input directions (each step has no component
along the three rotations), and the standard errors are of the rotation-free part. A light's
distance is determined by the falloff and the change of direction across the image, i.e. by
``width / distance``: far lights get large standard errors. The standard errors assume
independent residuals on the explained pixels, with the maps known: they are lower bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...model.near_lights import image_points
from ._solve import (
    SOLVE_CHUNK,
    LightCalibrationError,
    _Design,
    _explained_pass,
    _frame_sums,
    _gather,
    _lighting,
    _median_misfit,
    _normalised,
    _sample,
    _update,
)

__all__ = [
    "DomeRadius",
    "LightCalibration",
    "LightCalibrationError",
    "LambertFit",
    "PixelSample",
    "calibrate_lights",
    "lambert_fit",
    "dome_radius",
    "DOME_MARGIN",
]

RADII = (1.0, 1.5, 2.0, 3.0, 4.5, 7.0, 12.0, 25.0)
"""Dome radii (image widths) tried for the starting point of near lights when no radius is given."""
RADIUS_SAMPLE = 2048
"""Pixels of the sample (a fixed random subset) the start is made from: a dome radius (a median
misfit per candidate radius) and the first gains (medians of ratios); the alternation then uses the
whole sample. On the six captures of ``../shared/data/rti`` at half size, 2048 pixels made the same
choices as 4096 (radius as written and refitted, acceptance), but for realrti-item7's refitted
radius (7 widths instead of 4.5, whose median misfits differ by 0.1 % of their value: 0.0308 and
0.0308 against 0.0310 and 0.0308; its gains are refused either way), and 4096 the same as 16384 on
the four compared. Each halving halves the search's time."""
DOME_MARGIN = 0.1
"""``dome`` takes near lights only where they lower the median pixel misfit by this fraction of
the distant lights' (:func:`dome_radius`)."""


@dataclass(frozen=True)
class LightCalibration:
    """The calibrated lights of ``K`` frames and ``C`` channels.

    Attributes:
        gains: ``(K, C)`` irradiance at the image centre, each channel's gains of geometric mean 1.
        gain_std: ``(K, C)`` standard errors of ``gains``.
        positions: ``(K, 3)`` light positions (image widths, the module's frame), ``None`` for distant lights.
        position_std: ``(K, 3)`` standard errors of ``positions`` (rotation held), or ``None``.
        directions: ``(K, 3)`` unit directions at the image centre.
        explained: ``(H, W)`` bool: the pixels the Lambertian model explains well (those used).
        rms: ``(K,)`` relative RMS misfit per frame, ``sqrt(sum r^2 / sum I^2)`` over the lit, valid
            samples of the explained pixels (highlights included).
        iterations: the iterations run.
        radius: ``dome``'s radius (image widths), else ``None`` (also for distant lights);
            ``radius_misfit``: ``dome``'s median pixel misfit of ``"distant"`` and each of :data:`RADII`;
            ``radius_as_written``, ``radius_misfit_as_written``: the same under the gains as
            written (all 1), for a caller that refuses the gains (``None`` without ``dome``).
        judged: ``(H, W)`` bool, the pixels ``explained`` and ``rms`` judge: every pixel, or, where
            ``give_up`` stopped the calibration, the sample's only (the pass over every pixel is
            skipped for lights its caller refuses; ``explained`` is False outside them).
    """

    gains: Tensor
    gain_std: Tensor
    positions: Tensor | None
    position_std: Tensor | None
    directions: Tensor
    explained: Tensor
    rms: Tensor
    iterations: int
    radius: float | None = None
    radius_misfit: dict | None = None
    radius_as_written: float | None = None
    radius_misfit_as_written: dict | None = None
    judged: Tensor | None = None


@dataclass(frozen=True)
class LambertFit:
    """Lambertian maps of an image under given lights (:func:`lambert_fit`).

    Attributes:
        normal: ``(H, W, 3)`` unit normals (of the channels' ``b`` summed).
        albedo: ``(C, H, W)`` ``|b_c|``: the albedo over pi, times the lights' common scale.
        explained: ``(H, W)`` bool, as :attr:`LightCalibration.explained`.
        rms: ``(K,)`` as :attr:`LightCalibration.rms`, on ``explained`` (or the given ``pixels``).
    """

    normal: Tensor
    albedo: Tensor
    explained: Tensor
    rms: Tensor


@dataclass(frozen=True)
class PixelSample:
    """Pixels the lights are estimated from (:func:`calibrate_lights`'s ``sample``), ``n`` of them.

    Attributes:
        values: ``(n, K, C)`` the pixels' values in the working dtype (0 where not ``ok``).
        ok: ``(n, K, C)`` bool, the usable samples.
        points: ``(n, 3)`` the pixels' points on the object plane (the module's geometry).
        index: ``(n,)`` the pixels' flat indices in the image.
    """

    values: Tensor
    ok: Tensor
    points: Tensor
    index: Tensor

    def at(self, rows: Tensor) -> PixelSample:
        """The pixels ``rows`` of the sample (an index into its ``n``)."""
        return PixelSample(self.values[rows], self.ok[rows], self.points[rows], self.index[rows])


@dataclass(frozen=True)
class _Steps:
    """How :func:`calibrate_lights`'s alternation (:func:`_alternate`) starts and runs.

    Attributes:
        positions: ``(K, 3)`` the lights' starting positions, or ``None`` (distant lights).
        gains: ``(K, C)`` the starting gains.
        options: ``shadow``, ``cut`` and ``explain`` of :func:`_explained_pass`.
        near, iterations, damping, tolerance, give_up: :func:`calibrate_lights`'s.
    """

    positions: Tensor | None
    gains: Tensor
    options: dict[str, float]
    near: bool
    iterations: int
    damping: float
    tolerance: float
    give_up: float | tuple[float, float] | None


@dataclass(frozen=True)
class _Alternation:
    """The outcome of :func:`_alternate`.

    Attributes:
        gains: ``(K, C)`` the lights' gains.
        positions: ``(K, 3)`` their positions, or ``None`` (distant lights).
        covariance: ``(K P, K P)`` of the lights' parameters (:func:`_deviations`), ``None`` before a step.
        level: the explained pixels' bound on the relative RMS of the last pass (``None`` without one).
        iterations: the iterations run (steps taken).
        stopped: whether ``give_up`` stopped it.
        sample: the pixels it ran on (the calibration is judged on them where it ``stopped``).
    """

    gains: Tensor
    positions: Tensor | None
    covariance: Tensor | None
    level: Tensor | None
    iterations: int
    stopped: bool
    sample: PixelSample


def _check(frames: Tensor, directions: Tensor, valid: Tensor | None) -> None:
    if frames.dim() != 4:
        raise LightCalibrationError(f"frames must have shape (K, C, H, W); got {tuple(frames.shape)}.")
    k = frames.shape[0]
    if k < 4:
        raise LightCalibrationError(f"calibrating lights needs at least 4 frames; got {k}.")
    if tuple(directions.shape) != (k, 3):
        raise LightCalibrationError(
            f"directions must have shape ({k}, 3) for {k} frames; got {tuple(directions.shape)}."
        )
    if bool((directions[:, 2] <= 0).any()):
        bad = int(torch.nonzero(directions[:, 2] <= 0)[0, 0])
        raise LightCalibrationError(f"directions must lie above the object (z > 0); frame {bad} does not.")
    if valid is not None and tuple(valid.shape) != tuple(frames.shape):
        raise LightCalibrationError(
            f"valid must have the frames' shape {tuple(frames.shape)}; got {tuple(valid.shape)}."
        )


@dataclass(frozen=True)
class _RatioGains:
    """The outcome of :func:`_ratio_gains`.

    Attributes:
        gains: ``(K, C)`` the gains of the last round.
        level: the median pixel relative RMS of the last round (0-dim; ``inf`` without a round).
        first: the same of the first round: under the gains given.
    """

    gains: Tensor
    level: Tensor
    first: Tensor


@dataclass(frozen=True)
class DomeRadius:
    """:func:`dome_radius`'s choice under one set of gains.

    Attributes:
        radius: the radius of :data:`RADII` (image widths) chosen, or ``None`` (distant lights, or
            no radius tried).
        misfit: the median pixel misfit of ``"distant"`` and of each of :data:`RADII` (keyed by
            ``str(radius)``), or ``None`` (none tried).
    """

    radius: float | None
    misfit: dict[str, float] | None

    @classmethod
    def least(cls, misfit: dict[str, float]) -> DomeRadius:
        """The radius of least ``misfit``, or ``None`` unless that misfit is below
        ``1 - DOME_MARGIN`` of the distant lights'."""
        best = min(RADII, key=lambda r: misfit[str(r)])
        return cls(best if misfit[str(best)] < (1 - DOME_MARGIN) * misfit["distant"] else None, misfit)


def _ratio_gains(sample: PixelSample, directions, positions, gains, options, rounds: int) -> _RatioGains:
    """Gains from the median over explained pixels of each frame's ``value / prediction`` (robust to
    a frame's gain being far off, which a per-pixel cut would take for an outlier in every pixel),
    repeated ``rounds`` times or until they change by less than 1e-4, on the ``sample``'s pixels."""
    values, ok, points = sample.values, sample.ok, sample.points
    rms_level = first = values.new_tensor(math.inf)
    for round_ in range(rounds):
        found = _explained_pass(values, ok, points, directions, positions, gains, **options, shift=True)
        sel = found.explained
        rms_level = found.rms[sel].median()
        first = rms_level if round_ == 0 else first
        pred = _Design.of(_lighting(points[sel], directions, positions)[1], gains).predict(found.b[sel])
        use = found.lit[sel] & (pred > 0.1 * pred.amax(1, keepdim=True))
        ratio = torch.where(use, values[sel] / pred.clamp_min(1e-300), torch.nan).nanmedian(0).values
        ratio = _normalised(ratio.nan_to_num(1.0))
        gains = _normalised(gains * ratio)
        if float((ratio - 1).abs().max()) < 1e-4:
            break
    return _RatioGains(gains=gains, level=rms_level, first=first)


def _dome_misfit(sample: PixelSample, directions, radius, gains, options) -> _RatioGains:
    """:func:`_ratio_gains` (3 rounds) of lights at ``radius`` along ``directions`` (``None``:
    distant): its ``level`` the median pixel misfit with the gains refitted, its ``first`` under
    the gains given."""
    positions = None if radius is None else radius * directions
    return _ratio_gains(sample, directions, positions, gains, options, 3)


def dome_radius(sample: PixelSample, directions, gains, options) -> tuple[DomeRadius, DomeRadius]:
    """The dome radius of :data:`RADII` (all lights at it along their ``directions``) whose median
    pixel misfit (:func:`_dome_misfit`) on the ``sample`` is the least, or ``None`` (distant lights)
    unless that misfit is below ``1 - DOME_MARGIN`` of the distant lights' (:meth:`DomeRadius.least`):
    ``(with the gains refitted, under the gains given)``, from one pass."""
    tried = [_dome_misfit(sample, directions, r, gains, options) for r in (None, *RADII)]
    refitted, given = ({"distant": float(getattr(tried[0], way))} for way in ("level", "first"))
    for r, found in zip(RADII, tried[1:], strict=True):
        refitted[str(r)], given[str(r)] = float(found.level), float(found.first)
    return DomeRadius.least(refitted), DomeRadius.least(given)


def calibrate_lights(
    frames: Tensor,
    directions: Tensor,
    *,
    valid: Tensor | None = None,
    near: bool = False,
    dome: bool = False,
    iterations: int = 10,
    radius: float | None = None,
    sample: int = 16384,
    shadow: float = 0.1,
    cut: float = 3.0,
    explain: float = 2.5,
    damping: float = 1e-8,
    tolerance: float = 1e-5,
    give_up: float | tuple[float, float] | None = None,
) -> LightCalibration:
    """Calibrate the lights of a capture from its photographs (the module's model and method).

    Args:
        frames: ``(K, C, H, W)`` linear values, the exposure divided out; ``K >= 4``.
        directions: ``(K, 3)`` unit directions towards the lights (the light file's; for a near
            light, the direction at the image centre): the starting point, and the gauge.
        valid: ``(K, C, H, W)`` bool, the usable samples (e.g. not saturated); non-finite values
            are never used.
        near: estimate each light's position (a dome) besides its gains.
        dome: one radius for every light instead (:func:`dome_radius`: the lights at that distance
            along ``directions``, or distant where no radius explains the photographs better by
            :data:`DOME_MARGIN`; on :data:`RADIUS_SAMPLE` pixels of the sample), held while the
            gains are estimated; ignored with ``near``.
        iterations: alternations of maps and lights at most (stops earlier when the largest
            relative change of a parameter is below ``tolerance``).
        radius: the starting dome radius for ``near`` (image widths); ``None`` tries :data:`RADII`.
        sample: pixels (a fixed random subset) the lights are estimated from; all pixels get
            ``explained`` and enter ``rms``.
        shadow: samples with ``cos(normal, light) <= shadow`` are left out (attached shadows).
        cut: samples whose residual exceeds ``cut`` robust standard deviations of their pixel
            are left out (highlights, cast shadows).
        explain: a pixel is explained when its relative RMS is within ``explain`` times the median.
        damping: Levenberg-Marquardt damping of each step (relative to the diagonal).
        give_up: stop after two steps when the sample's median per-frame misfit (as ``rms``) then
            exceeds it (``iterations`` 2; ``explained``, ``rms`` of the sample only: ``judged``): a
            caller that refuses lights above a misfit need not pay for their refinement (two steps
            leave it within 1.1x of the converged one on a simulation: tests/test_lightcal.py); a
            pair ``(start, two steps)``: also before the first step, above ``start`` under the
            start's gains (``iterations`` 0, ``gain_std`` NaN)); first on the start's pixels.

    Returns:
        :class:`LightCalibration` in the dtype and on the device of ``frames``.

    Raises:
        LightCalibrationError: bad shapes, fewer than 4 frames, lights below the object, no
            explained pixel.
    """
    _check(frames, directions, valid)
    k, c, height, width = frames.shape
    work = torch.float64
    device = frames.device
    dirs = directions.to(device=device, dtype=work)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    index = _sample(height * width, sample, device)
    values, ok = _gather(frames, valid, index, work)
    points = image_points(height, width, dtype=work, device=device)[index]
    options = {"shadow": shadow, "cut": cut, "explain": explain}
    gains = torch.ones(k, c, dtype=work, device=device)
    positions, chosen, written = None, DomeRadius(None, None), DomeRadius(None, None)  # no dome radius tried
    whole = PixelSample(values, ok, points, index)
    few = _sample(values.shape[0], RADIUS_SAMPLE, device)  # the start's pixels
    start = whole.at(few)
    if near:
        if radius is None:  # the start: the radius of RADII whose lights leave the least misfit
            radius = min(RADII, key=lambda r: float(_dome_misfit(start, dirs, r, gains, options).level))
        positions = radius * dirs
    elif dome:
        chosen, written = dome_radius(start, dirs, gains, options)
        positions = None if chosen.radius is None else chosen.radius * dirs
    gains = _ratio_gains(start, dirs, positions, gains, options, 8).gains
    steps = _Steps(positions=positions, gains=gains, options=options, near=near, iterations=iterations,
                   damping=damping, tolerance=tolerance, give_up=give_up)  # fmt: skip
    found = _alternate_sample(whole, few, dirs, steps)
    gains, positions = found.gains, found.positions
    std = _deviations(found.covariance, gains, c + 3 if near else c)
    final = _final_pass(frames, valid, dirs, found, options)
    out = {"dtype": frames.dtype, "device": device}
    centre = dirs if positions is None else positions / positions.norm(dim=-1, keepdim=True)
    return LightCalibration(
        gains=gains.to(**out),
        gain_std=std[:, :c].to(**out),
        positions=None if positions is None else positions.to(**out),
        position_std=None if positions is None or not near else std[:, c:].to(**out),
        directions=centre.to(**out),
        explained=final.explained,
        rms=final.rms.to(**out),
        iterations=found.iterations,
        radius=chosen.radius,
        radius_misfit=chosen.misfit,
        radius_as_written=written.radius,
        radius_misfit_as_written=written.misfit,
        judged=_judged(found.sample.index if found.stopped else None, height, width, device),
    )


def _deviations(covariance: Tensor | None, gains: Tensor, p: int) -> Tensor:
    """``(K, p)`` standard errors of the lights' parameters from ``covariance``; NaN without one
    (no step taken)."""
    if covariance is None:
        return gains.new_full((gains.shape[0], p), math.nan)
    return covariance.diagonal().clamp_min(0).sqrt().reshape(gains.shape[0], -1)


def _judged(index: Tensor | None, height: int, width: int, device) -> Tensor:
    """``(H, W)`` bool: the flat pixels ``index``, or every pixel (``None``)."""
    if index is None:
        return torch.ones((height, width), dtype=torch.bool, device=device)
    return (
        torch.zeros(height * width, dtype=torch.bool, device=device).index_fill_(0, index, True).reshape(height, width)
    )


def _alternate_sample(sample: PixelSample, few: Tensor, dirs: Tensor, steps: _Steps) -> _Alternation:
    """:func:`_alternate` on the sample: with a give-up and a ``sample`` larger than the start's
    pixels ``few`` (:data:`RADIUS_SAMPLE`), its tests on those first; where they stop the
    calibration, the outcome on ``few`` (judged on them); else (or without a give-up) the alternation
    on the whole sample, as if that trial had not been made."""
    if steps.give_up is not None and few.shape[0] < sample.values.shape[0]:
        found = _alternate(sample.at(few), dirs, steps, trial=True)
        if found.stopped:  # stopped there: the calibration is judged on those pixels
            return found
    return _alternate(sample, dirs, steps)


def _alternate(sample: PixelSample, dirs: Tensor, steps: _Steps, trial: bool = False) -> _Alternation:
    """:func:`calibrate_lights`'s alternation of maps and lights on the ``sample``; ``trial``: only
    up to give_up's last test (what is returned is then of use only where it stopped)."""
    values, ok, points = sample.values, sample.ok, sample.points
    gains, positions, damping, give_up = steps.gains, steps.positions, steps.damping, steps.give_up
    run, covariance, level, strict, stopped = 0, None, None, False, False  # run: the steps taken
    bounds = dict(zip((1, 3), give_up if isinstance(give_up, tuple) else (None, give_up), strict=True))
    for done in range(1, max(steps.iterations, 1) + 1):
        found = _explained_pass(values, ok, points, dirs, positions, gains, **steps.options, shift=not strict)
        b, sel, level = found.b, found.explained, found.level
        bound = bounds.get(done)
        if (
            bound is not None
            and _median_misfit(values, points, dirs, positions, gains, b, found.lit & sel[:, None, None]) > bound
        ):
            stopped = True
            break
        if trial and done >= max(bounds):
            break
        step = _update(values[sel], found.weight[sel], b[sel], points[sel], dirs, positions, gains, steps.near, damping)
        gains, positions, covariance, damping = step.gains, step.positions, step.covariance, step.damping
        run = done
        if strict and step.change < steps.tolerance:
            break
        # the first half with frame shifts (gains far off), the rest strict (highlights out)
        strict = strict or step.change < 1e-3 or 2 * done >= steps.iterations
    return _Alternation(
        gains=gains, positions=positions, covariance=covariance, level=level, iterations=run, stopped=stopped,
        sample=sample,
    )  # fmt: skip


def _final_pass(frames: Tensor, valid: Tensor | None, dirs: Tensor, found: _Alternation, options) -> LambertFit:
    """The maps, ``explained`` and misfits under the calibrated lights (``found``): every pixel's
    (:func:`_full_pass`), or where give_up ``stopped`` the calibration (refused anyway), the pixels'
    of ``found.sample`` only, 0 and False elsewhere (a pass over every pixel cost realrti-item3 10
    of 24 s)."""
    gains, positions, level = found.gains, found.positions, found.level
    if not found.stopped:
        return _full_pass(frames, valid, dirs, positions, gains, options, level)
    height, width = frames.shape[2:]
    values, points, index = found.sample.values, found.sample.points, found.sample.index
    passed = _explained_pass(values, found.sample.ok, points, dirs, positions, gains, **options, level=level)
    b, explained = passed.b, passed.explained
    pred = _Design.of(_lighting(points, dirs, positions)[1], gains).predict(b)
    residual2, energy = _frame_sums(values, pred, passed.lit & explained[:, None, None])
    every = values.new_zeros((height * width, *b.shape[1:])).index_copy_(0, index, b)
    flat = torch.zeros(height * width, dtype=torch.bool, device=index.device).index_copy_(0, index, explained)
    return _lambert(every, flat, (residual2 / energy.clamp_min(1e-300)).sqrt(), height, width, values.dtype)


def _full_pass(frames, valid, dirs, positions, gains, options, level, pixels=None) -> LambertFit:
    """Maps of every pixel (chunks of :data:`SOLVE_CHUNK`), explained within ``level``, and each
    frame's relative RMS on ``pixels`` (the explained pixels by default)."""
    k, c, height, width = frames.shape
    work = gains.dtype
    rows = []
    residual2 = torch.zeros(k, dtype=work, device=frames.device)
    energy = torch.zeros_like(residual2)
    flat_pixels = None if pixels is None else pixels.reshape(-1).to(frames.device)
    every = image_points(height, width, dtype=work, device=frames.device)
    for s in range(0, height * width, SOLVE_CHUNK):
        index = torch.arange(s, min(s + SOLVE_CHUNK, height * width), device=frames.device)
        values, ok = _gather(frames, valid, index, work)
        points = every[index]
        found = _explained_pass(values, ok, points, dirs, positions, gains, **options, level=level)
        use = found.explained if flat_pixels is None else flat_pixels[index]
        pred = _Design.of(_lighting(points, dirs, positions)[1], gains).predict(found.b)
        sums = _frame_sums(values, pred, found.lit & use[:, None, None])
        residual2, energy = residual2 + sums[0], energy + sums[1]
        rows.append((found.b, found.explained))
    b, explained = (torch.cat(t) for t in zip(*rows, strict=True))
    return _lambert(b, explained, (residual2 / energy.clamp_min(1e-300)).sqrt(), height, width, frames.dtype)


def _lambert(b: Tensor, explained: Tensor, rms: Tensor, height: int, width: int, dtype) -> LambertFit:
    """The :class:`LambertFit` of every pixel's solution ``b (H W, C, 3)`` (0: no normal, no albedo),
    ``explained (H W,)`` and the frames' ``rms``; maps in ``dtype``."""
    total = b.sum(1)
    normal = total / total.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    return LambertFit(
        normal=normal.reshape(height, width, 3).to(dtype),
        albedo=b.norm(dim=-1).T.reshape(b.shape[1], height, width).to(dtype),
        explained=explained.reshape(height, width),
        rms=rms,
    )


def lambert_fit(
    frames: Tensor,
    directions: Tensor,
    *,
    gains: Tensor | None = None,
    positions: Tensor | None = None,
    valid: Tensor | None = None,
    pixels: Tensor | None = None,
    sample: int = 16384,
    shadow: float = 0.1,
    cut: float = 3.0,
    explain: float = 2.5,
) -> LambertFit:
    """Robust Lambertian maps of ``frames (K, C, H, W)`` under given lights: ``directions (K, 3)``
    (distant), or near lights at ``positions (K, 3)`` (the module's geometry), with ``gains (K, C)``
    (1 by default); the same photometric stereo :func:`calibrate_lights` alternates with.
    ``pixels (H, W)`` bool: the pixels whose misfit ``rms`` reports (the explained ones by default),
    e.g. to compare two sets of lights on the same pixels."""
    _check(frames, directions, valid)
    k, c, height, width = frames.shape
    work, device = torch.float64, frames.device
    dirs = directions.to(device=device, dtype=work)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    gains = torch.ones(k, c, dtype=work, device=device) if gains is None else gains.to(device=device, dtype=work)
    if tuple(gains.shape) != (k, c):
        raise LightCalibrationError(f"gains must have shape ({k}, {c}); got {tuple(gains.shape)}.")
    if positions is not None:
        if tuple(positions.shape) != (k, 3):
            raise LightCalibrationError(f"positions must have shape ({k}, 3); got {tuple(positions.shape)}.")
        positions = positions.to(device=device, dtype=work)
    if pixels is not None and tuple(pixels.shape) != (height, width):
        raise LightCalibrationError(f"pixels must have shape ({height}, {width}); got {tuple(pixels.shape)}.")
    options = {"shadow": shadow, "cut": cut, "explain": explain}
    index = _sample(height * width, sample, device)
    values, ok = _gather(frames, valid, index, work)
    points = image_points(height, width, dtype=work, device=device)[index]
    level = _explained_pass(values, ok, points, dirs, positions, gains, **options).level
    return _full_pass(frames, valid, dirs, positions, gains, options, level, pixels)
