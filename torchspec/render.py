"""The measurement model of ``capture-format.md``: what a pixel records under each frame's
extended light, differentiable in every SVBRDF parameter.

    value[p, k, c] = exposure_k irradiance_k,c integral D_k(l) rho_c(w(l), view; p) <n_p, w(l)> dl

(see :mod:`torchspec.lights` for the density ``D_k`` in the l-plane). Two terms:

- diffuse, ``k_d / pi integral D_k <n, w>^+``: the effective direction ``d_k`` of each frame gives
  it exactly as ``k_d / pi <n, d_k>`` when the kernel lies in the normal's hemisphere; where the
  kernel reaches behind the normal's horizon the clamped integral is taken piecewise between the
  horizon's crossings (:func:`torchspec.lights.clamped_cosine`).
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

import numpy as np
import torch
from torch import Tensor

from .brdf import SVBRDF, lambert, ward_cosine
from .geometry import dot, from_plane, reflect, tangent_frame
from .lights import (
    Lights,
    angular_reach,
    clamped_cosine,
    diffuse_directions,
    polar_nodes,
)

__all__ = ["render", "choose_path", "PATHS", "FAST_ORDER", "REFERENCE_ORDER", "DIFFUSE_ORDER"]

PATHS = ("auto", "point", "fast", "reference")
FAST_ORDER = 4  # Gauss-Hermite nodes per axis of the fast path
REFERENCE_ORDER = 16  # Gauss-Legendre radii of the reference path (twice as many angles)
DIFFUSE_ORDER = 16  # Gauss-Legendre nodes per line and segment of the exact clamped diffuse integral
INSIDE = 4.0  # the fast path needs the kernel this many widths inside the horizon
LOBE_REACH = 7.0  # the lobe is integrated out to this many (linearised) widths
BUDGET = 1 << 22  # pixel x frame x node elements per chunk


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


def choose_path(lights: Lights, path: str = "auto") -> list[str]:
    """The specular path of each frame.

    ``auto``: ``point`` for a point light; ``fast`` for a Gaussian kernel (either domain) whose
    mass lies ``INSIDE`` widths within the horizon; ``reference`` otherwise (a kernel reaching
    the horizon, super-Gaussian or tabulated kernels, whose shape a Gaussian rule cannot follow).
    A forced path must fit the kernel: ``point`` only for point lights, ``fast`` only for
    Gaussian kernels.
    """
    if path not in PATHS:
        raise ValueError(f"path must be one of {PATHS}; got {path!r}.")
    kernel = lights.kernel
    count = lights.directions.shape[0]
    if kernel.kind == "unknown":
        raise ValueError(
            "the light kernel is 'unknown': rendering needs its shape. Calibrate it into a tabulated "
            "kernel, or describe a known light (e.g. torchspec render --light FILE)."
        )
    if kernel.kind == "point":
        if path not in ("auto", "point"):
            raise ValueError(f"path {path!r} does not apply to a point light; use 'auto' or 'point'.")
        return ["point"] * count
    if path == "point":
        raise ValueError(f"path 'point' needs a point light; this one is {kernel.kind!r}.")
    if path == "fast" and kernel.kind != "gaussian":
        raise ValueError(f"path 'fast' needs a Gaussian kernel; this one is {kernel.kind!r}.")
    if path != "auto":
        return [path] * count
    if kernel.kind != "gaussian":
        return ["reference"] * count
    centre = lights.directions.detach().to("cpu", torch.float64)
    width = _width(kernel.covariance(centre))
    inside = (centre[:, :2].norm(dim=-1) + INSIDE * width) < 1.0
    return ["fast" if ok else "reference" for ok in inside.tolist()]


def _specular(svbrdf, lights, view, frames, path, order) -> Tensor:
    """``integral D_k S dl`` for the pixels of ``svbrdf (N,)`` and frames ``frames``: ``(N, F)``."""
    kernel = lights.kernel
    centre = lights.directions[frames]
    n = svbrdf.normal[:, None, :]
    alpha = svbrdf.roughness[:, None, :]
    rotation = None if svbrdf.rotation is None else svbrdf.rotation[:, None]
    v = view
    if path == "point":
        return ward_cosine(centre[None], v, n, alpha, rotation)
    # Nodes follow the parameters, so autograd gives the exact gradient of the value computed.
    lobe_centre, lobe_cov = _lobe(svbrdf, view)  # (N, 2), (N, 2, 2)
    kernel_cov = kernel.covariance(centre)  # (F, 2, 2)
    if path == "fast":
        inv_k = torch.linalg.inv(kernel_cov)[None]
        inv_l = torch.linalg.inv(lobe_cov)[:, None]
        cov = torch.linalg.inv(inv_k + inv_l)  # (N, F, 2, 2)
        kernel_mean = centre[:, :2] + kernel.offset(centre)
        mean = (cov @ (inv_k @ kernel_mean[None, :, :, None] + inv_l @ lobe_centre[:, None, :, None]))[..., 0]
        chol = torch.linalg.cholesky(cov)
        points, weights = _hermite(order, centre)
        l = mean[..., None, :] + (chol[..., None, :, :] @ points[:, :, None])[..., 0]  # (N, F, Q, 2)
        # weight / proposal density: the standard-normal density cancels in the ratio.
        density = torch.exp(-0.5 * (points * points).sum(-1)) / (2.0 * math.pi)
        area = weights / density * torch.linalg.det(chol)[..., None]
    else:
        # About the narrower of lobe and kernel, on a grid shaped like it.
        lobe_first = _width(lobe_cov)[:, None] < _width(kernel_cov)[None, :]  # (N, F)
        kernel_mean, kernel_shape, kernel_reach = kernel.grid(centre)
        middle = torch.where(lobe_first[..., None], lobe_centre[:, None, :], kernel_mean[None])
        lobe_shape = torch.linalg.cholesky(lobe_cov)[:, None]
        shape = torch.where(lobe_first[..., None, None], lobe_shape, kernel_shape[None])
        reach = torch.where(lobe_first, torch.full_like(middle[..., 0], LOBE_REACH), kernel_reach)
        l, area = polar_nodes(middle, shape, reach, radial=order, angular=2 * order)
    w = from_plane(l)
    value = kernel.density(l, centre[None, :, None, :]) * ward_cosine(
        w, v, n[..., None, :], alpha[..., None, :], None if rotation is None else rotation[..., None]
    )
    return (area * value).sum(-1)


def _diffuse(normal: Tensor, lights: Lights, direction: Tensor, reach: Tensor | None) -> Tensor:
    """``integral D_k <n, w>^+`` ``(N, K)``: ``<n, d_k>`` where the kernel lies in the normal's
    hemisphere, the exact clamped integral (:func:`torchspec.lights.clamped_cosine`) for the
    pairs whose kernel reaches behind the normal's horizon (one ``nonzero`` per call picks them)."""
    value = normal @ direction.T
    if reach is None:  # a point light: the clamp is exact as it is
        return value.clamp(min=0.0)
    behind = (normal @ lights.directions.T) < torch.sin(reach)[None, :]
    pairs = behind.nonzero()
    if pairs.shape[0]:
        exact = clamped_cosine(lights.kernel, lights.directions[pairs[:, 1]], normal[pairs[:, 0]], order=DIFFUSE_ORDER)
        value = value.index_put((pairs[:, 0], pairs[:, 1]), exact)
    return value


def render(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    *,
    path: str = "auto",
    order: int | None = None,
) -> Tensor:
    """Predicted values of every pixel under every frame: ``(*, K, C)``.

    Args:
        svbrdf: parameters with leading dims ``*`` and ``C`` channels (or grey ``k_s``).
        lights: ``K`` frames; the kernel must be known (not ``unknown``).
        view: ``(3,)`` unit direction towards the camera.
        path: ``auto`` (the rule of :func:`choose_path`), ``point``, ``fast`` or ``reference``.
        order: nodes per axis of the chosen quadrature: ``FAST_ORDER`` (Gauss-Hermite) for
            ``fast``, ``REFERENCE_ORDER`` (Gauss-Legendre radii) for ``reference``, or the
            table's size if larger for a tabulated kernel (its spline has a knot per pixel).

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
    if view.shape != (3,):
        raise ValueError(f"view must have shape (3,); got {tuple(view.shape)}.")
    count = svbrdf.diffuse.shape[-1]
    if lights.irradiance.shape[1] not in (1, count):
        raise ValueError(
            f"lights.irradiance must have 1 or {count} channels (the SVBRDF's {svbrdf.channels}); "
            f"got {lights.irradiance.shape[1]}."
        )
    paths = choose_path(lights, path)
    lead = svbrdf.shape
    flat = svbrdf.flatten()
    like = flat.diffuse
    lights = lights.to(dtype=like.dtype, device=like.device)
    view = view.to(dtype=like.dtype, device=like.device)
    groups = {p: [k for k, q in enumerate(paths) if q == p] for p in dict.fromkeys(paths)}
    reference = REFERENCE_ORDER
    if lights.kernel.kind == "tabulated":  # a knot per pixel: at least one radius node per pixel
        reference = max(reference, max(lights.kernel.table.shape))
    orders = {"point": 1, "fast": order or FAST_ORDER, "reference": order or reference}

    if lights.kernel.kind == "point":
        direction, reach = lights.directions, None
    else:
        direction, reach = diffuse_directions(lights), angular_reach(lights)

    per_node = max(orders[p] ** 2 * (2 if p == "reference" else 1) for p in groups)
    chunk = max(1, BUDGET // (lights.directions.shape[0] * per_node))
    out = []
    for start in range(0, flat.shape[0], chunk):
        part = flat[start : start + chunk]
        specular = torch.zeros(part.shape[0], lights.directions.shape[0], dtype=like.dtype, device=like.device)
        for p, frames in groups.items():
            index = torch.tensor(frames, device=like.device)
            specular[:, index] = _specular(part, lights, view, index, p, orders[p])
        diffuse = _diffuse(part.normal, lights, direction, reach)
        value = lambert(part.diffuse)[:, None, :] * diffuse[..., None] + part.specular[:, None, :] * specular[..., None]
        out.append(value * lights.scale[None])
    return torch.cat(out).reshape(*lead, lights.directions.shape[0], count)
