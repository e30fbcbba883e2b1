"""The quadrature nodes of the specular integral ``integral D_k(l) S(l) dl`` for every pair of a
pixel and a frame: the fast rule (Gauss-Hermite on the product of the two factors' Gaussians)
and the reference rule (polar Gauss-Legendre, clipped at the horizons), as l-plane nodes
``lx, ly`` and area weights ``(N, F, Q)``.

Two coordinates carry the rules: the l-plane, where a projected Gaussian kernel is exactly
Gaussian, and the slopes ``(<h, s>, <h, t>) / <h, n>`` of the half vector, where the Ward lobe is
exactly Gaussian (variances ``alpha^2 / 2``) however anisotropic it is. Each factor is mapped
into the other's coordinates by linearising about the product's mean (:func:`_pairs`).

Nodes are placed from the parameters (the lobe's mirror point and width): autograd follows
them, and a caller that wants the quadrature of the derivative instead detaches them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ..lm.picks import pick_pairs
from .fusion import FIXED_SIZES, fused
from .lights import Kernel, polar_nodes
from .lobe import LobeFrame, from_slope, lobe_moments, pick, slope_at
from .quadrature import hermite, legendre

__all__ = ["fast_rule", "reference_rule", "node_rules", "fallback_rule", "INSIDE", "LOBE_REACH", "PULL"]

INSIDE = 4.0  # the fast path needs the kernel this many widths inside the horizon
LOBE_REACH = 7.0  # the lobe is integrated out to this many (linearised) widths
PULL = 0.98  # the largest l-plane radius about which the factors are linearised


def _std(cov, largest: bool) -> Tensor:
    """The largest or smallest std of 2 x 2 covariances given as components ``xx, xy, yy``."""
    xx, xy, yy = cov
    spread = torch.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)
    return torch.sqrt((0.5 * (xx + yy) + (spread if largest else -spread)).clamp(min=0.0))


def _product(a, a_cov, b, b_cov):
    """Mean and covariance of the normalised product of two Gaussians, ``A (A + B)^-1 B`` and
    ``B S^-1 a + A S^-1 b``: no precision is formed, so a degenerate factor is harmless."""
    sxx, sxy, syy = (i + j for i, j in zip(a_cov, b_cov, strict=True))
    det = sxx * syy - sxy * sxy
    ixx, ixy, iyy = syy / det, -sxy / det, sxx / det
    axx, axy, ayy = a_cov
    bxx, bxy, byy = b_cov
    # K = A S^-1, then the covariance K B and the mean a + K (b - a).
    k00, k01 = axx * ixx + axy * ixy, axx * ixy + axy * iyy
    k10, k11 = axy * ixx + ayy * ixy, axy * ixy + ayy * iyy
    dx, dy = b[0] - a[0], b[1] - a[1]
    mean = (a[0] + k00 * dx + k01 * dy, a[1] + k10 * dx + k11 * dy)
    cxy = 0.5 * (k00 * bxy + k01 * byy + k10 * bxx + k11 * bxy)
    return mean, (k00 * bxx + k01 * bxy, cxy, k10 * bxy + k11 * byy)


def _cholesky(cov):
    xx, xy, yy = cov
    l11 = torch.sqrt(xx)
    l21 = xy / l11
    return l11, l21, torch.sqrt((yy - l21 * l21).clamp(min=0.0))


class _Pairs(NamedTuple):
    """Per pixel-frame moments ``(N, F, 1)`` of the integrand's two factors and their product."""

    facing: Tensor  # the half vector at the product's mean faces the normal (else the lobe is nil)
    narrow: Tensor  # the kernel is narrower than the lobe every way (or the lobe is nil there)
    mean: tuple[Tensor, Tensor]  # the product of kernel and linearised lobe, in the l-plane
    cov: tuple[Tensor, Tensor, Tensor]
    slope_mean: tuple[Tensor, Tensor]  # the product of linearised kernel and exact lobe, in slopes
    slope_cov: tuple[Tensor, Tensor, Tensor]



def _congruence(j, cov):
    """``J C J^T`` for a 2 x 2 ``J`` (components ``a, b, c, d`` by rows) and a covariance ``C``."""
    a, b, c, d = j
    xx, xy, yy = cov
    return (
        a * a * xx + 2.0 * a * b * xy + b * b * yy,
        a * c * xx + (a * d + b * c) * xy + b * d * yy,
        c * c * xx + 2.0 * c * d * xy + d * d * yy,
    )


def _pairs(kernel: Kernel, centre: Tensor, p: LobeFrame) -> _Pairs:
    """The moments of every pair of a pixel of ``p`` and a frame of ``centre (B, F, 3)``.

    The Ward lobe is exactly Gaussian in the slopes ``(u, v)`` of the half vector (see
    :func:`slope_at`), with variances ``alpha^2 / 2``; the kernel is (for a projected Gaussian
    exactly) Gaussian in the l-plane. A first product in the l-plane takes the lobe linearised
    about its mirror point; then both factors are linearised again about that product's mean (one
    Laplace step), where the integrand's mass is: the lobe mapped into the l-plane and the kernel
    into slopes. A strongly anisotropic lobe bends in the l-plane, and this second step follows
    the bend where the integrand is."""
    kernel_cov = kernel.covariance(centre)
    kcov = (kernel_cov[..., 0, 0, None], kernel_cov[..., 0, 1, None], kernel_cov[..., 1, 1, None])
    mean = centre[..., :2] + kernel.offset(centre)
    m = (mean[..., 0, None], mean[..., 1, None])
    lobe_centre, lobe_cov = lobe_moments(p)
    first, first_cov = _product(m, kcov, lobe_centre, lobe_cov)

    zero = torch.zeros_like(p.inv_ax)
    lobe_slope_cov = (0.5 / (p.inv_ax * p.inv_ax), zero, 0.5 / (p.inv_ay * p.inv_ay))
    # Linearise about the first product's mean, pulled inside the horizon if it lies beyond (the
    # product of two Gaussians knows nothing of the horizon; the slopes are singular there).
    radius = torch.sqrt(first[0] * first[0] + first[1] * first[1])
    pull = torch.where(radius > PULL, PULL / radius.clamp(min=PULL), torch.ones_like(radius))
    first = (first[0] * pull, first[1] * pull)
    (u, v), (a, b, c, d), facing = slope_at(p, *first)
    det = a * d - b * c
    det = torch.where(facing & (det.abs() > 0), det, torch.ones_like(det))
    inverse = (d / det, -b / det, -c / det, a / det)
    # The lobe about the first product's mean l0, in the l-plane: mean l0 - J^-1 z0, cov J^-1 Lambda J^-T.
    lobe = (first[0] - (inverse[0] * u + inverse[1] * v), first[1] - (inverse[2] * u + inverse[3] * v))
    plane_mean, plane_cov = _product(m, kcov, lobe, _congruence(inverse, lobe_slope_cov))
    # The kernel in slopes: mean z0 + J (m - l0), covariance J Sigma J^T.
    dx, dy = m[0] - first[0], m[1] - first[1]
    kernel_slope = (u + a * dx + b * dy, v + c * dx + d * dy)
    slope_mean, slope_cov = _product(kernel_slope, _congruence((a, b, c, d), kcov), (zero, zero), lobe_slope_cov)

    def keep(new, old):  # where the half vector there does not face the normal, the first product
        return tuple(torch.where(facing, i, j) for i, j in zip(new, old, strict=True))

    with torch.no_grad():
        narrow = ~facing | (_std(kcov, largest=True) <= _std(lobe_cov, largest=False))
    return _Pairs(facing, narrow, keep(plane_mean, first), keep(plane_cov, first_cov), slope_mean, slope_cov)



def fast_rule(kernel: Kernel, centre: Tensor, p: LobeFrame, order: int):
    """Gauss-Hermite nodes ``(N, F, Q)`` (x, y, area) on the product of the two factors and the
    pairs ``(N, F)`` whose product reaches the horizon (within ``INSIDE`` widths).

    The rule lives where one factor is exactly Gaussian: the l-plane for a projected Gaussian
    kernel, else the half-vector slopes, where the Ward lobe is (measured both ways by
    ``experiments/render_accuracy.py``: each choice is the more accurate for its kernel)."""
    q = _pairs(kernel, centre, p)
    lx, ly, area = _fast_nodes(kernel, q, p, order)
    return lx, ly, area, _reaches(q)


FIXED_SIZES.add(fast_rule)


def _reaches(q: _Pairs) -> Tensor:
    """The pairs ``(N, F)`` whose product reaches the horizon (within ``INSIDE`` widths)."""
    with torch.no_grad():
        return (torch.sqrt(q.mean[0] ** 2 + q.mean[1] ** 2) + INSIDE * _std(q.cov, largest=True) >= 1.0)[..., 0]


def _fast_nodes(kernel: Kernel, q: _Pairs, p: LobeFrame, order: int):
    """The fast rule's nodes ``(N, F, Q)`` (x, y, area) from the pairs' moments (:func:`fast_rule`)."""
    points, weights = hermite(order, p.inv_ax)
    xi, eta = points[:, 0], points[:, 1]
    # weight over the standard-normal density (times the Jacobian det(L) of each map below).
    weights = weights / (torch.exp(-0.5 * (points * points).sum(-1)) / (2.0 * math.pi))

    def nodes(mean, cov):
        (mx, my), (l11, l21, l22) = mean, _cholesky(cov)
        return mx + l11 * xi, my + l21 * xi + l22 * eta, weights * (l11 * l22)

    lx, ly, area = nodes(q.mean, q.cov)
    if kernel.domain != "projected":  # in slopes, but where the lobe is nil (not facing)
        u, v, slope_area = nodes(q.slope_mean, q.slope_cov)
        sx, sy, ratio = from_slope(p, u, v)
        lx, ly = torch.where(q.facing, sx, lx), torch.where(q.facing, sy, ly)
        area = torch.where(q.facing, slope_area * ratio, area)
    return lx, ly, area


def _first_root(a2: Tensor, a1: Tensor, a0: Tensor) -> Tensor:
    """The first positive root of ``a2 r^2 + a1 r + a0`` where ``a0 > 0`` (``2 a0 / (sqrt(disc) - a1)``,
    stable for every sign of ``a2``), ``inf`` where there is none."""
    disc = a1 * a1 - 4.0 * a2 * a0
    den = torch.sqrt(torch.where(disc > 0, disc, torch.ones_like(disc))) - a1
    crosses = (disc > 0) & (den > 0) & (a0 > 0)
    root = 2.0 * a0 / torch.where(crosses, den, torch.ones_like(den))
    return torch.where(crosses, root, torch.full_like(root, math.inf))


def _slope_polar(p: LobeFrame, mean, chol, reach: float, order: int):
    """Polar Gauss-Legendre in half-vector slopes about ``mean``, whitened by ``chol``, out to
    ``reach`` and clipped exactly where ``w`` meets the horizon or the normal's horizon (each a
    quadratic in the radius): slopes ``u, v`` and area weights ``(N, F, Q)``."""
    x, w = legendre(2 * order, p.inv_ax)
    angular = order
    psi = torch.arange(angular, dtype=x.dtype, device=x.device) * (2.0 * math.pi / angular)
    cos, sin = torch.cos(psi), torch.sin(psi)
    (nx, ny, nz), (sx, sy, sz), (tx, ty, tz) = p.n, p.s, p.t
    vx, vy, vz = p.view
    (cu, cv), (l11, l21, l22) = mean, chol
    su, sv = l11 * cos, l21 * cos + l22 * sin  # (N, F, A): slopes move by r (su, sv)
    # h(r) = A + r B, unnormalised, and w = 2 <v, h> h / |h|^2 - v. The ray leaves at the first
    # positive root of w_z |h|^2 = 2 <v, h> h_z - v_z |h|^2 (the horizon) or of <n, w> |h|^2 (the
    # normal's horizon; <n, A> = 1 and <n, B> = 0), each a quadratic in r.
    ax, ay, az = nx + cu * sx + cv * tx, ny + cu * sy + cv * ty, nz + cu * sz + cv * tz
    bx, by, bz = su * sx + sv * tx, su * sy + sv * ty, su * sz + sv * tz
    va, vb = vx * ax + vy * ay + vz * az, vx * bx + vy * by + vz * bz
    aa, ab, bb = ax * ax + ay * ay + az * az, ax * bx + ay * by + az * bz, bx * bx + by * by + bz * bz
    vn = p.cos_view
    horizon = _first_root(2.0 * vb * bz - vz * bb, 2.0 * (va * bz + vb * az) - 2.0 * vz * ab, 2.0 * va * az - vz * aa)
    normal = _first_root(-vn * bb, 2.0 * vb - 2.0 * vn * ab, 2.0 * va - vn * aa)
    top = torch.minimum(horizon, normal)
    exits = (top < reach)[..., None]  # (N, F, A, 1)
    top = top.clamp(max=reach)[..., None]
    # On rays that end at a horizon, r = top s (2 - s): dr / ds vanishes there, where the lobe's
    # sqrt(<n, w>) has an infinite slope that would slow Gauss-Legendre down.
    s = 0.5 * (x + 1.0)
    r = top * torch.where(exits, s * (2.0 - s), s)  # (N, F, A, R)
    dr = top * torch.where(exits, 2.0 * (1.0 - s), torch.ones_like(s)) * (0.5 * w)
    weight = dr * r * (2.0 * math.pi / angular) * (l11 * l22)[..., None]
    u = cu[..., None] + r * su[..., None]
    v = cv[..., None] + r * sv[..., None]
    return u.flatten(-2), v.flatten(-2), weight.flatten(-2)


def reference_rule(kernel: Kernel, centre: Tensor, p: LobeFrame, order: int):
    """Polar Gauss-Legendre nodes ``(N, F, Q)`` (x, y, area).

    Where the kernel is narrower than the lobe every way: in the l-plane on the kernel's own grid
    (:func:`torchspec.model.lights.polar_nodes`, clipped at the horizon), centred on the product's mean
    for a kernel without a finite support (the product sits in the kernel's tail when the lobe is
    far off) and on the kernel's for a tabulated one. Otherwise about the product of linearised
    kernel and exact lobe in half-vector slopes, where the lobe, however anisotropic, is Gaussian."""
    q = _pairs(kernel, centre, p)
    mean, shape, reach = kernel.grid(centre)
    if kernel.kind != "tabulated":
        product = torch.cat(q.mean, -1)
        inside = (product * product).sum(-1, keepdim=True) < (mean * mean).sum(-1, keepdim=True).clamp(min=0.99**2)
        mean = torch.where(inside, product, mean)
    l, area = polar_nodes(mean, shape, reach, radial=order, angular=2 * order)
    u, v, weight = _slope_polar(p, q.slope_mean, _cholesky(q.slope_cov), max(LOBE_REACH, reach), order)
    lx, ly, ratio = from_slope(p, u, v)
    narrow = q.narrow
    return (
        torch.where(narrow, l[..., 0], lx),
        torch.where(narrow, l[..., 1], ly),
        torch.where(narrow, area, weight * ratio),
    )


FIXED_SIZES.add(reference_rule)


def node_rules(kernel: Kernel, centre: Tensor, p: LobeFrame, path: str, orders: tuple[int, int]):
    """The nodes of every pixel-frame pair on ``path`` (``fast``, ``reference`` or ``auto``) for
    frames centred at ``centre (F, 3)`` and the orders ``(fast, reference)``
    (:meth:`torchspec.model.quadrature.Quadrature.orders`): x, y, area ``(N, F, Q)``, and for ``auto``
    the pairs ``(pixel, frame)`` whose product reaches the horizon, their validity and their
    reference nodes ``(M, 1, Q')`` (:func:`fallback_rule`; else ``None``)."""
    fast, reference = orders
    if path == "reference":
        return reference_rule(kernel, centre[None], p, reference), None
    lx, ly, area, reaches = fast_rule(kernel, centre[None], p, fast)
    if path == "fast":
        return (lx, ly, area), None
    return (lx, ly, area), fallback_rule(kernel, centre, p, reaches, reference)


def fallback_rule(kernel: Kernel, centre: Tensor, p: LobeFrame, reaches: Tensor, order: int, compile: bool = False):
    """The pairs ``(pixel, frame)`` of ``reaches (N, F)`` (:func:`torchspec.lm.picks.pick_pairs`:
    one ``nonzero``, or inside a solver step a fixed number of pairs, without a host
    synchronisation), whether each is one of them (``valid (M,)``, ``None``: all are) and their
    reference nodes ``(M, 1, Q')`` (x, y, area); ``None`` when there are none. A caller writes
    back the valid pairs' values only (:func:`torchspec.lm.picks.keep`). ``compile``: the rule
    fused by torch.compile."""
    pixel, frame, valid = pick_pairs(reaches, "lobe fallback")
    if not pixel.shape[0]:
        return None
    rule = fused(reference_rule, compile, pixel.shape[0])
    return pixel, frame, valid, rule(kernel, centre[frame][:, None], pick(p, pixel), order)

