"""The measurement model of ``capture-format.md``: what a pixel records under each frame's
extended light, differentiable in every SVBRDF parameter.

    value[p, k, c] = exposure_k irradiance_k,c integral D_k(l) rho_c(w(l), view; p) <n_p, w(l)> dl

(see :mod:`torchspec.lights` for the density ``D_k`` in the l-plane). Two terms:

- diffuse, ``k_d / pi integral D_k <n, w>^+``: the effective direction ``d_k`` of each frame gives
  it exactly as ``k_d / pi <n, d_k>`` when the kernel lies in the normal's hemisphere; where the
  kernel reaches behind the normal's horizon, the smaller of the parts in front of and behind it
  is integrated, piecewise between the horizon's crossings (:func:`torchspec.lights.clamped_diffuse`).
- specular, ``k_s integral D_k(l) S(l) dl`` with ``S`` the Ward lobe times the cosine
  (:func:`torchspec.brdf.ward_cosine`). The lobe is sharp where ``alpha`` is small and the kernel
  is sharp for a point-like light; the integral is taken about their product.

Two coordinates carry the quadratures: the l-plane, where a projected Gaussian kernel is exactly
Gaussian, and the slopes ``(<h, s>, <h, t>) / <h, n>`` of the half vector, where the Ward lobe is
exactly Gaussian (variances ``alpha^2 / 2``) however anisotropic it is - in the l-plane a 10:1
lobe bends into a banana that no Gaussian follows. Each factor is mapped into the other's
coordinates by linearising about the product's mean (:func:`_pairs`).

Paths of the specular term, chosen by the rule of :func:`choose_path`:

- ``point``: a point light, one exact evaluation per frame.
- ``fast``: Gauss-Hermite, ``FAST_ORDER^2`` nodes per pixel and frame, on the product of the two
  factors' Gaussians, in the l-plane for a projected Gaussian kernel and in slopes for an angular
  one (where the exact factor is the lobe); the ratio of the true integrand to that product is
  smooth. Its error against the reference is measured by ``experiments/render_accuracy.py``.
- ``reference``: polar Gauss-Legendre, accurate for any kernel, ``order`` setting the accuracy:
  on the kernel's own grid in the l-plane where the kernel is narrower than the lobe every way,
  else about the product in slopes (``2 order`` radii x ``order`` angles); the first is clipped
  exactly at the horizon, the second at the horizon and the normal's horizon.

Nodes are placed from the parameters (the lobe's mirror point and width) and autograd follows
them, so the gradient is exactly that of the value computed - the consistent Jacobian that
Levenberg-Marquardt needs - and converges to the true derivative with the quadrature. Pixels are
processed in chunks so that memory stays bounded for (pixels x frames x nodes).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
import torch
import torch.fx.experimental._config as fx_config
from torch import Tensor

from .brdf import SVBRDF, beckmann_cosine, lambert
from .geometry import from_plane, tangent_frame
from .lights import (
    Kernel,
    Lights,
    _gauss_rule,
    _gauss_table,
    _legendre,
    clamped_diffuse,
    diffuse_directions,
    polar_nodes,
)

__all__ = ["render", "choose_path", "PATHS", "FAST_ORDER", "REFERENCE_ORDER", "DIFFUSE_ORDER", "ClampRule", "CLAMPS"]

PATHS = ("auto", "point", "fast", "reference")
FAST_ORDER = 4  # Gauss-Hermite nodes per axis of the fast path
REFERENCE_ORDER = 16  # Gauss-Legendre radii of the reference path (twice as many angles)
DIFFUSE_ORDER = 12  # Gauss-Legendre nodes per piece of the clamped diffuse integral
HORIZON_MARGIN = 5.5  # kernel stds between its mean and the normal's horizon for the clamp to matter
INSIDE = 4.0  # the fast path needs the kernel this many widths inside the horizon
LOBE_REACH = 7.0  # the lobe is integrated out to this many (linearised) widths
PULL = 0.98  # the largest l-plane radius about which the factors are linearised
BUDGET = 1 << 20  # pixel x frame x node elements per chunk
FIXED_SIZES = set()
"""The functions compiled with fixed sizes but for their batch (:func:`_compiled`)."""


class ClampRule(NamedTuple):
    """How the diffuse clamp is integrated (:func:`_diffuse`): the pairs within ``margin`` kernel
    stds of the normal's horizon, with ``order`` Gauss-Legendre nodes per piece of ``lines``
    lines (``None``: ``torchspec.lights.ACROSS`` per kernel width)."""

    margin: float
    order: int
    lines: int | None


CLAMPS = {
    # The renderer's: the kernel's mass left out under 1e-6, the integral to ~1e-7.
    "exact": ClampRule(HORIZON_MARGIN, DIFFUSE_ORDER, None),
    # A fit's: 4x fewer pairs x nodes on bench_fit's capture, within 5e-4 of a pixel's largest value
    # for normals tilted up to 70 deg (tests/test_jacobian.py), far below a capture's noise.
    "fast": ClampRule(4.0, 8, 11),
}


def _standard_hermite(order: int):
    """The standard-normal rule (weights summing to 1) in float64."""
    x, w = np.polynomial.hermite.hermgauss(order)
    return x * math.sqrt(2.0), w / math.sqrt(math.pi)


_HERMITE = _gauss_table(_standard_hermite, range(1, 33))  # see lights._legendre


def _hermite(order: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """2D standard-normal Gauss-Hermite rule: points ``(Q, 2)``, weights ``(Q,)`` summing to 1."""
    x, w = _gauss_rule(_HERMITE, _standard_hermite, order, like)
    grid = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    return grid, (w[:, None] * w[None, :]).reshape(-1)


def choose_path(lights: Lights, path: str = "auto") -> str:
    """The specular path of the frames.

    ``auto``: ``point`` for a point light; ``fast`` for a Gaussian kernel (either domain), whose
    pixel-frame pairs fall back to ``reference`` where the product of kernel and lobe reaches
    the horizon (within ``INSIDE`` of its widths: a Gaussian rule cannot follow the cut);
    ``reference`` for super-Gaussian and tabulated kernels, whose shape a Gaussian rule cannot
    follow.
    A forced path must fit the kernel: ``point`` only for point lights, ``fast`` (then used for
    every pair) only for Gaussian kernels.
    """
    if path not in PATHS:
        raise ValueError(f"path must be one of {PATHS}; got {path!r}.")
    kernel = lights.kernel
    if kernel.kind == "unknown":
        raise ValueError(
            "the light kernel is 'unknown': rendering needs its shape. Calibrate it into a tabulated "
            "kernel, or describe a known light (e.g. torchspec render --light FILE)."
        )
    if kernel.kind == "point":
        if path not in ("auto", "point"):
            raise ValueError(f"path {path!r} does not apply to a point light; use 'auto' or 'point'.")
        return "point"
    if path == "point":
        raise ValueError(f"path 'point' needs a point light; this one is {kernel.kind!r}.")
    if path == "fast" and kernel.kind != "gaussian":
        raise ValueError(f"path 'fast' needs a Gaussian kernel; this one is {kernel.kind!r}.")
    if path != "auto":
        return path
    return "auto" if kernel.kind == "gaussian" else "reference"


class _Pixels(NamedTuple):
    """Per-pixel quantities of the Ward lobe, shaped ``(N, 1, 1)`` to broadcast over frames and
    nodes: the normal, the rotated tangents, the view's cosine and the lobe's constants."""

    n: tuple[Tensor, Tensor, Tensor]
    s: tuple[Tensor, Tensor, Tensor]
    t: tuple[Tensor, Tensor, Tensor]
    cos_view: Tensor
    inv_ax: Tensor
    inv_ay: Tensor
    scale: Tensor  # 1 / (4 pi a_x a_y), 0 where there is no lobe
    view: tuple[float, float, float]


def _pixels(svbrdf: SVBRDF, view: Tensor) -> _Pixels:
    n = svbrdf.normal
    s, t = tangent_frame(n, svbrdf.rotation)
    alpha = svbrdf.roughness
    lobe = (alpha[:, 0] > 0) & (alpha[:, 1] > 0)
    safe = torch.where(lobe[:, None], alpha, torch.ones_like(alpha))
    scale = torch.where(lobe, 1.0 / (4.0 * math.pi * safe[:, 0] * safe[:, 1]), torch.zeros_like(safe[:, 0]))

    def split(v):  # contiguous: views at offsets 0, 1, 2 would make torch.compile guard on them
        return tuple(v[:, j, None, None].contiguous() for j in range(3))

    cos_view = (n * view).sum(-1)
    return _Pixels(
        split(n),
        split(s),
        split(t),
        cos_view[:, None, None],
        1.0 / safe[:, 0, None, None],
        1.0 / safe[:, 1, None, None],
        scale[:, None, None],
        tuple(float(x) for x in view.tolist()),
    )


def _at_nodes(lx: Tensor, ly: Tensor, p: _Pixels):
    """The geometry at l-plane nodes ``(N, F, Q)``, componentwise: ``w_z``, ``<n, w>``, where the
    lobe is seen (``w`` above the horizon and in front of the normal, the view too), and the
    unnormalised half vector ``w + v`` with its ``<h, n>``."""
    r2 = lx * lx + ly * ly
    inside = r2 < 1.0
    wz = torch.sqrt(torch.where(inside, 1.0 - r2, torch.ones_like(r2)))
    nx, ny, nz = p.n
    vx, vy, vz = p.view
    cos_light = nx * lx + ny * ly + nz * wz
    front = inside & (cos_light > 0) & (p.cos_view > 0)
    hx, hy, hz = lx + vx, ly + vy, wz + vz
    return wz, cos_light, front, (hx, hy, hz), nx * hx + ny * hy + nz * hz


def _lobe_at(lx: Tensor, ly: Tensor, p: _Pixels) -> Tensor:
    """The Ward lobe times the cosine, ``ward_cosine``, at l-plane points ``(N, F, Q)``, written
    componentwise (no 3-vectors, no reductions): the hot loop of every path."""
    _, cos_light, front, (hx, hy, hz), hn = _at_nodes(lx, ly, p)
    (sx, sy, sz), (tx, ty, tz) = p.s, p.t
    hs = (sx * hx + sy * hy + sz * hz) * p.inv_ax
    ht = (tx * hx + ty * hy + tz * hz) * p.inv_ay
    safe_hn = torch.where(front, hn, torch.ones_like(hn))
    ratio = torch.where(front, cos_light, torch.ones_like(cos_light)) / torch.where(p.cos_view > 0, p.cos_view, 1.0)
    value = torch.exp(-(hs * hs + ht * ht) / (safe_hn * safe_hn)) * torch.sqrt(ratio) * p.scale
    return torch.where(front, value, torch.zeros_like(value))


def _lobe_moments(p: _Pixels):
    """Mirror point and covariance (components ``xx, xy, yy``) of each pixel's Ward lobe in the
    l-plane, linearised: ``h = n + d_s s + d_t t`` with ``d ~ N(0, diag(a_x^2, a_y^2) / 2)`` and
    ``w = 2 <v, h> h - v``. Shaped like the pixels' fields."""
    (nx, ny, _), (sx, sy, sz), (tx, ty, tz) = p.n, p.s, p.t
    vx, vy, vz = p.view
    vn = p.cos_view
    vs, vt = vx * sx + vy * sy + vz * sz, vx * tx + vy * ty + vz * tz
    dsx, dsy = 2.0 * (vs * nx + vn * sx), 2.0 * (vs * ny + vn * sy)  # dw / d(d_s)
    dtx, dty = 2.0 * (vt * nx + vn * tx), 2.0 * (vt * ny + vn * ty)
    ax2, ay2 = 0.5 / (p.inv_ax * p.inv_ax), 0.5 / (p.inv_ay * p.inv_ay)
    cov = (dsx * dsx * ax2 + dtx * dtx * ay2, dsx * dsy * ax2 + dtx * dty * ay2, dsy * dsy * ax2 + dty * dty * ay2)
    return (2.0 * vn * nx - vx, 2.0 * vn * ny - vy), cov


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


def _slope_at(p: _Pixels, lx: Tensor, ly: Tensor):
    """Half-vector slopes ``(u, v) = (<h, s>, <h, t>) / <h, n>`` of l-plane points, their Jacobian
    ``d(u, v) / dl`` (components ``ux, uy, vx, vy``) and whether the half vector faces the normal
    (elsewhere the lobe is nil, and the slopes are of no use)."""
    (nx, ny, nz), (sx, sy, sz), (tx, ty, tz) = p.n, p.s, p.t
    vx, vy, vz = p.view
    lz = torch.sqrt((1.0 - lx * lx - ly * ly).clamp(min=1e-12))
    hx, hy, hz = lx + vx, ly + vy, lz + vz
    hn = nx * hx + ny * hy + nz * hz
    facing = hn > 0.05 * torch.sqrt(hx * hx + hy * hy + hz * hz)
    hn = torch.where(facing, hn, torch.ones_like(hn))
    u, v = (sx * hx + sy * hy + sz * hz) / hn, (tx * hx + ty * hy + tz * hz) / hn
    # rows (s - u n) . dh/dl / <h, n>, with dh/dl = (1, 0, -lx/lz), (0, 1, -ly/lz).
    gx, gy = lx / lz, ly / lz
    ux, uy = (sx - u * nx - (sz - u * nz) * gx) / hn, (sy - u * ny - (sz - u * nz) * gy) / hn
    vx_, vy_ = (tx - v * nx - (tz - v * nz) * gx) / hn, (ty - v * ny - (tz - v * nz) * gy) / hn
    return (u, v), (ux, uy, vx_, vy_), facing


def _congruence(j, cov):
    """``J C J^T`` for a 2 x 2 ``J`` (components ``a, b, c, d`` by rows) and a covariance ``C``."""
    a, b, c, d = j
    xx, xy, yy = cov
    return (
        a * a * xx + 2.0 * a * b * xy + b * b * yy,
        a * c * xx + (a * d + b * c) * xy + b * d * yy,
        c * c * xx + 2.0 * c * d * xy + d * d * yy,
    )


def _pairs(kernel: Kernel, centre: Tensor, p: _Pixels) -> _Pairs:
    """The moments of every pair of a pixel of ``p`` and a frame of ``centre (B, F, 3)``.

    The Ward lobe is exactly Gaussian in the slopes ``(u, v)`` of the half vector (see
    :func:`_slope_at`), with variances ``alpha^2 / 2``; the kernel is (for a projected Gaussian
    exactly) Gaussian in the l-plane. A first product in the l-plane takes the lobe linearised
    about its mirror point; then both factors are linearised again about that product's mean (one
    Laplace step), where the integrand's mass is: the lobe mapped into the l-plane and the kernel
    into slopes. A strongly anisotropic lobe bends in the l-plane, and this second step follows
    the bend where the integrand is."""
    kernel_cov = kernel.covariance(centre)
    kcov = (kernel_cov[..., 0, 0, None], kernel_cov[..., 0, 1, None], kernel_cov[..., 1, 1, None])
    mean = centre[..., :2] + kernel.offset(centre)
    m = (mean[..., 0, None], mean[..., 1, None])
    lobe_centre, lobe_cov = _lobe_moments(p)
    first, first_cov = _product(m, kcov, lobe_centre, lobe_cov)

    zero = torch.zeros_like(p.inv_ax)
    lobe_slope_cov = (0.5 / (p.inv_ax * p.inv_ax), zero, 0.5 / (p.inv_ay * p.inv_ay))
    # Linearise about the first product's mean, pulled inside the horizon if it lies beyond (the
    # product of two Gaussians knows nothing of the horizon; the slopes are singular there).
    radius = torch.sqrt(first[0] * first[0] + first[1] * first[1])
    pull = torch.where(radius > PULL, PULL / radius.clamp(min=PULL), torch.ones_like(radius))
    first = (first[0] * pull, first[1] * pull)
    (u, v), (a, b, c, d), facing = _slope_at(p, *first)
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


def _from_slope(p: _Pixels, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The l-plane points ``lx, ly`` of half-vector slopes ``(u, v)`` and the area ratio
    ``dl / (du dv) = 4 <v, h> <h, n>^3 w_z`` (0 where ``w`` is below the horizon)."""
    (nx, ny, nz), (sx, sy, sz), (tx, ty, tz) = p.n, p.s, p.t
    vx, vy, vz = p.view
    hx, hy, hz = nx + u * sx + v * tx, ny + u * sy + v * ty, nz + u * sz + v * tz
    hn = torch.rsqrt(hx * hx + hy * hy + hz * hz)  # <h, n> of the unit half vector
    hx, hy, hz = hx * hn, hy * hn, hz * hn
    vh = vx * hx + vy * hy + vz * hz
    wx, wy, wz = 2.0 * vh * hx - vx, 2.0 * vh * hy - vy, 2.0 * vh * hz - vz
    ratio = 4.0 * vh * hn * hn * hn * wz
    return wx, wy, torch.where((wz > 0) & (vh > 0), ratio, torch.zeros_like(ratio))


def _fast_rule(kernel: Kernel, centre: Tensor, p: _Pixels, order: int):
    """Gauss-Hermite nodes ``(N, F, Q)`` (x, y, area) on the product of the two factors and the
    pairs ``(N, F)`` whose product reaches the horizon (within ``INSIDE`` widths).

    The rule lives where one factor is exactly Gaussian: the l-plane for a projected Gaussian
    kernel, else the half-vector slopes, where the Ward lobe is (measured both ways by
    ``experiments/render_accuracy.py``: each choice is the more accurate for its kernel)."""
    q = _pairs(kernel, centre, p)
    lx, ly, area = _fast_nodes(kernel, q, p, order)
    return lx, ly, area, _reaches(q)


FIXED_SIZES.add(_fast_rule)


def _reaches(q: _Pairs) -> Tensor:
    """The pairs ``(N, F)`` whose product reaches the horizon (within ``INSIDE`` widths)."""
    with torch.no_grad():
        return (torch.sqrt(q.mean[0] ** 2 + q.mean[1] ** 2) + INSIDE * _std(q.cov, largest=True) >= 1.0)[..., 0]


def _fast_nodes(kernel: Kernel, q: _Pairs, p: _Pixels, order: int):
    """The fast rule's nodes ``(N, F, Q)`` (x, y, area) from the pairs' moments (:func:`_fast_rule`)."""
    points, weights = _hermite(order, p.inv_ax)
    xi, eta = points[:, 0], points[:, 1]
    # weight over the standard-normal density (times the Jacobian det(L) of each map below).
    weights = weights / (torch.exp(-0.5 * (points * points).sum(-1)) / (2.0 * math.pi))

    def nodes(mean, cov):
        (mx, my), (l11, l21, l22) = mean, _cholesky(cov)
        return mx + l11 * xi, my + l21 * xi + l22 * eta, weights * (l11 * l22)

    lx, ly, area = nodes(q.mean, q.cov)
    if kernel.domain != "projected":  # in slopes, but where the lobe is nil (not facing)
        u, v, slope_area = nodes(q.slope_mean, q.slope_cov)
        sx, sy, ratio = _from_slope(p, u, v)
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


def _slope_polar(p: _Pixels, mean, chol, reach: float, order: int):
    """Polar Gauss-Legendre in half-vector slopes about ``mean``, whitened by ``chol``, out to
    ``reach`` and clipped exactly where ``w`` meets the horizon or the normal's horizon (each a
    quadratic in the radius): slopes ``u, v`` and area weights ``(N, F, Q)``."""
    x, w = _legendre(2 * order, p.inv_ax)
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


def _reference_rule(kernel: Kernel, centre: Tensor, p: _Pixels, order: int):
    """Polar Gauss-Legendre nodes ``(N, F, Q)`` (x, y, area).

    Where the kernel is narrower than the lobe every way: in the l-plane on the kernel's own grid
    (:func:`torchspec.lights.polar_nodes`, clipped at the horizon), centred on the product's mean
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
    lx, ly, ratio = _from_slope(p, u, v)
    narrow = q.narrow
    return (
        torch.where(narrow, l[..., 0], lx),
        torch.where(narrow, l[..., 1], ly),
        torch.where(narrow, area, weight * ratio),
    )


FIXED_SIZES.add(_reference_rule)


def _rules(kernel: Kernel, centre: Tensor, p: _Pixels, path: str, orders: dict):
    """The nodes of every pixel-frame pair on ``path`` (``fast``, ``reference`` or ``auto``): x, y,
    area ``(N, F, Q)``, and for ``auto`` the pairs ``(pixel, frame)`` whose product reaches the
    horizon with their reference nodes ``(M, 1, Q')`` (else ``None``)."""
    if path == "reference":
        return _reference_rule(kernel, centre[None], p, orders["reference"]), None
    lx, ly, area, reaches = _fast_rule(kernel, centre[None], p, orders["fast"])
    if path == "fast":
        return (lx, ly, area), None
    return (lx, ly, area), _fallback(kernel, centre, p, reaches, orders["reference"])


def _fallback(kernel: Kernel, centre: Tensor, p: _Pixels, reaches: Tensor, order: int, compiled: bool = False):
    """The pairs ``(pixel, frame)`` of ``reaches (N, F)`` with their reference nodes ``(M, 1, Q')``
    (x, y, area), or ``None`` when there are none; ``compiled``: the rule fused by torch.compile."""
    cut = reaches.nonzero()
    if not cut.shape[0]:
        return None
    pixel, frame = cut[:, 0], cut[:, 1]
    rule = _fused(_reference_rule, compiled, cut.shape[0])
    return pixel, frame, rule(kernel, centre[frame][:, None], _pick(p, pixel), order)


def _integrate(kernel, centre, pixels, lx, ly, area) -> Tensor:
    density = kernel.density_xy(lx, ly, centre[..., None, :])
    return (area * density * _lobe_at(lx, ly, pixels)).sum(-1)


FIXED_SIZES.add(_integrate)


def _integrate_beckmann(svbrdf: SVBRDF, view: Tensor):
    """The node integration with :func:`torchspec.brdf.beckmann_cosine` in place of Ward's lobe."""

    def integrate(kernel, centre, pixels, lx, ly, area, index=None):
        part = svbrdf if index is None else svbrdf[index]
        shape = (-1,) + (1,) * (lx.dim() - 1)
        w = from_plane(torch.stack(torch.broadcast_tensors(lx, ly), -1))
        rotation = None if part.rotation is None else part.rotation.reshape(shape)
        lobe = beckmann_cosine(w, view, part.normal.reshape(*shape, 3), part.roughness.reshape(*shape, 2), rotation)
        return (area * kernel.density_xy(lx, ly, centre[..., None, :]) * lobe).sum(-1)

    return integrate


_COMPILED = {}


def _compiled(function):
    """``function`` fused by ``torch.compile``, called as ``fused(rows, *args)`` (built on first
    use, kept). Every size may change between calls; for the functions in :data:`FIXED_SIZES` only
    the first axis of the tensor arguments with ``rows`` rows (the batch: pixels, pairs) may, and
    the other sizes (frames, nodes) are fixed: a fit keeps them, another capture compiles once more.

    - Fixed sizes make the fast and reference rules 1.3x and the node integrations 2x faster, but
      the clamp's integral 1.4x and the normal equations' sums over the frames ~10x slower
      (measured on bench_fit's capture): each function takes its faster kind.
    - Its Python floats (the view, a kernel's width) are constants of the graph: left symbolic,
      each would become an input tensor only after a second analysis of the whole function (~1/3
      of the compilation).
    - Sizes that happen to be equal are not taken to be the same size (duck shapes).
    """
    if function not in _COMPILED:
        fixed = function in FIXED_SIZES
        fused = torch.compile(function, dynamic=not fixed)

        @functools.wraps(function)
        def call(rows, *args, **kwargs):
            if fixed:
                _mark_batch((args, kwargs), rows)
            with torch._dynamo.config.patch(specialize_float=True), fx_config.patch(use_duck_shape=False):
                return fused(*args, **kwargs)

        _COMPILED[function] = call
    return _COMPILED[function]


def _mark_batch(value, rows: int) -> None:
    """Mark the first axis of the tensors in ``value`` (nested tuples, lists, dicts) with ``rows``
    rows as dynamic for torch.compile."""
    if isinstance(value, Tensor):
        if value.dim() and value.shape[0] == rows:
            torch._dynamo.maybe_mark_dynamic(value, 0)
    elif isinstance(value, (tuple, list)):
        for item in value:
            _mark_batch(item, rows)
    elif isinstance(value, dict):
        for item in value.values():
            _mark_batch(item, rows)


def _fused(function, compiled: bool, rows: int):
    """``function``, fused by torch.compile when ``compiled`` and its batch has 2 rows or more
    (the compiler specialises sizes 0 and 1: a batch of 1 would compile again; it runs eager)."""
    return functools.partial(_compiled(function), rows) if compiled and rows > 1 else function


def _specular(svbrdf, lights, view, path, orders, compiled=False, lobe="ward") -> Tensor:
    """``integral D_k S dl`` for the pixels of ``svbrdf (N,)`` and every frame: ``(N, K)``.

    Nodes are placed from the parameters (the lobe's mirror point and width) and autograd
    follows them, so the gradient is exactly that of the value computed.
    """
    kernel, centre = lights.kernel, lights.directions
    pixels = _pixels(svbrdf, view)
    integrate = (
        _fused(_integrate, compiled, svbrdf.normal.shape[0]) if lobe == "ward" else _integrate_beckmann(svbrdf, view)
    )
    if path == "point":
        if lobe == "beckmann":
            return beckmann_cosine(
                centre[None],
                view,
                svbrdf.normal[:, None],
                svbrdf.roughness[:, None],
                None if svbrdf.rotation is None else svbrdf.rotation[:, None],
            )
        return _lobe_at(centre[None, :, None, 0], centre[None, :, None, 1], pixels)[..., 0]
    (lx, ly, area), fallback = _rules(kernel, centre, pixels, path, orders)
    value = integrate(kernel, centre[None], pixels, lx, ly, area)
    if fallback is not None:  # auto: the pairs whose product reaches the horizon, by the reference rule
        p, k, (lx, ly, area) = fallback
        if lobe == "ward":
            exact = _integrate(kernel, centre[k][:, None], _pick(pixels, p), lx, ly, area)[:, 0]
        else:
            exact = integrate(kernel, centre[k][:, None], None, lx, ly, area, index=p)[:, 0]
        value = value.index_put((p, k), exact)
    return value


def _pick(pixels: _Pixels, index: Tensor) -> _Pixels:
    """The per-pixel quantities of the pixels ``index``."""

    def take(field):
        if isinstance(field, tuple):
            return field if isinstance(field[0], float) else tuple(c[index] for c in field)
        return field[index]

    return _Pixels(*(take(f) for f in pixels))


def _diffuse(
    normal: Tensor, lights: Lights, direction: Tensor, gradient: bool = False, clamp: str = "exact", compiled=False
):
    """``integral D_k <n, w>^+`` ``(N, K)``: ``<n, d_k>``, clamped exactly where the kernel reaches
    behind the normal's horizon (:func:`torchspec.lights.clamped_diffuse`, for the pairs one
    ``nonzero`` per call picks).

    A pair is picked when the normal's horizon passes within the ``margin`` of the rule
    ``CLAMPS[clamp]`` in kernel stds of the kernel's mean: the signed distance ``g / |grad g|`` of
    ``g(l) = <n, w(l)>``, in units of the kernel's std along ``grad g``. Beyond ``HORIZON_MARGIN``
    the kernel's mass behind the horizon, and the cosine's size there, are too small to matter
    (less than 1e-6 of the mass).

    With ``gradient``, also the derivative in the normal ``(N, K, 3)``: ``d_k``, or for the
    clamped pairs the kernel's effective direction over the part in front of the horizon.
    ``compiled``: the clamp's integral fused by ``torch.compile``.
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
    pairs = (g < rule.margin * spread).nonzero()
    if pairs.shape[0]:
        p, k = pairs[:, 0], pairs[:, 1]
        nodes = {"order": rule.order, "lines": rule.lines}
        integral = _fused(clamped_diffuse, compiled, pairs.shape[0])
        if gradient:
            exact, slope = integral(kernel, centre[k], normal[p], value[p, k], direction=direction[k], **nodes)
            grad_n = grad_n.index_put((p, k), slope)
        else:
            exact = integral(kernel, centre[k], normal[p], value[p, k], **nodes)
        value = value.index_put((p, k), exact)
    return (value, grad_n) if gradient else value


def render(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    *,
    path: str = "auto",
    order: int | None = None,
    compile: bool = False,
    lobe: str = "ward",
) -> Tensor:
    """Predicted values of every pixel under every frame: ``(*, K, C)``.

    Args:
        svbrdf: parameters with leading dims ``*`` and ``C`` channels (or grey ``k_s``), and a
            second lobe if it has one.
        lights: ``K`` frames; the kernel must be known (not ``unknown``).
        view: ``(3,)`` unit direction towards the camera.
        path: ``auto`` (the rule of :func:`choose_path`), ``point``, ``fast`` or ``reference``.
        order: nodes per axis of the chosen quadrature: ``FAST_ORDER`` (Gauss-Hermite) for
            ``fast``, ``REFERENCE_ORDER`` (Gauss-Legendre radii) for ``reference``, or twice the
            table's size if larger for a tabulated kernel (its spline has a knot per pixel).
        compile: fuse the node integration with ``torch.compile`` (~2.4x faster on CPU for the
            fast path, after a one-off compilation of ~30 s; off by default).
        lobe: ``ward`` (the format's model) or ``beckmann`` (:func:`torchspec.brdf.beckmann_cosine`,
            the physically based renderers' lobe, to tell a model's residual from an integration's).

    Returns:
        ``(*, K, C)`` in the dtype and on the device of ``svbrdf``.

    Example:
        >>> import torch
        >>> from torchspec.lights import Kernel, Lights
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> lights = Lights(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), Kernel("point"), one, one[0])
        >>> maps = SVBRDF(torch.tensor([[0.0, 0, 1]], dtype=torch.float64), one, one * 0, one.expand(1, 2) * 0)
        >>> round(float(render(maps, lights, torch.tensor([0.0, 0, 1], dtype=torch.float64))), 6)  # k_d / pi
        0.31831
    """
    if lobe not in ("ward", "beckmann"):
        raise ValueError(f"lobe must be 'ward' or 'beckmann'; got {lobe!r}.")
    if view.shape != (3,):
        raise ValueError(f"view must have shape (3,); got {tuple(view.shape)}.")
    count = svbrdf.diffuse.shape[-1]
    if lights.irradiance.shape[1] not in (1, count):
        raise ValueError(
            f"lights.irradiance must have 1 or {count} channels (the SVBRDF's {svbrdf.channels}); "
            f"got {lights.irradiance.shape[1]}."
        )
    chosen = choose_path(lights, path)
    lead = svbrdf.shape
    flat = svbrdf.flatten()
    like = flat.diffuse
    lights = lights.to(dtype=like.dtype, device=like.device)
    view = view.to(dtype=like.dtype, device=like.device)
    reference = REFERENCE_ORDER
    if lights.kernel.kind == "tabulated":  # a knot per pixel: two radius nodes per pixel
        reference = max(reference, 2 * max(lights.kernel.table.shape))
    orders = {"fast": order or FAST_ORDER, "reference": order or reference}
    if chosen == "auto":
        orders["reference"] = reference  # an order given is for the fast rule; fallbacks stay exact

    direction = lights.directions if lights.kernel.kind == "point" else diffuse_directions(lights)

    nodes_per_pair = {
        "point": 1,
        "auto": orders["fast"] ** 2,
        "fast": orders["fast"] ** 2,
        "reference": 2 * orders["reference"] ** 2,
    }[chosen]
    chunk = max(1, BUDGET // (lights.directions.shape[0] * nodes_per_pair))
    out = []
    for start in range(0, max(flat.shape[0], 1), chunk):  # one (empty) chunk for no pixels
        part = flat[start : start + chunk]
        specular = _specular(part, lights, view, chosen, orders, compile, lobe)
        diffuse = _diffuse(part.normal, lights, direction)
        value = lambert(part.diffuse)[:, None, :] * diffuse[..., None] + part.specular[:, None, :] * specular[..., None]
        second = part.second()
        if second is not None:  # the second lobe, on the pixels that have one (all when its k_s needs a derivative)
            lobed = (second.specular > 0).any(-1)
            tangent = torch.autograd.forward_ad.unpack_dual(second.specular).tangent
            if (torch.is_grad_enabled() and second.specular.requires_grad) or tangent is not None:
                lobed = torch.ones_like(lobed)
            index = lobed.nonzero()[:, 0]
            if index.numel():
                picked = second[index]
                lobe2 = _specular(picked, lights, view, chosen, orders, compile, lobe)
                lobe2 = (picked.specular[:, None, :] * lobe2[..., None]).expand(-1, -1, count)
                value = value.index_add(0, index, lobe2)
        out.append(value * lights.scale[None])
    return torch.cat(out).reshape(*lead, lights.directions.shape[0], count)
