"""Finite-rate-of-innovation location of blurred peaks.

A peak blurred by an unknown *symmetric* kernel keeps its location in the phase of its
Fourier coefficients: ``Y[m] = a_m e^{-i 2 pi m x / tau}`` with the kernel's spectrum ``a_m``
real. A handful of samples of the blurred peak therefore locate it exactly, where point-wise
sampling would only bracket it. :func:`locate` does this for any batch of 1D or 2D problems.

References:
    "Accurate recovery of a specularity from a few samples of the reflectance function",
    ICASSP 2016 (EPFL): the method this package is built on (Sec. 3-4, Fig. 2).
    Vetterli, Marziliano, Blu, "Sampling signals with finite rate of innovation", IEEE TSP 2002.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ...errors import TorchspecError
from . import pulses
from ._coefficients import frequency_list, scattered, uniform
from ._multi import locate_multi
from ._single import locate_single, pool_kernel

__all__ = ["Location", "METHODS", "estimate_kernel", "locate", "pulses"]

METHODS = ("coherent", "ml", "ls", "esprit", "cadzow")
"""``coherent`` is the default for one pulse, ``esprit`` for several; ``coherent`` and ``ml``
locate one pulse only."""

SNR_HALF_QUALITY = 20.0
"""The SNR of the fitted spectrum (its energy over the residual noise variance) at which quality
is 1/2: below it, outliers (error above a tenth of the period) become common on the paper's setups
(Gaussian kernels, M = 2 and 8)."""


@dataclass(frozen=True)
class Location:
    """The result of :func:`locate`.

    Attributes:
        position: ``(*)`` in 1D, ``(*, 2)`` in 2D, ``(*, K)`` for K pulses (ascending), in
            ``[0, period)``; NaN where the samples were not finite.
        quality: ``(*)`` in ``[0, 1]``: 1 for a clean, well-conditioned problem, falling as the
            residual that a symmetric pulse cannot explain grows against the explained part
            (noise, an asymmetric kernel, a second peak) or as a scattered layout loses
            conditioning; 0 for non-finite samples. Mask with e.g. ``quality > 0.5``, which flags
            most outliers (error > period / 10) on the paper's setups with M = 8.
            With a single coefficient per axis (N <= 4) nothing is left over to measure the
            noise, so quality then only reflects conditioning. For K >= 2 it is
            ``(1 - s_{K+1} / s_K)^2`` from the singular values of the Hankel matrix.
        std: like ``position``: the standard deviation of the position predicted from the data
            (residual noise over the Fisher information of the estimated spectrum). The noise
            is measured on ``P - D`` degrees of freedom (``P`` coefficients, ``D`` dims), so
            ``error / std`` follows a Student t with that many; NaN for K >= 2. For 1D uniform
            samples it adds the error that aliasing explains: point samples of a kernel whose
            spectrum has not died out by the Nyquist index hold aliases in their coefficients,
            which bias the position (``experiments/fri_aliasing.py``); the alias beyond noise
            also counts as noise in ``quality``.
    """

    position: Tensor
    quality: Tensor
    std: Tensor


def _is_real(value) -> bool:
    if isinstance(value, Tensor):
        return value.dim() == 0 and not value.is_complex() and value.dtype != torch.bool
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _periods(period) -> tuple[float, ...]:
    values = tuple(period) if isinstance(period, Sequence) else (period,)
    if len(values) not in (1, 2):
        raise TorchspecError(f"period must be a number (1D) or a pair (2D); got {period!r}.")
    for p in values:
        if not _is_real(p) or not math.isfinite(float(p)) or float(p) <= 0:
            raise TorchspecError(f"period must be finite and > 0; got {period!r}.")
    return tuple(float(p) for p in values)


def _bands(num_coefficients, dims: int, *, grid: tuple[int, ...] | None, scattered: int = 0) -> tuple[int, ...]:
    """``(M,)`` or ``(M1, M2)``: given, or the default for a ``grid`` or ``scattered`` samples."""
    if num_coefficients is None:
        if grid is not None:
            return tuple(max((n - 1) // 2, 1) for n in grid)
        # About twice as many samples as real unknowns keeps a random layout conditioned.
        if dims == 1:
            return (max((scattered // 2 - 1) // 2, 1),)
        side = max((math.isqrt(max(scattered // 2, 1)) - 1) // 2, 1)
        return (side, side)

    def integral(v) -> bool:
        return isinstance(v, numbers.Integral) and not isinstance(v, bool)

    values = (num_coefficients,) * dims if integral(num_coefficients) else tuple(num_coefficients)
    if len(values) != dims or not all(integral(v) for v in values):
        raise TorchspecError(
            f"num_coefficients must be an int or {dims} ints for a {dims}D problem; got {num_coefficients!r}."
        )
    values = tuple(int(v) for v in values)
    if min(values) < 1:
        raise TorchspecError(f"num_coefficients must be >= 1; got {num_coefficients!r}.")
    return values


def _check_samples(samples) -> Tensor:
    samples = torch.as_tensor(samples)  # a tensor keeps its device; a list or array lands on the CPU
    if samples.is_complex() or samples.dtype not in (torch.float32, torch.float64):
        raise TorchspecError(
            f"samples must be a real float32 or float64 tensor; got {samples.dtype}. "
            "Convert with .float() or .double()."
        )
    return samples


def locate(
    samples: Tensor,
    *,
    period: float | Sequence[float],
    method: str | None = None,
    num_coefficients: int | Sequence[int] | None = None,
    positions: Tensor | None = None,
    num_pulses: int = 1,
    kernel: Tensor | str | None = None,
) -> Location:
    """Locate the peak(s) of blurred pulses from a few samples, batched over any leading dims.

    The samples are of a periodic signal (period ``tau``): one pulse blurred by an unknown
    symmetric kernel, plus any constant offset (a negative one too: the DC term is never
    used). Exact without noise whenever the samples hold the coefficients ``|m| <= M``
    without aliasing (lowpass samples, or a kernel narrow against ``tau / N``).

    Args:
        samples: 1D ``(*, N)`` at ``t_n = n * period / N``; 2D ``(*, N1, N2)`` at
            ``(n1 tau1 / N1, n2 tau2 / N2)``; scattered ``(*, N)`` at ``positions``.
            float32 or float64, on any device; the result follows.
        period: ``tau`` (1D) or ``(tau1, tau2)`` (2D).
        method: one of :data:`METHODS`; ``None`` picks ``coherent`` (one pulse) or ``esprit``.
        num_coefficients: ``M`` (or ``(M1, M2)``): Fourier coefficients ``m = 1..M`` used.
            Default: every bin below Nyquist, ``(N - 1) // 2`` (the Nyquist bin of an even N is
            real and carries no phase); for scattered layouts the largest band with about two
            samples per unknown.
        positions: scattered sample positions, ``(N,)`` shared or ``(*, N)`` per problem in 1D,
            ``(N, 2)`` or ``(*, N, 2)`` in 2D. Coefficients come from regularised least
            squares; the layout's condition number lowers ``quality``.
        num_pulses: ``K``; ``K >= 2`` (1D, uniform or scattered) assumes geometric spectra
            (Lorentzian kernels) and needs ``M >= 2K``.
        kernel: the kernel's spectrum, shared by every problem, for ``coherent`` (one pulse):
            its coefficients are then weighed by it (the known-kernel maximum likelihood,
            efficient down to lower SNR) instead of by an envelope fitted to each problem's own
            noisy coefficients. Laid out as :func:`pulses.spectrum` (1D, ``(K + 1,)``: ``a_0..a_K``)
            or :func:`pulses.outer` (2D, ``(2 K1 + 1, 2 K2 + 1)`` centred) with ``K >= M``
            per axis; any scale; ``a_0`` is not used. ``"pooled"`` estimates it first from all
            the problems with :func:`estimate_kernel` (a tile whose pixels share one kernel);
            where that finds nothing (no finite, non-flat problem) each problem is on its own.

    Returns:
        :class:`Location` with ``position``, ``quality`` and ``std``.

    Raises:
        TorchspecError: a malformed call, naming the argument and shape at fault. Per-problem
            trouble (non-finite samples, a rank-deficient per-problem layout) is not raised:
            that problem gets a NaN position and zero quality.

    Example:
        >>> a = pulses.spectrum("gaussian", torch.tensor(0.05, dtype=torch.float64), 8)
        >>> y = pulses.sample(a, torch.tensor([[0.3]], dtype=torch.float64), num_samples=17)
        >>> round(float(locate(y, period=1.0).position[0]), 12)
        0.3

    References:
        "Accurate recovery of a specularity from a few samples of the reflectance function",
        ICASSP 2016, Sec. 3-4.
    """
    if isinstance(kernel, str) and kernel == "pooled":
        kernel = estimate_kernel(samples, period=period, num_coefficients=num_coefficients, positions=positions)
        if not bool((kernel != 0).any()):  # nothing to pool (no finite problem, or flat ones)
            kernel = None
    call = _parse(samples, period, method, num_coefficients, positions, num_pulses, kernel)
    samples, dims = call.samples, len(call.periods)
    out_tail = () if (dims == 1 and num_pulses == 1) else ((dims,) if num_pulses == 1 else (num_pulses,))
    if math.prod(call.batch) == 0:
        empty = samples.new_zeros((*call.batch, *out_tail))
        return Location(position=empty, quality=samples.new_zeros(tuple(call.batch)), std=empty.clone())
    found = _coefficients_of(call)
    y, dc, finite, condition = found.y, found.dc, found.finite, found.condition

    scale = torch.tensor(call.periods, dtype=y.real.dtype, device=y.device) / (2.0 * math.pi)
    if num_pulses == 1:
        size = call.samples.shape[-1] if call.positions is None and dims == 1 else None
        pulse = locate_single(y, dc, call.bands, call.method, size, call.kernel)
        theta, std = pulse.theta, pulse.variance.sqrt() * scale
        quality = _quality(pulse.snr, condition, finite)
    else:
        theta, gap = locate_multi(y, num_pulses, call.method)
        std = torch.full_like(theta, math.nan)
        quality = (1.0 - gap).clamp(0.0, 1.0) ** 2
    period = scale * (2.0 * math.pi)
    position = torch.remainder(theta * scale, period)
    position = torch.where(position >= period, position - period, position)  # rounding up to the period
    if num_pulses > 1:
        position = position.sort(-1).values
    if num_pulses > 1:
        quality = _conditioned(quality, condition, finite)
    position = torch.where(finite[:, None], position, torch.full_like(position, math.nan))
    std = torch.where(finite[:, None], std, torch.full_like(std, math.nan))
    return Location(
        position=position.reshape((*call.batch, *out_tail)),
        quality=quality.reshape(tuple(call.batch)),
        std=std.reshape((*call.batch, *out_tail)),
    )


def _conditioned(quality: Tensor, condition: Tensor, finite: Tensor) -> Tensor:
    """``quality`` lowered by the layout's ``condition`` number, 0 for non-finite problems."""
    quality = quality / (1.0 + condition * math.sqrt(torch.finfo(quality.dtype).eps))
    return torch.where(finite & torch.isfinite(quality), quality, torch.zeros_like(quality)).clamp(0.0, 1.0)


def _quality(snr: Tensor, condition: Tensor, finite: Tensor) -> Tensor:
    """One pulse's quality from the SNR of its fitted spectrum (see :data:`SNR_HALF_QUALITY`)."""
    return _conditioned(1.0 / (1.0 + (SNR_HALF_QUALITY / snr) ** 3), condition, finite)


def estimate_kernel(
    samples: Tensor,
    *,
    period: float | Sequence[float],
    num_coefficients: int | Sequence[int] | None = None,
    positions: Tensor | None = None,
) -> Tensor:
    """The spectrum of a kernel shared by every problem of the batch, pooled over all of them.

    Each problem is located with the default method, its coefficients rotated back by its
    location (which leaves its spectrum, times its amplitude, plus noise), and the spectra are
    averaged, each weighed by its quality and by its amplitude. At low SNR the mean of many
    problems is far less noisy than the envelope that :func:`locate` fits to one, so
    ``locate(samples, period=..., kernel=estimate_kernel(samples, period=...))`` (or
    ``kernel="pooled"``) stays near the Cramer-Rao bound down to lower SNR, when the problems
    do share a kernel (amplitudes and offsets may differ).

    Args:
        samples, period, num_coefficients, positions: as in :func:`locate` (one pulse).

    Returns:
        1D ``(M + 1,)`` as :func:`pulses.spectrum` lays it out, 2D ``(2 M1 + 1, 2 M2 + 1)`` as
        :func:`pulses.outer`: the spectrum at ``m = 1..M`` with unit norm over the
        coefficients used (2D: over one half-plane) and ``a_0 = 0`` (not estimated: the mean
        of the samples holds any offset). All zeros if no problem is finite.

    Raises:
        TorchspecError: as :func:`locate`.

    Example:
        >>> a = pulses.spectrum("gaussian", torch.tensor(0.1, dtype=torch.float64), 4)
        >>> y = pulses.sample(a, torch.rand(64, 1, dtype=torch.float64), num_samples=9)
        >>> torch.allclose(estimate_kernel(y, period=1.0)[1:], a[1:] / a[1:].norm())
        True
    """
    call = _parse(samples, period, None, num_coefficients, positions, 1, None)
    like = call.samples
    if math.prod(call.batch) == 0:
        return kernel_layout(like.new_zeros(len(frequency_list(call.bands))), call.bands)
    found = _coefficients_of(call)
    size = like.shape[-1] if call.positions is None and len(call.bands) == 1 else None
    pulse = locate_single(found.y, found.dc, call.bands, "coherent", size)
    weight = _quality(pulse.snr, found.condition, found.finite)
    theta = torch.where(found.finite[:, None], pulse.theta, torch.zeros_like(pulse.theta))
    return kernel_layout(pool_kernel(found.y, theta, call.bands, weight), call.bands)


def kernel_layout(vector: Tensor, bands: tuple[int, ...]) -> Tensor:
    """A spectrum ``(P,)`` in the order of the coefficients laid out as :func:`pulses.spectrum`
    (1D) or :func:`pulses.outer` (2D, filled by symmetry), ``a_0 = 0``."""
    if len(bands) == 1:
        return torch.cat([vector.new_zeros(1), vector])
    out = vector.new_zeros(2 * bands[0] + 1, 2 * bands[1] + 1)
    for p, (m1, m2) in enumerate(frequency_list(bands)):
        out[bands[0] + m1, bands[1] + m2] = vector[p]
        out[bands[0] - m1, bands[1] - m2] = vector[p]
    return out


def _kernel_vector(kernel, bands: tuple[int, ...], like: Tensor) -> Tensor:
    """``kernel`` laid out as :func:`pulses.spectrum` / :func:`pulses.outer`, checked, as ``(P,)``."""
    if not isinstance(kernel, Tensor) or kernel.is_complex() or not kernel.dtype.is_floating_point:
        raise TorchspecError(
            f"kernel must be a real floating tensor (or 'pooled'); got {type(kernel).__name__}"
            f"{'' if not isinstance(kernel, Tensor) else ' of dtype ' + str(kernel.dtype)}."
        )
    kernel = kernel.to(dtype=like.dtype, device=like.device)
    if len(bands) == 1:
        want = f"(K + 1,) with K >= {bands[0]}"
        ok = kernel.dim() == 1 and kernel.shape[0] >= bands[0] + 1
    else:
        want = f"(2 K1 + 1, 2 K2 + 1) with K1 >= {bands[0]}, K2 >= {bands[1]}"
        ok = kernel.dim() == 2 and all(n % 2 == 1 and n >= 2 * b + 1 for n, b in zip(kernel.shape, bands, strict=True))
    if not ok:
        raise TorchspecError(
            f"kernel must have shape {want} for num_coefficients={bands} (laid out as "
            f"pulses.{'spectrum' if len(bands) == 1 else 'outer'}); got shape {tuple(kernel.shape)}."
        )
    if len(bands) == 1:
        vector = kernel[1 : bands[0] + 1]
    else:
        c1, c2 = kernel.shape[0] // 2, kernel.shape[1] // 2
        vector = torch.stack([kernel[c1 + m1, c2 + m2] for m1, m2 in frequency_list(bands)])
    if not bool(torch.isfinite(vector).all()) or not bool((vector != 0).any()):
        raise TorchspecError(
            f"kernel must be finite and not all zero at the coefficients used (num_coefficients={bands}); "
            f"got {vector.tolist()}."
        )
    return vector


class _Call(NamedTuple):
    samples: Tensor
    periods: tuple[float, ...]
    method: str
    bands: tuple[int, ...]
    batch: torch.Size
    positions: Tensor | None
    kernel: Tensor | None  # (P,)


def _parse(samples, period, method, num_coefficients, positions, num_pulses, kernel) -> _Call:
    """Check a call of :func:`locate`; raise :class:`~torchspec.errors.TorchspecError` naming the argument."""
    samples = _check_samples(samples)
    periods = _periods(period)
    dims = len(periods)
    if not isinstance(num_pulses, int) or isinstance(num_pulses, bool) or num_pulses < 1:
        raise TorchspecError(f"num_pulses must be an int >= 1; got {num_pulses!r}.")
    if method is None:
        method = "coherent" if num_pulses == 1 else "esprit"
    if method not in METHODS:
        raise TorchspecError(f"method must be one of {METHODS}; got {method!r}.")
    if num_pulses > 1 and method in ("coherent", "ml"):
        raise TorchspecError(
            f"method {method!r} locates one pulse; for num_pulses={num_pulses} use 'esprit', 'cadzow' or 'ls'."
        )
    if num_pulses > 1 and dims == 2:
        raise TorchspecError(f"num_pulses must be 1 in 2D; got {num_pulses}.")
    if kernel is not None and (method != "coherent" or num_pulses > 1):
        raise TorchspecError(
            f"kernel is used by method 'coherent' with one pulse only; got method={method!r}, num_pulses={num_pulses}."
        )

    if positions is None:
        if samples.dim() < dims:
            raise TorchspecError(
                f"samples must have at least {dims} dims ({'(*, N1, N2)' if dims == 2 else '(*, N)'}) "
                f"for period {period!r}; got shape {tuple(samples.shape)}."
            )
        sizes = tuple(samples.shape[samples.dim() - dims :])
        bands = _bands(num_coefficients, dims, grid=sizes)
        for axis, (n, m) in enumerate(zip(sizes, bands, strict=True)):
            if n < 2 * m + 1:
                raise TorchspecError(
                    f"samples has {n} samples along axis {axis - dims} (shape {tuple(samples.shape)}); "
                    f"locating a peak with {m} Fourier coefficient(s) needs at least 2M + 1 = {2 * m + 1} samples "
                    "along each axis. Give more samples (light positions), or fewer coefficients."
                )
        batch = samples.shape[: samples.dim() - dims]
    else:
        positions = torch.as_tensor(positions)  # a tensor keeps its device (checked below); a list: the CPU
        if positions.dtype != samples.dtype or positions.device != samples.device:
            raise TorchspecError(
                f"positions must match samples' dtype and device ({samples.dtype}, {samples.device}); "
                f"got ({positions.dtype}, {positions.device})."
            )
        if samples.dim() < 1:
            raise TorchspecError(f"samples must have shape (*, N) with positions; got shape {tuple(samples.shape)}.")
        n = samples.shape[-1]
        tail = (n,) if dims == 1 else (n, 2)
        if positions.dim() < len(tail) or tuple(positions.shape[positions.dim() - len(tail) :]) != tail:
            raise TorchspecError(
                f"positions must have shape {'(*, N)' if dims == 1 else '(*, N, 2)'} with N = {n} "
                f"(samples shape {tuple(samples.shape)}); got shape {tuple(positions.shape)}."
            )
        if not bool(torch.isfinite(positions).all()):
            raise TorchspecError("positions must be finite; got NaN or Inf.")
        bands = _bands(num_coefficients, dims, grid=None, scattered=n)
        unknowns = 1 + 2 * len(frequency_list(bands))
        if n < unknowns:
            raise TorchspecError(
                f"a scattered layout of {n} samples cannot resolve num_coefficients={bands}: "
                f"that is {unknowns} real unknowns. Pass fewer coefficients or more samples."
            )
        batch = samples.shape[:-1]
        if positions.dim() > len(tail):
            try:
                batch = torch.broadcast_shapes(batch, positions.shape[: positions.dim() - len(tail)])
            except RuntimeError:
                raise TorchspecError(
                    f"positions shape {tuple(positions.shape)} does not broadcast with samples shape "
                    f"{tuple(samples.shape)}."
                ) from None
    if num_pulses > 1 and bands[0] < 2 * num_pulses:
        raise TorchspecError(f"num_pulses={num_pulses} needs num_coefficients >= {2 * num_pulses}; got {bands[0]}.")
    vector = None if kernel is None else _kernel_vector(kernel, bands, samples)
    return _Call(samples, periods, method, bands, batch, positions, vector)


@dataclass(frozen=True)
class _Coefficients:
    """The Fourier coefficients of a call's ``B`` flattened problems (:func:`_coefficients_of`).

    Attributes:
        y: ``(B, P)`` complex, in the order of ``frequency_list(bands)`` (0 where not ``finite``).
        dc: ``(B,)`` the DC term (0 where not ``finite``).
        finite: ``(B,)`` bool, the problems with finite samples (and a resolvable layout).
        condition: ``(B,)`` the condition number of each problem's layout (1 for uniform samples).
    """

    y: Tensor
    dc: Tensor
    finite: Tensor
    condition: Tensor


def _coefficients_of(call: _Call) -> _Coefficients:
    """The :class:`_Coefficients` of the flattened problems, with the coefficients of non-finite
    problems (and of rank-deficient per-problem layouts) zeroed."""
    dims = len(call.periods)
    if call.positions is None:
        shape = call.samples.shape[call.samples.dim() - dims :]
        flat = call.samples.reshape(-1, *shape)
        y, dc = uniform(flat, call.bands)
        finite = torch.isfinite(dc)  # one NaN or Inf sample poisons the mean
        condition = torch.ones_like(dc)
    else:
        flat = call.samples.expand(*call.batch, call.samples.shape[-1]).reshape(-1, call.samples.shape[-1])
        tail = call.positions.shape[call.positions.dim() - dims :]
        shared = call.positions.dim() == dims
        layout = call.positions if shared else call.positions.expand(*call.batch, *tail).reshape(-1, *tail)
        finite = torch.isfinite(flat.sum(-1))  # one NaN or Inf sample poisons the sum
        y, dc, condition = scattered(torch.where(finite[:, None], flat, 0.0), layout, call.bands, call.periods)
        resolvable = condition * torch.finfo(flat.dtype).eps * max(flat.shape[-1], y.shape[-1]) < 1
        if shared:
            if not bool(resolvable):
                raise TorchspecError(
                    f"the scattered layout cannot resolve num_coefficients={call.bands}: its design matrix is "
                    f"rank-deficient (condition number {float(condition):.3g}); positions repeat or "
                    "cluster. Pass fewer coefficients or spread the positions."
                )
            condition = condition.expand(flat.shape[0])
        else:
            finite = finite & resolvable
    y = torch.where(finite[:, None], y, torch.zeros_like(y))
    dc = torch.where(finite, dc, torch.zeros_like(dc))
    return _Coefficients(y=y, dc=dc, finite=finite, condition=condition)
