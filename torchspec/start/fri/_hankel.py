"""Hankel matrices of coefficient sequences, their signal subspace, and Cadzow denoising:
shared by the root methods of one pulse (rank 1, several snapshots) and of K pulses (rank K).

References:
    Cadzow, "Signal enhancement - a composite property mapping algorithm", IEEE TASSP 1988.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["rows_for", "hankel", "signal_subspace", "cadzow"]


def rows_for(length: int, rank: int) -> int:
    """Hankel rows for a sequence of ``length``: as square as possible, with at least
    ``rank + 1`` rows and ``rank`` columns."""
    return min(max(length // 2 + 1, rank + 1), length - rank + 1)


def hankel(seq: Tensor, rows: int) -> Tensor:
    """``(..., rows, L - rows + 1)`` Hankel matrices of sequences ``(..., L)``."""
    index = torch.arange(rows, device=seq.device)[:, None] + torch.arange(seq.shape[-1] - rows + 1, device=seq.device)
    return seq[..., index]


def signal_subspace(h: Tensor, rank: int) -> Tensor:
    """The ``rank`` leading left singular vectors ``(..., L1, rank)`` of the snapshots
    ``h (..., S, L1, L2)`` side by side, from the eigenvectors of their summed Gram matrix
    (strongest last)."""
    gram = torch.einsum("...sik,...sjk->...ij", h, h.conj())
    return torch.linalg.eigh(gram)[1][..., -rank:]


def cadzow(seq: Tensor, rank: int, iterations: int) -> Tensor:
    """Fixed-iteration Cadzow denoising of each sequence ``(..., L)``: the nearest rank-``rank``
    Hankel matrix, then the average along its anti-diagonals, ``iterations`` times."""
    length = seq.shape[-1]
    rows = rows_for(length, rank)
    if rows * (length - rows + 1) <= length:  # nothing to average: already the whole sequence
        return seq
    index = (
        torch.arange(rows, device=seq.device)[:, None] + torch.arange(length - rows + 1, device=seq.device)
    ).reshape(-1)
    count = torch.bincount(index, minlength=length).to(seq.real.dtype)
    for _ in range(iterations):
        h = hankel(seq, rows)
        u = signal_subspace(h[..., None, :, :], rank)
        low = (u @ (u.conj().transpose(-1, -2) @ h)).flatten(-2)
        seq = torch.zeros_like(seq).index_add_(-1, index, low) / count
    return seq
