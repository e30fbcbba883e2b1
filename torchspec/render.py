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
  is sharp for a point-like light; the integral is taken about whichever is narrower.

Paths of the specular term, chosen by the rule of :func:`choose_path`:

- ``point``: a point light, one exact evaluation per frame.
- ``fast``: Gauss-Hermite on the product of two Gaussians in the l-plane, the kernel's (exact for
  a Gaussian kernel) and the Ward lobe's linearised about the mirror direction; the ratio of the
  true integrand to that product is smooth, so ``FAST_ORDER^2`` nodes per pixel and frame suffice.
- ``reference``: polar Gauss-Legendre about the centre of the narrower of kernel and lobe, out to
  ``KERNEL_REACH`` widths and clipped at the horizon: accurate for any kernel, ``order`` sets the
  accuracy (``order`` radii x ``2 order`` angles per pixel and frame).

Nodes are placed from the parameters (the lobe's mirror point and width) and autograd follows
them, so the gradient is exactly that of the value computed - the consistent Jacobian that
Levenberg-Marquardt needs - and converges to the true derivative with the quadrature. Pixels are
processed in chunks so that memory stays bounded for (pixels x frames x nodes).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .brdf import SVBRDF, beckmann_cosine, lambert
from .geometry import dot, from_plane, reflect, tangent_frame
from .lights import (
    Kernel,
    Lights,
    clamped_diffuse,
    diffuse_directions,
    polar_nodes,
)

__all__ = ["render", "choose_path", "PATHS", "FAST_ORDER", "REFERENCE_ORDER", "DIFFUSE_ORDER"]

PATHS = ("auto", "point", "fast", "reference")
FAST_ORDER = 4  # Gauss-Hermite nodes per axis of the fast path
REFERENCE_ORDER = 16  # Gauss-Legendre radii of the reference path (twice as many angles)
DIFFUSE_ORDER = 12  # Gauss-Legendre nodes per piece of the clamped diffuse integral
HORIZON_MARGIN = 5.5  # kernel stds between its mean and the normal's horizon for the clamp to matter
INSIDE = 4.0  # the fast path needs the kernel this many widths inside the horizon
LOBE_REACH = 7.0  # the lobe is integrated out to this many (linearised) widths
BUDGET = 1 << 20  # pixel x frame x node elements per chunk


def _lobe(svbrdf: SVBRDF, view: Tensor) -> tuple[Tensor, Tensor]:
    """Mirror point ``(N, 2)`` and covariance ``(N, 2, 2)`` of each pixel's Ward lobe in the
    l-plane, linearised: ``h = n + d_s s + d_t t`` with ``d ~ N(0, diag(a_x^2, a_y^2) / 2)``, and
    ``w = 2 <v, h> h - v``."""
    n = svbrdf.normal
    v = view.expand_as(n)
    s, t = tangent_frame(n, svbrdf.rotation)
    alpha = torch.where(svbrdf.roughness > 0, svbrdf.roughness, torch.ones_like(svbrdf.roughness))
    vn = dot(v, n)[..., None]
    ds = 2.0 * (dot(v, s)[..., None] * n + vn * s)  # dw / d(d_s)
    dt = 2.0 * (dot(v, t)[..., None] * n + vn * t)
    jac = torch.stack([ds[..., :2], dt[..., :2]], -1)  # (N, 2, 2): columns are d_s, d_t
    cov = jac @ torch.diag_embed(0.5 * alpha**2) @ jac.transpose(-1, -2)
    return reflect(v, n)[..., :2], cov


def _width(cov: Tensor) -> Tensor:
    """Largest std ``(*)`` of covariances ``(*, 2, 2)``."""
    return torch.linalg.eigvalsh(cov)[..., -1].clamp(min=0.0).sqrt()


def _hermite(order: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """2D standard-normal Gauss-Hermite rule: points ``(Q, 2)``, weights ``(Q,)`` summing to 1."""
    x, w = np.polynomial.hermite.hermgauss(order)
    x = torch.tensor(x * math.sqrt(2.0), dtype=like.dtype, device=like.device)
    w = torch.tensor(w / math.sqrt(math.pi), dtype=like.dtype, device=like.device)
    grid = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    return grid, (w[:, None] * w[None, :]).reshape(-1)


def choose_path(lights: Lights, path: str = "auto") -> str:
    """The specular path of the frames.

    ``auto``: ``point`` for a point light; ``fast`` for a Gaussian kernel (either domain), whose
    pixel-frame pairs fall back to ``reference`` where the product of kernel and lobe reaches
    the horizon (within ``INSIDE`` widths: a Gaussian rule cannot follow the cut); ``reference``
    for super-Gaussian and tabulated kernels, whose shape a Gaussian rule cannot follow.
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

    def split(v):
        return tuple(v[:, j, None, None] for j in range(3))

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


def _lobe_at(lx: Tensor, ly: Tensor, p: _Pixels) -> Tensor:
    """The Ward lobe times the cosine, ``ward_cosine``, at l-plane points ``(N, F, Q)``, written
    componentwise (no 3-vectors, no reductions): the hot loop of every path."""
    r2 = lx * lx + ly * ly
    inside = r2 < 1.0
    wz = torch.sqrt(torch.where(inside, 1.0 - r2, torch.ones_like(r2)))
    (nx, ny, nz), (sx, sy, sz), (tx, ty, tz) = p.n, p.s, p.t
    vx, vy, vz = p.view
    cos_light = nx * lx + ny * ly + nz * wz
    front = inside & (cos_light > 0) & (p.cos_view > 0)
    hx, hy, hz = lx + vx, ly + vy, wz + vz
    hn = nx * hx + ny * hy + nz * hz
    hs = (sx * hx + sy * hy + sz * hz) * p.inv_ax
    ht = (tx * hx + ty * hy + tz * hz) * p.inv_ay
    safe_hn = torch.where(front, hn, torch.ones_like(hn))
    ratio = torch.where(front, cos_light, torch.ones_like(cos_light)) / torch.where(p.cos_view > 0, p.cos_view, 1.0)
    value = torch.exp(-(hs * hs + ht * ht) / (safe_hn * safe_hn)) * torch.sqrt(ratio) * p.scale
    return torch.where(front, value, torch.zeros_like(value))


def _product_rule(kernel: Kernel, centre: Tensor, lobe_centre: Tensor, lobe_cov: Tensor, order: int):
    """Gauss-Hermite nodes ``(N, F, Q)`` (x and y) and weights of the product of each frame's
    kernel Gaussian and each pixel's lobe Gaussian, with the proposal density divided out; 2 x 2
    algebra in closed form."""
    kernel_cov = kernel.covariance(centre)  # (F, 2, 2)
    kernel_mean = centre[:, :2] + kernel.offset(centre)

    def inverse(c):
        det = c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0]
        return torch.stack([c[..., 1, 1], -c[..., 0, 1], -c[..., 1, 0], c[..., 0, 0]], -1) / det[..., None]

    ik = inverse(kernel_cov)[None]  # (1, F, 4): a, b, c, d of [[a, b], [c, d]]
    il = inverse(lobe_cov)[:, None]  # (N, 1, 4)
    a, b, d = ik[..., 0] + il[..., 0], ik[..., 1] + il[..., 1], ik[..., 3] + il[..., 3]  # precision
    det = a * d - b * b
    cxx, cxy, cyy = d / det, -b / det, a / det  # covariance of the product
    rx = ik[..., 0] * kernel_mean[None, :, 0] + ik[..., 1] * kernel_mean[None, :, 1]
    rx = rx + il[..., 0] * lobe_centre[:, None, 0] + il[..., 1] * lobe_centre[:, None, 1]
    ry = ik[..., 2] * kernel_mean[None, :, 0] + ik[..., 3] * kernel_mean[None, :, 1]
    ry = ry + il[..., 2] * lobe_centre[:, None, 0] + il[..., 3] * lobe_centre[:, None, 1]
    mx, my = cxx * rx + cxy * ry, cxy * rx + cyy * ry
    l11 = torch.sqrt(cxx)
    l21 = cxy / l11
    l22 = torch.sqrt((cyy - l21 * l21).clamp(min=0.0))
    points, weights = _hermite(order, centre)
    xi, eta = points[:, 0], points[:, 1]
    lx = mx[..., None] + l11[..., None] * xi
    ly = my[..., None] + l21[..., None] * xi + l22[..., None] * eta
    # weight over the standard-normal density, times the Jacobian det(L) of the map.
    area = (weights / (torch.exp(-0.5 * (points * points).sum(-1)) / (2.0 * math.pi))) * (l11 * l22)[..., None]
    width = torch.sqrt(0.5 * (cxx + cyy) + torch.sqrt((0.25 * (cxx - cyy) ** 2 + cxy * cxy).clamp(min=0.0)))
    return lx, ly, area, mx, my, width


def _reference_rule(kernel: Kernel, centre: Tensor, lobe_centre: Tensor, lobe_cov: Tensor, order: int):
    """Polar Gauss-Legendre nodes about the narrower of lobe and kernel, on a grid shaped like
    it and clipped at the horizon. ``centre (*, 3)``, ``lobe_centre (*, 2)`` and ``lobe_cov
    (*, 2, 2)`` broadcast together: x, y and area weights ``(*, Q)``."""
    kernel_cov = kernel.covariance(centre)
    lobe_first = _width(lobe_cov) < _width(kernel_cov)
    kernel_mean, kernel_shape, kernel_reach = kernel.grid(centre)
    lobe_first, lobe_centre, kernel_mean = torch.broadcast_tensors(lobe_first[..., None], lobe_centre, kernel_mean)
    lobe_first = lobe_first[..., 0]
    middle = torch.where(lobe_first[..., None], lobe_centre, kernel_mean)
    shape = torch.where(lobe_first[..., None, None], torch.linalg.cholesky(lobe_cov), kernel_shape)
    reach = torch.where(
        lobe_first, torch.full_like(middle[..., 0], LOBE_REACH), torch.full_like(middle[..., 0], kernel_reach)
    )
    l, area = polar_nodes(middle, shape, reach, radial=order, angular=2 * order)
    return l[..., 0], l[..., 1], area


def _integrate(kernel, centre, pixels, lx, ly, area) -> Tensor:
    density = kernel.density_xy(lx, ly, centre[..., None, :])
    return (area * density * _lobe_at(lx, ly, pixels)).sum(-1)


def _integrate_beckmann(svbrdf: SVBRDF, view: Tensor):
    """The node integration with :func:`torchspec.brdf.beckmann_cosine` in place of Ward's lobe."""

    def integrate(kernel, centre, pixels, lx, ly, area, index=None):
        part = svbrdf if index is None else svbrdf[index]
        shape = (-1,) + (1,) * (lx.dim() - 1)
        w = from_plane(torch.stack(torch.broadcast_tensors(lx, ly), -1))
        rotation = None if part.rotation is None else part.rotation.reshape(shape)
        lobe = beckmann_cosine(
            w, view, part.normal.reshape(*shape, 3), part.roughness.reshape(*shape, 2), rotation
        )
        return (area * kernel.density_xy(lx, ly, centre[..., None, :]) * lobe).sum(-1)

    return integrate


_COMPILED = {}


def _integrator(compiled: bool):
    """The node integration, eager or fused by ``torch.compile`` (built on first use, kept)."""
    if not compiled:
        return _integrate
    if "integrate" not in _COMPILED:
        _COMPILED["integrate"] = torch.compile(_integrate, dynamic=True)
    return _COMPILED["integrate"]


def _specular(svbrdf, lights, view, path, orders, compiled=False, lobe="ward") -> Tensor:
    """``integral D_k S dl`` for the pixels of ``svbrdf (N,)`` and every frame: ``(N, K)``.

    Nodes are placed from the parameters (the lobe's mirror point and width) and autograd
    follows them, so the gradient is exactly that of the value computed.
    """
    kernel, centre = lights.kernel, lights.directions
    pixels = _pixels(svbrdf, view)
    integrate = _integrator(compiled) if lobe == "ward" else _integrate_beckmann(svbrdf, view)
    if path == "point":
        if lobe == "beckmann":
            return beckmann_cosine(centre[None], view, svbrdf.normal[:, None], svbrdf.roughness[:, None],
                                   None if svbrdf.rotation is None else svbrdf.rotation[:, None])
        return _lobe_at(centre[None, :, None, 0], centre[None, :, None, 1], pixels)[..., 0]
    lobe_centre, lobe_cov = _lobe(svbrdf, view)  # (N, 2), (N, 2, 2)
    if path == "reference":
        rule = _reference_rule(kernel, centre[None], lobe_centre[:, None], lobe_cov[:, None], orders["reference"])
        return integrate(kernel, centre[None], pixels, *rule)
    lx, ly, area, mx, my, width = _product_rule(kernel, centre, lobe_centre, lobe_cov, orders["fast"])
    value = integrate(kernel, centre[None], pixels, lx, ly, area)
    if path == "fast":
        return value
    # auto: the pairs whose kernel-lobe product reaches the horizon, by the reference rule.
    cut = (torch.sqrt(mx * mx + my * my) + INSIDE * width >= 1.0).nonzero()
    if cut.shape[0]:
        p, k = cut[:, 0], cut[:, 1]
        rule = _reference_rule(kernel, centre[k], lobe_centre[p], lobe_cov[p], orders["reference"])
        if lobe == "ward":
            exact = _integrate(kernel, centre[k][:, None], _pick(pixels, p), *(r[:, None] for r in rule))[:, 0]
        else:
            exact = integrate(kernel, centre[k][:, None], None, *(r[:, None] for r in rule), index=p)[:, 0]
        value = value.index_put((p, k), exact)
    return value


def _pick(pixels: _Pixels, index: Tensor) -> _Pixels:
    """The per-pixel quantities of the pixels ``index``."""

    def take(field):
        if isinstance(field, tuple):
            return field if isinstance(field[0], float) else tuple(c[index] for c in field)
        return field[index]

    return _Pixels(*(take(f) for f in pixels))


def _diffuse(normal: Tensor, lights: Lights, direction: Tensor) -> Tensor:
    """``integral D_k <n, w>^+`` ``(N, K)``: ``<n, d_k>``, clamped exactly where the kernel reaches
    behind the normal's horizon (:func:`torchspec.lights.clamped_diffuse`, for the pairs one
    ``nonzero`` per call picks).

    A pair is picked when the normal's horizon passes within ``HORIZON_MARGIN`` kernel stds of
    the kernel's mean: the signed distance ``g / |grad g|`` of ``g(l) = <n, w(l)>``, in units of
    the kernel's std along ``grad g``. Beyond that the kernel's mass behind the horizon, and the
    cosine's size there, are too small to matter (less than 1e-6 of the mass).
    """
    value = normal @ direction.T
    kernel = lights.kernel
    if kernel.kind == "point":  # the clamp is exact as it is
        return value.clamp(min=0.0)
    centre = lights.directions
    mean = centre[:, :2] + kernel.offset(centre)  # (K, 2)
    mz = torch.sqrt((1.0 - (mean * mean).sum(-1)).clamp(min=1e-12))
    g = normal[:, :2] @ mean.T + normal[:, 2:] * mz  # (N, K): the cosine at the kernel's mean
    grad = normal[:, None, :2] - normal[:, None, 2:] * (mean / mz[:, None])[None]  # (N, K, 2)
    cov = kernel.covariance(centre)  # (K, 2, 2)
    spread = torch.einsum("nki,kij,nkj->nk", grad, cov, grad).clamp(min=0.0).sqrt()
    pairs = (g < HORIZON_MARGIN * spread).nonzero()
    if pairs.shape[0]:
        p, k = pairs[:, 0], pairs[:, 1]
        exact = clamped_diffuse(lights.kernel, lights.directions[k], normal[p], value[p, k], order=DIFFUSE_ORDER)
        value = value.index_put((p, k), exact)
    return value


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
        svbrdf: parameters with leading dims ``*`` and ``C`` channels (or grey ``k_s``).
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
    for start in range(0, flat.shape[0], chunk):
        part = flat[start : start + chunk]
        specular = _specular(part, lights, view, chosen, orders, compile, lobe)
        diffuse = _diffuse(part.normal, lights, direction)
        value = lambert(part.diffuse)[:, None, :] * diffuse[..., None] + part.specular[:, None, :] * specular[..., None]
        out.append(value * lights.scale[None])
    return torch.cat(out).reshape(*lead, lights.directions.shape[0], count)
