"""Height from normals: the least-squares surface whose slopes are the fitted normals'.

Conventions (``docs/capture-format.md``): ``x`` along the image columns (right), ``y`` up, along
decreasing rows, ``z`` towards the camera. A height field ``h`` has the normal
``n ~ (-dh/dx, -dh/dy, 1)``, so in image axes

    dh/dcol = -n_x / n_z,        dh/drow = +n_y / n_z

(``torchspec.simulate.synth`` makes its normals from a height field the same way). Heights come out in the
unit of ``pitch``, the pixel pitch: ``pitch = 1`` (the default) gives heights in pixels, the unit of
``height.exr``; the pitch in millimetres gives millimetres. Their mean is 0: a normal map says
nothing of the absolute height.

The solve is least squares over the whole image on the grid's edges: between two neighbours the
height difference should be the mean of their two slopes (the trapezoid rule, exact for a
quadratic surface),

    min_h  sum_edges w_e (h_b - h_a - (g_a + g_b) / 2)^2,

whose normal equations are a graph Laplacian with Neumann boundaries. Unweighted, the discrete
cosine transform diagonalises it, so one pair of transforms (by FFT, on the input's device) solves
it exactly: the Frankot-Chellappa solve with an even extension, without its periodic artefacts.
With weights (the normals' confidence, e.g. ``1 / std^2``) the same system with edge weights is
solved by conjugate gradients preconditioned by the unweighted solve, started from the unweighted
solution, for a fixed number of iterations (no host synchronisation inside; the residual is checked
once at the end). An edge's weight is the harmonic mean of its two pixels' (an untrusted pixel cuts
its edges), plus ``floor`` times the mean weight, so that a region of untrusted pixels is filled
smoothly rather than left undetermined.
"""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor

from ..errors import TorchspecError

__all__ = ["height_from_normals", "normals_from_height", "slopes_from_normals", "dct", "idct", "poisson_solve"]


def dct(x: Tensor, dim: int = -1) -> Tensor:
    """Unnormalised DCT-II along ``dim``: ``X_k = sum_n x_n cos(pi k (2n + 1) / (2N))``, by an FFT of
    the even extension (any real float dtype, any device)."""
    x = x.movedim(dim, -1)
    n = x.shape[-1]
    spectrum = torch.fft.rfft(torch.cat([x, x.flip(-1)], -1), dim=-1)[..., :n]
    k = torch.arange(n, dtype=x.dtype, device=x.device)
    twiddle = torch.polar(torch.ones_like(k), -math.pi * k / (2 * n))
    return (0.5 * (spectrum * twiddle).real).movedim(-1, dim)


def idct(x: Tensor, dim: int = -1) -> Tensor:
    """The inverse of :func:`dct` along ``dim``."""
    x = x.movedim(dim, -1)
    n = x.shape[-1]
    k = torch.arange(n, dtype=x.dtype, device=x.device)
    twiddle = torch.polar(torch.ones_like(k), math.pi * k / (2 * n))
    spectrum = torch.cat([2.0 * x * twiddle, torch.zeros_like(x[..., :1]).to(twiddle.dtype)], -1)
    return torch.fft.irfft(spectrum, n=2 * n, dim=-1)[..., :n].movedim(-1, dim)


def _laplacian_eigenvalues(height: int, width: int, like: Tensor) -> Tensor:
    """``(H, W)`` eigenvalues of the Neumann grid Laplacian on the DCT-II basis (0 for the constant)."""
    kr = torch.arange(height, dtype=like.dtype, device=like.device)
    kc = torch.arange(width, dtype=like.dtype, device=like.device)
    return (2.0 - 2.0 * torch.cos(math.pi * kr / height))[:, None] + (2.0 - 2.0 * torch.cos(math.pi * kc / width))[None]


def poisson_solve(rhs: Tensor) -> Tensor:
    """The mean-zero solution ``h (*, H, W)`` of ``L h = rhs`` for the Neumann grid Laplacian ``L``
    (``(L h)_p = sum over the neighbours q of p of h_p - h_q``), by DCT; ``rhs``'s mean is ignored
    (the part ``L`` cannot reach)."""
    height, width = rhs.shape[-2:]
    eigen = _laplacian_eigenvalues(height, width, rhs)
    spectrum = dct(dct(rhs, -1), -2)
    spectrum = spectrum / torch.where(eigen > 0, eigen, torch.ones_like(eigen))
    spectrum = torch.where(eigen > 0, spectrum, torch.zeros_like(spectrum))
    return idct(idct(spectrum, -2), -1)


def _laplacian(h: Tensor, wc: Tensor, wr: Tensor) -> Tensor:
    """``D^T W D h``: the weighted Laplacian of ``h (*, H, W)`` with column-edge weights
    ``wc (*, H, W-1)`` and row-edge weights ``wr (*, H-1, W)``."""
    return _divergence(wc * (h[..., :, 1:] - h[..., :, :-1]), wr * (h[..., 1:, :] - h[..., :-1, :]))


def _divergence(fc: Tensor, fr: Tensor) -> Tensor:
    """``D^T f`` of edge values ``fc (*, H, W-1)`` (along columns) and ``fr (*, H-1, W)`` (along rows):
    each pixel gets ``f`` of the edge behind it minus ``f`` of the edge ahead of it."""
    zc = torch.zeros_like(fc[..., :, :1])
    zr = torch.zeros_like(fr[..., :1, :])
    return (torch.cat([zc, fc], -1) - torch.cat([fc, zc], -1)) + (torch.cat([zr, fr], -2) - torch.cat([fr, zr], -2))


def slopes_from_normals(normal: Tensor, max_slope: float) -> tuple[Tensor, Tensor, Tensor]:
    """``(dh/dcol, dh/drow, valid)`` of normals ``(*, H, W, 3)``: each ``(*, H, W)``; the slope's
    magnitude capped at ``max_slope`` keeping its direction (a normal at or below the horizon gets
    the cap), ``valid`` false where a component is not finite (slopes 0 there)."""
    valid = torch.isfinite(normal).all(-1)
    n = torch.where(valid[..., None], normal, torch.zeros_like(normal))
    nz = n[..., 2]
    tiny = torch.finfo(n.dtype).tiny
    flat = n[..., :2].square().sum(-1).sqrt()
    # The slope |n_xy| / n_z, capped: n_z <= |n_xy| / max_slope takes the cap.
    limit = flat / max_slope
    nz = torch.where(nz > limit, nz, limit)
    safe = torch.where(nz > tiny, nz, torch.ones_like(nz))
    gc = torch.where(nz > tiny, -n[..., 0] / safe, torch.zeros_like(nz))
    gr = torch.where(nz > tiny, n[..., 1] / safe, torch.zeros_like(nz))
    return gc, gr, valid & (flat + n[..., 2].abs() > 0)


def normals_from_height(height: Tensor, pitch: float = 1.0) -> Tensor:
    """Unit normals ``(*, H, W, 3)`` of a height field ``(*, H, W)`` in the unit of ``pitch``, by
    central differences (one-sided at the border): the inverse of :func:`height_from_normals` up to
    the discretisation."""
    h = height / pitch
    gc = torch.gradient(h, dim=-1)[0] if h.shape[-1] > 1 else torch.zeros_like(h)
    gr = torch.gradient(h, dim=-2)[0] if h.shape[-2] > 1 else torch.zeros_like(h)
    v = torch.stack([-gc, gr, torch.ones_like(h)], -1)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def _check(normal: Tensor, weight: Tensor | None, pitch: float) -> tuple[Tensor, Tensor | None]:
    if not isinstance(normal, Tensor) or normal.dim() not in (3, 4) or normal.shape[-1] != 3:
        shape = tuple(normal.shape) if isinstance(normal, Tensor) else type(normal).__name__
        raise TorchspecError(f"height_from_normals needs normals of shape (H, W, 3) or (B, H, W, 3); got {shape}.")
    if not normal.is_floating_point():
        raise TorchspecError(f"height_from_normals needs floating-point normals; got {normal.dtype}.")
    if min(normal.shape[-3:-1]) < 1:
        raise TorchspecError(
            f"height_from_normals needs a non-empty image; got normals of shape {tuple(normal.shape)}."
        )
    if not (isinstance(pitch, (int, float)) and math.isfinite(pitch) and pitch > 0):
        raise TorchspecError(f"height_from_normals needs a finite pitch > 0 (the pixel pitch); got {pitch!r}.")
    batched = normal.dim() == 4
    normal = normal if batched else normal[None]
    if weight is not None:
        size = tuple(normal.shape[1:3])
        if not isinstance(weight, Tensor) or weight.dim() not in (2, 3) or tuple(weight.shape[-2:]) != size:
            shape = tuple(weight.shape) if isinstance(weight, Tensor) else type(weight).__name__
            raise TorchspecError(
                f"height_from_normals: weight must have shape (H, W) or (B, H, W) = {tuple(normal.shape[1:3])} "
                f"like the normals; got {shape}."
            )
        weight = weight.to(device=normal.device, dtype=normal.dtype)
        weight = weight if weight.dim() == 3 else weight[None]
        weight = weight.expand(normal.shape[0], -1, -1)
    return normal, weight


def height_from_normals(
    normal: Tensor,
    weight: Tensor | None = None,
    pitch: float = 1.0,
    *,
    max_slope_deg: float = 85.0,
    iterations: int = 200,
    tol: float | None = None,
    floor: float = 1e-3,
) -> Tensor:
    """The least-squares height field of a normal map (the module's docstring gives the model).

    Args:
        normal: unit normals ``(H, W, 3)`` or a batch ``(B, H, W, 3)``, surface frame; NaN or Inf
            marks a pixel without a normal (weight 0).
        weight: the normals' confidence ``(H, W)`` or ``(B, H, W)``, e.g. ``1 / std^2`` (0: untrusted,
            ignored; NaN or Inf count as 0). ``None``: all pixels alike, solved in closed form.
        pitch: the pixel pitch in the unit wanted for the heights (1: heights in pixels).
        max_slope_deg: normals tilted further are taken at this tilt (keeping their azimuth).
        iterations: conjugate-gradient iterations of the weighted solve.
        tol: a weighted solve whose relative residual ends above it warns (one host sync); default
            the square root of the dtype's epsilon.
        floor: every edge's weight is raised by ``floor`` times the mean weight.

    Returns:
        Heights ``(H, W)`` (or ``(B, H, W)``), mean 0 over each image, in ``normal``'s dtype and
        on its device.

    Raises:
        TorchspecError: a shape other than ``(H, W, 3)`` / ``(B, H, W, 3)``, a weight of another
            size, a pitch that is not a positive number (the message names it).

    Example:
        >>> rows, cols = torch.meshgrid(torch.arange(6.0), torch.arange(8.0), indexing="ij")
        >>> n = normals_from_height(0.5 * cols - 0.25 * rows)
        >>> h = height_from_normals(n)
        >>> round(float(h[0, 1] - h[0, 0]), 6), round(float(h[1, 0] - h[0, 0]), 6)
        (0.5, -0.25)
    """
    batched = normal.dim() == 4 if isinstance(normal, Tensor) else False
    normal, weight = _check(normal, weight, pitch)
    gc, gr, valid = slopes_from_normals(normal, math.tan(math.radians(max_slope_deg)))
    # Target height differences on the edges: the mean of the two pixels' slopes.
    tc = 0.5 * (gc[..., :, 1:] + gc[..., :, :-1])
    tr = 0.5 * (gr[..., 1:, :] + gr[..., :-1, :])
    if weight is None and bool(valid.all()):
        height = poisson_solve(_divergence(tc, tr))
    else:
        height = _weighted(tc, tr, valid, weight, iterations, tol, floor)
    height = height * pitch
    return height if batched else height[0]


def _weighted(tc, tr, valid, weight, iterations: int, tol: float | None, floor: float) -> Tensor:
    """Preconditioned conjugate gradients on ``D^T W D h = D^T W t`` (module docstring)."""
    w = valid.to(tc.dtype) if weight is None else weight
    w = torch.where(valid & torch.isfinite(w) & (w > 0), w, torch.zeros_like(w))
    mean = w.mean(dim=(-2, -1), keepdim=True)
    mean = torch.where(mean > 0, mean, torch.ones_like(mean))
    w = w / mean  # mean weight 1: the preconditioner's scale

    def harmonic(a, b):
        s = a + b
        return torch.where(s > 0, 2.0 * a * b / torch.where(s > 0, s, torch.ones_like(s)), torch.zeros_like(s))

    wc = harmonic(w[..., :, 1:], w[..., :, :-1])
    wr = harmonic(w[..., 1:, :], w[..., :-1, :])
    # An edge that touches an untrusted pixel carries no slope: at the floor weight it asks for flatness.
    tc = torch.where(wc > 0, tc, torch.zeros_like(tc))
    tr = torch.where(wr > 0, tr, torch.zeros_like(tr))
    wc, wr = wc + floor, wr + floor
    b = _divergence(wc * tc, wr * tr)
    scale = 0.5 * (wc.mean(dim=(-2, -1), keepdim=True) + wr.mean(dim=(-2, -1), keepdim=True))
    h = poisson_solve(_divergence(tc, tr))
    r = b - _laplacian(h, wc, wr)
    z = poisson_solve(r) / scale
    p = z
    rz = (r * z).sum(dim=(-2, -1), keepdim=True)
    # An image whose residual has fallen to rounding stops moving (in place of a host-side test).
    floor_rz = rz * torch.finfo(rz.dtype).eps ** 2
    for _ in range(iterations):
        ap = _laplacian(p, wc, wr)
        pap = (p * ap).sum(dim=(-2, -1), keepdim=True)
        active = (rz > floor_rz) & (pap > 0)
        alpha = torch.where(active, rz / torch.where(active, pap, torch.ones_like(pap)), torch.zeros_like(pap))
        h = h + alpha * p
        r = r - alpha * ap
        z = poisson_solve(r) / scale
        rz_new = (r * z).sum(dim=(-2, -1), keepdim=True)
        beta = torch.where(active, rz_new / torch.where(active, rz, torch.ones_like(rz)), torch.zeros_like(rz))
        p = z + beta * p
        rz = torch.where(active, rz_new, rz)
    tol = math.sqrt(torch.finfo(b.dtype).eps) if tol is None else tol
    residual = (b - _laplacian(h, wc, wr)).square().sum(dim=(-2, -1)).sqrt()
    size = b.square().sum(dim=(-2, -1)).sqrt()
    if bool((residual > tol * size.clamp(min=torch.finfo(b.dtype).tiny)).any()):
        worst = float((residual / size.clamp(min=torch.finfo(b.dtype).tiny)).max())
        warnings.warn(
            f"height_from_normals: the weighted solve stopped at a relative residual {worst:.2g} "
            f"(above tol {tol:g}) after {iterations} iterations; raise iterations.",
            stacklevel=3,
        )
    return h - h.mean(dim=(-2, -1), keepdim=True)
