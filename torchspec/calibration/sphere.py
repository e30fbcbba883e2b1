"""Light directions from a reflective sphere photographed under each light (``torchspec
calibrate-sphere``), written as an ``.lp`` light file so that a fixed dome is calibrated once.

The sphere's outline is a circle in the image: given as centre and radius, found from a mask
image (white on the sphere: its centroid and ``sqrt(area / pi)``), or found automatically
(:func:`find_sphere`): a gradient Hough transform of the per-pixel median of the frames (the
highlights, which move from frame to frame, drop out of it) on a copy reduced to ~160 pixels,
refined at full resolution by a least-squares circle through the outermost edge along rays from
its centre (the silhouette; a reflection's edges lie inside it). A partial outline suffices (a dark ball on a
dark cloth shows only its upper rim): each edge pixel votes along its gradient. In each frame the highlight is
the centroid of the sphere's pixels above ``level`` times the frame's brightest one there (mean of
the channels), each weighed by its excess over that threshold; the sphere's normal at that point,
``n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - ...))`` (x right, y up, as in the ``.lp``), reflects
the orthographic view ``v = (0, 0, 1)`` into the direction of the light: ``l = 2 (n . v) n - v``.
The uncertainty of each direction is the angle by which one standard deviation of the highlight's
pixels about its centroid (at least a pixel's quantisation) moves ``l`` (``2 sigma / (r n_z)``
radians): a broad or split highlight is less certain.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_path, write_json
from ..errors import TorchspecError
from ..io.images import read_photo

__all__ = ["Circle", "SphereCalibration", "circle_from_mask", "find_sphere", "sphere_directions", "write_lp"]


@dataclass(frozen=True)
class Circle:
    """The sphere's outline in pixels: centre column ``cx``, row ``cy`` (row 0 at the top), radius ``r``."""

    cx: float
    cy: float
    r: float


@dataclass(frozen=True)
class SphereCalibration:
    """Light directions recovered from a sphere.

    Attributes:
        directions: ``(K, 3)`` float64 unit vectors towards each light (x right, y up, z to the camera).
        uncertainty_deg: ``(K,)`` the angle one standard deviation of the highlight moves it.
        highlights: ``(K, 2)`` the highlights' (column, row) in pixels.
        circle: the sphere's outline used.
    """

    directions: torch.Tensor
    uncertainty_deg: torch.Tensor
    highlights: torch.Tensor
    circle: Circle


def circle_from_mask(mask: str | Path | np.ndarray) -> Circle:
    """The circle of a mask image (or ``(H, W)`` array): pixels above half its maximum are the sphere."""
    if not isinstance(mask, np.ndarray):
        mask = read_photo(mask).pixels.mean(-1)
    inside = mask > 0.5 * mask.max() if mask.max() > 0 else np.zeros(mask.shape, bool)
    if inside.sum() < 10:
        raise TorchspecError(f"the sphere's mask must cover at least 10 pixels; got {int(inside.sum())}.")
    rows, cols = np.nonzero(inside)
    return Circle(cx=float(cols.mean()), cy=float(rows.mean()), r=float(math.sqrt(inside.sum() / math.pi)))


def _edges(image: np.ndarray, sigma: float):
    from scipy import ndimage

    smooth = ndimage.gaussian_filter(image, sigma)
    gx, gy = ndimage.sobel(smooth, 1), ndimage.sobel(smooth, 0)
    return gx, gy, np.hypot(gx, gy)


def _hough(image: np.ndarray, fraction: float = 0.04) -> tuple[float, float, float]:
    """The strongest circle of ``image`` (radius 5-50 % of its shorter side): the strongest
    ``fraction`` of edge pixels vote, weighed by their gradient, for centres one radius away along
    their gradient, either side; the most votes win (as in a plain Hough transform: votes per unit
    of arc would favour the tight curls of a rim's end)."""
    from scipy import ndimage

    h, w = image.shape
    gx, gy, magnitude = _edges(image, 1.0)
    rows, cols = np.nonzero(magnitude > np.quantile(magnitude, 1 - fraction))
    weight = magnitude[rows, cols]
    ux, uy = gx[rows, cols] / weight, gy[rows, cols] / weight
    radii = np.arange(max(3, int(min(h, w) * 0.05)), int(min(h, w) * 0.5) + 1)
    votes = np.zeros(len(radii) * h * w)
    index = np.arange(len(radii))[:, None]
    for side in (1, -1):
        cx = np.rint(cols + side * radii[:, None] * ux).astype(np.int64)
        cy = np.rint(rows + side * radii[:, None] * uy).astype(np.int64)
        inside = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        flat = ((index * h + cy) * w + cx)[inside]
        votes += np.bincount(flat, weights=np.broadcast_to(weight, cx.shape)[inside], minlength=votes.size)
    votes = ndimage.gaussian_filter(votes.reshape(len(radii), h, w), 1.0)
    r, y, x = np.unravel_index(votes.argmax(), votes.shape)
    return float(x), float(y), float(radii[r])


def _refine(image: np.ndarray, circle: Circle, sigma: float) -> tuple[Circle, int]:
    """The outline through the outermost edge along each of 360 rays from the centre (the
    silhouette is the ball's outermost edge; a reflection's edges lie inside it): along each ray,
    within a band about ``circle``, the outermost peak of the radial gradient's magnitude at least
    half the ray's largest and above the image's 90 % quantile, located to a fraction of a pixel
    by a parabola; then an algebraic least-squares circle through these points, weighed by their
    gradient. Three passes, the band narrowing; also returns the number of rays used."""
    from scipy import ndimage

    gx, gy, magnitude = _edges(image, sigma)
    floor = float(np.quantile(magnitude, 0.9))
    theta = np.linspace(0, 2 * np.pi, 360, endpoint=False)[:, None]
    cos, sin = np.cos(theta), np.sin(theta)
    cx, cy, r, used = circle.cx, circle.cy, circle.r, 0
    for band in (max(3.0, 0.06 * r), max(2.0, 0.03 * r), max(2.0, 0.03 * r)):
        step = 0.25
        offsets = np.arange(-band, band + step / 2, step)[None, :]
        x, y = cx + (r + offsets) * cos, cy + (r + offsets) * sin
        radial = np.abs(
            ndimage.map_coordinates(gx, [y, x], order=1, mode="nearest") * cos
            + ndimage.map_coordinates(gy, [y, x], order=1, mode="nearest") * sin
        )  # (rays, samples)
        peak = (radial[:, 1:-1] >= radial[:, :-2]) & (radial[:, 1:-1] > radial[:, 2:])
        peak &= (radial[:, 1:-1] >= 0.3 * radial.max(1, keepdims=True)) & (radial[:, 1:-1] > floor)
        rays = peak.any(1)
        used = int(rays.sum())
        if used < 10:
            break
        last = peak.shape[1] - 1 - np.argmax(peak[:, ::-1], axis=1)  # the outermost peak (index in 1:-1)
        ray = np.nonzero(rays)[0]
        k = last[ray] + 1
        left, mid, right = radial[ray, k - 1], radial[ray, k], radial[ray, k + 1]
        shift = 0.5 * (left - right) / np.where(left - 2 * mid + right < 0, left - 2 * mid + right, -1.0)
        distance = r + offsets[0, k] + np.clip(shift, -0.5, 0.5) * step
        px, py = cx + distance * cos[ray, 0], cy + distance * sin[ray, 0]
        root = np.sqrt(mid)
        system = np.stack([px, py, np.ones_like(px)], 1) * root[:, None]
        a, b, c = np.linalg.lstsq(system, (px * px + py * py) * root, rcond=None)[0]
        cx, cy = a / 2, b / 2
        r = math.sqrt(max(c + cx * cx + cy * cy, 0.0))
    return Circle(float(cx), float(cy), float(r)), used


def find_sphere(frames: torch.Tensor) -> Circle:
    """The outline of the sphere photographed in ``frames (K, C, H, W)`` (see the module's
    docstring), found without a mask.

    Raises:
        TorchspecError: frames without contrast, or no outline found (too few edge pixels on it):
            give ``--mask`` or ``--circle``.
    """
    from scipy import ndimage

    luminance = frames.to(torch.float64).mean(1).cpu().numpy()
    median = np.median(luminance, axis=0)
    scale = float(np.quantile(median, 0.995)) or float(median.max())
    if not scale > 0:
        raise TorchspecError("the sphere's frames are black; give its outline with --mask or --circle.")
    image = np.log1p(median / (0.02 * scale))  # dark surroundings matter as much as bright ones
    h, w = image.shape
    factor = max(1, math.ceil(min(h, w) / 160))
    small = ndimage.zoom(ndimage.gaussian_filter(image, factor / 2), 1 / factor, order=1) if factor > 1 else image
    x, y, r = _hough(small)
    coarse = Circle(x * factor + (factor - 1) / 2, y * factor + (factor - 1) / 2, r * factor)
    circle, used = _refine(image, coarse, max(1.0, min(h, w) / 300))
    if used < 10 or not (0 < circle.r < max(h, w)):
        raise TorchspecError(
            f"no sphere outline found in the {w}x{h} frames (best guess {coarse}); give it with --mask or --circle."
        )
    return circle


def sphere_directions(frames: torch.Tensor, circle: Circle, *, level: float = 0.5) -> SphereCalibration:
    """Light directions from ``frames (K, C, H, W)`` (linear or encoded: only the order of values
    matters) of a sphere with outline ``circle``.

    Raises:
        TorchspecError: a frame without light on the sphere; a circle outside the frames.
    """
    k, _, h, w = frames.shape
    dtype = torch.float64
    rows = torch.arange(h, dtype=dtype, device=frames.device)[:, None].expand(h, w)
    cols = torch.arange(w, dtype=dtype, device=frames.device)[None, :].expand(h, w)
    inside = (cols - circle.cx) ** 2 + (rows - circle.cy) ** 2 <= (0.97 * circle.r) ** 2  # off the rim
    if not inside.any():
        raise TorchspecError(f"the sphere's circle {circle} holds no pixel of the {w}x{h} frames.")
    y = frames.to(dtype).mean(1)  # (K, H, W)
    y = torch.where(inside, y, torch.full_like(y, -math.inf))
    top = y.flatten(1).amax(1)  # (K,)
    dark = (top <= 0).nonzero().flatten().tolist()
    if dark:
        raise TorchspecError(f"frames {dark} show no light on the sphere: check the circle or the frames.")
    # Weights fall to 0 at the threshold: a pixel crossing it moves the centroid continuously.
    weight = torch.where(inside, y - level * top[:, None, None], torch.zeros_like(y)).clamp(min=0)
    total = weight.sum((1, 2))
    cx = (weight * cols).sum((1, 2)) / total
    cy = (weight * rows).sum((1, 2)) / total
    second = (weight * ((cols - cx[:, None, None]) ** 2 + (rows - cy[:, None, None]) ** 2)).sum((1, 2)) / total
    spread = (second + 1 / 6).sqrt()  # at least a pixel's quantisation, 1/12 per axis
    nx, ny = (cx - circle.cx) / circle.r, -(cy - circle.cy) / circle.r
    nz = (1 - nx * nx - ny * ny).clamp(min=1e-6).sqrt()
    normal = torch.stack([nx, ny, nz], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    direction = 2 * normal[:, 2:3] * normal - torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=frames.device)
    uncertainty = torch.rad2deg(2 * spread / (circle.r * normal[:, 2])).clamp(max=180)
    return SphereCalibration(direction, uncertainty, torch.stack([cx, cy], -1), circle)


def write_lp(path: str | Path, names: list[str], calibration: SphereCalibration) -> None:
    """Write the directions as an ``.lp`` (``count``, then ``name x y z``), atomically, and
    ``PATH.json`` beside it: the circle, each light's highlight and uncertainty (degrees)."""
    path = Path(path)
    lines = [str(len(names))] + [
        f"{name} {x:.6f} {y:.6f} {z:.6f}"
        for name, (x, y, z) in zip(names, calibration.directions.tolist(), strict=True)
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    c = calibration.circle
    write_json(
        path.with_suffix(".json"),
        {
            "circle": {"cx": c.cx, "cy": c.cy, "r": c.r},
            "lights": [
                {"image": name, "direction": d, "highlight": hl, "uncertainty_deg": u}
                for name, d, hl, u in zip(
                    names,
                    calibration.directions.tolist(),
                    calibration.highlights.tolist(),
                    calibration.uncertainty_deg.tolist(),
                    strict=True,
                )
            ],
        },
    )
