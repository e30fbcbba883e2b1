"""Periodic pulses and their lowpass samples: the signal model of FRI location.

A pulse ``p`` of unit area, centred on ``x`` and repeated with period ``tau``, has the
Fourier-series coefficients ``a_m e^{-i 2 pi m x / tau}`` with ``a_m = P(m / tau) / tau``
real and even in ``m`` when ``p`` is symmetric. Its *lowpass samples* keep ``|m| <= M``:

    s(t) = sum_{|m| <= M} a_m cos(2 pi m (t - x) / tau)

This is the sampling model of classical FRI (a Dirichlet / sinc sampling kernel) and of the
Cramer-Rao bounds in :mod:`torchspec.model.crb`: ``N >= 2M + 1`` uniform samples of it hold every
coefficient without aliasing. Point samples of a pulse that is not bandlimited alias, and
the location then carries a model error (studied in ``experiments/``, not hidden here).

Used by the tests, the experiments and the benchmarks to plant pulses with a known answer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from ...errors import TorchspecError

__all__ = ["KINDS", "spectrum", "outer", "sample", "sample_2d"]

KINDS = ("gaussian", "lorentzian", "box", "triangle", "raised-cosine")


def _sinc(x: Tensor) -> Tensor:
    return torch.sinc(x)


def spectrum(kind: str, width: Tensor, num_coefficients: int, *, period: float = 1.0) -> Tensor:
    """Fourier-series coefficients ``a_m``, ``m = 0..M``, of a unit-area periodic pulse.

    Args:
        kind: one of :data:`KINDS`. ``width`` means: gaussian, the standard deviation;
            lorentzian, the half width at half maximum (its spectrum is geometric,
            ``a_m = r^m / tau`` with ``r = exp(-2 pi width / tau)``); box, the full width;
            triangle, the half base; raised-cosine, the full support of ``1 + cos``.
        width: ``(*)`` tensor of widths, same units as ``period``; it sets dtype and device.
        num_coefficients: ``M >= 0``.
        period: ``tau > 0``.

    Returns:
        ``(*, M + 1)``: ``a_0 .. a_M`` (``a_0 = 1 / tau``).

    Example:
        >>> a = spectrum("gaussian", torch.tensor(0.05, dtype=torch.float64), 8)
        >>> a.shape
        torch.Size([9])
    """
    if kind not in KINDS:
        raise TorchspecError(f"kind must be one of {KINDS}; got {kind!r}.")
    if not isinstance(width, Tensor):
        raise TypeError(
            f"width must be a tensor (it sets dtype and device); got {type(width).__name__}. "
            "Pass e.g. torch.tensor(0.05, dtype=torch.float64)."
        )
    if num_coefficients < 0:
        raise TorchspecError(f"num_coefficients must be >= 0; got {num_coefficients}.")
    if not period > 0:
        raise TorchspecError(f"period must be > 0; got {period}.")
    m = torch.arange(num_coefficients + 1, dtype=width.dtype, device=width.device)
    f = m / period  # frequency in cycles per unit
    w = width[..., None]
    if kind == "gaussian":
        a = torch.exp(-2.0 * math.pi**2 * (w * f) ** 2)
    elif kind == "lorentzian":
        a = torch.exp(-2.0 * math.pi * w * f)
    elif kind == "box":
        a = _sinc(w * f)
    elif kind == "triangle":
        a = _sinc(w * f) ** 2
    else:  # raised-cosine: FT of (1 + cos(2 pi t / w)) / w on |t| < w / 2
        x = w * f
        near = (x.abs() - 1.0).abs() < 1e-6
        safe = torch.where(near, torch.zeros_like(x), x)
        a = torch.where(near, torch.full_like(x, 0.5), _sinc(safe) / (1.0 - safe**2))
    return a / period


def outer(first: Tensor, second: Tensor) -> Tensor:
    """The full 2D spectrum of a separable pulse from two 1D half spectra.

    Args:
        first: ``(*, M1 + 1)`` coefficients ``a_0..a_M1`` along axis 1.
        second: ``(*, M2 + 1)`` along axis 2.

    Returns:
        ``(*, 2 M1 + 1, 2 M2 + 1)`` indexed by ``(m1 + M1, m2 + M2)``.
    """
    full1 = torch.cat([first[..., 1:].flip(-1), first], dim=-1)
    full2 = torch.cat([second[..., 1:].flip(-1), second], dim=-1)
    return full1[..., :, None] * full2[..., None, :]


def _grid(num_samples: int, period: float, like: Tensor) -> Tensor:
    return torch.arange(num_samples, dtype=like.dtype, device=like.device) * (period / num_samples)


def sample(
    spectrum: Tensor,
    location: Tensor,
    *,
    num_samples: int | None = None,
    positions: Tensor | None = None,
    amplitude: Tensor | None = None,
    period: float = 1.0,
) -> Tensor:
    """Lowpass samples of a sum of K symmetric periodic pulses (1D).

    Args:
        spectrum: ``a_0..a_M`` of each pulse, broadcastable to ``(*, K, M + 1)``.
        location: ``(*, K)`` pulse centres (``K = 1`` for one pulse).
        num_samples: ``N`` uniform samples at ``t_n = n * period / N``; or give ``positions``.
        positions: ``(N,)`` or ``(*, N)`` sample positions (scattered layouts).
        amplitude: pulse weights broadcastable to ``(*, K)``; ones by default.
        period: ``tau``.

    Returns:
        ``(*, N)`` noise-free samples.

    Example:
        >>> a = spectrum("gaussian", torch.tensor(0.05, dtype=torch.float64), 8)
        >>> sample(a, torch.tensor([0.3], dtype=torch.float64), num_samples=17).shape
        torch.Size([17])
    """
    if (num_samples is None) == (positions is None):
        raise TorchspecError("give exactly one of num_samples and positions.")
    t = _grid(num_samples, period, location) if positions is None else positions  # (N,) or (*, N)
    m = torch.arange(spectrum.shape[-1], dtype=location.dtype, device=location.device)
    weight = torch.where(m == 0, 1.0, 2.0) * spectrum  # (*, K, M + 1)
    phase = (2.0 * math.pi / period) * m * (t[..., None, :, None] - location[..., :, None, None])  # (*, K, N, M+1)
    values = (weight[..., None, :] * torch.cos(phase)).sum(-1)  # (*, K, N)
    if amplitude is not None:
        values = amplitude[..., None] * values
    return values.sum(-2)


def sample_2d(
    spectrum: Tensor,
    location: Tensor,
    *,
    shape: Sequence[int] | None = None,
    positions: Tensor | None = None,
    amplitude: Tensor | None = None,
    period: Sequence[float] = (1.0, 1.0),
) -> Tensor:
    """Lowpass samples of one centrally symmetric 2D periodic pulse.

    Args:
        spectrum: ``(*, 2 M1 + 1, 2 M2 + 1)`` real coefficients, even in ``m`` (see :func:`outer`).
        location: ``(*, 2)``.
        shape: ``(N1, N2)`` uniform grid at ``(n1 tau1 / N1, n2 tau2 / N2)``; or ``positions``.
        positions: ``(N, 2)`` or ``(*, N, 2)`` scattered sample positions.
        amplitude: ``(*)`` pulse weight.
        period: ``(tau1, tau2)``.

    Returns:
        ``(*, N1, N2)`` on a grid, ``(*, N)`` at scattered positions.
    """
    if (shape is None) == (positions is None):
        raise TorchspecError("give exactly one of shape and positions.")
    m1 = torch.arange(spectrum.shape[-2], dtype=location.dtype, device=location.device) - spectrum.shape[-2] // 2
    m2 = torch.arange(spectrum.shape[-1], dtype=location.dtype, device=location.device) - spectrum.shape[-1] // 2
    amp = torch.ones_like(location[..., 0]) if amplitude is None else amplitude
    if positions is None:
        t1 = _grid(shape[0], period[0], location)
        t2 = _grid(shape[1], period[1], location)
        p1 = (2 * math.pi / period[0]) * (t1[:, None] - location[..., 0, None, None]) * m1  # (*, N1, 2M1+1)
        p2 = (2 * math.pi / period[1]) * (t2[:, None] - location[..., 1, None, None]) * m2  # (*, N2, 2M2+1)
        # cos(p1 + p2) = cos p1 cos p2 - sin p1 sin p2, so the sum factors into matrix products.
        values = torch.cos(p1) @ spectrum @ torch.cos(p2).transpose(-1, -2)
        values = values - torch.sin(p1) @ spectrum @ torch.sin(p2).transpose(-1, -2)
        return amp[..., None, None] * values
    p1 = (2 * math.pi / period[0]) * (positions[..., 0, None] - location[..., 0, None, None]) * m1  # (*, N, 2M1+1)
    p2 = (2 * math.pi / period[1]) * (positions[..., 1, None] - location[..., 1, None, None]) * m2
    values = torch.einsum("...na,...ab,...nb->...n", torch.cos(p1), spectrum, torch.cos(p2))
    values = values - torch.einsum("...na,...ab,...nb->...n", torch.sin(p1), spectrum, torch.sin(p2))
    return amp[..., None] * values
