"""Location of one symmetric pulse from its Fourier coefficients, in D = 1 or 2 dimensions.

The model: ``Y_p = a_p e^{-i F_p . theta} + noise`` with ``a_p`` real (a symmetric kernel has a
real spectrum) and unknown, ``theta = 2 pi x / tau``. Rotating every coefficient back by the
true phase leaves ``c_p = Y_p e^{i F_p . theta}`` real: ``R_p = Re c_p`` holds the kernel's
spectrum, ``I_p = Im c_p`` only noise. Every estimator here is exact without noise, whatever
the kernel, because each solves a stationarity condition that ``I = 0`` satisfies.

- ``coherent`` (the default) maximises the matched filter ``h(theta) = sum_p b_p R_p(theta)``
  whose weights ``b`` are the kernel's spectrum estimated from the data: the best-fitting
  envelope of a small dictionary (Gaussian spectra; sinc ones where they fit clearly better
  than noise explains), blended back towards the raw ``R`` where that departs
  from the envelope by more than the noise. With ``b`` equal to the true spectrum this is the
  known-kernel maximum likelihood, which meets the Cramer-Rao bound; estimating ``b`` adds
  error at low SNR only. A ``kernel`` given (or pooled over many problems, :func:`pool_kernel`)
  replaces ``b``, and weighs the start's grid search too.
- ``ml`` is the kernel-free likelihood: Gauss-Newton on ``sum_p I_p(theta)^2``, which leaves
  every ``a_p`` free. Efficient at high SNR, but it pays for M nuisance amplitudes at low SNR.
- ``ls``, ``esprit``, ``cadzow``: the phase of the root of a length-2 annihilating filter on
  ``Y_0..Y_M`` (least squares: the paper's equation (5)), of the TLS-ESPRIT rotation, and of
  ESPRIT after fixed-iteration rank-1 Cadzow denoising. ``Y_0`` enters as ``|Y_0|``: after a
  diffuse part is subtracted it can be negative, which would turn the root by pi. In 2D each
  axis uses every row of the spectrum as a snapshot sharing that axis's root.

A symmetric periodic pulse is also symmetric about ``x + tau / 2``; where a method cannot
tell the two apart (the roots, ``ml``) the matched filter decides: it is larger at the peak.

References:
    Vetterli, Marziliano, Blu, "Sampling signals with finite rate of innovation", IEEE TSP 2002.
    Blu, Dragotti, Vetterli, Marziliano, Coulot, "Sparse sampling of signal innovations",
    IEEE Signal Processing Magazine 2008 (Cadzow, TLS-ESPRIT, the Cramer-Rao bound).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ._coefficients import axis_rows, frequencies
from ._hankel import cadzow, hankel, rows_for, signal_subspace

__all__ = ["SinglePulse", "locate_single", "pool_kernel"]

ITERATIONS = 3  # Newton steps of coherent / ml; convergence is quadratic from the grid start
CADZOW_ITERATIONS = 10
GRID_PER_COEFFICIENT = 4  # start grid points per period of the highest coefficient
BLEND = 9.0  # a departure from the envelope is kept once it exceeds ~3 noise std
FAMILY_PENALTY = 10.0  # noise variances a non-Gaussian envelope must gain to be chosen
CHUNK = 1 << 15  # problems per chunk: intermediates stay in cache, memory stays bounded


def _safe_div(num: Tensor, den: Tensor) -> Tensor:
    """``num / den``, 0 where ``den == 0``, with finite gradients too (double where)."""
    ok = den != 0
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _rotate(yr: Tensor, yi: Tensor, freq: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """``R, I (B, P)`` of ``Y e^{i F . theta}``."""
    phase = theta * freq[:, 0] if freq.shape[1] == 1 else theta @ freq.T
    cos, sin = torch.cos(phase), torch.sin(phase)
    return torch.addcmul(yr * cos, yi, sin, value=-1.0), torch.addcmul(yr * sin, yi, cos)


class _Dictionary(NamedTuple):
    u2: Tensor  # (P, 1) squared frequency relative to the band edge
    log_width: Tensor  # (G0,) log c of the refined Gaussian family exp(-c u^2), uniform steps
    families: tuple[Tensor, ...]  # (P, G_f) unit-norm envelopes; the refined Gaussians first
    penalty: tuple[float, ...]  # in noise variances, per family


def _dictionary(freq: Tensor, bands: tuple[int, ...]) -> _Dictionary:
    """Envelopes of symmetric kernels' spectra over ``freq``.

    With ``u`` the frequency relative to the band edge: Gaussian ``exp(-c u^2)`` (searched on a
    coarse grid of ``c`` and refined by a parabola in ``log c``; in 2D also separable ones of
    different widths per axis) and ``sinc(u / u0)`` (box- and disk-like kernels, whose
    spectra change sign), each from flat (a narrow kernel) to gone after the first coefficient
    (a wide one). Exponential spectra (Lorentzian kernels) need no family of their own: the
    Gaussian envelope fits them within noise.
    """
    like = dict(dtype=freq.dtype, device=freq.device)
    edge = torch.tensor(bands, **like)
    u = (freq / edge) ** 2
    u2 = u.sum(-1, keepdim=True)  # (P, 1)
    top = max(bands)
    log_width = torch.linspace(math.log(1e-2), math.log(6.0 * top**2), 16, **like)
    gaussian = torch.exp(-log_width.exp() * u2)
    families = [gaussian]
    penalty = [0.0]
    if len(bands) == 2:
        c = torch.logspace(-2.0, math.log10(6.0 * top**2), 10, **like)
        c1, c2 = torch.meshgrid(c, c, indexing="ij")
        families.append(torch.exp(-(u[:, :1] * c1.reshape(1, -1) + u[:, 1:] * c2.reshape(1, -1))))
        penalty.append(0.0)
    families.append(torch.sinc(u2.sqrt() / torch.logspace(math.log10(1.5 / top), math.log10(3.0), 8, **like)))
    penalty.append(FAMILY_PENALTY)
    families = tuple(f / f.norm(dim=0, keepdim=True) for f in families)
    return _Dictionary(u2[:, 0], log_width, families, tuple(penalty))


def _refined_gaussian(r: Tensor, scores: Tensor, dictionary: _Dictionary) -> tuple[Tensor, Tensor]:
    """Best Gaussian envelope, ``log c`` refined by a parabola through the best three scores:
    ``(amplitude (B, 1), unit atom (B, P))``."""
    size = scores.shape[-1]
    k = scores.argmax(-1, keepdim=True)
    inner = k.clamp(1, size - 2)
    sm, s0, sp = scores.gather(-1, inner + torch.arange(-1, 2, device=inner.device)).unbind(-1)
    curv = (sm - 2.0 * s0 + sp).clamp(max=-torch.finfo(scores.dtype).tiny)  # < 0 at a maximum
    offset = (0.5 * (sm - sp) / curv).clamp(-1.0, 1.0)[:, None]
    offset = torch.where(inner == k, offset, (k - inner).to(offset.dtype))  # at the ends: no refinement
    step = dictionary.log_width[1] - dictionary.log_width[0]
    width = (dictionary.log_width[inner[:, 0]][:, None] + offset * step).exp()
    atom = torch.exp(-width * dictionary.u2)
    atom = atom / atom.norm(dim=-1, keepdim=True)
    return (r * atom).sum(-1, keepdim=True), atom


def _noise(i: Tensor, dims: int) -> Tensor:
    """Noise variance per real component, from the imaginary residual: ``(B, 1)``."""
    dof = i.shape[-1] - dims
    if dof <= 0:
        return torch.zeros_like(i[:, :1])
    return (i**2).sum(-1, keepdim=True) / dof


def _envelope(r: Tensor, noise: Tensor, dictionary: _Dictionary) -> Tensor:
    """The kernel-spectrum estimate ``b (B, P)`` from the rotated real parts ``r (B, P)``.

    Each family's best atom (least squares, amplitude >= 0); a family other than the Gaussian
    wins only if it removes ``FAMILY_PENALTY`` more noise variances of residual, so that noise
    does not switch families. Departures of ``r`` from that envelope beyond ~3 noise std are
    kept (a spectrum no atom describes), smaller ones are taken for noise and dropped.
    """
    best_score = best_fit = None
    for family, (atoms, penalty) in enumerate(zip(dictionary.families, dictionary.penalty, strict=True)):
        scores = r @ atoms
        if family == 0:
            value, atom = _refined_gaussian(r, scores, dictionary)
        else:
            value, index = scores.max(-1, keepdim=True)
            atom = atoms.T[index[:, 0]]
        value = value.clamp(min=0.0)
        fit = value * atom
        score = value * value - penalty * noise
        if best_score is None:
            best_score, best_fit = score, fit
        else:
            better = score > best_score
            best_fit = torch.where(better, fit, best_fit)
            best_score = torch.where(better, score, best_score)
    dev = r - best_fit
    dev2 = dev * dev
    keep = (1.0 - (BLEND * noise) / dev2.clamp(min=torch.finfo(dev2.dtype).tiny)).clamp(min=0.0)
    return best_fit + keep * dev


def _newton_step(w: Tensor, curvature: Tensor, fallback: Tensor, i: Tensor, freq: Tensor) -> Tensor:
    """``-(sum curvature F F^T)^{-1} sum w I F``, with ``fallback >= 0`` in place of the
    curvature where that is not positive definite: ``(B, D)``."""
    if freq.shape[1] == 1:
        m = freq[:, 0]
        g = (w * i) @ m
        q = curvature @ (m * m)
        q = torch.where(q > 0, q, fallback @ (m * m))
        return (-g / q.clamp(min=torch.finfo(q.dtype).tiny))[:, None]
    g = (w * i) @ freq
    ff = (freq[:, :, None] * freq[:, None, :]).reshape(-1, 4)
    q = curvature @ ff
    q_fb = fallback @ ff
    det = q[:, 0] * q[:, 3] - q[:, 1] ** 2
    pd = ((det > 0) & (q[:, 0] > 0))[:, None]
    q = torch.where(pd, q, q_fb)
    det = q[:, 0] * q[:, 3] - q[:, 1] ** 2
    x0 = _safe_div(q[:, 3] * g[:, 0] - q[:, 1] * g[:, 1], det)
    x1 = _safe_div(q[:, 0] * g[:, 1] - q[:, 1] * g[:, 0], det)
    return -torch.stack([x0, x1], -1)


def _grid_start(yr: Tensor, yi: Tensor, band: int, kernel: Tensor | None = None) -> Tensor:
    """1D start ``(B, 1)``: the maximum of ``sum_m w_m Re(Y_m e^{i m theta})``, m = 1..band,
    over a grid, refined by a parabola through the best three points.

    Without a kernel ``w_m = |Y_m| / m``: weighting each coefficient by its magnitude makes this
    the matched filter of the data's own spectrum, which peaks at the pulse and not at its
    trough; dividing by ``m`` keeps bins that hold only noise (a wide kernel) from pulling the
    start off the peak. With a known ``kernel (band,)`` spectrum, ``w = kernel``: the matched
    filter itself. The grid is anchored at the phase of ``Y_1``, so that shifting or mirroring
    the samples shifts or mirrors the whole estimate exactly.
    """
    size = max(GRID_PER_COEFFICIENT * band, 16)
    m = torch.arange(1, band + 1, dtype=yr.dtype, device=yr.device)
    anchor = -torch.atan2(yi[:, :1], yr[:, :1])  # (B, 1)
    yr, yi = _rotate(yr, yi, m[:, None], anchor)
    phi = torch.arange(size, dtype=yr.dtype, device=yr.device) * (2.0 * math.pi / size)
    phi = torch.where(phi > math.pi, phi - 2.0 * math.pi, phi)  # symmetric about the anchor
    arg = m[:, None] * phi[None, :]
    weight = torch.hypot(yr, yi) / m if kernel is None else kernel.expand_as(yr)
    h = torch.cat([weight * yr, weight * yi], -1) @ torch.cat([torch.cos(arg), -torch.sin(arg)], 0)
    k = h.argmax(-1, keepdim=True)
    hm, h0, hp = h.gather(-1, torch.remainder(k + torch.arange(-1, 2, device=k.device), size)).unbind(-1)
    curv = (hm - 2.0 * h0 + hp).clamp(max=-torch.finfo(h.dtype).tiny)  # < 0 at a maximum
    offset = (0.5 * (hm - hp) / curv).clamp(-0.5, 0.5)
    return anchor + (phi[k[:, 0]] + offset * (2.0 * math.pi / size))[:, None]


def _start(yr: Tensor, yi: Tensor, bands: tuple[int, ...], kernel: Tensor | None = None) -> Tensor:
    """Start ``(B, D)``: per axis, the grid start on that axis's marginal spectrum (weighted by
    the ``kernel (P,)`` there, if given)."""
    columns = []
    for axis, band in enumerate(bands):
        index = [e - 1 for e in axis_rows(bands, axis, all_rows=False)[0][1:]]  # m = 1..M, unconjugated
        weight = None if kernel is None else kernel[index]
        columns.append(_grid_start(yr[:, index], yi[:, index], band, weight))
    return torch.cat(columns, -1)


def _iterate(yr, yi, freq, bands, theta, weights, refits=range(ITERATIONS)):
    """Fixed-count Newton iterations on ``theta``.

    ``weights(r, i) -> w`` per coefficient, recomputed at the iterations in ``refits`` and kept
    in between: the step is ``-(sum w R F F^T)^{-1} sum w I F`` (Newton on the matched filter
    ``sum w R``), with the Gauss-Newton curvature ``sum w^2 F F^T`` where that is not positive
    definite (far from a peak). Returns ``theta`` and the last weights.
    """
    limit = torch.tensor([math.pi / (4.0 * band) for band in bands], dtype=yr.dtype, device=yr.device)
    w = None
    for k in range(ITERATIONS):
        r, i = _rotate(yr, yi, freq, theta)
        if w is None or k in refits:
            w = weights(r, i)
        theta = theta + _newton_step(w, w * r, w * w, i, freq).clamp(-limit, limit)
    return theta, w


def _pick_peak(yr: Tensor, yi: Tensor, freq: Tensor, theta: Tensor) -> Tensor:
    """Of ``theta + pi s``, ``s`` in ``{0, 1}^D``, the one where the matched filter peaks."""
    dims = freq.shape[1]
    mag = torch.sqrt(yr**2 + yi**2)
    best, best_h = theta, None
    for s in torch.cartesian_prod(*[torch.tensor([0.0, math.pi], dtype=yr.dtype, device=yr.device)] * dims).reshape(
        -1, dims
    ):
        candidate = theta + s
        h = (mag * _rotate(yr, yi, freq, candidate)[0]).sum(-1)
        if best_h is None:
            best, best_h = candidate, h
        else:
            best = torch.where((h > best_h)[:, None], candidate, best)
            best_h = torch.maximum(h, best_h)
    return best


# --- root methods -------------------------------------------------------------------------


def _root(y: Tensor, dc: Tensor, bands: tuple[int, ...], method: str) -> Tensor:
    """``theta (B, D)`` from the common root of every row along each axis."""
    table = torch.cat([dc.abs().to(y.dtype)[:, None], y, y.conj()], -1)
    theta = []
    for axis in range(len(bands)):
        seq = table[:, torch.tensor(axis_rows(bands, axis), device=y.device)]  # (B, S, M + 1)
        if method == "cadzow":
            seq = cadzow(seq, 1, CADZOW_ITERATIONS)
        if method == "ls":  # the paper's equation (5): least-squares annihilation, summed over rows
            z = (seq[..., 1:] * seq[..., :-1].conj()).sum((-2, -1))
        else:
            v = signal_subspace(hankel(seq, rows_for(seq.shape[-1], 1)), 1)[..., 0]
            z = (v[..., :-1].conj() * v[..., 1:]).sum(-1)
        theta.append(-torch.angle(z))  # Y_m = a_m e^{-i m theta}: the root is e^{-i theta}
    return torch.stack(theta, -1)


def _aliasing(r: Tensor, i: Tensor, b: Tensor, w: Tensor, noise: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """1D uniform samples: the error of ``theta`` that aliasing explains, ``(variance (B, 1),
    noise (B,))``: its square (the fitted alias times its effect on ``theta``), added to the
    predicted variance, and the noise variance that would cause as large an error beyond what
    noise alone fits, added to the noise of the SNR behind quality.

    Point samples of a kernel whose spectrum has not died out by the Nyquist index hold, in
    coefficient ``m``, the alias ``a_{N-m} e^{i (N - m) theta}``: rotated back, ``c_m = a_m +
    a_{N-m} e^{i N theta}``, so the imaginary parts carry ``s p_m`` with ``s = sin(N theta)`` and
    ``p_m = a_{N-m}``, which looks like noise but is not spread like it: it grows with ``m``,
    where the matched filter weighs most. ``p`` is the estimated spectrum ``b`` continued
    geometrically from its last two coefficients (an upper bound for log-concave spectra:
    Gaussian, Lorentzian); ``s`` is fitted to the residual beside the shift it causes (``m b_m``).
    Lowpass samples leave ``s = 0`` (up to noise), so they are not penalised.
    """
    m = torch.arange(1, b.shape[-1] + 1, dtype=b.dtype, device=b.device)
    top = b.shape[-1]
    mag = b.abs()
    ratio = _safe_div(mag[:, -1:], mag[:, -2:-1]).clamp(0.0, 1.0)  # (B, 1)
    p = mag[:, -1:] * ratio ** ((size - m) - top)  # (B, M): a_{N-m}, continued
    shift = m * r  # the residual's response to a shift of theta
    # Least squares of i on [p, shift]: the 2 x 2 normal equations per problem.
    spp, sss, sps = (p * p).sum(-1), (shift * shift).sum(-1), (p * shift).sum(-1)
    sip, sis = (i * p).sum(-1), (i * shift).sum(-1)
    det = spp * sss - sps * sps
    s = _safe_div(sip * sss - sis * sps, det)  # the alias's amplitude, sin(N theta) when it is one
    gain = _safe_div((w * p * m).sum(-1), (w * r * m * m).sum(-1))  # theta's error per unit s
    spread = _safe_div(sss, det) * noise[:, 0]  # var(s) from noise alone
    beyond = (s * s - spread).clamp(min=0.0) * gain * gain
    return (s * s * gain * gain)[:, None], beyond * (b * b * m * m).sum(-1)  # variance x information


@dataclass(frozen=True)
class SinglePulse:
    """One pulse located in each of ``B`` problems (:func:`locate_single`).

    Attributes:
        theta: ``(B, D)`` its position in radians (not wrapped).
        variance: ``(B, D)`` the variance of ``theta`` predicted from the data.
        snr: ``(B,)`` the energy of the estimated spectrum over the noise variance.
    """

    theta: Tensor
    variance: Tensor
    snr: Tensor


def _locate_chunk(y, dc, freq, bands, dictionary, method, size=None, kernel=None) -> SinglePulse:
    yr, yi = y.real, y.imag
    dims = len(bands)
    start = _start(yr, yi, bands, kernel) if method in ("coherent", "ml") else None
    if kernel is not None:  # the known-kernel maximum likelihood; the spectrum is its LS multiple
        theta, _ = _iterate(yr, yi, freq, bands, start, lambda r, i: kernel.expand_as(r), (0,))
    elif method == "coherent":
        # One envelope, fitted at the start: refitting it later changed nothing measurable.
        theta, b = _iterate(yr, yi, freq, bands, start, lambda r, i: _envelope(r, _noise(i, dims), dictionary), (0,))
    elif method == "ml":
        theta, _ = _iterate(yr, yi, freq, bands, start, lambda r, i: r)
        theta = _pick_peak(yr, yi, freq, theta)
    else:
        theta = _pick_peak(yr, yi, freq, _root(y, dc, bands, method))
    r, i = _rotate(yr, yi, freq, theta)
    noise = _noise(i, dims)
    if kernel is not None:
        b = (r @ kernel / (kernel @ kernel)).clamp(min=0.0)[:, None] * kernel
    elif method != "coherent":
        b = _envelope(r, noise, dictionary)
    info = (b * b) @ (freq[:, :, None] * freq[:, None, :]).reshape(-1, dims * dims)  # Fisher x noise
    if dims == 1:
        det = info[:, 0]
        variance = _safe_div(noise, info)
    else:
        det = info[:, 0] * info[:, 3] - info[:, 1] ** 2
        variance = noise * torch.stack([_safe_div(info[:, 3], det), _safe_div(info[:, 0], det)], -1)
    variance = torch.where((det > 0)[:, None], variance, torch.full_like(variance, math.inf))
    alias = torch.zeros_like(theta[:, 0])
    if dims == 1 and size is not None and bands[0] >= 2:
        excess, alias = _aliasing(r, i, b, b, noise, size)
        variance = variance + excess
    snr = (b * b).sum(-1) / (noise[:, 0] + alias)  # inf without residual degrees of freedom
    return SinglePulse(theta=theta, variance=variance, snr=snr)


def locate_single(
    y: Tensor, dc: Tensor, bands: tuple[int, ...], method: str, size: int | None = None, kernel: Tensor | None = None
) -> SinglePulse:
    """Locate one pulse (:class:`SinglePulse`).

    Args:
        y: ``(B, P)`` complex coefficients in the order of ``frequency_list(bands)``.
        dc: ``(B,)`` the DC term (root methods only).
        bands: ``(M,)`` or ``(M1, M2)``.
        method: ``coherent``, ``ml``, ``ls``, ``esprit`` or ``cadzow``.
        size: ``N``, the uniform samples per period of a 1D problem: the variance and the SNR
            then include what aliasing explains (:func:`_aliasing`); ``None`` (2D, scattered)
            checks no aliasing.
        kernel: ``(P,)`` the kernel's spectrum at the coefficients (any scale, not all zero),
            shared by every problem: ``coherent`` then weighs the coefficients by it (the
            known-kernel maximum likelihood) instead of by an envelope fitted per problem.

    Returns:
        ``theta (B, D)`` in radians (not wrapped); its ``variance (B, D)`` predicted from the
        data, the noise measured in the imaginary residual (``P - D`` degrees of freedom) over
        the Fisher information of the estimated spectrum, ``inf`` where that information is
        zero and 0 with no residual degrees of freedom (one coefficient in 1D); and ``snr (B,)``,
        the energy of the estimated spectrum over that noise variance. With ``size``, the
        variance adds the error the fitted alias explains and the SNR counts the alias beyond
        noise as noise (:func:`_aliasing`).
    """
    freq = frequencies(bands, y.real)
    dictionary = _dictionary(freq, bands)
    if y.shape[0] == 0:
        empty = y.real.new_zeros(0, len(bands))
        return SinglePulse(theta=empty, variance=empty, snr=empty[:, 0])
    # Chunks keep the per-problem intermediates (P x atoms) in cache and bound memory.
    chunks = zip(y.split(CHUNK), dc.split(CHUNK), strict=True)
    parts = [_locate_chunk(yc, dcc, freq, bands, dictionary, method, size, kernel) for yc, dcc in chunks]
    return SinglePulse(
        theta=torch.cat([p.theta for p in parts]),
        variance=torch.cat([p.variance for p in parts]),
        snr=torch.cat([p.snr for p in parts]),
    )


def pool_kernel(y: Tensor, theta: Tensor, bands: tuple[int, ...], weight: Tensor) -> Tensor:
    """The spectrum shared by every problem: ``(P,)``, unit norm (zeros if nothing is left).

    Each problem's coefficients rotated back by its ``theta (B, D)`` leave its spectrum in the
    real parts ``R (B, P)``, noise aside; their quality-``weight``ed (``(B,)``, >= 0) mean is a
    first estimate ``s``, and one power-iteration step (each problem weighed again by its
    amplitude along ``s``) lets the strong problems lead, so that problems holding only noise
    (whose ``R`` leans towards whatever envelope located them) barely count.
    """
    r = _rotate(y.real, y.imag, frequencies(bands, y.real), theta)[0]
    s = weight @ r
    amplitude = (r @ s).clamp(min=0.0) * weight
    s = amplitude @ r
    norm = s.norm()
    return torch.where(norm > 0, s / torch.where(norm > 0, norm, torch.ones_like(norm)), torch.zeros_like(s))
