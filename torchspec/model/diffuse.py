"""The diffuse term of the measurement model, ``integral D_k(l) <n, w(l)>^+ dl`` for every pixel
and frame (:func:`diffuse_integral`): ``<n, d_k>`` with the frame's effective direction ``d_k``
(:func:`torchspec.model.lights.diffuse_directions`) wherever the kernel lies in the normal's
hemisphere, and where it reaches behind the normal's horizon the clamped integral of
:func:`clamped_diffuse`, on lines across the kernel cut at the horizon's crossings.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..lm.picks import keep, pick_pairs
from .fusion import fused
from .lights import Kernel, Lights
from .quadrature import CLAMPS, legendre

__all__ = ["diffuse_integral", "clamped_diffuse", "ACROSS"]

ACROSS = 2.7
"""Lines per kernel width across a kernel in :func:`clamped_diffuse`'s integral."""


def diffuse_integral(
    normal: Tensor, lights: Lights, direction: Tensor, *, gradient: bool = False, clamp: str = "exact", compile=False
):
    """``integral D_k <n, w>^+`` ``(N, K)`` for normals ``(N, 3)`` and the frames' effective
    directions ``direction (K, 3)`` (:func:`torchspec.model.lights.diffuse_directions`): ``<n, d_k>``,
    clamped exactly where the kernel reaches behind the normal's horizon
    (:func:`clamped_diffuse`, for the pairs :func:`torchspec.lm.picks.pick_pairs` picks: one
    ``nonzero`` per call, or inside a solver step a fixed number of pairs, without a host
    synchronisation).

    A pair is picked when the normal's horizon passes within the ``margin`` of the rule
    ``CLAMPS[clamp]`` in kernel stds of the kernel's mean: the signed distance ``g / |grad g|`` of
    ``g(l) = <n, w(l)>``, in units of the kernel's std along ``grad g``. Beyond ``HORIZON_MARGIN``
    the kernel's mass behind the horizon, and the cosine's size there, are too small to matter
    (less than 1e-6 of the mass).

    With ``gradient``, also the derivative in the normal ``(N, K, 3)``: ``d_k``, or for the
    clamped pairs the kernel's effective direction over the part in front of the horizon.
    ``compile``: the clamp's integral fused by ``torch.compile``.
    """
    value = normal @ direction.T
    kernel = lights.kernel
    if kernel.kind == "point":  # the clamp is exact as it is
        if not gradient:
            return value.clamp(min=0.0)
        front = (value > 0)[..., None]
        return value.clamp(min=0.0), torch.where(front, direction[None], torch.zeros_like(direction[None]))
    grad_n = direction[None].expand(normal.shape[0], -1, -1).clone() if gradient else None
    centre = lights.directions
    mean = centre[:, :2] + kernel.offset(centre)  # (K, 2)
    mz = torch.sqrt((1.0 - (mean * mean).sum(-1)).clamp(min=1e-12))
    g = normal[:, :2] @ mean.T + normal[:, 2:] * mz  # (N, K): the cosine at the kernel's mean
    grad = normal[:, None, :2] - normal[:, None, 2:] * (mean / mz[:, None])[None]  # (N, K, 2)
    cov = kernel.covariance(centre)  # (K, 2, 2)
    gx, gy = grad[..., 0], grad[..., 1]  # a quadratic form written out: no batched small products
    spread = (gx * gx * cov[:, 0, 0] + 2.0 * gx * gy * cov[:, 0, 1] + gy * gy * cov[:, 1, 1]).clamp(min=0.0).sqrt()
    rule = CLAMPS[clamp]
    p, k, valid = pick_pairs(g < rule.margin * spread, "diffuse clamp")
    if p.shape[0]:
        nodes = {"order": rule.order, "lines": rule.lines}
        integral = fused(clamped_diffuse, compile, p.shape[0])
        linear = value[p, k]
        if gradient:
            exact, slope = integral(kernel, centre[k], normal[p], linear, direction=direction[k], **nodes)
            grad_n = grad_n.index_put((p, k), keep(valid, slope, grad_n[p, k]))
        else:
            exact = integral(kernel, centre[k], normal[p], linear, **nodes)
        value = value.index_put((p, k), keep(valid, exact, linear))
    return (value, grad_n) if gradient else value


def _cosine(lx: Tensor, ly: Tensor, nx: Tensor, ny: Tensor, nz: Tensor) -> tuple[Tensor, Tensor]:
    """``<n, w(l)>`` and ``w_z`` at l-plane points given by their coordinates (``w_z = 0`` at and
    beyond the horizon, as :func:`torchspec.model.geometry.from_plane`)."""
    z2 = (1.0 - lx * lx - ly * ly).clamp(min=0.0)
    wz = torch.where(z2 > 0, torch.sqrt(torch.where(z2 > 0, z2, torch.ones_like(z2))), torch.zeros_like(z2))
    return nx * lx + ny * ly + nz * wz, wz


def _lines(kernel: Kernel, centre: Tensor, normal: Tensor, order: int, lines: int | None):
    """The lines of :func:`clamped_diffuse` across the kernels centred at ``centre (M, 3)``,
    parallel to the gradient of ``<n, w(l)>`` at the kernel's mean: ``l = base + u d`` with
    ``base (M, V, 2)``, ``d (M, 1, 2)`` and ``u`` in ``[lo, hi] (M, V)`` (clipped at the unit
    circle), the Gauss-Legendre rule ``(V,)`` across them and their half-width ``(M,)``."""
    mean, shape, reach = kernel.grid(centre)  # the kernel's mean and extent in the l-plane
    # Lines in proportion to the reach (in widths): ~2 per width is plenty for a smooth correction;
    # a tabulated kernel is a piecewise cubic with a knot per pixel: two lines per pixel.
    across = max(order, math.ceil(ACROSS * reach)) if lines is None else lines
    if kernel.kind == "tabulated":
        across = max(across, 2 * max(kernel.table.shape))
    xv, wv = legendre(across, centre)
    c = mean
    nxy, nz = normal[:, :2], normal[:, 2:]
    # Gradient of <n, w(l)> at l = c: n_xy - n_z c / w_z(c).
    cz = torch.sqrt((1.0 - (c * c).sum(-1, keepdim=True)).clamp(min=1e-12))
    grad = nxy - nz * c / cz
    fallback = torch.zeros_like(grad)
    fallback[:, 0] = 1.0
    e1 = torch.where(grad.norm(dim=-1, keepdim=True) > 1e-12, grad, fallback)
    e1 = e1 / e1.norm(dim=-1, keepdim=True)
    e2 = torch.stack([-e1[:, 1], e1[:, 0]], -1)
    # Half-widths of the kernel's reach along e1 and across it (its l-plane image may be elongated).
    half_u = reach * torch.linalg.vector_norm(shape.transpose(-1, -2) @ e1[..., None], dim=(-2, -1))
    half_v = reach * torch.linalg.vector_norm(shape.transpose(-1, -2) @ e2[..., None], dim=(-2, -1))
    v = half_v[:, None] * xv  # (M, V) offsets across the lines
    base = c[:, None, :] + v[..., None] * e2[:, None, :]  # (M, V, 2): l = base + u e1
    d = e1[:, None, :]
    # The unit circle along each line: |base + u d|^2 = 1.
    bd = (base * d).sum(-1)
    b2 = (base * base).sum(-1)
    root = torch.sqrt((bd * bd - b2 + 1.0).clamp(min=0.0))
    lo = torch.maximum(-bd - root, -half_u[:, None])
    hi = torch.maximum(torch.minimum(-bd + root, half_u[:, None]), lo)  # a line off the disk: length 0
    return base, d, lo, hi, (xv, wv), half_v


def _pieces(normal: Tensor, base: Tensor, d: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """The ends ``(M, V, 4)`` of the three pieces of each line of :func:`_lines` between the
    crossings of the normal's horizon (a piece of no length where a line crosses it less than
    twice)."""
    nxy, nz = normal[:, :2], normal[:, 2:]
    bd = (base * d).sum(-1)
    b2 = (base * base).sum(-1)
    # The normal's horizon: p + u q + n_z sqrt(1 - b2 - 2 u bd - u^2) = 0, squared: a quadratic in u.
    p = (nxy[:, None, :] * base).sum(-1)
    q = (nxy[:, None, :] * d).sum(-1)
    nz2 = nz * nz
    qa = q * q + nz2
    qb = 2.0 * (p * q + nz2 * bd)
    qc = p * p - nz2 * (1.0 - b2)
    disc = torch.sqrt((qb * qb - 4.0 * qa * qc).clamp(min=0.0))
    roots = torch.stack([(-qb - disc) / (2.0 * qa), (-qb + disc) / (2.0 * qa)], -1)
    # A root of the squared equation is a crossing only where p + u q <= 0 (the sqrt term is >= 0).
    valid = (roots > lo[..., None]) & (roots < hi[..., None]) & ((p[..., None] + roots * q[..., None]) <= 1e-12)
    roots = torch.where(valid, roots, hi[..., None])
    return torch.cat([lo[..., None], roots.sort(-1).values, hi[..., None]], -1)


def clamped_diffuse(
    kernel: Kernel,
    centre: Tensor,
    normal: Tensor,
    linear: Tensor,
    *,
    order: int = 12,
    lines: int | None = None,
    direction: Tensor | None = None,
) -> Tensor | tuple[Tensor, Tensor]:
    """``integral D(l) max(<n, w(l)>, 0) dl`` for pairs of frame centres and normals ``(M, 3)``
    whose kernel reaches behind the normal's horizon: ``(M,)``. ``linear (M,)`` is the unclamped
    integral ``<n, d_k>``.

    Where ``linear >= 0`` (most of the kernel in front) the part behind the horizon is
    integrated and added back: ``linear + integral D max(-<n, w>, 0)``; elsewhere the part in
    front is integrated directly. Either way the integral taken is the smaller one, so no large
    terms cancel and few nodes suffice.

    Lines run parallel to the cosine's gradient at the kernel's mean; the normal's horizon crosses
    each at most twice (roots of a quadratic) and the unit circle ends it: Gauss-Legendre on each
    piece (``order`` nodes), mapped flat at both ends, has no kink or square-root slope inside.
    ``lines`` across the kernel: by default ``ACROSS`` per kernel width of its reach, and at least
    ``order``; for a tabulated kernel two per pixel of its table at least, whatever is given.

    With ``direction`` (the pairs' effective directions ``d_k (M, 3)``), also returns the
    gradient in the normal ``(M, 3)``: ``integral D w [<n, w> > 0]``, from the same nodes (the
    integrand vanishes on the horizon, so the moving limits add nothing).
    """
    if kernel.kind == "point":
        cos = (normal * centre).sum(-1)
        if direction is None:
            return cos.clamp(min=0.0)
        return cos.clamp(min=0.0), torch.where((cos > 0)[:, None], centre, torch.zeros_like(centre))
    if lines is not None and lines < 1:
        raise TorchspecError(f"lines must be >= 1; got {lines}.")
    add_back = (linear >= 0)[:, None, None]  # integrate the negative pieces, else the positive ones
    base, d, lo, hi, (xv, wv), half_v = _lines(kernel, centre, normal, order, lines)
    xu, wu = legendre(order, centre)
    edges = _pieces(normal, base, d, lo, hi)  # (M, V, 4)
    a, b = edges[..., :-1], edges[..., 1:]
    # Below, componentwise (no (..., 2) or (..., 3) points), as torch.compile fuses best.
    bx, by, dx, dy = base[..., 0, None], base[..., 1, None], d[..., 0, None], d[..., 1, None]  # (M, V | 1, 1)
    nx, ny, nz = (normal[:, j, None, None] for j in range(3))
    # Keep the pieces on the side to integrate: test each piece at its middle.
    middle = 0.5 * (a + b)
    behind = _cosine(bx + middle * dx, by + middle * dy, nx, ny, nz)[0] < 0
    b = torch.where(behind == add_back, b, a)
    # u = a + (b - a) (3 s^2 - 2 s^3): flat at both ends, where a piece may meet the unit circle.
    t = 0.5 * (xu + 1.0)
    u = a[..., None] + (b - a)[..., None] * (3.0 * t * t - 2.0 * t**3)  # (M, V, 3, U)
    lx, ly = bx[..., None] + u * dx[..., None], by[..., None] + u * dy[..., None]
    cos, wz = _cosine(lx, ly, nx[..., None], ny[..., None], nz[..., None])
    cos = torch.where(add_back[..., None], (-cos).clamp(min=0.0), cos.clamp(min=0.0))
    density = kernel.density_xy(lx, ly, centre[:, None, None, None, :])
    weight = (half_v[:, None] * wv)[..., None, None] * (b - a)[..., None] * 3.0 * t * (1.0 - t) * wu
    mass = weight * density
    part = (mass * cos).sum((-3, -2, -1))
    value = torch.where(linear >= 0, linear + part, part)
    if direction is None:
        return value
    # The nodes cover one side of the horizon: the part behind it (then d_k minus its share) or in front.
    side = mass * (cos > 0).to(mass.dtype)
    share = torch.stack([(side * c).sum((-3, -2, -1)) for c in (lx, ly, wz)], -1)
    return value, torch.where((linear >= 0)[:, None], direction - share, share)
