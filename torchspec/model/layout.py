"""Facts of a capture's light layout that the fit's stages share: where the lights lie in the
l-plane (:func:`layout_of`: a line or a plane, a grid or scattered), how far apart they are
(:func:`light_spacing`), the kernel's blur (:func:`kernel_variance`), and where a normal mirrors
the view (:func:`mirror_point`, the l-plane position of a specular peak), the narrowest lobe point
lights resolve (:func:`resolvable_roughness`) and how close a lobe's peak lies to a light
(:func:`lobe_support`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..start.photometric import GridCells, grid_layout
from .geometry import tangent_frame
from .lights import Lights

__all__ = [
    "MIN_FRAMES",
    "MIN_PEAK_SAMPLES",
    "Layout",
    "coverage_warning",
    "fit_problem",
    "layout_of",
    "light_spacing",
    "kernel_variance",
    "mirror_point",
    "resolvable_roughness",
    "lobe_support",
]

MIN_FRAMES = 4
"""A fit needs 3 frames for the normal and ``k_d`` and one more for a lobe."""
MIN_PEAK_SAMPLES = 3
"""Lights along each axis of a layout that a lobe's peak needs: the peak and a sample on either side
(the FRI start's ``2M + 1`` samples per axis with one Fourier coefficient, ``M = 1``); a scattered
planar layout needs ``MIN_PEAK_SAMPLES ** 2`` frames (the ``1 + 2 x 4`` real unknowns of ``M = 1`` in 2D)."""


@dataclass(frozen=True)
class Layout:
    """The geometry of the light positions that the peak search needs.

    Attributes:
        l: ``(K, 2)`` positions in the l-plane.
        dims: 2 for a planar layout, 1 for lights along a line.
        axis: ``(2,)`` the line's unit direction (1D); ``origin``: ``(2,)`` a point of it.
        area: ``(K,)`` the l-plane area (1D: length) each sample stands for.
        period: the FRI period per dimension: the span plus one spacing.
        start: ``(dims,)`` the coordinate mapped to 0.
        grid: for lights on a grid clipped to a disk (or not at all), the cell of each frame and
            the lattice's size (:class:`torchspec.start.photometric.GridCells`); ``None`` otherwise.
        spacing: the median distance between neighbouring samples.
    """

    l: Tensor
    dims: int
    axis: Tensor
    origin: Tensor
    area: Tensor
    period: tuple[float, ...]
    start: Tensor
    grid: GridCells | None = None
    spacing: float = 0.0

    def coordinates(self) -> Tensor:
        """``(K, dims)`` sample coordinates shifted into ``[0, period)``."""
        if self.dims == 1:
            return ((self.l - self.origin) @ self.axis)[:, None] - self.start
        return self.l - self.start


def layout_of(l: Tensor) -> Layout:
    """Describe the light positions ``(K, 2)``: a line (1D) when they are collinear, else planar.

    Raises:
        ValueError: ``l`` is not ``(K, 2)`` with ``K >= 3``.

    Example:
        >>> ticks = torch.linspace(-0.2, 0.2, 5, dtype=torch.float64)
        >>> grid = torch.stack(torch.meshgrid(ticks, ticks, indexing="xy"), -1).reshape(-1, 2)
        >>> found = layout_of(grid)
        >>> found.dims, (found.grid.rows, found.grid.columns), round(found.spacing, 3)
        (2, (5, 5), 0.1)
        >>> layout_of(torch.stack([ticks, 0.5 * ticks], -1)).dims
        1
    """
    if l.dim() != 2 or l.shape[-1] != 2 or l.shape[0] < 3:
        raise TorchspecError(f"light positions must have shape (K, 2) with K >= 3; got {tuple(l.shape)}.")
    centre = l.mean(0)
    _, s, vh = torch.linalg.svd(l - centre, full_matrices=False)
    if s[1] <= 1e-6 * s[0]:
        axis = vh[0]
        t = (l - centre) @ axis
        order = t.sort().values
        gaps = order.diff()
        step = gaps.median()
        area = torch.empty_like(t)
        width = torch.cat([gaps[:1], 0.5 * (gaps[1:] + gaps[:-1]), gaps[-1:]])
        area[t.argsort()] = width
        span = float(order[-1] - order[0] + step)
        return Layout(l, 1, axis, centre, area, (span,), order[:1] - 0.5 * step, None, float(step))
    cells = grid_layout(l)
    low, high = l.min(0).values, l.max(0).values
    if cells is not None:
        row, col, dy, dx = cells.row, cells.col, cells.spacing_y, cells.spacing_x
        ny, nx = cells.rows, cells.columns
        # Empty cells may be filled with zeros only where the lobe is not: outside the lit disk
        # (a grid clipped to a radius), not between the frames (every second frame of a grid).
        filled = torch.zeros(ny, nx, dtype=torch.bool, device=l.device)
        filled[row, col] = True
        ys = low[1] + dy * torch.arange(ny, dtype=l.dtype, device=l.device)
        xs = low[0] + dx * torch.arange(nx, dtype=l.dtype, device=l.device)
        radius = torch.sqrt(ys[:, None] ** 2 + xs[None, :] ** 2)
        if (~filled).any() and float(radius[~filled].min()) < float(radius[filled].max()) - 1e-9 * max(dx, dy):
            cells = None
    if cells is not None:  # the lattice's own spacing: a period of exactly nx (ny) cells
        step = torch.tensor([dx, dy], dtype=l.dtype, device=l.device)
        area = torch.full_like(l[:, 0], dx * dy)
        period = (nx * dx, ny * dy)
        return Layout(l, 2, torch.zeros_like(centre), centre, area, period, low, cells, float(min(dx, dy)))
    step = light_spacing(l)
    period = tuple(float(v) for v in (high - low + step))
    # Each sample stands for its share of the layout's convex area: a disk or a square here.
    hull = math.pi * float(((l - centre).norm(dim=-1).max() + 0.5 * step) ** 2)
    box = float((high - low + step).prod())
    area = torch.full_like(l[:, 0], min(hull, box) / l.shape[0])
    return Layout(l, 2, torch.zeros_like(centre), centre, area, period, low - 0.5 * step, None, float(step))


def light_spacing(points: Tensor) -> Tensor:
    """The median distance from each of ``points (K, D)`` to its nearest neighbour: a 0-dim tensor
    of their dtype (``inf`` for fewer than two points).

    Example:
        >>> float(light_spacing(torch.tensor([[0.0, 0.0], [0.0, 0.1], [0.3, 0.0]], dtype=torch.float64)))
        0.1
    """
    if points.shape[0] < 2:
        return torch.tensor(math.inf, dtype=points.dtype, device=points.device)
    d = torch.cdist(points, points)
    d = d + torch.diag(torch.full_like(d[0], math.inf))
    return d.min(-1).values.median()


def kernel_variance(lights: Lights, *, frames: str) -> float:
    """The light kernel's mean per-axis variance in the l-plane (0 for point lights).

    Args:
        lights: the frames' lights.
        frames: ``"first"``: the kernel's covariance at the first frame's direction (the specular
            start's blur); ``"all"``: the mean over every frame (the peak checks' blur). The two
            agree for a kernel whose covariance does not depend on the direction, up to rounding.

    Example:
        >>> from torchspec.model.lights import Kernel
        >>> directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
        >>> lights = Lights(directions, Kernel("gaussian", sigma=0.1), torch.ones(3, 1), torch.ones(3))
        >>> round(kernel_variance(lights, frames="all"), 6)
        0.01
    """
    if lights.kernel.kind == "point":
        return 0.0
    if frames == "first":
        return float(lights.kernel.covariance(lights.directions[:1])[0].diagonal().mean())
    if frames == "all":
        cov = lights.kernel.covariance(lights.directions)
        return float(cov.diagonal(dim1=-2, dim2=-1).mean())
    raise TorchspecError(f"kernel_variance: frames must be 'first' or 'all'; got {frames!r}.")


def mirror_point(normal: Tensor, view: Tensor) -> Tensor:
    """``(*, 2)``: the l-plane position of the direction that ``normal (*, 3)`` mirrors ``view (3,)``
    into (``2 <n, v> n - v``, in ``normal``'s dtype): where the peak of a specular lobe lies.

    Example:
        >>> mirror_point(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.0, 0.0, 1.0]))
        tensor([[0., 0.]])
    """
    v = view.to(normal.dtype)
    return (2.0 * (normal @ v)[..., None] * normal - v)[..., :2]


def _describe(layout: Layout) -> str:
    if layout.dims == 1:
        return "on a line"
    if layout.grid is not None:
        return f"on a {layout.grid.rows} x {layout.grid.columns} grid (rows x columns)"
    return "scattered over the plane"


def fit_problem(l: Tensor, *, lobe: bool = True) -> str | None:
    """Why frames at the l-plane positions ``l (K, 2)`` cannot be fitted, in the user's terms (how
    many frames and what layout they have, what the fit needs, what to do), or ``None``.

    A fit needs :data:`MIN_FRAMES`; a lobe (every model but ``diffuse``) also needs its peak sampled
    by :data:`MIN_PEAK_SAMPLES` lights along each axis of the layout: a line of at least 3, a grid
    of at least 3 x 3, or 9 scattered frames.

    Example:
        >>> ticks = torch.tensor([-0.27, 0.27], dtype=torch.float64)
        >>> square = torch.stack(torch.meshgrid(ticks, ticks, indexing="xy"), -1).reshape(-1, 2)
        >>> print(fit_problem(square))  # doctest: +NORMALIZE_WHITESPACE
        4 frames on a 2 x 2 grid (rows x columns): a lobe's peak needs at least 3 lights along each axis (a
        3 x 3 grid, or 9 scattered frames). Use a denser layout (e.g. acquire --layout grid:12x12), more of
        the frames, or fit without a lobe (model: diffuse).
        >>> fit_problem(square, lobe=False) is None
        True
    """
    count = l.shape[0]
    if count < MIN_FRAMES:
        return (
            f"{count} frame(s): a fit needs at least {MIN_FRAMES} (3 for the normal and k_d, one more for a lobe). "
            "Use more of the frames, or acquire more."
        )
    if not lobe:
        return None
    layout = layout_of(l)
    if layout.dims == 1:
        short = count < MIN_PEAK_SAMPLES
    elif layout.grid is not None:
        short = min(layout.grid.rows, layout.grid.columns) < MIN_PEAK_SAMPLES
    else:
        short = count < MIN_PEAK_SAMPLES**2
    if not short:
        return None
    n = MIN_PEAK_SAMPLES
    return (
        f"{count} frames {_describe(layout)}: a lobe's peak needs at least {n} lights along each axis (a {n} x {n} "
        f"grid, or {n * n} scattered frames). Use a denser layout (e.g. acquire --layout grid:12x12), more of the "
        "frames, or fit without a lobe (model: diffuse)."
    )


def coverage_warning(l: Tensor, view: Tensor) -> str | None:
    """A warning when the lights at ``l (K, 2)`` stay away from where a flat object's specular peaks
    lie (the mirror direction of ``view (3,)`` about the normal ``(0, 0, 1)``): farther than two
    spacings from the nearest light, or from a line of lights; ``None`` otherwise.

    Example:
        >>> row = torch.tensor([[x, 0.65] for x in (-0.36, -0.22, -0.07, 0.07)], dtype=torch.float64)
        >>> view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        >>> print(coverage_warning(row, view))  # doctest: +NORMALIZE_WHITESPACE
        the 4 frames lie on a line 0.65 from the mirror direction of a flat object (l = (0.00, 0.00)), more
        than two light spacings (0.14): the lobes' peaks of most pixels lie outside the lights and cannot be
        located. Use frames around the mirror direction.
    """
    if l.shape[0] < 3:
        return None
    layout = layout_of(l)
    flat = torch.tensor([0.0, 0.0, 1.0], dtype=l.dtype, device=l.device)
    mirror = mirror_point(flat, view.to(l.dtype))
    if layout.dims == 1:
        along = (mirror - layout.origin) @ layout.axis
        distance = float((mirror - layout.origin - along * layout.axis).norm())
        where = "on a line"
    else:
        distance = float((l - mirror).norm(dim=-1).min())
        where = "with the nearest"
    if distance <= 2.0 * layout.spacing:
        return None
    x, y = (float(v) for v in mirror)
    return (
        f"the {l.shape[0]} frames lie {where} {distance:.2f} from the mirror direction of a flat object "
        f"(l = ({x:.2f}, {y:.2f})), more than two light spacings ({layout.spacing:.2f}): the lobes' peaks of "
        "most pixels lie outside the lights and cannot be located. Use frames around the mirror direction."
    )


def resolvable_roughness(lights: Lights, resolution: float, least: float) -> float:
    """The smallest Ward roughness the frames' lights can resolve: ``resolution`` times the
    spacing of the half vectors (half the median nearest-neighbour distance of the light
    directions in the l-plane, :func:`light_spacing`) for point lights, and ``least`` (no bound
    from the sampling) for an extended kernel, whose blur reveals a narrower lobe's location.

    With point lights, a lobe narrower than the half vectors' spacing falls between the frames:
    it is fitted to one frame's sample and predicts nothing between them (relighting explodes).

    Example:
        >>> from torchspec.model.lights import Kernel
        >>> d = torch.tensor([[0.0, 0, 1], [0.2, 0, 1], [0, 0.2, 1]], dtype=torch.float64)
        >>> one = torch.ones(3, 1, dtype=torch.float64)
        >>> resolvable_roughness(Lights(d, Kernel("point"), one, one[:, 0]), 0.5, 1e-3)
        0.05
    """
    if lights.kernel.kind != "point" or resolution <= 0:
        return least
    spacing = float(light_spacing(lights.directions[:, :2].double()))
    return max(least, round(resolution * spacing / 2, 6)) if math.isfinite(spacing) else least


def lobe_support(svbrdf, lights: Lights, view: Tensor) -> Tensor:
    """``(n,)`` the largest fraction of its peak that each pixel's Ward lobe shape reaches at any
    of the ``lights`` (``exp(E)`` of :func:`torchspec.model.brdf.ward_cosine` at each light's half
    vector, whose peak ``exp(0) = 1`` lies at the half vector ``n``; the sharper of two lobes);
    ``1`` where a pixel has no lobe (``k_s = 0``), ``0`` where no light is in front.

    A lobe whose peak lies between the lights, farther from each than its own width (a support
    below 1/2: no light within its half maximum), is not determined by their samples: its height is
    extrapolated from its tails, and a light at its peak sees it at any height.

    Example:
        >>> from torchspec.model.brdf import SVBRDF
        >>> from torchspec.model.lights import Kernel
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
        >>> flat = SVBRDF(n, one, one, torch.full((1, 2), 0.1, dtype=torch.float64))
        >>> at_peak = Lights(n, Kernel("point"), one, one[:, 0])
        >>> float(lobe_support(flat, at_peak, n[0]))
        1.0
    """
    dtype = svbrdf.normal.dtype
    wi = lights.directions.to(dtype=dtype, device=svbrdf.normal.device)  # (K, 3)
    wo = view.to(wi) / view.to(wi).norm()
    n = svbrdf.normal[:, None]  # (n, 1, 3)
    s, t = tangent_frame(svbrdf.normal, svbrdf.rotation)
    h = wi + wo  # (K, 3)
    hn = (h * n).sum(-1)  # (n, K)
    front = (hn > 0) & ((wi * n).sum(-1) > 0) & ((wo * n).sum(-1) > 0)
    safe = torch.where(front, hn, torch.ones_like(hn))

    def shape(alpha: Tensor) -> Tensor:
        a = alpha.clamp(min=torch.finfo(dtype).tiny)[:, None]  # (n, 1, 2)
        hs, ht = (h * s[:, None]).sum(-1), (h * t[:, None]).sum(-1)
        exponent = -((hs / a[..., 0]) ** 2 + (ht / a[..., 1]) ** 2) / (safe * safe)
        return torch.where(front, torch.exp(exponent), torch.zeros_like(exponent)).amax(-1)

    support = torch.where(svbrdf.specular.amax(-1) > 0, shape(svbrdf.roughness), torch.ones_like(hn[:, 0]))
    if svbrdf.specular2 is not None:
        second = torch.where(svbrdf.specular2.amax(-1) > 0, shape(svbrdf.roughness2), torch.ones_like(support))
        support = torch.minimum(support, second)
    return support
