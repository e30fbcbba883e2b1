"""The robust Lambertian least squares that :mod:`torchspec.calibration.lights` alternates with the lights:
per-pixel photometric stereo under given lights (:func:`_stereo`, :func:`_explained_pass`) and the
variable-projection Levenberg-Marquardt step of the lights' parameters (:func:`_update`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ...errors import TorchspecError
from ...model.near_lights import near_light
from ...start.photometric import MAD_SCALE


class LightCalibrationError(TorchspecError):
    """Input :func:`calibrate_lights` cannot calibrate from (shapes, frame count, no explained pixel)."""


CHUNK = 512
"""Pixels a variable-projection step handles at once (its Jacobian is ``(chunk, C, K, P, 3)``)."""
SOLVE_CHUNK = 8192
"""Pixels a photometric-stereo pass handles at once."""
DARK = 0.05
"""Before the first solve, samples below this fraction of the pixel's median are shadows."""
RIDGE = 1e-30
"""The least ridge of a pixel's normal equations (one with no inlier then solves to 0, unexplained)."""
MIN_SAMPLES = 20
"""A frame's gain in a channel is estimated from at least this many inlier samples (else kept)."""
FLOOR = 1e-3
"""The robust scale is at least this fraction of the pixel's RMS value (a noise-free capture)."""


def _lighting(points: Tensor, directions: Tensor, positions: Tensor | None) -> tuple[Tensor, Tensor]:
    """``(unit, vector)``: each sample's light direction, and it times the falloff; ``(n, K, 3)``
    for near lights, the directions ``(K, 3)`` themselves for distant ones (the same at every pixel)."""
    if positions is None:
        return directions, directions
    unit, falloff = near_light(positions, points)
    return unit, unit * falloff[..., None]


@dataclass(frozen=True)
class _Design:
    """The Lambertian design ``a_nkci = v_nki g_kc`` (``vector (n, K, 3)``, or ``(K, 3)`` for distant
    lights) and ``gains (K, C)``, never built as ``(n, K, C, 3)``: each sum over the frames is a
    matrix product (for distant lights one product for all pixels; operands made contiguous, as a
    strided batch falls off BLAS)."""

    vector: Tensor
    gains: Tensor
    outer: Tensor  # v v^T: (K, 9) or (n, K, 9)

    @classmethod
    def of(cls, vector: Tensor, gains: Tensor) -> _Design:
        return cls(vector, gains, (vector[..., :, None] * vector[..., None, :]).flatten(-2))

    def gram(self, w: Tensor) -> Tensor:
        """``a^T W a``: ``(n, C, 3, 3)`` for weights ``w (n, K, C)``."""
        return ((w * self.gains**2).transpose(1, 2).contiguous() @ self.outer).unflatten(-1, (3, 3))

    def project(self, y: Tensor) -> Tensor:
        """``a^T y``: ``(n, C, 3)``."""
        return (y * self.gains).transpose(1, 2).contiguous() @ self.vector

    def predict(self, b: Tensor) -> Tensor:
        """``a b``: ``(n, K, C)`` for ``b (n, C, 3)``."""
        return (self.vector @ b.transpose(1, 2)) * self.gains


def _solve(design: _Design, y: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Per pixel and channel weighted least squares ``b (n, C, 3)`` of ``y ~ a b`` and ``a^T W a``."""
    m = _ridged(design.gram(w))
    return torch.linalg.solve(m, design.project(w * y)).nan_to_num(0.0, 0.0, 0.0), m


def _ridged(m: Tensor) -> Tensor:
    """``m (..., 3, 3)`` plus a ridge of ``1e-12`` its trace (at least :data:`RIDGE`)."""
    ridge = (1e-12 * m.diagonal(dim1=-2, dim2=-1).sum(-1)).clamp_min(RIDGE)
    return m + ridge[..., None, None] * torch.eye(3, dtype=m.dtype, device=m.device)


@dataclass(frozen=True)
class StereoFit:
    """Robust photometric stereo of ``n`` pixels (:func:`_stereo`).

    Attributes:
        b: ``(n, C, 3)`` each pixel's solution per channel (albedo times normal), solved on ``weight``.
        weight: ``(n, K, C)`` bool, the inliers.
        lit: ``(n, K, C)`` bool, the valid samples in front of ``b``'s normal.
    """

    b: Tensor
    weight: Tensor
    lit: Tensor


def _stereo(values, valid, unit, design, *, shadow: float, cut: float, shift: bool, rounds: int = 5) -> StereoFit:
    """Robust photometric stereo of ``n`` pixels: ``values, valid (n, K, C)``.

    Reweighted least squares: each round, a sample is an inlier when it is lit and its residual
    lies within ``cut`` robust standard deviations (1.4826 MAD of the previous inliers, per pixel
    and channel) of the fit; above the fit (a highlight only adds light) the cut is half as wide.
    With ``shift`` (while the gains are far off), the residual is taken after each frame's median
    relative residual over the pixels is removed: a frame whose gain is off is then not an outlier in
    every pixel (but a highlight that covers most of a frame is then taken in).

    Returns the :class:`StereoFit`: ``b`` solved on ``weight`` (the inliers), ``lit`` the valid
    samples in front of ``b``'s normal.
    """
    typical = torch.where(valid, values, torch.nan).nanmedian(1, keepdim=True).values.nan_to_num(0.0)
    weight = valid & (values > DARK * typical)
    for _ in range(rounds):
        b, _ = _solve(design, values, weight.to(values.dtype))
        normal = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        lit = valid & (unit @ normal.transpose(1, 2) > shadow)
        pred = design.predict(b)
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
    b, _ = _solve(design, values, weight.to(values.dtype))
    return StereoFit(b=b, weight=weight, lit=lit)


def _pixel_quality(values, weight, lit, design, b):
    """Per pixel relative RMS on the inliers, and whether it has enough inliers to be judged."""
    w = weight.to(values.dtype)
    residual = values - design.predict(b)
    rms = ((w * residual**2).flatten(1).sum(1) / (w * values**2).flatten(1).sum(1).clamp_min(1e-300)).sqrt()
    enough = (weight.sum(1).amin(1) >= 4) & (weight.flatten(1).sum(1) >= 0.5 * lit.flatten(1).sum(1))
    return rms, enough


def _sample(count: int, sample: int, device, seed: int = 0) -> Tensor:
    """A deterministic subset of ``sample`` flat pixel indices (all when ``count <= sample``)."""
    if count <= sample:
        return torch.arange(count, device=device)
    # on the CPU: a seeded draw, the same on every device; moved below
    chosen = torch.randperm(count, generator=torch.Generator().manual_seed(seed))[:sample]
    return chosen.sort().values.to(device)


def _gather(frames: Tensor, valid: Tensor | None, index: Tensor, dtype) -> tuple[Tensor, Tensor]:
    """``(values, valid) (n, K, C)`` of the flat pixel ``index``, in ``dtype``."""
    k, c = frames.shape[:2]
    values = frames.reshape(k, c, -1)[:, :, index].permute(2, 0, 1).to(dtype)
    ok = torch.isfinite(values)
    if valid is not None:
        ok &= valid.reshape(k, c, -1)[:, :, index].permute(2, 0, 1)
    return torch.where(ok, values, torch.zeros_like(values)), ok


@dataclass(frozen=True)
class ExplainedPass:
    """Robust photometric stereo of ``n`` pixels under given lights (:func:`_explained_pass`).

    Attributes:
        b: ``(n, C, 3)`` each pixel's solution per channel (albedo times normal), solved on ``weight``.
        weight: ``(n, K, C)`` bool, the inliers (:func:`_stereo`).
        lit: ``(n, K, C)`` bool, the valid samples in front of ``b``'s normal.
        rms: ``(n,)`` each pixel's relative RMS on its inliers.
        explained: ``(n,)`` bool, the pixels with enough inliers and ``rms`` within ``level``.
        level: the largest ``rms`` of an explained pixel (a 0-dim tensor, or the level given).
    """

    b: Tensor
    weight: Tensor
    lit: Tensor
    rms: Tensor
    explained: Tensor
    level: Tensor | float


def _explained_pass(
    values, ok, points, directions, positions, gains, *, shadow, cut, explain, level=None, shift=False
) -> ExplainedPass:
    """Photometric stereo of a pixel sample in chunks (:class:`ExplainedPass`), explained within
    ``level`` (``explain`` times the median pixel's relative RMS unless given)."""
    parts = []
    for s in range(0, values.shape[0], SOLVE_CHUNK):
        unit, vector = _lighting(points[s : s + SOLVE_CHUNK], directions, positions)
        design = _Design.of(vector, gains)
        chunk = values[s : s + SOLVE_CHUNK]
        fit = _stereo(chunk, ok[s : s + SOLVE_CHUNK], unit, design, shadow=shadow, cut=cut, shift=shift)
        rms, enough = _pixel_quality(chunk, fit.weight, fit.lit, design, fit.b)
        parts.append((fit.b, fit.weight, fit.lit, rms, enough))
    b, weight, lit, rms, enough = (torch.cat(t) for t in zip(*parts, strict=True))
    if not bool(enough.any()):
        raise LightCalibrationError(
            "no pixel is explained by the Lambertian model (too few lit inlier samples everywhere): "
            "check the frames, the directions and the valid mask."
        )
    if level is None:
        level = explain * rms[enough].median()
    return ExplainedPass(b=b, weight=weight, lit=lit, rms=rms, explained=enough & (rms <= level), level=level)


def _derivatives(values, b, points, directions, positions, gains, near: bool):
    """``(design, pred (n,K,C), D (n,K,C,P))``: the model, its prediction and its derivatives
    with respect to each light's parameters (``C`` gains, then ``x, y, z`` when ``near``)."""
    k, c = gains.shape
    a = _Design.of(_lighting(points, directions, positions)[1], gains)
    pred = a.predict(b)
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


@dataclass(frozen=True)
class _NormalEquations:
    """Variable-projection normal equations of the lights' ``K P`` parameters (:func:`_normal_equations`).

    Attributes:
        jtj: ``(K P, K P)`` ``J^T W J``, the maps eliminated per pixel.
        jtr: ``(K P,)`` ``J^T W r``.
        chi2: the weighted sum of squared residuals (0-dim).
        samples: the weighted count of samples (0-dim).
    """

    jtj: Tensor
    jtr: Tensor
    chi2: Tensor
    samples: Tensor


def _normal_equations(values, weight, b, points, directions, positions, gains, near: bool) -> _NormalEquations:
    """Variable-projection normal equations of the lights' parameters (:class:`_NormalEquations`),
    the maps eliminated per pixel (Kaufman's approximation)."""
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
        m = _ridged(a.gram(w))
        vector = a.vector.expand(y.shape[0], k, 3)  # A^T W D:
        dwa = torch.einsum("nkcp,nki->ncikp", dw * gains[..., None], vector).reshape(y.shape[0], c, 3, k * p)
        g = torch.linalg.inv(m) @ dwa  # M^-1 A^T W D: (n, C, 3, KP)
        jtj -= dwa.reshape(-1, k * p).T @ g.reshape(-1, k * p)
        chi2 += (r * r).sum()
        samples += w.sum()
    return _NormalEquations(jtj=jtj, jtr=jtr, chi2=chi2, samples=samples)


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
        design = _Design.of(_lighting(points[s : s + SOLVE_CHUNK], directions, positions)[1], gains)
        y, w = values[s : s + SOLVE_CHUNK], weight[s : s + SOLVE_CHUNK].to(values.dtype)
        b, _ = _solve(design, y, w)
        total += (w * (y - design.predict(b)) ** 2).sum()
    return total


@dataclass(frozen=True)
class LightStep:
    """The outcome of a Levenberg-Marquardt step of the lights (:func:`_update`).

    Attributes:
        gains: ``(K, C)`` the gains after the step (as before where no step lowered the sum of squares).
        positions: ``(K, 3)`` the positions after it, or ``None`` (distant lights).
        covariance: ``(K P, K P)`` of the gauge-fixed parameters (:func:`_step`).
        change: the largest relative change of a parameter (0 where no step was taken).
        damping: the damping for the next step.
    """

    gains: Tensor
    positions: Tensor | None
    covariance: Tensor
    change: float
    damping: float


def _update(values, weight, b, points, directions, positions, gains, near: bool, damping: float) -> LightStep:
    """A Levenberg-Marquardt step of the lights on fixed inliers (a step is taken only when it lowers
    the sum of squares; the damping grows tenfold until it does): :class:`LightStep`. A frame with
    fewer than :data:`MIN_SAMPLES` inliers in a channel keeps its gain (and its position)."""
    k, c = gains.shape
    equations = _normal_equations(values, weight, b, points, directions, positions, gains, near)
    jtj, jtr, chi2 = equations.jtj, equations.jtr, equations.chi2
    sigma2 = chi2 / (equations.samples - 3 * c * values.shape[0] - jtj.shape[0]).clamp_min(1)
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
            return LightStep(trial_gains, trial_positions, covariance, change, max(damping / 10, 1e-12))
        damping *= 10
    return LightStep(gains, positions, covariance, 0.0, damping)


def _normalised(gains: Tensor) -> Tensor:
    gains = gains.clamp_min(1e-6 * gains.abs().amax().clamp_min(1e-300))
    return gains / gains.log().mean(0, keepdim=True).exp()


def _frame_sums(values: Tensor, pred: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """Per frame, the squared residuals and the squared values of the ``mask``ed samples ``(n, K, C)``."""
    mask = mask.to(values.dtype)
    return (mask * (values - pred) ** 2).sum((0, 2)), (mask * values**2).sum((0, 2))


def _median_misfit(values, points, directions, positions, gains, b, use) -> float:
    """The median over the frames of their relative RMS misfit on the ``use (n, K, C)`` samples."""
    pred = _Design.of(_lighting(points, directions, positions)[1], gains).predict(b)
    residual2, energy = _frame_sums(values, pred, use)
    return float((residual2 / energy.clamp_min(1e-300)).sqrt().median())
