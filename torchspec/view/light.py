"""The page's light: a point, or a capture's extended kernel as a fixed quadrature that the shader
sums (``manifest.json``'s ``kernel_*`` keys); and near lights' positions (:func:`near_lights`).

An extended kernel is shipped as at most :data:`MAX_NODES` nodes, offsets from the light's centre
with weights (the kernel's mass at each), the same for every centre: the page's relit value is
``sum_q weight_q value(w_q)``, the point-light model at each node ``w_q`` above the horizon (nodes
at or beyond it carry no light, as the format says). Offsets are in the l-plane for a
``projected`` kernel (``l_q = l + offset``) and, for an ``angular`` one, angles in the plane
tangent to the sphere at the centre (``w_q = cos g c + sin g u``, ``g`` the offset's length, ``u``
its direction in the tangent frame ``e1 = x - c_x c`` normalised, ``e2 = c x e1``), where the
kernel is the same about every centre.

A Gaussian kernel takes the product Gauss-Hermite rule of ``order`` nodes an axis (those of
:func:`torchspec.model.quadrature.hermite`, which ``torchspec.render`` places on a broad lobe's product
with the kernel); a tabulated or super-Gaussian kernel the reference nodes of
:func:`torchspec.model.lights.nodes` about the zenith merged into at most ``order x order`` cells of its
whitened extent (each cell's mass at its centre of mass: mass and mean kept).

Under a Gaussian kernel the page does better than a fixed rule, as ``torchspec.render``'s fast path
does: a lobe narrower than the nodes' spacing would fall between them, so for a ``projected``
Gaussian each lobe takes render's own fast rule (``FAST_ORDER x FAST_ORDER`` Gauss-Hermite points)
placed on its own product with the kernel (the lobe linearised in the l-plane about its mirror
point, then about that product's mean: :func:`torchspec.model.nodes.fast_rule`). A Gaussian's diffuse
term is ``<n, d>`` with the kernel's effective direction ``d``
(:func:`torchspec.model.lights.diffuse_directions`, exact at the horizon, where fixed nodes are cut)
interpolated in a table over the centre's distance from the zenith, plus the nodes' share behind
the normal's horizon (or the share in front where that is the smaller,
:func:`torchspec.model.diffuse.diffuse_integral`'s rule). Other kernels are summed on the fixed nodes for
both terms: their lobes narrower than :attr:`LightQuadrature.spacing` are not resolved.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from ..errors import TorchspecError
from ..io import Capture
from ..model.lights import Kernel, Lights, diffuse_directions, nodes
from ..model.quadrature import FAST_ORDER, Quadrature, hermite
from ..model.rendering import TILE_PIXELS
from ..pipeline.tiling import BLOCK_ANGLE, LEAST_BLOCK, near_block
from ..relight import fit_positions

__all__ = ["MAX_NODES", "DIFFUSE_ROWS", "DIFFUSE_REACH", "LightQuadrature", "light_quadrature", "near_lights"]

MAX_NODES = 64
"""The most nodes of an extended light the page sums (its shader's uniform array)."""
DIFFUSE_ROWS = 128
"""Centres of a Gaussian kernel's table of effective diffuse directions (two a uniform vec4)."""
DIFFUSE_REACH = 0.995
"""The table's last centre's distance from the zenith in the l-plane (the page's farthest light)."""


@dataclass(frozen=True)
class LightQuadrature:
    """A kernel's nodes as the page sums them.

    Attributes:
        kind: the kernel's kind (``point``: no nodes; the page's point path).
        angular: offsets are angles in the tangent plane at the centre, else l-plane offsets.
        offsets: ``(Q, 2)`` float64.
        weights: ``(Q,)`` float64, summing to the kernel's mass (1).
        spacing: the largest distance from a node to its nearest neighbour among the nodes that
            hold 99 % of the mass (l units or radians): a lobe narrower than this falls between
            nodes.
        label: what the page says of its light.
        sigma: a projected Gaussian kernel's std (else 0): the page then places the points of
            ``lobe_rule`` on each lobe's product with the kernel.
        lobe_rule: ``(Q, 3)``: ``torchspec.render``'s fast rule (standard normal Gauss-Hermite
            points, ``FAST_ORDER`` an axis, and weights) for a projected Gaussian, else none.
        diffuse: ``(DIFFUSE_ROWS, 2)`` for a Gaussian kernel (else none): its effective diffuse
            direction (:func:`torchspec.model.lights.diffuse_directions`) ``(a c_xy / |c_xy|, b)`` for
            centres ``c`` at ``|c_xy|`` evenly spaced on ``[0, DIFFUSE_REACH]``; the page
            interpolates it (the fixed nodes cannot follow the horizon's cut of the kernel).
    """

    kind: str
    angular: bool
    offsets: np.ndarray
    weights: np.ndarray
    spacing: float
    label: str
    sigma: float = 0.0
    diffuse: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    lobe_rule: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    def describe(self) -> dict:
        """The manifest's keys: ``kernel``, ``kernel_label``, ``kernel_angular``, ``kernel_spacing``
        and ``kernel_nodes`` (``[x, y, weight]`` rows; none for a point)."""
        rows = np.concatenate([self.offsets, self.weights[:, None]], 1) if len(self.weights) else np.zeros((0, 3))
        return {
            "kernel": self.kind,
            "kernel_label": self.label,
            "kernel_angular": self.angular,
            "kernel_spacing": self.spacing,
            "kernel_nodes": rows.tolist(),
            "kernel_sigma": self.sigma,
            "kernel_lobe_rule": self.lobe_rule.tolist(),
            "kernel_diffuse": self.diffuse.tolist(),
            "kernel_diffuse_reach": DIFFUSE_REACH,
        }


POINT = LightQuadrature("point", False, np.zeros((0, 2)), np.zeros(0), 0.0, "point light")


def _spacing(offsets: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(-weights)
    keep = order[: int(np.searchsorted(np.cumsum(weights[order]) / weights.sum(), 0.99)) + 1]
    if keep.size < 2:
        return 0.0
    points = offsets[keep]
    distance = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(distance, np.inf)
    return float(distance.min(1).max())


def _gaussian(kernel: Kernel, order: int) -> tuple[np.ndarray, np.ndarray]:
    grid, weight = hermite(order, torch.zeros((), dtype=torch.float64))  # CPU on purpose: nodes for the page's JSON
    offsets, weights = kernel.sigma * grid.numpy(), weight.numpy()
    if kernel.domain == "angular":  # solid angle over tangent-plane area: sin g / g
        weights = weights * np.sinc(np.linalg.norm(offsets, axis=-1) / math.pi)
        weights = weights / weights.sum()
    return offsets, weights


def _merged(kernel: Kernel, order: int) -> tuple[np.ndarray, np.ndarray]:
    """The reference nodes about the zenith merged into at most ``order x order`` cells."""
    zenith = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)  # CPU on purpose: nodes for the page's JSON
    one = torch.ones(1, 1, dtype=torch.float64)  # CPU on purpose: nodes for the page's JSON
    fine = max(24, Quadrature().orders(kernel)[1])  # a tabulated kernel: two radii a pixel of its table
    direction, weight = (t[0].numpy() for t in nodes(Lights(zenith, kernel, one, one[0]), order=fine))
    offsets = direction[:, :2]
    if kernel.domain == "angular":  # the exponential map's coordinates at the zenith
        g = np.arccos(np.clip(direction[:, 2], -1.0, 1.0))
        offsets = offsets * (g / np.maximum(np.linalg.norm(offsets, axis=-1), 1e-300))[:, None]
    held = weight > 1e-9 * weight.max()
    offsets, weight = offsets[held], weight[held]
    mean = (weight[:, None] * offsets).sum(0) / weight.sum()
    cov = np.cov(offsets.T, aweights=weight, bias=True)
    white = np.linalg.solve(np.linalg.cholesky(cov), (offsets - mean).T).T
    reach = np.abs(white).max() * (1 + 1e-9)
    cell = np.clip(((white + reach) / (2 * reach) * order).astype(int), 0, order - 1)
    index = cell[:, 0] * order + cell[:, 1]
    mass = np.bincount(index, weight, order * order)
    centre = np.stack([np.bincount(index, weight * offsets[:, j], order * order) for j in range(2)], -1)
    full = mass > 0
    return centre[full] / mass[full, None], mass[full]


def _diffuse_table(kernel: Kernel) -> np.ndarray:
    """:attr:`LightQuadrature.diffuse` of a Gaussian kernel (symmetric about its centre, so its
    effective direction depends on the centre's distance from the zenith only)."""
    rho = torch.linspace(0.0, DIFFUSE_REACH, DIFFUSE_ROWS, dtype=torch.float64)  # CPU on purpose: a table for JSON
    centre = torch.stack([rho, torch.zeros_like(rho), torch.sqrt(1.0 - rho * rho)], -1)
    ones = torch.ones(DIFFUSE_ROWS, 1, dtype=torch.float64)  # CPU on purpose: a table for the page's JSON
    direction = diffuse_directions(Lights(centre, kernel, ones, ones[:, 0]))
    return direction[:, [0, 2]].numpy()


def light_quadrature(kernel: Kernel | None, order: int = 8) -> LightQuadrature:
    """The page's light for ``kernel`` (``None`` or a point: the point light).

    Raises:
        TorchspecError: ``order * order`` above :data:`MAX_NODES`.
    """
    if order * order > MAX_NODES:
        raise TorchspecError(f"the page sums at most {MAX_NODES} nodes of a light; order {order} gives {order**2}.")
    if kernel is None or kernel.kind == "point":
        return POINT
    if kernel.kind == "unknown":
        return replace(POINT, label="point light (the capture's kernel is unknown)")
    offsets, weights = _gaussian(kernel, order) if kernel.kind == "gaussian" else _merged(kernel, order)
    if kernel.kind == "tabulated":
        size = f"{kernel.table.shape[1]} x {kernel.table.shape[0]} table over +-{kernel.extent:g}"
    else:
        size = f"{'sigma' if kernel.kind == 'gaussian' else 'radius'} {kernel.sigma:g}"
    label = f"the capture's {kernel.kind} kernel ({size}, {kernel.domain}), {len(weights)} nodes"
    gaussian = kernel.kind == "gaussian" and kernel.domain == "projected"
    points, weight = hermite(FAST_ORDER, torch.zeros((), dtype=torch.float64))  # CPU on purpose: for the JSON
    return LightQuadrature(
        kernel.kind,
        kernel.domain == "angular",
        offsets,
        weights,
        _spacing(offsets, weights),
        label,
        kernel.sigma if gaussian else 0.0,
        _diffuse_table(kernel) if kernel.kind == "gaussian" else np.zeros((0, 2)),
        torch.cat([points, weight[:, None]], 1).numpy() if gaussian else np.zeros((0, 3)),
    )


def near_lights(capture: Capture | None, meta: dict, height: int, width: int) -> dict:
    """The manifest's keys of near lights (:mod:`torchspec.model.near_lights`): ``positions``, each of
    the capture's ``K`` frames' light position ``[x, y, z]`` in image widths from the image's
    centre (``[]``: distant lights); ``near_radius``, the distance the page's light starts at (the
    positions' median distance; ``None``: distant); ``near_source``, what the positions come from;
    ``near_block``, the side in pixels of the square blocks that ``torchspec render`` lights from
    one direction each under these positions (:func:`torchspec.relight.render_near`,
    :func:`torchspec.pipeline.tiling.near_block`), for an ``H x W`` image (``None``: no positions);
    and :func:`block_rule`'s keys, with which the page finds the block of a light of its own.

    The positions are those ``torchspec render`` takes (:func:`torchspec.relight.fit_positions`:
    the capture's, or the fit's calibrated dome radius or positions; ``meta`` is ``svbrdf.json``).

    Raises:
        TorchspecError: as :func:`torchspec.relight.fit_positions`.
    """
    none = {"positions": [], "near_radius": None, "near_source": "", "near_block": None, **block_rule(height, width)}
    if capture is None:
        return none
    positions, source = fit_positions(capture, meta)
    if positions is None:
        return none
    radius = float(positions.norm(dim=-1).median())
    block = near_block(height, width, TILE_PIXELS, positions.to(torch.float64))
    return {**none, "positions": positions.tolist(), "near_radius": radius, "near_source": source, "near_block": block}


def block_rule(height: int, width: int) -> dict:
    """What the page needs to find ``torchspec render``'s block for a light of its own
    (:func:`torchspec.pipeline.tiling.near_block` of that one light): ``block_angle`` (radians),
    ``least_block`` and ``most_block`` (pixels)."""
    return {"block_angle": BLOCK_ANGLE, "least_block": LEAST_BLOCK, "most_block": math.isqrt(TILE_PIXELS)}
