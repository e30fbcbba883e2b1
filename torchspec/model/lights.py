"""Extended light kernels of ``docs/capture-format.md``: their densities, quadrature nodes and weights
around K centres at once, and the effective diffuse directions.

Every kernel is handled as a density per unit area of the l-plane, so that a frame's value is

    value_k = exposure_k irradiance_k  integral_{|l| < 1} D_k(l) rho(w(l)) <n, w(l)> dl

with ``D_k = K_k`` for the projected and tabulated kernels (their measure is l-plane area) and
``D_k = K_k / w_z`` for angular ones (solid angle: ``dw = dl / w_z``). Each ``K_k`` integrates to 1
over its whole domain; what falls below the horizon (``|l| >= 1``) is lost, as the format says.

Quadrature: polar coordinates about a centre in the l-plane, trapezoid in the angle (spectrally
accurate for a periodic integrand) and Gauss-Legendre in the radius, which is clipped exactly at
the unit circle, so the horizon costs no accuracy. The same nodes serve kernel-centred (here)
and lobe-centred (in :mod:`torchspec.model.nodes`) integration.

Kernels: ``point``; ``gaussian`` in the ``projected`` (std ``sigma`` in l units) or ``angular``
(``exp(-g^2 / (2 sigma^2))``, ``g`` the angle to the centre) domain; ``tabulated`` (an image over
``l - l_k`` in ``[-extent, extent]^2``, row 0 at ``+extent`` in ``y``, reconstructed as the cubic
B-spline surface with the pixel values as control points: smooth (C2) and non-negative, of the
table's mass, ending two pixels beyond it; it blurs the table by the spline's 1/3 pixel^2 variance,
where an interpolating spline would ring into negative light); and, beyond the
format, ``supergaussian`` (angular, ``exp(-(g / radius)^power)``: a disk-like source, used to
describe a calibrated or known light). ``unknown`` kernels cannot be integrated.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import TorchspecError
from .gauss import legendre
from .geometry import from_plane

__all__ = [
    "Kernel",
    "Lights",
    "polar_nodes",
    "nodes",
    "diffuse_directions",
    "KERNEL_REACH",
    "SPLINE_PAD",
    "bspline_weights",
]

SPLINE_PAD = 2
"""Pixels a tabulated kernel's cubic B-spline reaches beyond its last control value."""

KERNEL_REACH = 6.0
"""Kernels are integrated out to this many widths (std, or radius for the super-Gaussian): what
lies beyond is below 1e-8 of the mass for a Gaussian."""


def bspline_weights(t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Cubic B-spline weights of the four taps around a point ``t`` in ``[0, 1)`` past the first."""
    s = 1.0 - t
    return (
        s**3 / 6.0,
        (3.0 * t**3 - 6.0 * t**2 + 4.0) / 6.0,
        (-3.0 * t**3 + 3.0 * t**2 + 3.0 * t + 1.0) / 6.0,
        t**3 / 6.0,
    )


@dataclass(frozen=True)
class Kernel:
    """The light's shape, shared by all frames.

    Attributes:
        kind: ``point``, ``gaussian``, ``supergaussian``, ``tabulated`` or ``unknown``.
        domain: ``projected`` (l-plane area) or ``angular`` (solid angle).
        sigma: the Gaussian's std (l units or radians), or the super-Gaussian's radius (radians).
        power: the super-Gaussian's exponent (2 would be a Gaussian of std ``radius / sqrt(2)``).
        table: ``(Hk, Wk)`` tabulated kernel, any positive scale (it is normalised here).
        extent: the tabulated kernel covers ``l - l_k`` in ``[-extent, extent]^2``.
    """

    kind: str
    domain: str = "projected"
    sigma: float = 0.0
    power: float = 2.0
    table: Tensor | None = None
    extent: float = 0.0

    def __post_init__(self):
        kinds = ("point", "gaussian", "supergaussian", "tabulated", "unknown")
        if self.kind not in kinds:
            raise TorchspecError(f"Kernel.kind must be one of {kinds}; got {self.kind!r}.")
        if self.domain not in ("projected", "angular"):
            raise TorchspecError(f"Kernel.domain must be 'projected' or 'angular'; got {self.domain!r}.")
        if self.kind in ("gaussian", "supergaussian") and not self.sigma > 0:
            raise TorchspecError(f"a {self.kind} kernel needs sigma (or radius) > 0; got {self.sigma!r}.")
        if self.kind == "supergaussian" and not self.power > 0:
            raise TorchspecError(f"a supergaussian kernel needs power > 0; got {self.power!r}.")
        if self.kind == "tabulated":
            if self.table is None or self.table.dim() != 2 or not self.extent > 0:
                raise TorchspecError("a tabulated kernel needs a (Hk, Wk) table (Kernel.table) and Kernel.extent > 0.")
            if not bool(torch.isfinite(self.table).all()) or bool((self.table < 0).any()) or not self.table.sum() > 0:
                raise TorchspecError("a tabulated kernel's Kernel.table must be finite, >= 0 and not all zero.")
            if self.domain != "projected":
                raise TorchspecError(
                    f"a tabulated kernel lives in the projected domain; got Kernel.domain {self.domain!r}."
                )
        if self.kind in ("gaussian", "supergaussian"):
            # Once per kernel, as a Python float: a constant of the compiled graphs, not work (and a graph
            # break) in each density call.
            object.__setattr__(self, "_normaliser", self._integrate_profile())

    @staticmethod
    def from_spec(spec, table: Tensor | None = None) -> Kernel:
        """The kernel of a capture's ``light`` description: a mapping with the keys of the format
        (``kernel``, ``domain``, ``sigma``, ``extent``, ...), an object with those attributes, or
        a light JSON of the development data (``kind``: ``gaussian``/``supergaussian``, ``domain``,
        ``sigma`` or ``radius``, ``power``)."""
        get = spec.get if isinstance(spec, Mapping) else (lambda key, default=None: getattr(spec, key, default))
        kind = get("kernel") or get("kind")
        if kind in ("disk",):
            kind = "supergaussian"
        sigma = get("sigma") or get("radius") or 0.0
        return Kernel(
            kind=kind,
            domain=get("domain") or ("angular" if kind == "supergaussian" else "projected"),
            sigma=float(sigma),
            power=float(get("power") or 2.0),
            table=table,
            extent=float(get("extent") or 0.0),
        )

    def reach(self) -> float:
        """Radius in the l-plane (or radians) beyond which the kernel holds no mass to speak of."""
        if self.kind == "tabulated":
            return (self.extent + SPLINE_PAD * 2.0 * self.extent / min(self.table.shape)) * math.sqrt(2.0)
        if self.kind == "supergaussian":
            return self.sigma * (math.log(1e8) ** (1.0 / self.power))
        return KERNEL_REACH * self.sigma

    def covariance(self, centre: Tensor) -> Tensor:
        """Covariance ``(*, 2, 2)`` in the l-plane of the kernels centred at ``centre (*, 3)``
        (exact for a projected Gaussian; to first order for angular kernels, whose l-plane image
        is squeezed along the radius by ``cos(theta)``)."""
        eye = torch.eye(2, dtype=centre.dtype, device=centre.device)
        if self.kind == "tabulated":
            table = self.table.to(dtype=centre.dtype, device=centre.device)
            hk, wk = table.shape
            x = (torch.arange(wk, dtype=centre.dtype, device=centre.device) + 0.5) / wk * 2.0 - 1.0
            y = 1.0 - (torch.arange(hk, dtype=centre.dtype, device=centre.device) + 0.5) / hk * 2.0
            p = table / table.sum()
            mx, my = (p.sum(0) * x).sum(), (p.sum(1) * y).sum()
            cxx = (p.sum(0) * (x - mx) ** 2).sum()
            cyy = (p.sum(1) * (y - my) ** 2).sum()
            cxy = (p * (x - mx)[None, :] * (y - my)[:, None]).sum()
            # The spline adds its own spread: a cubic B-spline has variance 1/3 pixel^2 per axis.
            cxx = cxx + (2.0 / wk) ** 2 / 3.0
            cyy = cyy + (2.0 / hk) ** 2 / 3.0
            cov = torch.stack([torch.stack([cxx, cxy]), torch.stack([cxy, cyy])]) * self.extent**2
            return cov.expand(*centre.shape[:-1], 2, 2)
        if self.kind == "gaussian":
            variance = self.sigma**2
        elif self.kind == "supergaussian":  # per-axis variance of exp(-(g / r)^p): r^2 Gamma(4/p) / (2 Gamma(2/p))
            variance = self.sigma**2 * math.gamma(4.0 / self.power) / (2.0 * math.gamma(2.0 / self.power))
        else:
            raise TorchspecError(f"a {self.kind} kernel has no covariance.")
        if self.domain == "projected":
            return variance * eye.expand(*centre.shape[:-1], 2, 2)
        c = centre[..., :2]
        return variance * (eye - c[..., :, None] * c[..., None, :])  # the tangent plane, projected

    def offset(self, like: Tensor) -> Tensor:
        """``(2,)`` the kernel's mean relative to its centre in the l-plane: 0 but for a tabulated
        kernel whose image is not centred."""
        zero = torch.zeros(2, dtype=like.dtype, device=like.device)
        if self.kind != "tabulated":
            return zero
        table = self.table.to(dtype=like.dtype, device=like.device)
        hk, wk = table.shape
        x = (torch.arange(wk, dtype=like.dtype, device=like.device) + 0.5) / wk * 2.0 - 1.0
        y = 1.0 - (torch.arange(hk, dtype=like.dtype, device=like.device) + 0.5) / hk * 2.0
        p = table / table.sum()
        return torch.stack([(p.sum(0) * x).sum(), (p.sum(1) * y).sum()]) * self.extent

    def grid(self, centre: Tensor) -> tuple[Tensor, Tensor, float]:
        """Mean ``(*, 2)``, shape ``(*, 2, 2)`` and reach (whitened units) of a quadrature grid that
        covers the kernels centred at ``centre (*, 3)``: ``l = mean + shape @ x``, ``|x| <= reach``."""
        # cholesky_ex: a kernel's covariance is positive definite by construction, and the checked
        # cholesky's error test is a side effect that keeps torch.compile's graph out of its cache.
        chol = torch.linalg.cholesky_ex(self.covariance(centre)).L
        mean = centre[..., :2] + self.offset(centre)
        if self.kind == "tabulated":
            # Out to the farthest pixel that carries any mass (plus the spline's skirt), from the mean.
            table = self.table.to(dtype=centre.dtype, device=centre.device)
            hk, wk = table.shape
            x = (torch.arange(wk, dtype=centre.dtype, device=centre.device) + 0.5) / wk * 2.0 - 1.0
            y = 1.0 - (torch.arange(hk, dtype=centre.dtype, device=centre.device) + 0.5) / hk * 2.0
            gy, gx = torch.meshgrid(y, x, indexing="ij")
            skirt = SPLINE_PAD * 2.0 / min(hk, wk)
            points = torch.stack([gx, gy], -1)[table > 1e-9 * table.max()] * self.extent - self.offset(centre)
            corners = points[:, None, :] + skirt * self.extent * torch.tensor(
                [[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=centre.dtype, device=centre.device
            )
            first = chol.reshape(-1, 2, 2)[:1]  # a tabulated kernel has one shape for every frame
            whitened = torch.linalg.solve_triangular(first, corners.reshape(-1, 2, 1), upper=False)
            return mean, chol, float(whitened.norm(dim=-2).max())
        if self.kind == "gaussian":
            return mean, chol, KERNEL_REACH
        std = math.sqrt(self.sigma**2 * math.gamma(4.0 / self.power) / (2.0 * math.gamma(2.0 / self.power)))
        return mean, chol, self.reach() / std

    def _radial_normaliser(self) -> float:
        """``integral K dmu`` of the unnormalised radial profile (computed once per kernel)."""
        if self.domain == "projected" and self.kind != "gaussian":
            raise TorchspecError(f"a projected {self.kind} kernel has no radial profile.")
        return self._normaliser

    def _integrate_profile(self) -> float:
        """:meth:`_radial_normaliser`: exact for ``projected``; for ``angular``, ``2 pi integral_0^pi
        profile(g) sin g dg`` by 256-node Gauss-Legendre on ``[0, min(pi, reach)]`` in float64."""
        if self.domain == "projected":
            return 2.0 * math.pi * self.sigma**2
        top = min(math.pi, self.reach())
        x, w = np.polynomial.legendre.leggauss(256)
        g = torch.from_numpy(0.5 * top * (x + 1.0))
        weight = torch.from_numpy(0.5 * top * w)
        return float(2.0 * math.pi * (self._profile(g) * torch.sin(g) * weight).sum())

    def _profile(self, g: Tensor) -> Tensor:
        if self.kind == "gaussian":
            return torch.exp(-0.5 * (g / self.sigma) ** 2)
        return torch.exp(-((g / self.sigma) ** self.power))

    def density_xy(self, lx: Tensor, ly: Tensor, centre: Tensor) -> Tensor:
        """:meth:`density` at points given by their coordinates ``lx, ly (*)``, ``centre (*, 3)``
        broadcasting: the same values, without building ``(*, 2)`` points for Gaussian kernels."""
        if self.kind != "gaussian":
            return self.density(torch.stack(torch.broadcast_tensors(lx, ly), -1), centre)
        r2 = lx * lx + ly * ly
        inside = r2 < 1.0
        normaliser = self._radial_normaliser()
        if self.domain == "projected":
            d2 = (lx - centre[..., 0]) ** 2 + (ly - centre[..., 1]) ** 2
            return torch.where(inside, torch.exp(-0.5 / self.sigma**2 * d2) / normaliser, torch.zeros_like(d2))
        wz = torch.sqrt(torch.where(inside, 1.0 - r2, torch.ones_like(r2)))
        chord = torch.sqrt((lx - centre[..., 0]) ** 2 + (ly - centre[..., 1]) ** 2 + (wz - centre[..., 2]) ** 2)
        g = 2.0 * torch.asin((0.5 * chord).clamp(max=1.0))
        return torch.where(inside, torch.exp(-0.5 / self.sigma**2 * g * g) / normaliser / wz, torch.zeros_like(g))

    def density(self, l: Tensor, centre: Tensor) -> Tensor:
        """Kernel density per unit l-plane area at ``l (*, 2)`` for frames centred at
        ``centre (*, 3)`` (broadcasting); 0 at and beyond the horizon."""
        if self.kind in ("point", "unknown"):
            raise TorchspecError(f"a {self.kind} kernel has no density to integrate.")
        inside = (l * l).sum(-1) < 1.0
        if self.kind == "tabulated":
            return torch.where(inside, self._table_density(l - centre[..., :2]), torch.zeros_like(l[..., 0]))
        normaliser = self._radial_normaliser()
        if self.domain == "projected":
            r2 = ((l - centre[..., :2]) ** 2).sum(-1)
            return torch.where(inside, torch.exp(-0.5 * r2 / self.sigma**2) / normaliser, torch.zeros_like(r2))
        w = from_plane(l)
        # The angle from the chord, exact and (unlike acos) stable at the centre.
        g = 2.0 * torch.asin((0.5 * torch.linalg.vector_norm(w - centre, dim=-1)).clamp(max=1.0))
        wz = torch.where(inside, w[..., 2], torch.ones_like(w[..., 2]))
        return torch.where(inside & (wz > 0), self._profile(g) / normaliser / wz, torch.zeros_like(g))

    def _table_density(self, offset: Tensor) -> Tensor:
        coeff = F.pad(self.table.to(dtype=offset.dtype, device=offset.device), (SPLINE_PAD,) * 4)
        hk, wk = self.table.shape
        size_y, size_x = coeff.shape
        # Continuous pixel coordinates in the padded table: column from x, row from -y (row 0 is +y).
        fx = (offset[..., 0] / self.extent + 1.0) * (wk / 2.0) - 0.5 + SPLINE_PAD
        fy = (1.0 - offset[..., 1] / self.extent) * (hk / 2.0) - 0.5 + SPLINE_PAD
        value = torch.zeros_like(fx)
        ix0, iy0 = torch.floor(fx), torch.floor(fy)
        tx, ty = fx - ix0, fy - iy0
        wx, wy = bspline_weights(tx), bspline_weights(ty)
        for a in range(4):
            iy = iy0.long() + a - 1
            for b in range(4):
                ix = ix0.long() + b - 1
                ok = (ix >= 0) & (ix < size_x) & (iy >= 0) & (iy < size_y)
                c = coeff[iy.clamp(0, size_y - 1), ix.clamp(0, size_x - 1)]
                value = value + torch.where(ok, wy[a] * wx[b] * c, torch.zeros_like(c))
        area = (2.0 * self.extent / wk) * (2.0 * self.extent / hk)
        # Each B-spline integrates to one pixel: the spline's mass is sum(coefficients) = sum(table).
        return value / (self.table.to(dtype=offset.dtype, device=offset.device).sum() * area)


@dataclass(frozen=True)
class Lights:
    """The K frames' lights.

    Attributes:
        directions: ``(K, 3)`` unit kernel centres.
        kernel: the shared :class:`Kernel`.
        irradiance: ``(K, C)`` or ``(K, 1)``.
        exposure: ``(K,)``.
    """

    directions: Tensor
    kernel: Kernel
    irradiance: Tensor
    exposure: Tensor

    def __post_init__(self):
        k = self.directions.shape[0]
        if self.directions.dim() != 2 or self.directions.shape[1] != 3:
            raise TorchspecError(f"Lights.directions must have shape (K, 3); got {tuple(self.directions.shape)}.")
        if self.irradiance.dim() != 2 or self.irradiance.shape[0] != k:
            raise TorchspecError(
                f"Lights.irradiance must have shape ({k}, C) or ({k}, 1); got {tuple(self.irradiance.shape)}."
            )
        if tuple(self.exposure.shape) != (k,):
            raise TorchspecError(f"Lights.exposure must have shape ({k},); got {tuple(self.exposure.shape)}.")
        if bool((self.directions[:, 2] <= 0).any()):
            raise TorchspecError("Lights.directions must lie above the horizon (z > 0 in every row).")
        # Quantities that depend on the lights only (effective diffuse directions), computed once
        # per object: a fit renders the same lights at every solver step.
        object.__setattr__(self, "_cache", {})

    @property
    def scale(self) -> Tensor:
        """``exposure * irradiance``: ``(K, C)`` or ``(K, 1)``."""
        return self.exposure[:, None] * self.irradiance

    def to(self, *args, **kwargs) -> Lights:
        """Tensors moved or cast like :meth:`torch.Tensor.to` (the same object when nothing changes)."""
        moved = [t.to(*args, **kwargs) for t in (self.directions, self.irradiance, self.exposure)]
        if all(m is t for m, t in zip(moved, (self.directions, self.irradiance, self.exposure), strict=True)):
            return self
        return Lights(moved[0], self.kernel, moved[1], moved[2])

    def __getitem__(self, index) -> Lights:
        """The frames ``index`` (a list of frame numbers, a slice, a bool mask or an index tensor) as
        lights of their own: e.g. the frames a fit left out, to predict them."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        elif isinstance(index, (list, tuple)):
            index = torch.as_tensor(index, dtype=torch.long, device=self.directions.device)
        return Lights(self.directions[index], self.kernel, self.irradiance[index], self.exposure[index])


def polar_nodes(
    centre: Tensor, shape: Tensor, reach: Tensor | float, *, radial: int, angular: int
) -> tuple[Tensor, Tensor]:
    """Polar quadrature in the l-plane about ``centre (*, 2)``, clipped at the unit circle: nodes
    ``(*, Q, 2)`` and area weights ``(*, Q)``, ``Q = radial * angular``.

    The polar grid lives in whitened coordinates: ``l = centre + shape @ (r cos psi, r sin psi)``
    for ``r <= reach``, so an elongated integrand (an anisotropic lobe) gets an elliptic grid.
    Trapezoid in the angle, Gauss-Legendre in ``r`` on ``[0, min(reach, exit)]``, ``exit`` where
    the ray leaves the unit disk: the horizon is integrated exactly, not by a cut weight. The
    radius is mapped so that its slope vanishes at the exit (the square-root slope of ``w_z``
    there would otherwise slow Gauss-Legendre down to algebraic convergence).

    Args:
        centre: ``(*, 2)`` inside the unit disk.
        shape: ``(*, 2, 2)`` invertible (a Cholesky factor of the integrand's covariance).
        reach: ``(*)`` or a number, in whitened units.
    """
    x, w = legendre(radial, centre)
    psi = torch.arange(angular, dtype=centre.dtype, device=centre.device) * (2.0 * math.pi / angular)
    u = torch.stack([torch.cos(psi), torch.sin(psi)], -1)  # (A, 2)
    step = (shape[..., None, :, :] @ u[:, :, None])[..., 0]  # (*, A, 2): l moves by r * step
    # exit: the positive root of |c + r step|^2 = 1.
    a = (step * step).sum(-1)
    b = (centre[..., None, :] * step).sum(-1)
    c2 = (centre * centre).sum(-1, keepdim=True)
    exit_ = (-b + torch.sqrt((b * b - a * (c2 - 1.0)).clamp(min=0.0))) / a
    reach = torch.as_tensor(reach, dtype=centre.dtype, device=centre.device)
    top = torch.minimum(exit_, reach[..., None] if reach.dim() else reach).clamp(min=0.0)  # (*, A)
    # On rays that end at the horizon, r = top s (2 - s) for s in [0, 1]: dr / ds vanishes there,
    # where w_z = sqrt(1 - |l|^2) has an infinite slope that would slow Gauss-Legendre down.
    s = 0.5 * (x + 1.0)
    at_exit = (exit_ < (reach[..., None] if reach.dim() else reach))[..., None]
    r = top[..., None] * torch.where(at_exit, s * (2.0 - s), s)  # (*, A, R)
    dr = top[..., None] * torch.where(at_exit, 2.0 * (1.0 - s), torch.ones_like(s)) * 0.5 * w
    jacobian = torch.linalg.det(shape)[..., None, None].abs()
    weight = dr * r * (2.0 * math.pi / angular) * jacobian
    points = centre[..., None, None, :] + r[..., None] * step[..., :, None, :]
    return points.flatten(-3, -2), weight.flatten(-2)


def nodes(lights: Lights, *, order: int = 24) -> tuple[Tensor, Tensor]:
    """Kernel-centred quadrature of every frame: directions ``(K, Q, 3)`` and weights ``(K, Q)``
    (the kernel's density times the node's area), so that a frame's integral of ``f`` is
    ``sum_q weights[k, q] f(directions[k, q])``. The weights sum to the kernel's mass above the
    horizon (1 for a point light).

    Args:
        order: Gauss-Legendre nodes in the radius; twice as many angles.
    """
    kernel, centre = lights.kernel, lights.directions
    if kernel.kind == "unknown":
        raise TorchspecError(
            "the light kernel is 'unknown': rendering needs its shape. Calibrate it (a tabulated "
            "kernel) or pass a known light description."
        )
    if kernel.kind == "point":
        return centre[:, None, :], torch.ones_like(centre[:, :1])
    mean, shape, reach = kernel.grid(centre)
    points, area = polar_nodes(mean, shape, reach, radial=order, angular=2 * order)
    weight = area * kernel.density(points, centre[:, None, :])
    return from_plane(points), weight


def diffuse_directions(lights: Lights, *, order: int = 32) -> Tensor:
    """Effective diffuse directions ``d_k = integral K_k(w) w dmu`` ``(K, 3)``: the diffuse term
    of a frame is ``k_d / pi <n, d_k>`` wherever the kernel lies in the normal's hemisphere.
    Computed once per :class:`Lights` object and order (a fit renders the same lights at every
    solver step); a caller that modifies ``directions`` in place gets a fresh value."""
    cache = lights.__dict__.setdefault("_cache", {})
    key = ("diffuse_directions", order, lights.directions._version)
    if key not in cache:
        directions, weight = nodes(lights, order=order)
        cache[key] = (weight[..., None] * directions).sum(-2)
    return cache[key]
