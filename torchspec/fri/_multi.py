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

__all__ = ["locate_multi"]

CADZOW_ITERATIONS = 20


def _hankel(seq: Tensor, rows: int) -> Tensor:
    """``(B, rows, M - rows + 1)`` Hankel matrix of ``seq (B, M)``."""
    cols = seq.shape[-1] - rows + 1
    index = torch.arange(rows, device=seq.device)[:, None] + torch.arange(cols, device=seq.device)[None, :]
    return seq[:, index]


def _rows(length: int, k: int) -> int:
    """Hankel rows: as square as possible, with at least K + 1 rows and K columns."""
    return min(max(length // 2 + 1, k + 1), length - k + 1)


def _cadzow(seq: Tensor, k: int) -> Tensor:
    rows = _rows(seq.shape[-1], k)
    cols = seq.shape[-1] - rows + 1
    index = (torch.arange(rows)[:, None] + torch.arange(cols)[None, :]).reshape(-1).to(seq.device)
    ones = torch.ones(index.shape, dtype=seq.real.dtype, device=seq.device)
    count = torch.zeros(seq.shape[-1], dtype=seq.real.dtype, device=seq.device).index_add_(0, index, ones)
    for _ in range(CADZOW_ITERATIONS):
        u, s, vh = torch.linalg.svd(_hankel(seq, rows), full_matrices=False)
        low = (u[..., :k] * s[..., None, :k].to(u.dtype)) @ vh[..., :k, :]
        seq = torch.zeros_like(seq).index_add_(-1, index, low.reshape(low.shape[0], -1)) / count
    return seq


def _esprit(seq: Tensor, k: int) -> Tensor:
    """TLS-ESPRIT roots ``(B, K)``."""
    u, _, _ = torch.linalg.svd(_hankel(seq, _rows(seq.shape[-1], k)), full_matrices=False)
    signal = u[..., :k]  # (B, L, K)
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
    seq = _cadzow(y, k) if method == "cadzow" else y
    roots = _prony(seq, k) if method == "ls" else _esprit(seq, k)
    s = torch.linalg.svdvals(_hankel(y, _rows(y.shape[-1], k)))
    if s.shape[-1] > k:
        gap = s[..., k] / s[..., k - 1].clamp(min=torch.finfo(s.dtype).tiny)
    else:
        gap = torch.zeros_like(s[..., 0])
    return -torch.angle(roots), gap
