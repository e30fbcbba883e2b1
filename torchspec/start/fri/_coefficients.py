"""Fourier-series coefficients of the samples: uniform grids by FFT, scattered layouts by
regularised least squares.

Every function returns the coefficients of positive frequency that FRI needs, normalised as
Fourier-series coefficients (``Y[m] = (1 / N) sum_n y_n e^{-i 2 pi m n / N}``), so that a
pulse ``a_m e^{-i 2 pi m x / tau}`` reads back as exactly that. ``Y[0]`` is never returned:
after a diffuse part is subtracted it holds an offset of either sign and no location.

Frequencies are rows of an integer-valued ``F (P, D)``. In 2D they cover one half-plane,
``{m2 > 0, |m1| <= M1} + {m2 = 0, 1 <= m1 <= M1}``: the other half is its complex conjugate.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["frequency_list", "frequencies", "axis_rows", "uniform", "scattered", "design_matrix"]


def frequency_list(bands: tuple[int, ...]) -> list[tuple[int, ...]]:
    """The frequencies for ``bands = (M,)`` or ``(M1, M2)``, in the order of every ``(B, P)``."""
    if len(bands) == 1:
        return [(m,) for m in range(1, bands[0] + 1)]
    m1_max, m2_max = bands
    return [
        (m1, m2)
        for m1 in range(-m1_max, m1_max + 1)
        for m2 in range(0, m2_max + 1)
        if m2 > 0 or m1 > 0
    ]


def frequencies(bands: tuple[int, ...], like: Tensor) -> Tensor:
    """``F (P, D)`` as a tensor with the dtype and device of ``like``."""
    return torch.tensor(frequency_list(bands), dtype=like.dtype, device=like.device)


def axis_rows(bands: tuple[int, ...], axis: int, *, all_rows: bool = True) -> list[list[int]]:
    """Rows of coefficients along ``axis``, ``m = 0..M`` there, one row per value of the other
    frequency (only the row through the origin with ``all_rows=False``).

    An entry indexes ``[Y_dc, Y_1..Y_P, conj(Y_1)..conj(Y_P)]``: 0 is the DC term and
    ``P + p + 1`` reads ``Y_p`` conjugated (``Y[-f] = conj(Y[f])`` for real samples).
    """
    freq = frequency_list(bands)
    position = {f: p + 1 for p, f in enumerate(freq)}
    zero = (0,) * len(bands)

    def entry(key):
        if key == zero:
            return 0
        if key in position:
            return position[key]
        return len(freq) + position[tuple(-c for c in key)]

    if len(bands) == 1:
        return [[entry((m,)) for m in range(bands[0] + 1)]]
    other_band = bands[1 - axis]
    values = range(-other_band, other_band + 1) if all_rows else [0]
    return [[entry((m, v) if axis == 0 else (v, m)) for m in range(bands[axis] + 1)] for v in values]


def uniform(samples: Tensor, bands: tuple[int, ...]) -> Tensor:
    """Coefficients of uniform samples.

    Args:
        samples: ``(B, N)`` or ``(B, N1, N2)`` real, taken at ``t_n = n tau / N``.
        bands: ``(M,)`` or ``(M1, M2)`` with ``2 M + 1 <= N`` on each axis.

    Returns:
        ``(Y (B, P) complex, in the order of :func:`frequency_list`; dc (B,) real)``.
    """
    if len(bands) == 1:
        spectrum = torch.fft.rfft(samples, dim=-1) / samples.shape[-1]
        return spectrum[..., 1 : bands[0] + 1], spectrum[..., 0].real
    n1, n2 = samples.shape[-2:]
    spectrum = (torch.fft.rfft2(samples, dim=(-2, -1)) / (n1 * n2)).flatten(-2)  # (B, N1 (N2 // 2 + 1))
    width = n2 // 2 + 1
    index = [(m1 % n1) * width + m2 for m1, m2 in frequency_list(bands)]
    return spectrum[..., index], spectrum[..., 0].real


def design_matrix(positions: Tensor, freq: Tensor, period: tuple[float, ...]) -> Tensor:
    """Real LS design matrix ``A (*, N, 1 + 2P)`` with unknowns ``[Y0, Re Y_p, Im Y_p]``.

    ``s(t) = Y0 + sum_p 2 (Re Y_p cos(phi_p) - Im Y_p sin(phi_p))``, ``phi_p = 2 pi F_p . t / tau``.
    """
    scale = torch.tensor([2.0 * math.pi / p for p in period], dtype=positions.dtype, device=positions.device)
    pos = positions[..., None] if len(period) == 1 else positions  # (*, N, D)
    phase = (pos * scale) @ freq.T  # (*, N, P)
    ones = torch.ones_like(phase[..., :1])
    return torch.cat([ones, 2.0 * torch.cos(phase), -2.0 * torch.sin(phase)], dim=-1)


def scattered(samples: Tensor, positions: Tensor, bands: tuple[int, ...], period: tuple[float, ...]):
    """Coefficients of scattered samples by Tikhonov-regularised least squares.

    The regularisation ``lambda = (eps * s_max)^2`` only keeps a nearly singular layout bounded;
    on a well-conditioned one the answer is the exact least-squares fit.

    Args:
        samples: ``(B, N)``.
        positions: ``(N,)`` / ``(N, 2)`` shared by all problems, or ``(B, N)`` / ``(B, N, 2)``.
        bands, period: as in :func:`uniform`.

    Returns:
        ``(Y (B, P) complex, dc (B,), condition (B,) or ())``: ``condition`` is the layout's
        condition number.
    """
    freq = frequencies(bands, samples)
    a = design_matrix(positions, freq, period)  # (N, Q) or (B, N, Q)
    u, s, vh = torch.linalg.svd(a, full_matrices=False)
    eps = torch.finfo(samples.dtype).eps
    lam = (eps * s[..., :1]) ** 2
    filt = s / (s**2 + lam)
    # x = V diag(filt) U^T y; a shared layout is one matrix for the whole batch.
    if a.dim() == 2:
        x = ((samples @ u) * filt) @ vh
    else:
        x = ((samples[..., None, :] @ u)[..., 0, :] * filt)[..., None, :] @ vh
        x = x[..., 0, :]
    p = freq.shape[0]
    coefficients = torch.complex(x[..., 1 : 1 + p], x[..., 1 + p :])
    condition = s[..., 0] / s[..., -1]
    return coefficients, x[..., 0], condition
