"""Light directions from a reflective sphere photographed under each light (``torchspec
calibrate-sphere``), written as an ``.lp`` light file so that a fixed dome is calibrated once.

The sphere's outline is a circle in the image: given as centre and radius, or found from a mask
image (white on the sphere: its centroid and ``sqrt(area / pi)``). In each frame the highlight is
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

from .atomic import atomic_path, write_json
from .errors import TorchspecError
from .io.images import read_photo

__all__ = ["Circle", "SphereCalibration", "circle_from_mask", "sphere_directions", "write_lp"]


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


def sphere_directions(frames: torch.Tensor, circle: Circle, *, level: float = 0.5) -> SphereCalibration:
    """Light directions from ``frames (K, C, H, W)`` (linear or encoded: only the order of values
    matters) of a sphere with outline ``circle``.

    Raises:
        TorchspecError: a frame without light on the sphere; a circle outside the frames.
    """
    k, _, h, w = frames.shape
    dtype = torch.float64
    rows = torch.arange(h, dtype=dtype)[:, None].expand(h, w)
    cols = torch.arange(w, dtype=dtype)[None, :].expand(h, w)
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
    direction = 2 * normal[:, 2:3] * normal - torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
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
