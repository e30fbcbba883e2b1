"""Cast shadows from a height field: each pixel's horizon along a light's azimuth, and a soft
visibility of the light against it.

A pixel ``p`` of a height field ``h`` (``torchspec.model.height``: rows down, columns right, surface ``y``
up) sees a light in direction ``w`` when the light's elevation ``e = atan2(w_z, |w_xy|)`` is above
the horizon along the light's azimuth,

    horizon(p, w) = max_{0 < t <= reach} atan((h(p + t d) - h(p)) / t),

``d`` the unit step in the image along ``w_xy`` (``+x`` = a column to the right, ``+y`` = a row
up) and ``t`` in pixels from ``step`` on (:func:`marched_distances`), heights in pixels
(``height / pitch``). The height is sampled bilinearly (``grid_sample``) along the ray, every
``step`` pixels but denser near the pixel, for all pixels and lights at once, in chunks of
lights and steps that bound the memory. Beyond the image border there is no occluder: a ray that
leaves the image ends there (a pixel at the border looking out sees down to ``-pi/2``).

The visibility is ``sigmoid((e - horizon) / softness)``: smooth in the height field and in the
light's direction, so its derivatives exist; ``softness`` (radians) is the width of the penumbra
in elevation. Near lights give a direction per pixel: ``(H, W, K, 3)`` directions are accepted
everywhere a ``(K, 3)`` one is.

Extended kernels (:func:`kernel_visibility`) average the visibility over the kernel. The default
rule, ``probit``, takes the kernel's spread along the elevation only: its l-plane covariance
(:meth:`torchspec.model.lights.Kernel.covariance`) along the radius gives the elevation variance
``s_e^2 = var_r / w_z^2`` (``|l| = cos e``), and a Gaussian in elevation against the sigmoid is
close to a sigmoid of widened softness (the probit approximation),
``E[sigmoid((e - H) / s)] ~ sigmoid((e_c - H) / sqrt(s^2 + pi s_e^2 / 8))``; the horizon is taken at
the centre's azimuth. The ``nodes`` rule integrates the visibility exactly on the kernel's own
quadrature (:func:`torchspec.model.lights.nodes`, ``order`` radial nodes): slower (one horizon per node),
the reference of the first.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from ..errors import TorchspecError
from .geometry import from_plane, spiral_plane
from .lights import Kernel, Lights, nodes
from .near_lights import image_points

__all__ = [
    "horizon",
    "visibility",
    "kernel_visibility",
    "frame_visibility",
    "frame_visibilities",
    "elevation",
    "shadow_reach",
    "marched_distances",
    "marched_horizon",
    "sky_view",
    "CHUNK_ELEMENTS",
    "FOOTPRINT",
    "SOFTNESS",
]

SOFTNESS = math.radians(1.0)
"""The default penumbra width in elevation, radians (1 degree)."""

FOOTPRINT = 2
""":func:`frame_visibility` averages each pixel's visibility over ``FOOTPRINT x FOOTPRINT`` points
of its footprint."""

EDGE = 1e-6
"""Pixels beyond the image's border a ray's sample still counts as inside: a light along an image
axis (``cos(270 degrees)`` is ``-1.8e-16``, not 0) would otherwise leave the border's rays in or
out by the sign of a rounding error."""

CHUNK_ELEMENTS = 1 << 18
"""The most height samples (pixels x lights x steps) one chunk of :func:`horizon` takes at once
(16 MB a float64 plane of them). Smaller is faster on the CPU, down to here: 10 lights over a
160 x 160 height took 7.1 s on one thread in chunks of 2^23 samples, 3.0 in chunks of 2^20, 2.1
in chunks of 2^18, 3.1 in chunks of 2^16 (the large chunks' buffers are paged in afresh each time)."""


def _check(height: Tensor, directions: Tensor, pitch: float, step: float) -> None:
    if not isinstance(height, Tensor) or height.dim() != 2 or not height.is_floating_point():
        shape = tuple(height.shape) if isinstance(height, Tensor) else type(height).__name__
        raise TorchspecError(f"a height field must be a floating-point tensor of shape (H, W); got {shape}.")
    size = tuple(height.shape)
    if not isinstance(directions, Tensor) or directions.shape[-1] != 3 or directions.dim() not in (2, 4):
        shape = tuple(directions.shape) if isinstance(directions, Tensor) else type(directions).__name__
        raise TorchspecError(f"light directions must have shape (K, 3) or (H, W, K, 3); got {shape}.")
    if directions.dim() == 4 and tuple(directions.shape[:2]) != size:
        raise TorchspecError(
            f"per-pixel light directions must have shape (H, W, K, 3) with (H, W) = {size} as the height "
            f"field; got {tuple(directions.shape)}."
        )
    for name, value in (("pitch", pitch), ("step", step)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise TorchspecError(f"{name} must be a finite number > 0; got {value!r}.")


def elevation(directions: Tensor) -> Tensor:
    """The elevation ``atan2(w_z, |w_xy|)`` of directions ``(*, 3)``, radians ``(*)``."""
    flat = torch.linalg.vector_norm(directions[..., :2], dim=-1)
    return torch.atan2(directions[..., 2], flat)


def _azimuth_steps(directions: Tensor) -> Tensor:
    """Unit image steps ``(*, 2)`` = (columns, rows) along the directions' azimuths; straight up
    (no azimuth) takes ``+x``, harmless since nothing shadows the zenith."""
    flat = torch.linalg.vector_norm(directions[..., :2], dim=-1, keepdim=True)
    ok = flat > 0
    u = directions[..., :2] / torch.where(ok, flat, torch.ones_like(flat))
    u = torch.where(ok, u, torch.tensor([1.0, 0.0], dtype=u.dtype, device=u.device))
    return torch.stack([u[..., 0], -u[..., 1]], -1)  # surface y is up: a row less


def marched_distances(step: float, reach: float, levels: int = 3) -> Tensor:
    """The distances (pixels, float64 on the CPU: a small table) at which :func:`horizon` samples a
    ray: from ``step`` on, ``2^levels`` times finer than ``step`` up to ``2 step``, half as fine
    again up to ``4 step``, ..., then every ``step``, up to ``reach`` (included): the angle of a near
    occluder changes fast with the distance, and every distance is a multiple of ``step / 2^levels``
    (whole pixels are sampled when ``step`` divides 1). A light is not hidden by what lies within
    ``step`` of the pixel: there the surface's own slope (its attached shadow, ``<n, w> <= 0``)
    decides."""
    near = [step * 2**level * (1.0 + i / 2**levels) for level in range(levels) for i in range(2**levels)]
    start = step * 2**levels
    far = [start + i * step for i in range(max(0, math.ceil((reach - start) / step)))]
    return torch.tensor([t for t in near + far if t < reach] + [reach], dtype=torch.float64, device="cpu")


def shadow_reach(height: Tensor, directions: Tensor, pitch: float = 1.0, margin: float = 0.0) -> float:
    """The farthest distance (pixels) at which the field can hide a light at elevation above the
    lowest of ``directions`` less ``margin`` (radians): its height range over that elevation's
    tangent, at most the image's diagonal (one host sync)."""
    rows, cols = height.shape
    diagonal = math.hypot(rows, cols)
    span = float(height.max() - height.min()) / pitch if height.numel() else 0.0
    low = float(elevation(directions.detach()).min()) - margin
    if low <= 0:
        return diagonal
    return min(diagonal, span / math.tan(low) + 1.0)


def horizon(
    height: Tensor,
    directions: Tensor,
    pitch: float = 1.0,
    *,
    step: float = 0.5,
    reach: float | None = None,
    distances: Tensor | None = None,
) -> Tensor:
    """The horizon elevation of every pixel along every light's azimuth (module docstring).

    Args:
        height: the height field ``(H, W)``, in the unit of ``pitch``.
        directions: light directions ``(K, 3)`` (distant lights) or ``(H, W, K, 3)`` (a direction per
            pixel: near lights); only their azimuth counts here. Need not be unit.
        pitch: the pixel pitch, in the height's unit (heights in pixels: 1).
        step: the largest distance between samples along the ray, and the nearest one, pixels.
        reach: how far the ray goes, pixels (default: the image's diagonal).
        distances: the distances (pixels, increasing, ``> 0``) at which each ray samples the
            height, in place of :func:`marched_distances` of ``step`` and ``reach`` (the viewer's
            sparser schedule, :func:`torchspec.view.shadows.view_distances`).

    Returns:
        ``(H, W, K)`` radians in ``[-pi/2, pi/2)``, the height's dtype and device; differentiable in
        ``height`` and ``directions``.

    Raises:
        TorchspecError: a height that is not ``(H, W)``, directions not ``(K, 3)`` or
            ``(H, W, K, 3)``, a pitch or step that is not a positive number.

    Example:
        >>> h = torch.zeros(5, 9, dtype=torch.float64)
        >>> h[2, 6] = 2.0  # a post two pixels right of the centre, 2 pixels high
        >>> east = torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64)
        >>> round(math.degrees(float(horizon(h, east)[2, 4, 0])), 3)
        45.0
    """
    _check(height, directions, pitch, step)
    rows, cols = height.shape
    h = height / pitch
    reach = math.hypot(rows, cols) if reach is None else float(reach)
    distances = marched_distances(step, reach) if distances is None else distances
    distances = distances.to(dtype=h.dtype, device=h.device)
    samples = distances.shape[0]
    directions = directions.to(h)
    per_pixel = directions.dim() == 4
    lights = directions.shape[-2]
    steps = _azimuth_steps(directions)  # (K, 2) or (H, W, K, 2)
    steps = steps.reshape(-1, lights, 2) if per_pixel else steps[None]  # (1 or P, K, 2)
    r = torch.arange(rows, dtype=h.dtype, device=h.device)
    c = torch.arange(cols, dtype=h.dtype, device=h.device)
    rr, cc = torch.meshgrid(r, c, indexing="ij")
    base = torch.stack([cc, rr], -1).reshape(-1, 1, 1, 2)  # (P, 1, 1, 2) as (col, row)
    here = h.reshape(-1, 1, 1)
    image = h[None, None]
    scale = torch.tensor([2.0 / max(cols - 1, 1), 2.0 / max(rows - 1, 1)], dtype=h.dtype, device=h.device)
    pixels = rows * cols
    pixel_chunk = max(1, min(pixels, CHUNK_ELEMENTS))
    light_chunk = max(1, min(lights, CHUNK_ELEMENTS // pixel_chunk))
    sample_chunk = max(1, min(samples, CHUNK_ELEMENTS // (pixel_chunk * light_chunk)))
    lowest = torch.finfo(h.dtype).max
    blocks = []
    for p0 in range(0, pixels, pixel_chunk):  # each sample independent of the others: the chunks change nothing
        p1 = min(pixels, p0 + pixel_chunk)
        origin, level = base[p0:p1], here[p0:p1]
        ray = steps if steps.shape[0] == 1 else steps[p0:p1]
        parts = []
        for k0 in range(0, lights, light_chunk):
            d = ray[:, k0 : k0 + light_chunk, None, :]  # (1 or p, k, 1, 2)
            best = torch.full((p1 - p0, d.shape[1]), -lowest, dtype=h.dtype, device=h.device)
            for s0 in range(0, samples, sample_chunk):
                t = distances[s0 : s0 + sample_chunk]
                at = origin + t[None, None, :, None] * d  # (p, k, s, 2) in (col, row)
                col, row = at[..., 0], at[..., 1]  # a ray along the border stays in: its rounding decides nothing
                inside = (col >= -EDGE) & (col <= cols - 1 + EDGE) & (row >= -EDGE) & (row <= rows - 1 + EDGE)
                grid = (at * scale - 1.0).reshape(1, p1 - p0, -1, 2)
                value = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
                rise = (value.reshape(p1 - p0, -1, t.shape[0]) - level) / t  # (p, k, s)
                rise = torch.where(inside, rise, torch.full_like(rise, -lowest))
                best = torch.maximum(best, rise.amax(-1))
            parts.append(torch.atan(best))
        blocks.append(torch.cat(parts, -1))
    return torch.cat(blocks, 0).reshape(rows, cols, lights)


def visibility(
    height: Tensor,
    directions: Tensor,
    pitch: float = 1.0,
    softness: float | Tensor = SOFTNESS,
    *,
    step: float = 0.5,
    reach: float | None = None,
) -> Tensor:
    """Soft visibility ``sigmoid((e - horizon) / softness)`` ``(H, W, K)`` in ``[0, 1]`` of lights in
    ``directions`` (``(K, 3)`` or per pixel ``(H, W, K, 3)``) over the height field ``(H, W)``.

    ``softness``: radians, a number or one per light ``(K,)``. ``reach`` defaults to
    :func:`shadow_reach` with a margin of 8 softnesses (farther occluders cannot change the value
    by more than ``sigmoid(-8)``, 3e-4). Other arguments as :func:`horizon`.

    Example:
        >>> flat = torch.zeros(4, 4, dtype=torch.float64)
        >>> low = torch.tensor([[0.9, 0.0, 0.2]], dtype=torch.float64)
        >>> bool((visibility(flat, low) > 0.999).all())
        True
    """
    _check(height, directions, pitch, step)
    soft = torch.as_tensor(softness, dtype=height.dtype, device=height.device)
    if not bool((soft > 0).all()):
        raise TorchspecError(f"softness must be > 0 (radians); got {softness!r}.")
    if reach is None:
        reach = shadow_reach(height, directions, pitch, margin=8.0 * float(soft.max()))
    e = elevation(directions.to(height))
    e = e if directions.dim() == 4 else e.expand(*height.shape, -1)
    return torch.sigmoid((e - horizon(height, directions, pitch, step=step, reach=reach)) / soft)


def kernel_visibility(
    height: Tensor,
    lights: Lights,
    pitch: float = 1.0,
    softness: float = SOFTNESS,
    *,
    rule: str = "probit",
    order: int = 4,
    step: float = 0.5,
) -> Tensor:
    """The visibility ``(H, W, K)`` of extended lights, averaged over each frame's kernel (the
    module docstring gives the two rules); a point light's is :func:`visibility` of its direction.

    Args:
        height: the height field ``(H, W)``, in the unit of ``pitch``.
        lights: distant lights (one direction per frame) and their kernel.
        rule: ``probit`` (closed form, elevation spread only) or ``nodes`` (the kernel's quadrature,
            ``order`` radial nodes and twice as many angles: ``2 order^2`` horizons per frame).

    Raises:
        TorchspecError: an unknown rule, an ``unknown`` kernel, or the arguments of :func:`visibility`.
    """
    if rule not in ("probit", "nodes"):
        raise TorchspecError(f"kernel_visibility: rule must be 'probit' or 'nodes'; got {rule!r}.")
    kernel = lights.kernel
    centre = lights.directions.to(height)
    if kernel.kind == "point":
        return visibility(height, centre, pitch, softness, step=step)
    if kernel.kind == "unknown":
        raise TorchspecError("kernel_visibility needs the light kernel's shape; the kernel is 'unknown'.")
    if rule == "nodes":
        points, weight = nodes(lights.to(device=height.device, dtype=height.dtype), order=order)
        k, q = weight.shape
        seen = visibility(height, points.reshape(k * q, 3), pitch, softness, step=step).reshape(*height.shape, k, q)
        mass = weight.sum(-1)
        return (seen * weight).sum(-1) / torch.where(mass > 0, mass, torch.ones_like(mass))
    mean, spread = _probit(kernel, centre)
    return visibility(height, mean, pitch, torch.sqrt(softness**2 + spread), step=step)


def marched_horizon(
    height: Tensor, directions: Tensor, start: float = 0.5, step: float = 1.0 / 32, rows: int = 8
) -> Tensor:
    """The reference of :func:`horizon` (``(H, W, K)``, radians, pixel pitch 1): every ray marched in
    fine ``step``s from ``start`` to the image's diagonal over the bilinear height field, indexing
    the four neighbours directly (no ``grid_sample``), light by light and in bands of ``rows`` rows.
    Slow (a loop over lights; for tests and ``experiments/shadows_synthetic.py``, in float64)."""
    height_rows, cols = height.shape
    like = dict(dtype=height.dtype, device=height.device)
    t = torch.arange(start, math.hypot(height_rows, cols) + step, step, **like)
    out = height.new_empty(height_rows, cols, directions.shape[0])
    for k in range(directions.shape[0]):  # the reference: one light at a time
        u = torch.stack([directions[k, 0], -directions[k, 1]]).to(**like)
        u = u / u.norm()
        for top in range(0, height_rows, rows):
            r, c = torch.meshgrid(
                torch.arange(top, min(height_rows, top + rows), **like), torch.arange(cols, **like), indexing="ij"
            )
            pc, pr = c[..., None] + t * u[0], r[..., None] + t * u[1]
            inside = (pc >= -EDGE) & (pc <= cols - 1 + EDGE) & (pr >= -EDGE) & (pr <= height_rows - 1 + EDGE)
            pc, pr = pc.clamp(0, cols - 1), pr.clamp(0, height_rows - 1)
            c0, r0 = pc.floor().long().clamp(max=cols - 2), pr.floor().long().clamp(max=height_rows - 2)
            fc, fr = pc - c0, pr - r0
            v = (height[r0, c0] * (1 - fc) + height[r0, c0 + 1] * fc) * (1 - fr) + (
                height[r0 + 1, c0] * (1 - fc) + height[r0 + 1, c0 + 1] * fc
            ) * fr
            rise = torch.where(inside, (v - height[top : top + rows, :, None]) / t, torch.full_like(v, -math.inf))
            out[top : top + rows, :, k] = torch.atan(rise.amax(-1))
    return out


def sky_view(height: Tensor, count: int = 64) -> Tensor:
    """``(H, W)`` each pixel's cosine-weighted visible share of the hemisphere over ``height (H, W)``
    (pixels): the mean visibility (:func:`visibility`) of ``count`` directions spread evenly in
    cosine-weighted solid angle (:func:`torchspec.model.geometry.spiral_plane`). 1 on a flat surface."""
    directions = from_plane(spiral_plane(count, dtype=height.dtype, device=height.device))
    return visibility(height, directions).mean(-1)


def frame_visibility(
    height: Tensor,
    lights: Lights,
    positions: Tensor | None = None,
    footprint: int = FOOTPRINT,
    softness: float = SOFTNESS,
) -> Tensor:
    """``(H, W, K)`` the visibility of a capture's frames over ``height (H, W)`` (pixels), as a fit
    with cast shadows and ``torchspec render`` take it: distant lights through their kernel
    (:func:`kernel_visibility`, its ``probit`` rule; a kernel of ``unknown`` shape as a point);
    near lights at ``positions (K, 3)`` (object units, :mod:`torchspec.model.near_lights`) by each pixel's
    own direction to the light (their kernel left out). Averaged over each pixel's footprint: the
    height resampled ``footprint`` times finer (bicubic), the visibility computed there and
    box-averaged back (a pixel a shadow's edge crosses is partly lit, as its photograph is; 1: at
    the pixels' centres only). ``softness``: the penumbra's width in elevation, radians
    (:func:`visibility`). In the height's dtype and on its device."""
    return next(frame_visibilities(height, lights, positions, (1.0,), (softness,), footprint))[2]


def frame_visibilities(
    height: Tensor,
    lights: Lights,
    positions: Tensor | None = None,
    depths=(1.0,),
    softnesses=(SOFTNESS,),
    footprint: int = FOOTPRINT,
):
    """:func:`frame_visibility` of ``height`` scaled by each of ``depths`` with each penumbra of
    ``softnesses`` (radians), from one horizon: a height scaled by ``d`` has the horizon
    ``atan(d tan H)`` (every rise scales by ``d``), and the penumbra enters only the sigmoid. The
    horizon reaches as far as the deepest height can hide a light with the widest penumbra's margin,
    so each visibility is :func:`frame_visibility`'s but where a farther occluder moves it by less
    than ``sigmoid(-8)`` (3e-4). Yields ``(depth, softness, (H, W, K))`` for each pair, depths
    outer; one horizon's memory and time for all of them (the fit's judge tries 8 pairs a round)."""
    if footprint < 1:
        raise TorchspecError(f"footprint must be a whole number >= 1; got {footprint!r}.")
    lights = lights.to(device=height.device, dtype=height.dtype)
    h, w = height.shape
    fine = height
    if footprint > 1:  # heights in pixels: a finer pixel is 1 / footprint of one
        grid = (height * footprint)[None, None]
        fine = F.interpolate(grid, scale_factor=footprint, mode="bicubic", align_corners=False)[0, 0]
    spread = torch.zeros((), dtype=height.dtype, device=height.device)  # the kernel's elevation variance term
    if positions is not None:
        points = image_points(h, w, dtype=height.dtype, device=height.device).reshape(h, w, 1, 3)
        directions = positions.to(height)[None, None] - points  # (H, W, K, 3)
        length = torch.linalg.vector_norm(directions, dim=-1, keepdim=True).clamp(min=1e-12)
        directions = (directions / length).repeat_interleave(footprint, 0).repeat_interleave(footprint, 1)
    elif lights.kernel.kind in ("unknown", "point"):
        directions = lights.directions
    else:  # kernel_visibility's probit rule: the mean's direction, the penumbra widened
        directions, spread = _probit(lights.kernel, lights.directions)
    widest = math.sqrt(max(softnesses) ** 2 + float(spread.max()))  # one host sync
    reach = shadow_reach(fine * max(depths), directions, margin=8.0 * widest)
    found = horizon(fine, directions, reach=reach)
    rise = torch.tan(found) if any(depth != 1.0 for depth in depths) else None  # not for render's one depth
    e = elevation(directions)
    e = e if directions.dim() == 4 else e.expand(*fine.shape, -1)
    for depth in depths:
        level = found if depth == 1.0 else torch.atan(depth * rise)
        for softness in softnesses:
            seen = torch.sigmoid((e - level) / torch.sqrt(softness**2 + spread))
            if footprint > 1:  # box-averaged back to the pixels
                seen = F.avg_pool2d(seen.permute(2, 0, 1)[None], footprint)[0].permute(1, 2, 0)
            yield depth, softness, seen


def _probit(kernel: Kernel, centre: Tensor) -> tuple[Tensor, Tensor]:
    """The directions ``(K, 3)`` of ``kernel``'s means about the centres ``(K, 3)`` and the
    penumbra's widening ``(K,)`` (``pi s_e^2 / 8``, radians squared) of :func:`kernel_visibility`'s
    ``probit`` rule."""
    l = centre[:, :2] + kernel.offset(centre)
    radius = torch.linalg.vector_norm(l, dim=-1, keepdim=True)
    u = torch.where(radius > 0, l / torch.where(radius > 0, radius, torch.ones_like(radius)), torch.zeros_like(l))
    cov = kernel.covariance(centre)  # (K, 2, 2)
    along = torch.einsum("ki,kij,kj->k", u, cov, u)
    radial = torch.where(radius[:, 0] > 0, along, 0.5 * cov.diagonal(dim1=-2, dim2=-1).sum(-1))  # zenith: the mean
    wz = (1.0 - radius[:, 0].square()).clamp(min=1e-6).sqrt()
    return torch.cat([l, wz[:, None]], -1), (math.pi / 8.0) * radial / wz.square()
