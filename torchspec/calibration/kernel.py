"""Light calibration: the extended light's kernel, tabulated, from a mirror captured under it
(``torchspec calibrate MIRROR -o kernel.exr``).

A near-perfect mirror turns the rendering equation into a sampler of the light's shape. Pixel
``p`` of a mirror with normal ``n_p`` reflects the view ``v`` into ``r_p = reflect(v, n_p)``,
and its narrow lobe (mass ``m_p ~ k_s``) picks the kernel's density there::

    value_pk / (exposure_k irradiance_k) = floor_pk + m_p (K * g_p)(r_p - l_k)

with ``floor_pk`` the diffuse term, ``g_p`` the mirror's lobe in the l-plane (a Gaussian of std
``sqrt(2) alpha`` near normal incidence; a Dirac for a perfect mirror) and ``l_k`` the frame's
centre. So every frame gives, per pixel, one sample of the kernel at the offset ``r_p - l_k``:
a grid of frames around the reflection samples the kernel on that grid, and a curved mirror (many
``r_p``) fills in between the frames. The steps, per pixel and then pooled:

1. the diffuse floor, a robust (one-sided trimmed) least-squares fit of ``b . w_k`` (Lambert with
   the kernels' centres as directions), is subtracted; its residual spread is the pixel's noise;
2. pixels whose remaining peak does not stand out of the noise never see the light: left out
   (none left: the capture is not a mirror, an error);
3. the reflection ``r_p``: the centroid of the pixel's response in a window grown over its own
   spread (so the light's centre *is* the kernel's centroid: the convention that makes an
   asymmetric kernel's offset identifiable without the normal), or ``reflect(v, n)`` for a
   known ``normal``, which also recovers the kernel's offset;
4. pixels whose response still shows on the layout's edge frames (the kernel is cut off) are
   left out; too few distinct offsets inside the kernel's half-maximum footprint is an error
   that names the coverage;
5. the samples ``(r_p - l_k, y_pk / m_p)`` of every pixel (``m_p`` from the response's area
   integral, refined by least squares against the fitted kernel) are fitted by weighted least
   squares with the cubic B-spline surface that :class:`torchspec.model.lights.Kernel` reconstructs a
   tabulated kernel with (the table *is* its control grid, so the density the package integrates
   is the one fitted, with no extra blur), a Laplacian smoothness prior, the mirror's lobe
   modelled when ``mirror_alpha > 0`` (a discrete Gaussian on the table), non-negativity by an
   active set, Cholesky on the normal equations (``S^2`` unknowns, ``S <= 64``);
6. the table is normalised to unit integral over the l-plane (projected domain, as the format's
   ``tabulated`` kernel).

A line of frames only samples one section of the kernel: it is then taken as radially symmetric
(``symmetry="radial"``), and unless the normal is known, each pixel's reflection is taken on the
line (as a 1D FRI or fit assumes too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..model.geometry import reflect
from ..model.layout import layout_of
from ..model.lights import SPLINE_PAD, Kernel
from ._kernel_table import (
    CalibrationError,
    asymmetry,
    bin_samples,
    blur_taps,
    laplacian_matrix,
    radial_samples,
    separable_blur,
    solve_table,
    spline_design,
    table_moments,
)

__all__ = [
    "CalibrationError",
    "Calibration",
    "calibrate",
    "recover_kernel",
    "kernel_outputs",
    "write_kernel",
    "SYMMETRIES",
    "MIN_CORE",
]

SYMMETRIES = ("auto", "none", "radial")
MIN_CORE = {1: 5, 2: 20}
"""Distinct sample offsets (cells of 3/4 the frame spacing) needed inside the kernel's
half-maximum footprint, along a line (1D, radial profile) or over the plane (2D)."""
DETECT = 10.0
"""A pixel sees the light when its peak exceeds this many times its noise (and 1e-3 of its range)."""
EDGE = 0.01
"""A pixel whose response on an edge frame of the layout exceeds this share of its peak is cut off."""
WIDTH = 0.25
"""A pixel whose response's RMS width is off the lit pixels' median by more than this share is left
out (dust, a scratch, a diffuse patch); fewer than half alike: the capture is not of a mirror."""
DEFAULT_SMOOTHING = 0.03
"""The Laplacian prior's weight relative to the data's: much lower lets noise through a
deconvolution, much higher rounds a disk kernel's edge."""
MAX_SIZE = 64


@dataclass(frozen=True)
class Calibration:
    """The result of :func:`recover_kernel` and :func:`calibrate`.

    Attributes:
        table: ``(S, S)`` the kernel's density over ``l - l_k`` in ``[-extent, extent]^2`` (row 0
            at ``+extent`` in ``y``), as the control grid of the cubic B-spline surface
            :class:`~torchspec.model.lights.Kernel` reconstructs; ``sum(table) * pixel_area = 1``.
        extent: the half-width of the table in l units.
        reflection: ``(N, 2)`` each pixel's reflection direction used (l-plane); NaN where unused.
        used: ``(N,)`` the pixels whose samples were fitted.
        stats: JSON-ready: the settings chosen, the counts, the kernel's centroid, covariance,
            standard deviations, asymmetry, the fit's residual and notes.
    """

    table: Tensor
    extent: float
    reflection: Tensor
    used: Tensor
    stats: dict = field(default_factory=dict)

    def kernel(self) -> Kernel:
        """The :class:`~torchspec.model.lights.Kernel` of the table."""
        return Kernel("tabulated", table=self.table, extent=self.extent)

    def light(self, file: str = "kernel.exr") -> dict:
        """The capture manifest's ``light`` entry for this kernel written to ``file``."""
        return {"kernel": "tabulated", "file": file, "extent": self.extent}

    def summary(self) -> str:
        """A few lines: the width, symmetry, residual and what was assumed."""
        s = self.stats
        std = s["std"]
        lines = [
            f"kernel {s['size']}x{s['size']} over +-{self.extent:.4g} (l units), from {s['pixels_used']} of "
            f"{s['pixels']} pixels x {s['frames']} frames ({s['samples']} samples)",
            f"  width: std {std[0]:.4g} x {std[1]:.4g} (principal axes, l units; ~{math.degrees(std[0]):.3g} x "
            f"{math.degrees(std[1]):.3g} deg near the zenith), centroid ({s['centroid'][0]:+.2e}, "
            f"{s['centroid'][1]:+.2e})",
            f"  symmetry: {s['symmetry']}; point asymmetry {100 * s['asymmetry']:.2f} %, anisotropy "
            f"{s['anisotropy']:.3f}",
            f"  residual: {100 * s['residual']:.2f} % relative RMS; {s['core_offsets']} distinct offsets in the "
            "half-maximum footprint",
            f"  reflection: {s['reflection']}",
        ]
        return "\n".join(lines + [f"  note: {note}" for note in s["notes"]])


def _masked_median(x: Tensor, mask: Tensor) -> Tensor:
    return torch.nanmedian(torch.where(mask, x, torch.full_like(x, math.nan)), dim=-1).values


def _background(y: Tensor, valid: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """The diffuse floor ``(N, K)`` and noise ``(N,)``: a one-sided trimmed least-squares fit of
    ``b . w_k`` (specular peaks only ever add light, so only samples far above the fit are cut)."""
    eye = torch.eye(3, dtype=y.dtype, device=y.device)
    include = valid
    fitted = torch.zeros_like(y)
    scale = torch.zeros_like(y[:, 0])
    for _ in range(6):
        weight = include.to(y.dtype)
        gram = torch.einsum("nk,ki,kj->nij", weight, w, w)
        ridge = 1e-9 * gram.diagonal(dim1=-2, dim2=-1).sum(-1).clamp(min=torch.finfo(y.dtype).tiny)
        rhs = torch.einsum("nk,nk,ki->ni", weight, y, w)
        b, _ = torch.linalg.solve_ex(gram + ridge[:, None, None] * eye, rhs)
        fitted = b @ w.T
        residual = y - fitted
        middle = _masked_median(residual, include)
        scale = 1.4826 * _masked_median((residual - middle[:, None]).abs(), include)
        include = valid & (residual <= middle[:, None] + 3.0 * scale[:, None])
    return fitted, scale


def _edge_frames(l: Tensor, dims: int, axis: Tensor, spacing: float) -> Tensor:
    """``(K,)`` the frames on the layout's edge: the ends of a line; in the plane, those with an
    empty quadrant (no other frame within three spacings in it)."""
    if dims == 1:
        t = l @ axis
        return (t == t.min()) | (t == t.max())
    d = l[None, :, :] - l[:, None, :]  # (K, K, 2): from frame k to frame j
    near = d.norm(dim=-1) <= 3.0 * spacing
    near.fill_diagonal_(False)
    angle = torch.atan2(d[..., 1], d[..., 0])
    quadrant = torch.remainder(torch.floor((angle + math.pi / 4) / (math.pi / 2)), 4).long()
    seen = torch.stack([(near & (quadrant == q)).any(-1) for q in range(4)], -1)
    return ~seen.all(-1)


def _centroids(s: Tensor, l: Tensor, area: Tensor, spacing: float, dims: int, axis: Tensor) -> tuple[Tensor, Tensor]:
    """Each pixel's response centroid ``(N, 2)`` and RMS width per axis ``(N,)``, in a window grown
    over its own spread."""
    if dims == 1:
        t = ((l - l.mean(0)) @ axis)[None, :].expand_as(s)
        coords = t[..., None]
    else:
        coords = l[None].expand(s.shape[0], -1, -1)
    centre = coords.gather(1, s.argmax(-1)[:, None, None].expand(-1, 1, coords.shape[-1]))[:, 0]  # (N, D)
    tiny = torch.finfo(s.dtype).tiny
    # A start: the half-maximum footprint's size, from the number of frames inside it.
    half = (s >= 0.5 * s.max(-1, keepdim=True).values).to(s.dtype)
    footprint = (half * area).sum(-1)
    reach = (footprint if dims == 1 else torch.sqrt(footprint / math.pi)) * 2.0 + 2.0 * spacing
    for _ in range(8):
        inside = ((coords - centre[:, None, :]).norm(dim=-1) <= reach[:, None]).to(s.dtype)
        weight = inside * s * area
        mass = weight.sum(-1).clamp(min=tiny)
        centre = (weight[..., None] * coords).sum(1) / mass[:, None]
        spread = (weight * (coords - centre[:, None, :]).pow(2).sum(-1)).sum(-1) / mass
        reach = 4.5 * (spread.clamp(min=0.0) / dims).sqrt() + 2.0 * spacing
    width = (spread.clamp(min=0.0) / dims).sqrt()
    if dims == 1:
        return l.mean(0) + centre * axis, width
    return centre, width


@dataclass(frozen=True)
class _Responses:
    """Each pixel's specular response ``(N, K)`` (the diffuse floor removed), its peak, noise
    and whether it sees the light at all."""

    s: Tensor
    valid: Tensor
    peak: Tensor
    noise: Tensor
    lit: Tensor
    centroid: Tensor  # (N, 2) in the l-plane
    width: Tensor  # (N,) RMS width per axis


def _responses(values: Tensor, centres: Tensor, layout) -> _Responses:
    valid = torch.isfinite(values)
    y = torch.where(valid, values, torch.zeros_like(values))
    floor, noise = _background(y, valid, centres)
    s = torch.where(valid, y - floor, torch.zeros_like(y))
    peak = s.max(-1).values
    level = torch.maximum(noise, 1e-3 * y.abs().max(-1).values)
    lit = peak > DETECT * level
    if not bool(lit.any()):
        best = float((peak / level.clamp(min=torch.finfo(y.dtype).tiny)).max())
        raise CalibrationError(
            f"the capture must show a mirror's specular peak in some pixel; got none: the highest peak stands "
            f"{best:.3g} times above its pixel's noise (or 1e-3 of its range), {DETECT:g} needed. Calibrate from "
            "a mirror lit through its reflection direction (frames around the direction that mirrors the camera)."
        )
    centroid, width = _centroids(s, layout.l, layout.area, layout.spacing, layout.dims, layout.axis)
    return _Responses(s, valid, peak, noise, lit, centroid, width)


def _usable(r: _Responses, reflection: Tensor, layout, radial: bool, along_line: bool) -> tuple[Tensor, int]:
    """The pixels whose response the layout holds whole ``(N,)``, and the distinct offsets
    sampled inside the kernel's half-maximum footprint; raises when either is short."""
    l, spacing = layout.l, layout.spacing
    edge = _edge_frames(l, layout.dims, layout.axis, spacing)
    on_edge = torch.where(edge[None], r.s, torch.full_like(r.s, -math.inf)).max(-1).values
    cut = on_edge > EDGE * r.peak + 3.0 * r.noise
    typical = r.width[r.lit].median()
    alike = (r.width / typical - 1.0).abs() <= WIDTH
    if float(alike[r.lit].to(r.width.dtype).mean()) < 0.5:
        q = torch.tensor([0.05, 0.95], dtype=r.width.dtype, device=r.width.device)
        low, high = torch.quantile(r.width[r.lit], q).tolist()
        raise CalibrationError(
            f"the capture must be of a mirror, whose pixels all see the light's one kernel: their responses' widths "
            f"must agree within {100 * WIDTH:g} %; got widths from {low:.3g} to {high:.3g} (l units, 5-95 %), "
            f"{100 * float(alike[r.lit].to(r.width.dtype).mean()):.0f} % of the {int(r.lit.sum())} lit pixels within "
            f"{100 * WIDTH:g} % of their median {float(typical):.3g}. Calibrate from a uniform mirror."
        )
    used = r.lit & alike & ~cut
    if not bool(used.any()):
        worst = float((on_edge[r.lit] / r.peak[r.lit]).min())
        raise CalibrationError(
            f"the frames must extend beyond the kernel around each pixel's reflection; got every one of "
            f"{int(r.lit.sum())} lit pixel(s) cut off by the layout's edge (at least {100 * worst:.1f} % of the "
            f"peak on an edge frame, {100 * EDGE:g} % allowed). Add frames so the light's whole footprint around "
            "the mirror direction is inside the layout."
        )
    core = (reflection[used][:, None, :] - l[None, :, :])[r.s[used] >= 0.5 * r.peak[used][:, None]]
    if along_line:
        core = (core @ layout.axis)[:, None]
    cells = torch.unique(torch.round(core / (0.75 * spacing)).long(), dim=0).shape[0] if core.numel() else 0
    needed = MIN_CORE[1 if radial else 2]
    if cells < needed:
        raise CalibrationError(
            f"the frames must sample the kernel's half-maximum footprint at >= {needed} distinct offsets "
            f"({'along the line, radial profile' if radial else 'over the plane'}); got {cells} (frame spacing "
            f"{spacing:.3g} in l units, {int(used.sum())} usable pixel(s)). Space the frames closer around the "
            "reflection direction (a few per kernel width), or use a curved mirror whose pixels see the light at "
            "different offsets."
        )
    return used, cells


@dataclass(frozen=True)
class _KernelFit:
    """What :func:`_fit` found: the ``table (S, S)`` (unit integral), its ``extent``, the relative
    RMS ``residual`` and the number of ``samples`` fitted."""

    table: Tensor
    extent: float
    residual: float
    samples: int


def _fit(
    r: _Responses,
    used: Tensor,
    offsets: Tensor,
    layout,
    *,
    radial: bool,
    size: int,
    extent: float | None,
    blur: float,
    smoothing: float,
) -> _KernelFit:
    """The :class:`_KernelFit` of the used pixels' samples at ``offsets (P, K, 2)``."""
    spacing, area = layout.spacing, layout.area
    s, peak = r.s[used], r.peak[used]
    tiny = torch.finfo(s.dtype).tiny
    # Each pixel's scale: the area integral of its response, out to where it falls below 1 % of its peak.
    radius = offsets.norm(dim=-1)
    window = (radius * (s >= 0.01 * peak[:, None])).amax(-1, keepdim=True) + 2.0 * spacing
    mass = (s * area * (radius <= window)).sum(-1).clamp(min=tiny)
    target = s / mass[:, None]
    sigma = torch.maximum(r.noise[used], 1e-6 * peak) / mass
    weight = r.valid[used].to(s.dtype) / sigma[:, None] ** 2
    if extent is None:
        strong = target >= torch.maximum(0.01 * target.max(), 5.0 * sigma[:, None])
        far = radius[strong].max() if radial else offsets[strong].abs().max()
        extent = min(1.2 * (float(far) + spacing), 0.95)
    step = 2.0 * extent / size
    reach = extent + SPLINE_PAD * step
    keep = ((radius < reach) if radial else (offsets.abs().amax(-1) < reach)) & (weight > 0)  # (P, K)
    at = torch.stack([radius, torch.zeros_like(radius)], -1) if radial else offsets
    taps = blur_taps(blur / step, s) if blur > 0 else None
    design = spline_design(at[keep], extent, size)
    predicted = torch.zeros_like(target)
    free, prior = None, laplacian_matrix(size, s)
    for rounds in range(3):  # the fit, then each pixel's scale against it (twice)
        if radial:
            bu, bt, bw = radial_samples(radius[keep], target[keep], weight[keep], step)
        else:
            bu, bt, bw = bin_samples(offsets[keep], target[keep], weight[keep], 0.25 * step)
        table, free = solve_table(spline_design(bu, extent, size), bt, bw / bw.mean(), prior, smoothing, taps, free)
        predicted[keep] = design.apply(table if taps is None else separable_blur(table[None], taps)[0])
        if rounds == 2:
            break
        w = weight * keep
        gain = (w * target * predicted).sum(-1) / (w * predicted * predicted).sum(-1).clamp(min=tiny)
        gain = torch.where(gain > 0, gain, torch.ones_like(gain))
        target, weight = target / gain[:, None], weight * gain[:, None] ** 2
    w = weight * keep
    residual = float(torch.sqrt((w * (target - predicted) ** 2).sum() / (w * target**2).sum()))
    return _KernelFit(table / (table.sum() * step * step), float(extent), residual, int(keep.sum()))


def _reflection(responses: _Responses, normal: Tensor | None, view: Tensor, layout) -> tuple[Tensor, str]:
    """Each pixel's reflection of the view in the l-plane ``(N, 2)``, and how it was found, in words:
    from ``normal`` when given, otherwise the centroid of the pixel's response."""
    if normal is None:
        how = "estimated: each pixel's response centroid (the kernel's centroid is the light's centre)"
        how += "; on the line of frames (a line cannot see across it)" if layout.dims == 1 else ""
        return responses.centroid, how
    n = normal.to(dtype=view.dtype, device=view.device)
    reflection = reflect(view, n / n.norm(dim=-1, keepdim=True))[..., :2].expand(responses.centroid.shape[0], 2)
    return reflection, "from the given normal (the kernel's offset is recovered)"


def recover_kernel(
    values: Tensor,
    centres: Tensor,
    *,
    view: Tensor,
    normal: Tensor | None = None,
    size: int = 32,
    extent: float | None = None,
    symmetry: str = "auto",
    mirror_alpha: float = 0.0,
    smoothing: float = DEFAULT_SMOOTHING,
) -> Calibration:
    """The light's tabulated kernel from a mirror's responses.

    Args:
        values: ``(N, K)`` each pixel's value under each frame, divided by the frame's exposure
            and irradiance (and averaged over channels); NaN or Inf samples are left out.
        centres: ``(K, 3)`` the frames' unit light directions (kernel centres).
        view: ``(3,)`` unit direction towards the camera.
        normal: the mirror's unit normal, ``(3,)`` for a flat mirror or ``(N, 3)`` per pixel; by
            default each pixel's reflection is estimated as its response's centroid (the
            kernel's centroid then sits at ``l_k``).
        size: ``S``, the table's pixels per side.
        extent: the table's half-width in l units; by default 1.2 times the farthest offset where
            the response exceeds 1 % of its peak, plus a frame spacing.
        symmetry: ``radial`` (a radially symmetric kernel: needed for a line of frames),
            ``none``, or ``auto`` (radial for a line, none for a planar layout).
        mirror_alpha: the mirror's Ward roughness; its lobe (std ``sqrt(2) alpha`` in the l-plane)
            is deconvolved. 0 for a perfect mirror: the table is then the kernel blurred by it.
        smoothing: the weight of the Laplacian prior, relative to the data's.

    Returns:
        :class:`Calibration`.

    Raises:
        CalibrationError: no pixel shows a peak (not a mirror, or the light never reflects into
            the camera), every pixel's response is cut off by the layout's edge, or the frames
            cover the kernel's footprint too sparsely (the message gives the counts).
            Also: malformed shapes or settings (the message names the argument).

    Example:
        >>> from torchspec.model.geometry import from_plane
        >>> from torchspec.model.lights import Kernel
        >>> g = torch.linspace(-0.08, 0.08, 21, dtype=torch.float64)
        >>> centres = from_plane(torch.cartesian_prod(g, g))  # (K = 441, 3): a 21 x 21 grid of frames
        >>> light = Kernel("gaussian", "projected", 0.02)
        >>> zenith = torch.zeros(441, 2, dtype=torch.float64)  # 4 pixels of a perfect mirror, reflecting to it:
        >>> values = light.density(zenith, centres).expand(4, -1)  # (N = 4, K)
        >>> view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        >>> calibration = recover_kernel(values, centres, view=view, size=16)
        >>> [round(std, 3) for std in calibration.stats["std"]]
        [0.02, 0.02]
    """
    _check_arguments(
        values, centres, size=size, extent=extent, symmetry=symmetry, mirror_alpha=mirror_alpha, smoothing=smoothing
    )
    like = dict(dtype=values.dtype, device=values.device)
    centres, view = centres.to(**like), view.to(**like)
    layout = layout_of(centres[:, :2])
    radial = symmetry == "radial" or (symmetry == "auto" and layout.dims == 1)
    along_line = layout.dims == 1 and normal is None  # offsets known along the line only

    responses = _responses(values, centres, layout)
    reflection, how = _reflection(responses, normal, view, layout)
    used, cells = _usable(responses, reflection, layout, radial, along_line)
    offsets = reflection[used][:, None, :] - layout.l[None, :, :]  # (P, K, 2)
    if along_line:
        offsets = (offsets @ layout.axis)[..., None] * layout.axis
    blur = math.sqrt(2.0) * mirror_alpha
    fitted = _fit(
        responses, used, offsets, layout, radial=radial, size=size, extent=extent, blur=blur, smoothing=smoothing
    )
    table, extent = fitted.table, fitted.extent

    centroid, covariance = table_moments(table, extent)
    if radial:
        centroid = torch.zeros_like(centroid)
    stats = {
        "size": size,
        "extent": extent,
        "pixels": values.shape[0],
        "pixels_lit": int(responses.lit.sum()),
        "pixels_used": int(used.sum()),
        "frames": values.shape[1],
        "samples": fitted.samples,
        "layout": "line" if layout.dims == 1 else "plane",
        "spacing": layout.spacing,
        "core_offsets": cells,
        "symmetry": "radial (imposed)" if radial else "none imposed",
        "reflection": how,
        "mirror_alpha": mirror_alpha,
        "smoothing": smoothing,
        **_shape_stats(table, extent, centroid, covariance),
        "residual": fitted.residual,
        "notes": _notes(radial, mirror_alpha, blur),
    }
    out = torch.full_like(values[:, :2], math.nan)
    out[used] = reflection[used]
    return Calibration(table, extent, out, used, stats)


def _check_arguments(
    values: Tensor, centres: Tensor, *, size: int, extent, symmetry: str, mirror_alpha: float, smoothing: float
) -> None:
    """Raise :class:`CalibrationError` naming the argument of :func:`recover_kernel` at fault."""
    if values.dim() != 2 or centres.dim() != 2 or centres.shape != (values.shape[1], 3):
        raise CalibrationError(
            f"values must have shape (N, K) and centres (K, 3); got {tuple(values.shape)} and {tuple(centres.shape)}."
        )
    if values.shape[1] < 3:
        raise CalibrationError(f"a calibration needs at least 3 frames; got {values.shape[1]}.")
    if symmetry not in SYMMETRIES:
        raise CalibrationError(f"symmetry must be one of {SYMMETRIES}; got {symmetry!r}.")
    if not 8 <= size <= MAX_SIZE:
        raise CalibrationError(
            f"size must be in 8..{MAX_SIZE} table pixels per side (the solve is dense in size^2 unknowns); got {size}."
        )
    if extent is not None and not 0 < extent < 1:
        raise CalibrationError(f"extent must be in (0, 1) (l units); got {extent!r}.")
    if not mirror_alpha >= 0 or not smoothing >= 0:
        raise CalibrationError(f"mirror_alpha and smoothing must be >= 0; got {mirror_alpha!r}, {smoothing!r}.")


def _shape_stats(table: Tensor, extent: float, centroid: Tensor, covariance: Tensor) -> dict:
    """The kernel's centroid, covariance, principal stds (largest first), anisotropy and asymmetry."""
    std = torch.linalg.eigvalsh(covariance).clamp(min=0.0).sqrt().flip(0)
    return {
        "centroid": [float(v) for v in centroid],
        "covariance": [[float(v) for v in row] for row in covariance],
        "std": [float(v) for v in std],
        "anisotropy": float(std[0] / std[1].clamp(min=torch.finfo(std.dtype).tiny)),
        "asymmetry": asymmetry(table, extent, centroid),
    }


def _notes(radial: bool, mirror_alpha: float, blur: float) -> list[str]:
    """The assumptions a calibration made, in words."""
    notes = []
    if radial:
        notes.append("radial symmetry imposed: the table is the rotation of the samples' radial profile")
    if mirror_alpha > 0:
        notes.append(f"the mirror's lobe (alpha {mirror_alpha:g}, std {blur:.3g} in l) is deconvolved")
    else:
        notes.append(
            "a perfect mirror is assumed: the table is the kernel blurred by the mirror's lobe (variance "
            "2 alpha^2 per axis; pass mirror_alpha to remove it)"
        )
    return notes


def calibrate(
    capture,
    *,
    frames: str | list[int] | None = None,
    normal: Tensor | None = None,
    size: int = 32,
    extent: float | None = None,
    symmetry: str = "auto",
    mirror_alpha: float = 0.0,
    smoothing: float = DEFAULT_SMOOTHING,
    device: torch.device | str = "cpu",
) -> Calibration:
    """Calibrate the light kernel from a mirror capture (:func:`recover_kernel` on its frames),
    computed on ``device``; the result is on the CPU.

    Args:
        capture: a :class:`~torchspec.io.Capture` or its folder; its light may be ``unknown``.
        frames: a SPEC of :func:`torchspec.pipeline.select_frames` or a list of indices.
        normal, size, extent, symmetry, mirror_alpha, smoothing: see :func:`recover_kernel`.

    Returns:
        :class:`Calibration` (computed in float64).

    Example:
        >>> calibration = calibrate("mirror-dev-1d")  # doctest: +SKIP
        >>> write_kernel("kernel.exr", calibration)  # doctest: +SKIP
    """
    from ..io import Capture, read_capture
    from ..pipeline import select_frames

    capture = capture if isinstance(capture, Capture) else read_capture(capture)
    picked = frames if isinstance(frames, list) else select_frames(frames, len(capture.frames))
    stack = capture.read_frames(picked, dtype=torch.float64, device=device, nonfinite="keep")  # (K, C, H, W)
    index = torch.tensor(picked)  # on the CPU: it indexes the capture's CPU tables (exposure, irradiance, directions)
    scale = (capture.exposure()[index, None] * capture.irradiance()[index]).to(stack.device)  # (K, C)
    values = (stack / scale[:, :, None, None]).mean(1).flatten(1).T  # (H W, K)
    if normal is not None:
        normal = torch.as_tensor(normal, dtype=torch.float64, device=values.device)
        if normal.dim() == 3:
            normal = normal.reshape(-1, 3)
    try:
        result = recover_kernel(
            values,
            capture.directions()[index].to(values.device),
            view=torch.tensor(capture.view, dtype=torch.float64, device=values.device),
            normal=normal,
            size=size,
            extent=extent,
            symmetry=symmetry,
            mirror_alpha=mirror_alpha,
            smoothing=smoothing,
        )
    except CalibrationError as error:
        raise CalibrationError(f"{capture.root}: {error}") from None
    h, w = capture.height, capture.width
    stats = {**result.stats, "capture": str(capture.root), "image": [h, w]}
    return Calibration(result.table.cpu(), result.extent, result.reflection.cpu(), result.used.cpu(), stats)


def kernel_outputs(path: str | Path, *, overwrite: bool = False, flag: str = "overwrite=True") -> Path:
    """Check, before a calibration, that its kernel ``path`` and the ``.json`` beside it can be written
    and do not exist (unless ``overwrite``): :func:`torchspec.outputs.check_output` on each."""
    from ..outputs import check_output

    path = Path(path)
    for file in (path, path.with_suffix(".json")):
        check_output(file, overwrite=overwrite, folder=False, flag=flag)
    return path


def write_kernel(path: str | Path, calibration: Calibration, *, overwrite: bool = False) -> dict:
    """Write the table as a single-channel (``Y``) EXR, atomically, and beside it (same stem,
    ``.json``) the manifest's ``light`` entry with the calibration's statistics. Either file
    existing is refused unless ``overwrite`` (:func:`kernel_outputs`).

    Returns:
        The ``light`` entry for a capture whose manifest sits in the same folder as ``path``.
    """
    from ..atomic import write_json
    from ..io import write_exr

    path = kernel_outputs(path, overwrite=overwrite)
    write_exr(path, calibration.table.to(torch.float32), ["Y"])
    light = calibration.light(path.name)
    write_json(path.with_suffix(".json"), {"light": light, "calibration": calibration.stats})
    return light
