"""Directions on the hemisphere above a nearly flat object, in the surface frame of
``docs/capture-format.md``: ``x`` right, ``y`` up, ``z`` towards the camera; every direction is a unit
vector pointing away from the surface.

A direction ``w`` projects to ``l = (w_x, w_y)`` in the l-plane (``|l| <= 1``), the paper's light
coordinates; areas there relate to solid angle by ``dl = w_z dw``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "angle",
    "dot",
    "normalize",
    "from_plane",
    "to_plane",
    "reflect",
    "halfway",
    "tangent_frame",
    "normal_from_angles",
    "angles_from_normal",
    "normal_derivative",
]


def dot(a: Tensor, b: Tensor) -> Tensor:
    """``<a, b>`` over the last axis, broadcasting: ``(*, 3), (*, 3) -> (*)``."""
    return (a * b).sum(-1)


def normalize(v: Tensor) -> Tensor:
    """``v / |v|`` over the last axis; a zero vector stays zero (finite gradients too)."""
    norm2 = (v * v).sum(-1, keepdim=True)
    ok = norm2 > 0
    safe = torch.where(ok, norm2, torch.ones_like(norm2))
    return torch.where(ok, v * torch.rsqrt(safe), torch.zeros_like(v))


def from_plane(l: Tensor) -> Tensor:
    """Hemisphere direction ``(*, 3)`` of l-plane points ``l (*, 2)``; ``|l| >= 1`` gives ``z = 0``
    (the horizon): such points carry no light and callers give them zero weight."""
    z2 = (1.0 - (l * l).sum(-1, keepdim=True)).clamp(min=0.0)
    safe = torch.where(z2 > 0, z2, torch.ones_like(z2))
    z = torch.where(z2 > 0, torch.sqrt(safe), torch.zeros_like(z2))
    return torch.cat([l, z], dim=-1)


def spiral_plane(count: int, radius: float = 1.0, *, dtype: torch.dtype = torch.float64, device=None) -> Tensor:
    """``(count, 2)`` l-plane points of a Fibonacci spiral spread evenly over the disk of ``radius``
    (point ``k`` at radius ``radius sqrt((k + 1/2) / count)``, golden-angle turns): through
    :func:`from_plane`, directions spread evenly in cosine-weighted solid angle out to the zenith
    angle ``asin(radius)``; deterministic; of ``dtype`` on ``device``."""
    k = torch.arange(count, dtype=dtype, device=device) + 0.5
    r = radius * (k / count).sqrt()
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * phi.cos(), r * phi.sin()], -1)


def to_plane(w: Tensor) -> Tensor:
    """The l-plane point ``(*, 2)`` of directions ``w (*, 3)``."""
    return w[..., :2]


def reflect(w: Tensor, n: Tensor) -> Tensor:
    """Mirror direction of ``w`` about ``n``: ``2 <w, n> n - w`` (both unit, ``(*, 3)``)."""
    return 2.0 * dot(w, n)[..., None] * n - w


def halfway(wi: Tensor, wo: Tensor) -> Tensor:
    """Unit halfway vector of two unit directions (zero if they are opposite)."""
    return normalize(wi + wo)


def tangent_frame(n: Tensor, rotation: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Tangents ``s, t (*, 3)`` of unit normals ``n (*, 3)``.

    ``s`` is the surface ``x`` axis projected onto the plane orthogonal to ``n`` and normalised,
    ``t = n x s``; with ``rotation (*)`` (radians) both turn by that angle about ``n``,
    counter-clockwise seen from above: the anisotropic Ward lobe's frame of the format. For a
    normal along ``x`` (never a painting's) the ``y`` axis takes the place of ``x``.
    """
    x = torch.zeros_like(n)
    x[..., 0] = 1.0
    s = x - n[..., :1] * n
    norm2 = (s * s).sum(-1, keepdim=True)
    y = torch.zeros_like(n)
    y[..., 1] = 1.0
    degenerate = norm2 < 1e-12
    s = torch.where(degenerate, y - n[..., 1:2] * n, s)
    s = normalize(s)
    t = torch.linalg.cross(n, s, dim=-1)
    if rotation is not None:
        c, si = torch.cos(rotation)[..., None], torch.sin(rotation)[..., None]
        s, t = c * s + si * t, c * t - si * s
    return s, t


def normal_from_angles(angles: Tensor) -> Tensor:
    """Unit normals ``(*, 3)`` from two tilt angles ``(*, 2)``: ``n ~ (tan a, tan b, 1)``.

    ``a`` tilts the normal in the ``xz`` plane and ``b`` in the ``yz`` plane (radians, in
    ``(-pi/2, pi/2)``). Smooth at the zenith, where painting normals sit, unlike polar angles.
    """
    v = torch.stack([torch.tan(angles[..., 0]), torch.tan(angles[..., 1]), torch.ones_like(angles[..., 0])], -1)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def normal_derivative(n: Tensor) -> Tensor:
    """``dn / d(a, b)`` ``(N, 3, 2)`` of :func:`normal_from_angles` at the angles of normals
    ``n (N, 3)`` (:func:`angles_from_normal`), in closed form: there ``v = (tan a, tan b, 1) =
    (n_x, n_y, n_z) / n_z`` and ``m = v / |v|``, so ``dm/da = (e_x - m_x m) (1 + tan^2 a) / |v|``
    and likewise for ``b`` with ``y`` (``tests/test_geometry.py`` compares it with automatic
    differentiation)."""
    tangent = n[:, :2] / n[:, 2:]  # (tan a, tan b)
    length = (1.0 + (tangent * tangent).sum(-1, keepdim=True)).sqrt()  # |v|
    m = torch.cat([tangent, torch.ones_like(length)], -1) / length
    eye = torch.eye(3, 2, dtype=n.dtype, device=n.device)
    return (eye - m[:, :, None] * m[:, None, :2]) * ((1.0 + tangent * tangent) / length)[:, None, :]


def angles_from_normal(n: Tensor) -> Tensor:
    """The inverse of :func:`normal_from_angles` for normals with ``n_z > 0``: ``(*, 2)``."""
    return torch.stack([torch.atan2(n[..., 0], n[..., 2]), torch.atan2(n[..., 1], n[..., 2])], -1)


def angle(a: Tensor, b: Tensor) -> Tensor:
    """The angle between directions ``a`` and ``b`` ``(*, 3)``, in radians ``(*)``: from
    ``atan2(|a x b|, a . b)``, accurate near 0 and pi where ``acos`` of the dot product is not
    (it loses half the digits there: 1e-8 rad in float64)."""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))
