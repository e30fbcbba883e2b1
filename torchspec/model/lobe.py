"""The Ward lobe of each pixel, written componentwise for the node loops of
:mod:`torchspec.model.nodes`, :mod:`torchspec.model.rendering` and :mod:`torchspec.model.jacobian`: the per-pixel
lobe frame (:class:`LobeFrame`), the lobe times the cosine at l-plane nodes (:func:`lobe_at`),
its linearised moments in the l-plane and the map between the l-plane and the half vector's
slopes ``(<h, s>, <h, t>) / <h, n>``, where the lobe is exactly Gaussian.

Every function here takes and returns tensors broadcasting as ``(N, F, Q)`` (pixels, frames,
nodes) and no 3-vectors: torch.compile fuses such code into one loop.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .brdf import SVBRDF
from .geometry import tangent_frame

__all__ = ["LobeFrame", "lobe_frame", "pick", "at_nodes", "lobe_at", "lobe_moments", "slope_at", "from_slope"]


class LobeFrame(NamedTuple):
    """Per-pixel quantities of the Ward lobe, shaped ``(N, 1, 1)`` to broadcast over frames and
    nodes: the normal, the rotated tangents, the view's cosine and the lobe's constants."""

    n: tuple[Tensor, Tensor, Tensor]
    s: tuple[Tensor, Tensor, Tensor]
    t: tuple[Tensor, Tensor, Tensor]
    cos_view: Tensor
    inv_ax: Tensor
    inv_ay: Tensor
    scale: Tensor  # 1 / (4 pi a_x a_y), 0 where there is no lobe
    view: tuple[Tensor, Tensor, Tensor]  # 0-dim: read where they are used, never on the host


def lobe_frame(svbrdf: SVBRDF, view: Tensor) -> LobeFrame:
    """The lobe frame of the pixels of a flat ``svbrdf (N,)`` seen from ``view (3,)``."""
    n = svbrdf.normal
    s, t = tangent_frame(n, svbrdf.rotation)
    alpha = svbrdf.roughness
    lobe = (alpha[:, 0] > 0) & (alpha[:, 1] > 0)
    safe = torch.where(lobe[:, None], alpha, torch.ones_like(alpha))
    scale = torch.where(lobe, 1.0 / (4.0 * math.pi * safe[:, 0] * safe[:, 1]), torch.zeros_like(safe[:, 0]))

    def split(v):  # contiguous: views at offsets 0, 1, 2 would make torch.compile guard on them
        return tuple(v[:, j, None, None].contiguous() for j in range(3))

    cos_view = (n * view).sum(-1)
    return LobeFrame(
        split(n),
        split(s),
        split(t),
        cos_view[:, None, None],
        1.0 / safe[:, 0, None, None],
        1.0 / safe[:, 1, None, None],
        scale[:, None, None],
        tuple(view.to(n).unbind()),
    )


def at_nodes(lx: Tensor, ly: Tensor, p: LobeFrame):
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


def lobe_at(lx: Tensor, ly: Tensor, p: LobeFrame) -> Tensor:
    """The Ward lobe times the cosine, ``ward_cosine``, at l-plane points ``(N, F, Q)``, written
    componentwise (no 3-vectors, no reductions): the hot loop of every path."""
    _, cos_light, front, (hx, hy, hz), hn = at_nodes(lx, ly, p)
    (sx, sy, sz), (tx, ty, tz) = p.s, p.t
    hs = (sx * hx + sy * hy + sz * hz) * p.inv_ax
    ht = (tx * hx + ty * hy + tz * hz) * p.inv_ay
    safe_hn = torch.where(front, hn, torch.ones_like(hn))
    ratio = torch.where(front, cos_light, torch.ones_like(cos_light)) / torch.where(p.cos_view > 0, p.cos_view, 1.0)
    value = torch.exp(-(hs * hs + ht * ht) / (safe_hn * safe_hn)) * torch.sqrt(ratio) * p.scale
    return torch.where(front, value, torch.zeros_like(value))


def lobe_moments(p: LobeFrame):
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


def slope_at(p: LobeFrame, lx: Tensor, ly: Tensor):
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



def from_slope(p: LobeFrame, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor, Tensor]:
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



def pick(pixels: LobeFrame, index: Tensor) -> LobeFrame:
    """The lobe frame of the pixels ``index (M,)`` of ``pixels``."""

    def take(field):
        if isinstance(field, tuple):
            return field if field[0].dim() == 0 else tuple(c[index] for c in field)  # the view: shared
        return field[index]

    return LobeFrame(*(take(f) for f in pixels))

