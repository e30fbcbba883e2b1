"""The tabulated kernel's least squares (:mod:`torchspec.calibration.kernel`): samples of a light's shape,
scattered over offsets in the l-plane, fitted on the B-spline surface :class:`torchspec.model.lights.Kernel`
rebuilds from a table, with a smoothness prior and non-negativity; and the table's moments."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..model.lights import SPLINE_PAD, Kernel, bspline_weights

ANGLES = 2.0
"""Radial symmetry: copies of a sample per table pixel of arc length on its ring."""


class CalibrationError(TorchspecError):
    """A capture or setting from which no kernel can be calibrated; the message says why and how to fix it."""


@dataclass(frozen=True)
class Design:
    """Rows of the B-spline design: each sample's 16 taps into the ``S x S`` table and their weights."""

    index: Tensor  # (M, 16) long, flat table indices (clamped; weight 0 where off the table)
    weight: Tensor  # (M, 16)
    size: int

    def apply(self, table: Tensor) -> Tensor:
        return (self.weight * table.reshape(-1)[self.index]).sum(-1)

    def normal(self, weight: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
        """``A^T W A`` ``(S^2, S^2)`` and ``A^T W y`` ``(S^2,)``, accumulated from the tap pairs."""
        cells = self.size * self.size
        matrix = self.weight.new_zeros(cells * cells)
        pairs = (self.index[:, :, None] * cells + self.index[:, None, :]).reshape(-1)
        products = (self.weight[:, :, None] * self.weight[:, None, :] * weight[:, None, None]).reshape(-1)
        matrix.index_add_(0, pairs, products)
        rhs = self.weight.new_zeros(cells).index_add_(
            0, self.index.reshape(-1), (self.weight * (weight * target)[:, None]).reshape(-1)
        )
        return matrix.reshape(cells, cells), rhs


def spline_design(u: Tensor, extent: float, size: int) -> Design:
    """The design of density samples at offsets ``u (M, 2)`` for the table of :class:`Kernel`:
    its cubic B-spline surface, control point ``(row, col)`` at ``(x, y) = ((col + 1/2) 2 e / S - e,
    e - (row + 1/2) 2 e / S)`` and zero beyond the table."""
    fx = (u[:, 0] / extent + 1.0) * (size / 2.0) - 0.5 + SPLINE_PAD
    fy = (1.0 - u[:, 1] / extent) * (size / 2.0) - 0.5 + SPLINE_PAD
    ix0, iy0 = torch.floor(fx), torch.floor(fy)
    wx, wy = torch.stack(bspline_weights(fx - ix0), -1), torch.stack(bspline_weights(fy - iy0), -1)  # (M, 4)
    taps = torch.arange(4, device=u.device) - 1 - SPLINE_PAD
    col, row = ix0.long()[:, None] + taps, iy0.long()[:, None] + taps  # (M, 4) table columns and rows
    ok = ((row >= 0) & (row < size))[:, :, None] & ((col >= 0) & (col < size))[:, None, :]  # (M, 4, 4)
    weight = wy[:, :, None] * wx[:, None, :] * ok.to(u.dtype)
    index = row.clamp(0, size - 1)[:, :, None] * size + col.clamp(0, size - 1)[:, None, :]
    return Design(index.reshape(-1, 16), weight.reshape(-1, 16), size)


def blur_taps(sigma: float, like: Tensor) -> Tensor:
    """A symmetric discrete kernel of variance ``sigma^2`` (table pixels): ``[a, 1 - 2a, a]`` for a
    small one, a sampled Gaussian (its variance within 1e-3 of ``sigma^2`` from sigma = 0.7) beyond."""
    if sigma * sigma <= 0.5:
        a = 0.5 * sigma * sigma
        return like.new_tensor([a, 1.0 - 2.0 * a, a])
    radius = math.ceil(4.0 * sigma)
    k = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    g = torch.exp(-0.5 * (k / sigma) ** 2)
    return g / g.sum()


def separable_blur(images: Tensor, taps: Tensor) -> Tensor:
    """Separable convolution of ``(B, S, S)`` with ``taps``, zero outside (the spline's padding)."""
    size, pad = images.shape[-1], taps.numel() // 2
    k = torch.arange(size, device=images.device)
    d = k[:, None] - k[None, :] + pad
    g = torch.where((d >= 0) & (d < taps.numel()), taps[d.clamp(0, taps.numel() - 1)], torch.zeros_like(taps[:1]))
    return g @ images @ g.T


def laplacian_matrix(size: int, like: Tensor) -> Tensor:
    """``L^T L`` ``(S^2, S^2)`` of the 5-point Laplacian with zero outside the table: ``L = I (x) D + D (x) I``
    with ``D`` the 1D second difference, so ``L^2 = I (x) D^2 + 2 D (x) D + D^2 (x) I``."""
    eye = torch.eye(size, dtype=like.dtype, device=like.device)
    d = -2.0 * eye + torch.diag(like.new_ones(size - 1), 1) + torch.diag(like.new_ones(size - 1), -1)
    d2 = d @ d
    return torch.kron(eye, d2) + 2.0 * torch.kron(d, d) + torch.kron(d2, eye)


def solve_table(
    design: Design,
    target: Tensor,
    weight: Tensor,
    prior: Tensor,
    smoothing: float,
    taps: Tensor | None,
    free: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Weighted least squares for the table ``(S, S)``: ``|W^(1/2) (A G t - y)|^2 + lam |L t|^2``
    (``prior`` is ``L^T L``)
    with ``G`` the mirror's blur (or none), ``t >= 0`` by an active set, Cholesky on the normal
    equations (``S^2`` unknowns: dense is fine up to the 64 x 64 cap). ``free`` ``(S^2,)``: the
    cells not held at 0 to start from; returns the table and the final ``free``."""
    size = design.size
    cells = size * size
    matrix, rhs = design.normal(weight, target)
    if taps is not None:  # G^T N G for the symmetric convolution G
        matrix = separable_blur(matrix.reshape(cells, size, size), taps).reshape(cells, cells).T.contiguous()
        matrix = separable_blur(matrix.reshape(cells, size, size), taps).reshape(cells, cells)
        rhs = separable_blur(rhs.reshape(1, size, size), taps).reshape(-1)
    diagonal = matrix.diagonal()
    covered = diagonal > 1e-12 * diagonal.max()
    scale = float(diagonal[covered].mean())
    system = matrix + (smoothing * scale / 20.0) * prior
    system.diagonal().add_(1e-10 * scale)
    free = torch.ones(cells, dtype=torch.bool, device=matrix.device) if free is None else free
    table = torch.zeros_like(rhs)
    for _ in range(8):  # active set: cells that go negative are held at 0
        sub = system[free][:, free]
        factor, info = torch.linalg.cholesky_ex(sub)
        if int(info) != 0:
            raise CalibrationError(
                f"the kernel's least-squares system must be positive definite; got a failed Cholesky (info {int(info)})"
                ". Raise smoothing or lower size."
            )
        table = torch.zeros_like(rhs)
        table[free] = torch.cholesky_solve(rhs[free][:, None], factor)[:, 0]
        negative = free & (table < 0)
        if not bool(negative.any()):
            break
        free = free & ~negative
    return table.clamp(min=0.0).reshape(size, size), free


def bin_samples(u: Tensor, y: Tensor, w: Tensor, cell: float) -> tuple[Tensor, Tensor, Tensor]:
    """Samples merged per square cell of side ``cell``: weighted mean offset and value, summed weight."""
    key = torch.round(u / cell).long()
    _, inverse = torch.unique(key, dim=0, return_inverse=True)
    count = int(inverse.max()) + 1
    total = w.new_zeros(count).index_add_(0, inverse, w)
    safe = total.clamp(min=torch.finfo(w.dtype).tiny)
    mean_u = u.new_zeros(count, 2).index_add_(0, inverse, w[:, None] * u) / safe[:, None]
    mean_y = y.new_zeros(count).index_add_(0, inverse, w * y) / safe
    keep = total > 0
    return mean_u[keep], mean_y[keep], total[keep]


def radial_samples(rho: Tensor, y: Tensor, w: Tensor, step: float) -> tuple[Tensor, Tensor, Tensor]:
    """A radially symmetric kernel's samples at radii ``rho``: binned on the radius, then copied
    around their ring (``ANGLES`` copies per table pixel of arc), each with its share of the weight."""
    key = torch.round(rho / (0.25 * step)).long()
    _, inverse = torch.unique(key, return_inverse=True)
    count = int(inverse.max()) + 1
    total = w.new_zeros(count).index_add_(0, inverse, w)
    safe = total.clamp(min=torch.finfo(w.dtype).tiny)
    radius = rho.new_zeros(count).index_add_(0, inverse, w * rho) / safe
    value = y.new_zeros(count).index_add_(0, inverse, w * y) / safe
    copies = torch.clamp(torch.ceil(2.0 * math.pi * radius / step * ANGLES), min=1).long()
    ring = torch.repeat_interleave(torch.arange(count, device=rho.device), copies)
    first = torch.cumsum(copies, 0) - copies
    position = torch.arange(ring.numel(), device=rho.device) - first[ring]
    angle = (position.to(rho.dtype) + 0.5) * (2.0 * math.pi / copies[ring].to(rho.dtype))
    u = radius[ring, None] * torch.stack([torch.cos(angle), torch.sin(angle)], -1)
    return u, value[ring], total[ring] / copies[ring].to(w.dtype)


def table_moments(table: Tensor, extent: float) -> tuple[Tensor, Tensor]:
    """Centroid ``(2,)`` and covariance ``(2, 2)`` of the spline density (the table's point masses
    plus the cubic B-spline's own variance of 1/3 pixel^2 per axis)."""
    kernel = Kernel("tabulated", table=table, extent=extent)
    zenith = table.new_tensor([0.0, 0.0, 1.0])
    return kernel.offset(zenith), kernel.covariance(zenith)


def asymmetry(table: Tensor, extent: float, centroid: Tensor) -> float:
    """``|D(u) - D(2 mu - u)| / |D|`` (L2) of the spline density over a fine grid: 0 for a kernel
    symmetric about its centroid."""
    kernel = Kernel("tabulated", table=table, extent=extent)
    reach = extent * (1.0 + 2.0 * SPLINE_PAD / table.shape[0])
    axis = torch.linspace(-reach, reach, 2 * table.shape[0] + 1, dtype=table.dtype, device=table.device)
    gy, gx = torch.meshgrid(axis, axis, indexing="ij")
    u = torch.stack([gx, gy], -1) + centroid
    origin = table.new_tensor([0.0, 0.0, 1.0])
    here = kernel.density(u, origin)
    there = kernel.density(2.0 * centroid - u, origin)
    return float((here - there).norm() / here.norm().clamp(min=torch.finfo(table.dtype).tiny))
