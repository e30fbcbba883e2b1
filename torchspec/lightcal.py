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
:func:`torchspec.near_lights.near_light` gives ``d_k(x)`` and the falloff ``s_k(x)``.

Geometry (:mod:`torchspec.near_lights`, shared with the fit; points from
:func:`torchspec.near_lights.image_points`): the
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

from .errors import TorchspecError
from .near_lights import image_points, near_light
from .photometric import MAD_SCALE

__all__ = [
    "LightCalibration",
    "LightCalibrationError",
    "LambertFit",
    "calibrate_lights",
    "lambert_fit",
    "dome_radius",
    "DOME_MARGIN",
]

CHUNK = 512
"""Pixels a variable-projection step handles at once (its Jacobian is ``(chunk, C, K, P, 3)``)."""
SOLVE_CHUNK = 8192
"""Pixels a photometric-stereo pass handles at once."""
RADII = (1.0, 1.5, 2.0, 3.0, 4.5, 7.0, 12.0, 25.0)
"""Dome radii (image widths) tried for the starting point of near lights when no radius is given."""
DOME_MARGIN = 0.1
"""``dome`` takes near lights only where they lower the median pixel misfit by this fraction of
the distant lights' (:func:`dome_radius`)."""
DARK = 0.05
"""Before the first solve, samples below this fraction of the pixel's median are shadows."""
RIDGE = 1e-30
"""The least ridge of a pixel's normal equations (one with no inlier then solves to 0, unexplained)."""
MIN_SAMPLES = 20
"""A frame's gain in a channel is estimated from at least this many inlier samples (else kept)."""
FLOOR = 1e-3
"""The robust scale is at least this fraction of the pixel's RMS value (a noise-free capture)."""


class LightCalibrationError(TorchspecError):
    """Input :func:`calibrate_lights` cannot calibrate from (shapes, frame count, no explained pixel)."""


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
            ``radius_misfit``: ``dome``'s median pixel misfit of ``"distant"`` and each of :data:`RADII`.
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


def _lighting(points: Tensor, directions: Tensor, positions: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(unit (n, K, 3), vector (n, K, 3))``: each sample's light direction, and it times the falloff."""
    if positions is None:
        unit = directions[None].expand(points.shape[0], -1, -1)
        return unit, unit
    unit, falloff = near_light(positions, points)
    return unit, unit * falloff[..., None]


def _solve(a: Tensor, y: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Per pixel and channel weighted least squares ``b (n, C, 3)`` of ``y ~ a b`` and ``a^T W a``."""
    aw = a * w[..., None]
    m = torch.einsum("nkci,nkcj->ncij", aw, a)
    rhs = torch.einsum("nkci,nkc->nci", aw, y)
    ridge = (1e-12 * m.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp_min(RIDGE)
    eye = torch.eye(3, dtype=a.dtype, device=a.device)
    m = m + ridge[..., None, None] * eye
    return torch.linalg.solve(m, rhs).nan_to_num(0.0, 0.0, 0.0), m


def _stereo(values, valid, unit, vector, gains, *, shadow: float, cut: float, shift: bool, rounds: int = 5):
    """Robust photometric stereo of ``n`` pixels: ``values, valid (n, K, C)``.

    Reweighted least squares: each round, a sample is an inlier when it is lit and its residual
    lies within ``cut`` robust standard deviations (1.4826 MAD of the previous inliers, per pixel
    and channel) of the fit; above the fit (a highlight only adds light) the cut is half as wide.
    With ``shift`` (while the gains are far off), the residual is taken after each frame's median
    relative residual over the pixels is removed: a frame whose gain is off is then not an outlier in
    every pixel (but a highlight that covers most of a frame is then taken in).

    Returns ``(b (n, C, 3), weight (n, K, C) bool, lit (n, K, C) bool, a (n, K, C, 3))`` with ``b``
    solved on ``weight`` (the inliers) and ``lit`` the valid samples in front of ``b``'s normal.
    """
    a = vector[:, :, None, :] * gains[None, :, :, None]
    typical = torch.where(valid, values, torch.nan).nanmedian(1, keepdim=True).values.nan_to_num(0.0)
    weight = valid & (values > DARK * typical)
    for _ in range(rounds):
        b, _ = _solve(a, values, weight.to(values.dtype))
        normal = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        lit = valid & (torch.einsum("nkj,ncj->nkc", unit, normal) > shadow)
        pred = torch.einsum("nkcj,ncj->nkc", a, b)
        # a frame's gain error is the same relative residual in every pixel: not an outlier
        residual = values - pred
        if shift:
            relative = torch.where(lit, residual / pred.clamp_min(1e-300), torch.nan).nanmedian(0).values
            residual = residual - pred * relative.nan_to_num(0.0)
        inlier = weight & lit
        scale = MAD_SCALE * torch.where(inlier, residual.abs(), torch.nan).nanmedian(1).values
        level = (torch.where(lit, values, torch.zeros_like(values)) ** 2).sum(1)
        level = (level / lit.sum(1).clamp_min(1)).sqrt()
        bound = (cut * torch.maximum(scale.nan_to_num(0.0), FLOOR * level))[:, None, :]
        weight = lit & (residual <= 0.5 * bound) & (residual >= -bound)
    b, _ = _solve(a, values, weight.to(values.dtype))
    return b, weight, lit, a


def _pixel_quality(values, weight, lit, a, b):
    """Per pixel relative RMS on the inliers, and whether it has enough inliers to be judged."""
    w = weight.to(values.dtype)
    residual = values - torch.einsum("nkcj,ncj->nkc", a, b)
    rms = ((w * residual**2).flatten(1).sum(1) / (w * values**2).flatten(1).sum(1).clamp_min(1e-300)).sqrt()
    enough = (weight.sum(1).amin(1) >= 4) & (weight.flatten(1).sum(1) >= 0.5 * lit.flatten(1).sum(1))
    return rms, enough


def _gather(frames: Tensor, valid: Tensor | None, index: Tensor, dtype) -> tuple[Tensor, Tensor]:
    """``(values, valid) (n, K, C)`` of the flat pixel ``index``, in ``dtype``."""
    k, c = frames.shape[:2]
    values = frames.reshape(k, c, -1)[:, :, index].permute(2, 0, 1).to(dtype)
    ok = torch.isfinite(values)
    if valid is not None:
        ok &= valid.reshape(k, c, -1)[:, :, index].permute(2, 0, 1)
    return torch.where(ok, values, torch.zeros_like(values)), ok


def _explained_pass(values, ok, points, directions, positions, gains, *, shadow, cut, explain, level=None, shift=False):
    """Photometric stereo of a pixel sample in chunks: ``(b, weight, lit, rms, explained (n,), level)``,
    explained within ``level`` (``explain`` times the median pixel's relative RMS unless given)."""
    parts = []
    for s in range(0, values.shape[0], SOLVE_CHUNK):
        unit, vector = _lighting(points[s : s + SOLVE_CHUNK], directions, positions)
        b, weight, lit, a = _stereo(
            values[s : s + SOLVE_CHUNK],
            ok[s : s + SOLVE_CHUNK],
            unit,
            vector,
            gains,
            shadow=shadow,
            cut=cut,
            shift=shift,
        )
        rms, enough = _pixel_quality(values[s : s + SOLVE_CHUNK], weight, lit, a, b)
        parts.append((b, weight, lit, rms, enough))
    b, weight, lit, rms, enough = (torch.cat(t) for t in zip(*parts, strict=True))
    if not bool(enough.any()):
        raise LightCalibrationError(
            "no pixel is explained by the Lambertian model (too few lit inlier samples everywhere): "
            "check the frames, the directions and the valid mask."
        )
    if level is None:
        level = explain * rms[enough].median()
    return b, weight, lit, rms, enough & (rms <= level), level


def _derivatives(values, b, points, directions, positions, gains, near: bool):
    """``(a (n,K,C,3), pred (n,K,C), D (n,K,C,P))``: the model, its prediction and its derivatives
    with respect to each light's parameters (``C`` gains, then ``x, y, z`` when ``near``)."""
    k, c = gains.shape
    unit, vector = _lighting(points, directions, positions)
    a = vector[:, :, None, :] * gains[None, :, :, None]
    pred = torch.einsum("nkcj,ncj->nkc", a, b)
    eye = torch.eye(c, dtype=values.dtype, device=values.device)
    dgain = (pred / gains[None])[..., None] * eye[None, None]
    if not near:
        return a, pred, dgain
    v = positions[None] - points[:, None]
    dist2 = (v * v).sum(-1)
    p2 = (positions * positions).sum(-1)[None]
    bv = torch.einsum("ncj,nkj->nkc", b, v)
    inv3 = dist2 ** (-1.5)
    dpos = (
        2 * positions[None, :, None, :] * (bv * inv3[..., None])[..., None]
        + (p2 * inv3)[:, :, None, None] * b[:, None, :, :]
        - 3 * (p2 * inv3 / dist2)[:, :, None, None] * bv[..., None] * v[:, :, None, :]
    ) * gains[None, :, :, None]
    return a, pred, torch.cat([dgain, dpos], dim=-1)


def _normal_equations(values, weight, b, points, directions, positions, gains, near: bool):
    """Variable-projection normal equations of the lights' parameters: ``(JtJ (KP, KP), Jtr (KP,),
    chi2, samples)``, the maps eliminated per pixel (Kaufman's approximation)."""
    k, c = gains.shape
    p = c + 3 if near else c
    jtj = values.new_zeros(k * p, k * p)
    jtr = values.new_zeros(k * p)
    chi2, samples = values.new_zeros(()), values.new_zeros(())
    for s in range(0, values.shape[0], CHUNK):
        y, w = values[s : s + CHUNK], weight[s : s + CHUNK].to(values.dtype)
        a, pred, d = _derivatives(y, b[s : s + CHUNK], points[s : s + CHUNK], directions, positions, gains, near)
        r = (y - pred) * w
        dw = d * w[..., None]
        jtj += torch.block_diag(*torch.einsum("nkcp,nkcq->kpq", dw, d))
        jtr += torch.einsum("nkcp,nkc->kp", dw, r).reshape(-1)
        m = torch.einsum("nkci,nkcj->ncij", a * w[..., None], a)
        eye = torch.eye(3, dtype=y.dtype, device=y.device)
        m = m + (1e-12 * m.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp_min(RIDGE)[..., None, None] * eye
        dwa = torch.einsum("nkcp,nkci->ncikp", dw, a).reshape(y.shape[0], c, 3, k * p)  # A^T W D
        g = torch.linalg.inv(m) @ dwa  # M^-1 A^T W D: (n, C, 3, KP)
        jtj -= dwa.reshape(-1, k * p).T @ g.reshape(-1, k * p)
        chi2 += (r * r).sum()
        samples += w.sum()
    return jtj, jtr, chi2, samples


def _gauge(gains: Tensor, positions: Tensor | None) -> Tensor:
    """``(KP, m)`` orthonormal directions the pixels do not (or barely) see: each channel's common
    gain factor and, for near lights, the three rotations of all positions about the origin."""
    k, c = gains.shape
    modes = []
    for ch in range(c):
        mode = torch.zeros_like(gains)
        mode[:, ch] = gains[:, ch]
        modes.append(mode if positions is None else torch.cat([mode, torch.zeros_like(positions)], 1))
    if positions is not None:
        for axis in torch.eye(3, dtype=gains.dtype, device=gains.device):
            rotated = torch.linalg.cross(axis.expand_as(positions), positions)
            modes.append(torch.cat([torch.zeros_like(gains), rotated], 1))
    basis = torch.stack([m.reshape(-1) for m in modes], 1)
    return torch.linalg.qr(basis).Q


def _step(jtj, jtr, gauge, sigma2, damping: float, frozen: Tensor) -> tuple[Tensor, Tensor]:
    """A damped Gauss-Newton step with no component along ``gauge`` nor on the ``frozen (KP,)``
    parameters, and the covariance of the gauge-fixed parameters ``sigma2 P (JtJ + mu G G^T)^-1 P``
    (infinite on the frozen ones: nothing determines them)."""
    mu = jtj.diagonal().mean().clamp_min(1e-300)
    fixed = jtj + mu * gauge @ gauge.T + torch.diag(frozen.to(jtj.dtype) * 1e12 * mu)
    project = torch.eye(jtj.shape[0], dtype=jtj.dtype, device=jtj.device) - gauge @ gauge.T
    covariance = sigma2 * project @ torch.linalg.pinv(fixed, hermitian=True) @ project
    covariance.diagonal()[frozen] = math.inf
    damped = fixed + damping * torch.diag(fixed.diagonal())
    delta = project @ torch.linalg.solve(damped, jtr)
    return torch.where(frozen, 0.0, delta), covariance


def _objective(values, weight, points, directions, positions, gains) -> Tensor:
    """The weighted sum of squares with the maps solved per pixel on ``weight`` (variable projection)."""
    total = values.new_zeros(())
    for s in range(0, values.shape[0], SOLVE_CHUNK):
        _, vector = _lighting(points[s : s + SOLVE_CHUNK], directions, positions)
        a = vector[:, :, None, :] * gains[None, :, :, None]
        y, w = values[s : s + SOLVE_CHUNK], weight[s : s + SOLVE_CHUNK].to(values.dtype)
        b, _ = _solve(a, y, w)
        total += (w * (y - torch.einsum("nkcj,ncj->nkc", a, b)) ** 2).sum()
    return total


def _update(values, weight, b, points, directions, positions, gains, near: bool, damping: float):
    """A Levenberg-Marquardt step of the lights on fixed inliers (a step is taken only when it lowers
    the sum of squares; the damping grows tenfold until it does): ``(gains, positions, covariance,
    change, damping)``. A frame with fewer than :data:`MIN_SAMPLES` inliers in a channel keeps its
    gain (and its position)."""
    k, c = gains.shape
    jtj, jtr, chi2, n = _normal_equations(values, weight, b, points, directions, positions, gains, near)
    sigma2 = chi2 / (n - 3 * c * values.shape[0] - jtj.shape[0]).clamp_min(1)
    frozen = weight.sum(0) < MIN_SAMPLES
    if near:
        frozen = torch.cat([frozen, frozen.any(1, keepdim=True).expand(k, 3)], 1)
    old = torch.cat([gains, positions], 1) if near else gains
    gauge = _gauge(gains, positions if near else None)  # held positions (dome) have no gauge
    for _ in range(8):
        delta, covariance = _step(jtj, jtr, gauge, sigma2, damping, frozen.reshape(-1))
        delta = delta.reshape(old.shape)
        trial_gains, trial_positions = _normalised(gains + delta[:, :c]), positions
        if near:
            moved = positions + delta[:, c:]
            trial_positions = torch.where(moved[:, 2:] > 0.05 * positions[:, 2:], moved, positions)
        if _objective(values, weight, points, directions, trial_positions, trial_gains) <= chi2 * (1 + 1e-12):
            change = float((delta.abs() / old.abs().amax(0, keepdim=True)).amax())
            return trial_gains, trial_positions, covariance, change, max(damping / 10, 1e-12)
        damping *= 10
    return gains, positions, covariance, 0.0, damping


def _sample(count: int, sample: int, device) -> Tensor:
    """A deterministic subset of ``sample`` flat pixel indices (all when ``count <= sample``)."""
    if count <= sample:
        return torch.arange(count, device=device)
    chosen = torch.randperm(count, generator=torch.Generator().manual_seed(0))[:sample]
    return chosen.sort().values.to(device)


def _ratio_gains(values, ok, points, directions, positions, gains, options, rounds: int) -> tuple[Tensor, Tensor]:
    """Gains from the median over explained pixels of each frame's ``value / prediction`` (robust to
    a frame's gain being far off, which a per-pixel cut would take for an outlier in every pixel),
    repeated ``rounds`` times or until they change by less than 1e-4: ``(gains, median pixel rms)``."""
    rms_level = values.new_tensor(math.inf)
    for _ in range(rounds):
        b, _, lit, rms, sel, _ = _explained_pass(
            values, ok, points, directions, positions, gains, **options, shift=True
        )
        rms_level = rms[sel].median()
        _, vector = _lighting(points[sel], directions, positions)
        pred = torch.einsum("nkj,kc,ncj->nkc", vector, gains, b[sel])
        use = lit[sel] & (pred > 0.1 * pred.amax(1, keepdim=True))
        ratio = torch.where(use, values[sel] / pred.clamp_min(1e-300), torch.nan).nanmedian(0).values
        ratio = _normalised(ratio.nan_to_num(1.0))
        gains = _normalised(gains * ratio)
        if float((ratio - 1).abs().max()) < 1e-4:
            break
    return gains, rms_level


def _dome_misfit(values, ok, points, directions, radius, gains, options) -> float:
    """The median pixel misfit of lights at ``radius`` along ``directions`` (``None``: distant), gains refitted."""
    positions = None if radius is None else radius * directions
    return float(_ratio_gains(values, ok, points, directions, positions, gains, options, 3)[1])


def dome_radius(values, ok, points, directions, gains, options) -> tuple[float | None, dict]:
    """The dome radius of :data:`RADII` (all lights at it along their ``directions``) whose median
    pixel misfit (:func:`_dome_misfit`) is the least, or ``None`` (distant lights)
    unless that misfit is below ``1 - DOME_MARGIN`` of the distant lights': ``(radius, misfit of
    each candidate)``."""
    misfit = {"distant": _dome_misfit(values, ok, points, directions, None, gains, options)}
    for r in RADII:
        misfit[str(r)] = _dome_misfit(values, ok, points, directions, r, gains, options)
    best = min(RADII, key=lambda r: misfit[str(r)])
    return (best if misfit[str(best)] < (1 - DOME_MARGIN) * misfit["distant"] else None), misfit


def _normalised(gains: Tensor) -> Tensor:
    gains = gains.clamp_min(1e-6 * gains.abs().amax().clamp_min(1e-300))
    return gains / gains.log().mean(0, keepdim=True).exp()


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
            :data:`DOME_MARGIN`), held while the gains are estimated; ignored with ``near``.
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
    positions, chosen, misfit = None, None, None
    if near:
        if radius is None:  # the start: the radius of RADII whose lights leave the least misfit
            radius = min(RADII, key=lambda r: _dome_misfit(values, ok, points, dirs, r, gains, options))
        positions = radius * dirs
    elif dome:
        chosen, misfit = dome_radius(values, ok, points, dirs, gains, options)
        positions = None if chosen is None else chosen * dirs
    gains = _ratio_gains(values, ok, points, dirs, positions, gains, options, 8)[0]
    done, covariance, level, strict = 0, None, None, False
    for done in range(1, max(iterations, 1) + 1):
        b, weight, _, _, sel, level = _explained_pass(
            values, ok, points, dirs, positions, gains, **options, shift=not strict
        )
        gains, positions, covariance, change, damping = _update(
            values[sel], weight[sel], b[sel], points[sel], dirs, positions, gains, near, damping
        )
        if strict and change < tolerance:
            break
        # the first half with frame shifts (gains far off), the rest strict (highlights out)
        strict = strict or change < 1e-3 or 2 * done >= iterations
    std = covariance.diagonal().clamp_min(0).sqrt().reshape(k, -1)
    gain_std = std[:, :c]
    final = _full_pass(frames, valid, dirs, positions, gains, options, level)
    out = {"dtype": frames.dtype, "device": device}
    centre = dirs if positions is None else positions / positions.norm(dim=-1, keepdim=True)
    return LightCalibration(
        gains=gains.to(**out),
        gain_std=gain_std.to(**out),
        positions=None if positions is None else positions.to(**out),
        position_std=None if positions is None or not near else std[:, c:].to(**out),
        directions=centre.to(**out),
        explained=final.explained,
        rms=final.rms.to(**out),
        iterations=done,
        radius=chosen,
        radius_misfit=misfit,
    )


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
        b, _, lit, rms, explained, _ = _explained_pass(
            values, ok, points, dirs, positions, gains, **options, level=level
        )
        use = explained if flat_pixels is None else flat_pixels[index]
        _, vector = _lighting(points, dirs, positions)
        pred = torch.einsum("nkj,kc,ncj->nkc", vector, gains, b)
        mask = (lit & use[:, None, None]).to(work)
        residual2 += (mask * (values - pred) ** 2).sum((0, 2))
        energy += (mask * values**2).sum((0, 2))
        rows.append((b, explained))
    b, explained = (torch.cat(t) for t in zip(*rows, strict=True))
    total = b.sum(1)
    normal = total / total.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    out = {"dtype": frames.dtype}
    return LambertFit(
        normal=normal.reshape(height, width, 3).to(**out),
        albedo=b.norm(dim=-1).T.reshape(c, height, width).to(**out),
        explained=explained.reshape(height, width),
        rms=(residual2 / energy.clamp_min(1e-300)).sqrt(),
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
    level = _explained_pass(values, ok, points, dirs, positions, gains, **options)[-1]
    return _full_pass(frames, valid, dirs, positions, gains, options, level, pixels)
