"""Location of K >= 2 pulses whose spectra are geometric (Lorentzian, i.e. periodic Poisson
kernels): ``Y_m = sum_k c_k z_k^m`` for ``m >= 1`` with ``z_k = r_k e^{-i 2 pi x_k / tau}``.
That is a sum of exponentials, annihilated by a filter of length K + 1 whose roots are the
``z_k``; each pulse may have its own width ``r_k``. The DC term is not used.

References:
    Vetterli, Marziliano, Blu, "Sampling signals with finite rate of innovation", IEEE TSP 2002.
    Roy, Kailath, "ESPRIT - estimation of signal parameters via rotational invariance
    techniques", IEEE TASSP 1989.
    Cadzow, "Signal enhancement - a composite property mapping algorithm", IEEE TASSP 1988.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._hankel import cadzow, hankel, rows_for, signal_subspace

__all__ = ["locate_multi"]

CADZOW_ITERATIONS = 20


def _esprit(seq: Tensor, k: int) -> Tensor:
    """TLS-ESPRIT roots ``(B, K)``."""
    signal = signal_subspace(hankel(seq, rows_for(seq.shape[-1], k))[:, None], k)  # (B, L, K)
    both = torch.cat([signal[:, :-1], signal[:, 1:]], dim=-1)  # (B, L - 1, 2K)
    _, _, vh = torch.linalg.svd(both, full_matrices=True)
    v = vh.conj().transpose(-1, -2)  # (B, 2K, 2K)
    v12, v22 = v[:, :k, k:], v[:, k:, k:]
    psi = -v12 @ torch.linalg.inv(v22)
    return torch.linalg.eigvals(psi)


def _prony(seq: Tensor, k: int) -> Tensor:
    """Least-squares annihilating filter ``h_0 = 1``: roots ``(B, K)``."""
    rows = seq.shape[-1] - k
    index = torch.arange(rows, device=seq.device)[:, None] + torch.arange(k, 0, -1, device=seq.device)[None, :] - 1
    a = seq[:, index]  # (B, rows, K): Y_{m-1} .. Y_{m-K} for m = K+1..M
    b = -seq[:, k:]  # (B, rows)
    ah = a.conj().transpose(-1, -2)
    h = torch.linalg.solve(ah @ a, (ah @ b[..., None]))[..., 0]  # (B, K)
    companion = torch.zeros(seq.shape[0], k, k, dtype=seq.dtype, device=seq.device)
    companion[:, 0, :] = -h
    if k > 1:
        companion[:, 1:, :-1] = torch.eye(k - 1, dtype=seq.dtype, device=seq.device)
    return torch.linalg.eigvals(companion)


def locate_multi(y: Tensor, k: int, method: str) -> tuple[Tensor, Tensor]:
    """Locate K pulses from ``y (B, M)`` (m = 1..M, ``M >= 2K``).

    Returns:
        ``theta (B, K)`` in radians (not wrapped, unordered) and ``gap (B,)``: the ratio of the
        (K+1)-th to the K-th singular value of the Hankel matrix, 0 without noise and near 1
        where noise or a (K+1)-th pulse fills the signal subspace.
    """
    seq = cadzow(y, k, CADZOW_ITERATIONS) if method == "cadzow" else y
    roots = _prony(seq, k) if method == "ls" else _esprit(seq, k)
    s = torch.linalg.svdvals(hankel(y, rows_for(y.shape[-1], k)))
    if s.shape[-1] > k:
        gap = s[..., k] / s[..., k - 1].clamp(min=torch.finfo(s.dtype).tiny)
    else:
        gap = torch.zeros_like(s[..., 0])
    return -torch.angle(roots), gap
