"""The page's cast shadows: maps fitted with a height (``height.exr``, issue 39) relight in the
browser with each light's visibility over it, as ``torchspec render`` relights them.

The tiles hold *horizon maps* (:func:`horizon_planes`): for each of :data:`AZIMUTHS` azimuths
``phi_j = 2 pi j / AZIMUTHS`` (the surface frame: ``x`` right, ``y`` up, ``phi`` from ``+x``
towards ``+y``) the horizon elevation of every pixel along it, radians
(:func:`torchspec.model.visibility.horizon` over the height, in pixels), and the indirect share
``b`` (``indirect.exr``). The page takes a light's horizon linearly between the two azimuths
about it and shades

    term(V r) + b D,   V = sigmoid((e - H) / s),

``r`` the maps' rendering, ``e`` the light's elevation, ``s`` the fit's penumbra
(``svbrdf.json``'s ``height.softness_deg``) widened under an extended kernel by its spread in
elevation (:func:`torchspec.model.visibility.kernel_visibility`'s ``probit`` rule, from the
kernel's covariance and mean offset in the manifest: :func:`shadow_manifest`), ``D`` the flat
diffuse (:mod:`torchspec.model.indirect`) and the residual term after the visibility
(:func:`torchspec.relight.shaded_render`). A near light's visibility takes each pixel's own
direction to the light, as :func:`torchspec.model.visibility.frame_visibility` does.

Where the page differs from ``torchspec render`` (the tests bound each):

- it takes the visibility at the pixel's centre (``render`` averages ``2 x 2`` points of the
  pixel's footprint): they differ on the pixels a shadow's edge crosses;
- between two of the azimuths its horizon is interpolated;
- the rays sample the height as the fit does within 4 pixels, then every 1/32 of the distance
  (:func:`view_distances`: 114 samples where the fit takes 248 at a reach of 115 pixels, and
  the fewer the farther; a narrow far peak between two samples lowers the horizon, by 1.1
  degrees at most and 0.0035 on average on the test's bumps), out to :func:`view_reach`: the distance at which
  the height's range can hide a light :data:`LOWEST_DEG` above the plane (a lower light may
  miss a farther occluder);
- a coarser level averages the horizons of the pixels it covers (a display's approximation).

Horizons are made in blocks of :data:`BAND` rows aligned on multiples of it, each from the
height's rows within the reach above and below: a band of rows read lazily
(:meth:`torchspec.view.tiles.Pyramid.of_folder`) gets the horizons of the whole image, bit for bit.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..errors import TorchspecError
from ..io.exr import read_exr
from ..model.lights import Kernel
from ..model.visibility import horizon, marched_distances, shadow_reach

__all__ = [
    "AZIMUTHS",
    "BAND",
    "GROWTH",
    "LOWEST_DEG",
    "SHADOW_TEXTURES",
    "horizon_planes",
    "read_height",
    "shadow_manifest",
    "shadow_planes",
    "view_distances",
    "view_reach",
]

AZIMUTHS = 32
"""Azimuths of the horizon maps, evenly spaced (11.25 degrees apart: at 22.5 a compact bump's shadow
between two of them was off by up to 44 codes on 3 % of the pixels, at 11.25 by up to 12 on 1.6 %)."""
LOWEST_DEG = 5.0
"""The lowest light elevation (degrees) whose occluders the horizon maps reach."""
BAND = 256
"""Rows of the blocks the horizons are made in."""
GROWTH = 1.0 / 32.0
"""Beyond 4 pixels, a ray's next sample lies this share of its distance farther (at least half a pixel)."""
NEAR = 4.0
"""Within this many pixels a ray samples as the fit's does (:func:`torchspec.model.visibility.marched_distances`)."""

SHADOW_TEXTURES = tuple(
    (f"shadow{i}", "float16", tuple(f"horizon_{4 * i + j}" for j in range(4))) for i in range(AZIMUTHS // 4)
) + ((f"shadow{AZIMUTHS // 4}", "float16", ("indirect", "shadow_pad_0", "shadow_pad_1", "shadow_pad_2")),)
"""The tile's textures of maps with a height: the horizons (radians), then the indirect share."""


def view_distances(reach: float) -> torch.Tensor:
    """The distances (pixels, float64 on the CPU) at which the page's horizons sample a ray: the
    fit's within :data:`NEAR` pixels, then each :data:`GROWTH` of the distance farther (at least
    half a pixel), up to ``reach`` (included). 1/16 lowered a far narrow peak's horizon by up to
    2.2 degrees, 1/64 by 0.56 at 1.4 times 1/32's cost."""
    base = marched_distances(0.5, reach)
    far, t = [], NEAR
    while t < reach:
        far.append(t)
        t += max(0.5, GROWTH * t)
    return torch.tensor(base[base < min(NEAR, reach)].tolist() + far + [reach], dtype=torch.float64, device="cpu")


def view_reach(height: torch.Tensor) -> float:
    """How far (pixels) the page's horizons look: where the height's range can hide a light
    :data:`LOWEST_DEG` above the plane, at most the image's diagonal (one host sync)."""
    low = math.radians(LOWEST_DEG)
    direction = torch.tensor([[math.cos(low), 0.0, math.sin(low)]], dtype=height.dtype, device=height.device)
    return shadow_reach(height, direction)


def read_height(folder: str | Path) -> torch.Tensor:
    """``(H, W)`` float32: a map folder's ``height.exr`` (pixels), whole.

    Raises:
        TorchspecError: a value that is not finite (naming the file and the first such pixel).
    """
    path = Path(folder) / "height.exr"
    value = torch.from_numpy(np.ascontiguousarray(read_exr(path)[..., 0]))
    bad = ~value.isfinite()
    if bool(bad.any()):
        row, col = (int(i) for i in bad.nonzero()[0])
        raise TorchspecError(
            f"{path}: {int(bad.sum())} height values are NaN or Inf (the first at row {row}, column {col})."
        )
    return value


def horizon_planes(height: torch.Tensor, start: int, stop: int, reach: float) -> dict[str, torch.Tensor]:
    """The horizons ``horizon_j`` (radians, ``(stop - start, W)`` float32 each) of rows ``start``
    to ``stop - 1`` of ``height (H, W)`` (pixels), reaching ``reach`` pixels: made in blocks of
    :data:`BAND` rows aligned on its multiples (module docstring), in the height's dtype and on
    its device."""
    rows = height.shape[0]
    phi = torch.arange(AZIMUTHS, dtype=torch.float64, device=height.device) * (2.0 * math.pi / AZIMUTHS)
    directions = torch.stack([phi.cos(), phi.sin(), torch.zeros_like(phi)], -1).to(height.dtype)
    distances = view_distances(reach)
    halo = math.ceil(reach)
    parts = []
    for first in range(start // BAND * BAND, stop, BAND):
        last = min(rows, first + BAND)
        top, bottom = max(0, first - halo), min(rows, last + halo)
        block = horizon(height[top:bottom], directions, reach=reach, distances=distances)[first - top : last - top]
        parts.append(block[max(0, start - first) : stop - first])
    found = torch.cat(parts, 0).float()
    return {f"horizon_{j}": found[..., j] for j in range(AZIMUTHS)}


def shadow_planes(
    height: torch.Tensor, share: torch.Tensor | None, start: int, stop: int, reach: float
) -> dict[str, torch.Tensor]:
    """The planes of :data:`SHADOW_TEXTURES` for rows ``start`` to ``stop - 1``: the horizons of
    ``height (H, W)`` (the whole height: a ray looks beyond the rows) and the indirect share
    ``share`` of those rows (``(stop - start, W)``; ``None``: 0)."""
    planes = horizon_planes(height, start, stop, reach)
    zero = torch.zeros(stop - start, height.shape[1], device=height.device)
    planes["indirect"] = zero if share is None else share.float().to(height.device)
    planes.update({f"shadow_pad_{k}": zero for k in range(3)})
    return planes


def shadow_manifest(softness: float, kernel: Kernel | None, reach: float) -> dict:
    """The manifest's ``shadows``: ``azimuths``, ``softness_deg`` (the fit's penumbra ``softness``,
    radians: :func:`torchspec.relight.softness_of`), ``reach``
    (pixels) and ``lowest_deg`` of the horizons, and the kernel's l-plane ``covariance`` (2 x 2, at
    the zenith) and mean ``offset`` with ``angular``: the covariance squeezed along the radius by
    ``1 - |c_xy|^2`` at a centre ``c`` (:meth:`torchspec.model.lights.Kernel.covariance`); a point
    or unknown kernel: a zero covariance."""
    covariance, offset, angular = [[0.0, 0.0], [0.0, 0.0]], [0.0, 0.0], False
    if kernel is not None and kernel.kind not in ("point", "unknown"):
        zenith = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, device="cpu")  # the manifest's numbers
        covariance = kernel.covariance(zenith)[0].tolist()
        offset = kernel.offset(zenith).tolist()
        angular = kernel.kind != "tabulated" and kernel.domain != "projected"
    return {
        "azimuths": AZIMUTHS,
        "softness_deg": math.degrees(softness),
        "reach": reach,
        "lowest_deg": LOWEST_DEG,
        "covariance": covariance,
        "offset": offset,
        "angular": angular,
    }
