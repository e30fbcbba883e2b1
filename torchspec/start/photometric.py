"""The diffuse stage: sample masks, a light-domain lowpass and robust photometric stereo.

A pixel's diffuse light under an extended kernel is ``k_d / pi <n, d_k>`` with the kernel's
*effective direction* ``d_k = integral K_k(w) w dmu`` (:func:`torchspec.model.lights.diffuse_directions`),
wherever the kernel lies in front of the normal. Photometric stereo solves that linear model per
pixel, batched, and leaves out what it cannot explain: the specular peak only ever adds light, so
samples far above the fit are dropped (reweighted least squares with a one-sided cut), and masked
samples (non-finite, saturated, shadowed) never enter.

- :func:`sample_masks`: the samples to leave out of a ``(K, C, H, W)`` stack, with saturated
  regions grown in the image by kornia morphology (blooming spreads around a clipped highlight).
- :func:`lowpass`: smooth each pixel's samples over the light positions. A grid layout is a small
  image per pixel, ``(N, C, ny, nx)``, blurred by ``kornia.filters``; a scattered one is
  smoothed with Gaussian kernel weights. Missing samples are handled by normalised convolution.
- :func:`photometric_stereo`: normal, ``k_d``, inliers, a noise estimate and a quality per pixel.

References:
    Woodham, "Photometric method for determining surface orientation from multiple images",
    Optical Engineering 1980.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields

import kornia
import torch
from torch import Tensor

from ..errors import TorchspecError

__all__ = [
    "Masks",
    "Diffuse",
    "sample_masks",
    "peak_of",
    "saturation_level",
    "GridCells",
    "grid_layout",
    "lowpass",
    "photometric_stereo",
    "MAD_SCALE",
]

BAND_ELEMENTS = 1 << 22
"""Values of the stack :func:`sample_masks` works on at once (rows of every frame and channel)."""

MAD_SCALE = 1.4826
"""The median absolute deviation times this is the standard deviation of Gaussian noise."""

CLIP_REPEATS = 16
"""A stack's maximum is the sensor's clipping level when at least this many values share it
exactly (a clipped sensor repeats its ceiling; a smooth highlight does not)."""


@dataclass(frozen=True)
class Masks:
    """Samples to leave out of a ``(K, C, H, W)`` stack, each ``(K, H, W)`` bool (a sample is a
    pixel in a frame, all channels together); :meth:`flat` and :meth:`of_pixels` give the same
    three kinds over flat pixels, each ``(K, n)`` (e.g. a tile's, ``torchspec.pipeline.tile``).

    Attributes:
        nonfinite: NaN or Inf in some channel.
        saturated: at or above the saturation level in some channel, grown by ``grow`` pixels.
        shadowed: far below the pixel's typical level (a cast shadow, or a light behind it).
    """

    nonfinite: Tensor
    saturated: Tensor
    shadowed: Tensor

    @property
    def invalid(self) -> Tensor:
        """Any of the three, in the masks' shape (``(K, H, W)``)."""
        return self.nonfinite | self.saturated | self.shadowed

    @property
    def usable(self) -> Tensor:
        """The samples that hold a measurement: finite and not saturated (shadowed ones too)."""
        return ~(self.nonfinite | self.saturated)

    def counts(self) -> dict[str, int]:
        """Samples flagged per kind (one host sync per kind), in the fields' order."""
        return {f.name: int(getattr(self, f.name).sum()) for f in fields(self)}

    def map(self, change: Callable[[Tensor], Tensor]) -> Masks:
        """Each kind's mask through ``change`` (the same for all three)."""
        return Masks(**{f.name: change(getattr(self, f.name)) for f in fields(self)})

    def flat(self) -> Masks:
        """Each kind ``(K, H W)``: the pixels in row-major order (views where the masks are contiguous)."""
        return self.map(lambda mask: mask.flatten(1))

    def of_pixels(self, at: slice) -> Masks:
        """The flat masks' (:meth:`flat`) pixels ``at``: each ``(K, n)``."""
        return self.map(lambda mask: mask[:, at])


def sample_masks(stack: Tensor, *, saturation: float | None = None, grow: int = 1, shadow: float = 0.02) -> Masks:
    """Masks of the samples a fit must not use.

    Args:
        stack: ``(K, C, H, W)`` values as recorded (frames as the batch).
        saturation: the level at which the sensor clips; ``None`` finds it: the stack's maximum
            when at least 16 samples share it exactly (a clipped sensor repeats its ceiling),
            otherwise nothing is saturated.
        grow: saturated regions are dilated by this many pixels (a ``2 grow + 1`` square), since
            blooming and demosaicking spread a clipped highlight into its neighbours.
        shadow: a sample is shadowed below this fraction of its pixel's median over the frames
            (in every channel); 0 turns the test off.

    Returns:
        :class:`Masks`.
    """
    if stack.dim() != 4:
        raise TorchspecError(f"stack must have shape (K, C, H, W); got {tuple(stack.shape)}.")
    if grow < 0 or shadow < 0:
        raise TorchspecError(f"grow and shadow must be >= 0; got grow={grow}, shadow={shadow}.")
    k, c, h, w = stack.shape
    # Bands of rows bound the working memory (a few copies of a band, not of the stack).
    rows = max(1, BAND_ELEMENTS // max(k * c * w, 1))
    bands = [(r, min(r + rows, h)) for r in range(0, h, rows)]
    if saturation is None:
        level = saturation_level([peak_of(stack[:, :, r0:r1]) for r0, r1 in bands])
    else:
        level = torch.as_tensor(saturation, dtype=stack.dtype, device=stack.device)
    nonfinite = torch.zeros((k, h, w), dtype=torch.bool, device=stack.device)
    clipped = torch.zeros_like(nonfinite)
    for r0, r1 in bands:
        band = stack[:, :, r0:r1]
        nonfinite[:, r0:r1] = ~torch.isfinite(band).all(1)
        clipped[:, r0:r1] = (torch.nan_to_num(band, nan=0.0) >= level).any(1)
    clipped &= ~nonfinite
    if grow > 0 and k > 0:
        element = torch.ones(2 * grow + 1, 2 * grow + 1, dtype=stack.dtype, device=stack.device)
        saturated = torch.zeros_like(clipped)
        for r0, r1 in bands:  # with a halo of `grow` rows
            a, b = max(r0 - grow, 0), min(r1 + grow, h)
            grown = kornia.morphology.dilation(clipped[:, None, a:b].to(stack.dtype), element)
            saturated[:, r0:r1] = grown[:, 0, r0 - a : r1 - a] > 0.5
    else:
        saturated = clipped
    # Shadows: against the per-pixel median of the usable samples, channel by channel.
    shadowed = torch.zeros_like(nonfinite)
    for r0, r1 in bands:
        band = stack[:, :, r0:r1]
        usable = (~nonfinite[:, r0:r1] & ~saturated[:, r0:r1])[:, None]
        if k == 0:
            break
        median = torch.where(usable, band, torch.full_like(band, math.nan)).nanmedian(0).values
        dark = (torch.nan_to_num(band, nan=math.inf) < shadow * median[None]).all(1) & (median[None] > 0).all(1)
        shadowed[:, r0:r1] = dark & usable[:, 0]
    return Masks(nonfinite=nonfinite, saturated=saturated, shadowed=shadowed)


def peak_of(values: Tensor) -> tuple[Tensor, Tensor]:
    """``(top, count)``, 0-dim tensors: the largest finite value of ``values`` (``-inf`` when there
    is none) and how many values equal it, of one part of a stack, for :func:`saturation_level`."""
    if values.numel() == 0:
        top = values.new_full((), -math.inf)
    else:
        top = torch.where(torch.isfinite(values), values, -math.inf).amax()
    count = torch.where(torch.isfinite(top), (values == top).sum(), 0)
    return top, count


def saturation_level(peaks: list[tuple[Tensor, Tensor]]) -> Tensor:
    """The clipping level of a stack from the :func:`peak_of` of each of its parts (bands of rows in
    :func:`sample_masks`, single frames in :func:`torchspec.info.inspect_capture`): 0-dim, the
    largest finite value when at least :data:`CLIP_REPEATS` values share it exactly, else ``inf``
    (nothing is saturated)."""
    tops = torch.stack([top for top, _ in peaks])
    counts = torch.stack([count for _, count in peaks])
    top = tops.amax()
    at_top = torch.where(tops == top, counts, 0).sum()
    return torch.where(at_top >= CLIP_REPEATS, top, torch.full_like(top, math.inf))


@dataclass(frozen=True)
class GridCells:
    """The cells of ``K`` light positions on an evenly spaced lattice (:func:`grid_layout`); cells
    may be empty (a grid clipped to a disk).

    Attributes:
        row, col: ``(K,)`` long, each position's row (along y) and column (along x).
        rows, columns: the lattice's size (its last row and column hold a position).
        spacing_y, spacing_x: the lattice's spacings (l-plane units).
    """

    row: Tensor
    col: Tensor
    rows: int
    columns: int
    spacing_y: float
    spacing_x: float


def grid_layout(l: Tensor, *, tolerance: float = 1e-6) -> GridCells | None:
    """The cells of a grid layout of light positions, or ``None`` when they do not lie on one.

    Args:
        l: ``(K, 2)`` light positions in the l-plane.

    Returns:
        The :class:`GridCells` of the positions, or ``None``.
    """
    if l.dim() != 2 or l.shape[-1] != 2 or l.shape[0] < 2:
        return None
    cells = []
    for axis in (1, 0):  # rows run along y, columns along x
        values = l[:, axis].double()
        unique = torch.unique(torch.round(values / tolerance)) * tolerance
        if unique.numel() < 2:
            return None
        low, span = values.min(), values.max() - values.min()
        step = span / torch.round(span / unique.diff().min())  # exact from the span, not the rounded gaps
        index = torch.round((values - low) / step)
        if not bool(((values - low - index * step).abs() <= 1e-3 * step).all()):
            return None
        cells.append((index.long(), float(step)))
    (row, dy), (col, dx) = cells
    rows, columns = int(row.max()) + 1, int(col.max()) + 1
    key = row * columns + col
    if torch.unique(key).numel() != key.numel():  # two frames in one cell
        return None
    if rows * columns > 4 * l.shape[0]:  # mostly empty: not a grid
        return None
    return GridCells(row=row, col=col, rows=rows, columns=columns, spacing_y=dy, spacing_x=dx)


def lowpass(samples: Tensor, l: Tensor, *, sigma: float, valid: Tensor | None = None) -> Tensor:
    """Smooth each pixel's samples over the light positions with a Gaussian of std ``sigma``
    (l-plane units); masked samples are filled from their neighbours (normalised convolution).

    Args:
        samples: ``(N, K, C)``.
        l: ``(K, 2)`` light positions.
        sigma: the lowpass's std in the l-plane; 0 returns the samples (masked ones as NaN).
        valid: ``(N, K)`` bool, the samples to use; all by default.

    Returns:
        ``(N, K, C)`` smoothed values at the same positions; NaN where no valid sample is near.
    """
    n, k, c = samples.shape
    if tuple(l.shape) != (k, 2):
        raise TorchspecError(f"l must have shape ({k}, 2) for samples {tuple(samples.shape)}; got {tuple(l.shape)}.")
    if valid is None:
        valid = torch.isfinite(samples).all(-1)
    weight = valid.to(samples.dtype)[..., None]
    values = torch.where(valid[..., None], samples, torch.zeros_like(samples))
    nan = torch.full_like(samples, math.nan)
    if sigma <= 0:
        return torch.where(valid[..., None], samples, nan)
    grid = grid_layout(l)
    if grid is not None:
        row, col, dy, dx = grid.row, grid.col, grid.spacing_y, grid.spacing_x
        ny, nx = grid.rows, grid.columns
        image = samples.new_zeros((n, c + 1, ny, nx))
        image[:, :c, row, col] = values.transpose(1, 2)
        image[:, c, row, col] = weight[..., 0]
        sy, sx = sigma / dy, sigma / dx
        size = (2 * math.ceil(3 * sy) + 1, 2 * math.ceil(3 * sx) + 1)
        blurred = kornia.filters.gaussian_blur2d(image, size, (sy, sx), border_type="constant")
        top, bottom = blurred[:, :c, row, col].transpose(1, 2), blurred[:, c, row, col][..., None]
    else:
        d2 = (l[:, None, :] - l[None, :, :]).pow(2).sum(-1)
        kernel = torch.exp(-0.5 * d2 / sigma**2).to(samples.dtype)  # (K, K)
        top = torch.einsum("jk,nkc->njc", kernel, values)
        bottom = torch.einsum("jk,nkc->njc", kernel, weight)
    floor = torch.finfo(samples.dtype).eps * bottom.amax(1, keepdim=True).clamp(min=1.0)
    return torch.where(bottom > floor, top / bottom.clamp(min=torch.finfo(samples.dtype).tiny), nan)


@dataclass(frozen=True)
class Diffuse:
    """The result of :func:`photometric_stereo` for ``N`` pixels.

    Attributes:
        normal: ``(N, 3)`` unit normals (``(0, 0, 1)`` where the pixel could not be solved).
        diffuse: ``(N, C)`` ``k_d`` (clamped at 0).
        inliers: ``(N, K)`` the samples the final fit used.
        noise: ``(N,)`` robust std of the inliers' residual, in the units of the samples.
        quality: ``(N,)`` in ``[0, 1]``: the share of inliers times the conditioning of the
            directions they leave (smallest over largest eigenvalue of their scatter, relative
            to the layout's own); 0 where fewer than 3 samples were left.
    """

    normal: Tensor
    diffuse: Tensor
    inliers: Tensor
    noise: Tensor
    quality: Tensor


def _weighted_solve(a: Tensor, y: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """``argmin sum_k w_k (y_k - <b, a_k>)^2`` per pixel, the minimum-norm one where the weighted
    directions leave ``b`` undetermined (a line of lights): ``(N, 3)``, and the eigenvalues of the
    weighted scatter ``(N, 3)``, ascending."""
    scatter = torch.einsum("nk,ki,kj->nij", w, a, a)
    rhs = torch.einsum("nk,nk,ki->ni", w, y, a)
    eig, vec = torch.linalg.eigh(scatter)
    keep = eig > 1e3 * torch.finfo(a.dtype).eps * eig[:, -1:].clamp(min=torch.finfo(a.dtype).tiny)
    inverse = torch.where(keep, 1.0 / torch.where(keep, eig, torch.ones_like(eig)), torch.zeros_like(eig))
    b = vec @ (inverse[..., None] * (vec.transpose(-1, -2) @ rhs[..., None]))
    return b[..., 0], eig


def photometric_stereo(
    samples: Tensor,
    directions: Tensor,
    *,
    valid: Tensor | None = None,
    iterations: int = 8,
    cut: float = 3.0,
    trim: float = 0.25,
) -> Diffuse:
    """Robust photometric stereo: per pixel, ``samples[k, c] ~ k_d[c] / pi <n, d_k>`` on the
    samples it can explain.

    The normal comes from the mean over channels (the direction of ``b = mean(k_d) / pi n``), then
    ``k_d`` per channel by least squares along it. The first fit leaves out the brightest
    ``trim`` of each pixel's samples; each later one keeps the samples whose residual lies below
    ``cut`` robust standard deviations (one-sided: a specular peak only adds light; shadows are
    left to :func:`sample_masks`), and never fewer than the better-fitting half. Layouts that
    leave the normal undetermined in some direction (lights along a line) get the minimum-norm
    solution there.

    Args:
        samples: ``(N, K, C)`` values divided by the frames' exposure and irradiance.
        directions: ``(K, 3)`` effective directions ``d_k``
            (:func:`torchspec.model.lights.diffuse_directions`).
        valid: ``(N, K)`` samples allowed to enter (e.g. ``~masks.invalid``); all finite ones by
            default.
        iterations: reweighting passes after the first fit.
        cut: the one-sided outlier threshold in robust standard deviations.
        trim: the share of brightest samples left out of the first fit.

    Returns:
        :class:`Diffuse`.

    Example:
        >>> d = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866], [-0.5, 0.0, 0.866]])
        >>> fit = photometric_stereo((d @ torch.tensor([0.0, 0.0, 0.3]))[None, :, None], d)
        >>> [round(v, 4) for v in fit.normal[0].tolist()], round(float(fit.diffuse[0, 0]), 4)
        ([0.0, 0.0, 1.0], 0.9425)
    """
    n, k, c = _checked_stereo(samples, directions, iterations=iterations, cut=cut, trim=trim)
    dtype = samples.dtype
    d = directions.to(dtype)
    finite = torch.isfinite(samples).all(-1)
    valid = finite if valid is None else (valid & finite)
    values = torch.where(valid[..., None], samples, torch.zeros_like(samples))
    grey = values.mean(-1)  # (N, K)

    # First fit: the brightest `trim` of the valid samples left out.
    count = valid.sum(-1)
    rank = torch.where(valid, grey, torch.full_like(grey, -math.inf)).argsort(-1, descending=True).argsort(-1)
    weight = (valid & (rank >= (trim * count.to(dtype)).floor()[:, None])).to(dtype)
    b, eig = _weighted_solve(d, grey, weight)
    noise = _reweight(grey, valid, d, weight, b, eig, iterations=iterations, cut=cut)
    inliers = weight > 0
    quality = _quality(d, grey, valid, inliers, eig, count)
    normal, kd = _normal_and_diffuse(b, weight, values, d)
    return Diffuse(
        normal=normal,
        diffuse=kd,
        inliers=inliers,
        noise=torch.nan_to_num(noise, nan=0.0),
        quality=quality,
    )


def _checked_stereo(samples: Tensor, directions: Tensor, *, iterations: int, cut: float, trim: float) -> tuple:
    """``(N, K, C)`` of the samples after checking the arguments of :func:`photometric_stereo`."""
    if samples.dim() != 3:
        raise TorchspecError(f"samples must have shape (N, K, C); got {tuple(samples.shape)}.")
    n, k, c = samples.shape
    if tuple(directions.shape) != (k, 3):
        raise TorchspecError(
            f"directions must have shape ({k}, 3) for samples {tuple(samples.shape)}; got {tuple(directions.shape)}."
        )
    if not 0 <= trim < 1 or cut <= 0 or iterations < 0:
        raise TorchspecError(
            f"need 0 <= trim < 1, cut > 0, iterations >= 0; got trim={trim}, cut={cut}, iterations={iterations}."
        )
    return n, k, c


def _reweight(
    grey: Tensor, valid: Tensor, d: Tensor, weight: Tensor, b: Tensor, eig: Tensor, *, iterations: int, cut: float
) -> Tensor:
    """The reweighting passes of :func:`photometric_stereo`, updating ``weight (N, K)``, ``b (N, 3)``
    and ``eig (N, 3)`` in place; returns the robust noise ``(N,)`` (NaN where no inlier is left)."""
    n, dtype = grey.shape[0], grey.dtype
    noise = grey.new_zeros(n)
    # Floor the scale at a fraction of the pixel's typical value, so a noise-free pixel keeps its
    # near-exact samples (and a peak's tails do not set the scale).
    level = torch.where(valid, grey.abs(), torch.full_like(grey, math.nan)).nanmedian(-1).values
    floor = (1e-4 * torch.nan_to_num(level, nan=0.0) + torch.finfo(dtype).tiny)[:, None]
    # Only the pixels whose inlier set still changes are iterated: one whose set is unchanged has
    # reached its fixed point (the same solve, residuals and set again), so stopping it is exact.
    active = torch.arange(n, device=grey.device)
    for _ in range(iterations):
        if not active.numel():
            break
        g, ok, w_old = grey[active], valid[active], weight[active]
        residual = g - b[active] @ d.T
        kept = torch.where(w_old > 0, residual, torch.full_like(residual, math.nan))
        centre = kept.nanmedian(-1, keepdim=True).values
        spread = MAD_SCALE * (kept - centre).abs().nanmedian(-1).values
        scale = torch.maximum(torch.nan_to_num(spread, nan=0.0)[:, None], floor[active])
        # Never fewer than the better-fitting half of the samples: a poor first fit must not
        # collapse the set onto a handful of samples that fit it by chance (the lower median: half
        # of an even count).
        half = torch.where(ok, residual, torch.full_like(residual, math.nan)).nanmedian(-1, keepdim=True).values
        upper = torch.maximum(cut * scale, torch.nan_to_num(half, nan=0.0))
        w_new = (ok & (residual <= upper)).to(dtype)
        noise[active] = spread
        weight[active] = w_new
        b[active], eig[active] = _weighted_solve(d, g, w_new)
        active = active[(w_new != w_old).any(-1)]
    return noise


def _quality(d: Tensor, grey: Tensor, valid: Tensor, inliers: Tensor, eig: Tensor, count: Tensor) -> Tensor:
    """:attr:`Diffuse.quality` ``(N,)``: the share of inliers times the conditioning of their
    directions relative to that of all valid samples; 0 below 3 inliers."""
    dtype = grey.dtype
    tiny = torch.finfo(dtype).tiny
    _, eig_all = _weighted_solve(d, grey, valid.to(dtype))
    conditioning = (eig[:, 0] / eig[:, 2].clamp(min=tiny)) / (eig_all[:, 0] / eig_all[:, 2].clamp(min=tiny)).clamp(
        min=tiny
    )
    share = inliers.sum(-1).to(dtype) / count.clamp(min=1).to(dtype)
    return torch.where(inliers.sum(-1) >= 3, share * conditioning.clamp(0.0, 1.0), torch.zeros_like(share))


def _normal_and_diffuse(b: Tensor, weight: Tensor, values: Tensor, d: Tensor) -> tuple[Tensor, Tensor]:
    """The unit normal ``(N, 3)`` along ``b`` (``+z`` where ``b`` vanishes, flipped to face the
    camera) and ``k_d (N, C) >= 0`` by least squares along it on the weighted samples."""
    dtype = b.dtype
    tiny = torch.finfo(dtype).tiny
    length = b.norm(dim=-1, keepdim=True)
    up = torch.zeros_like(b)
    up[:, 2] = 1.0
    solved = (length[:, 0] > tiny) & torch.isfinite(length[:, 0])
    normal = torch.where(solved[:, None], b / length.clamp(min=tiny), up)
    normal = torch.where((normal[:, 2:] < 0), -normal, normal)  # the camera sees the front
    shading = normal @ d.T  # (N, K)
    w = weight * (shading > 0).to(dtype)
    kd = math.pi * (w[..., None] * values * shading[..., None]).sum(1) / (w * shading * shading).sum(1)[:, None].clamp(
        min=tiny
    )
    return normal, kd.clamp(min=0.0)
