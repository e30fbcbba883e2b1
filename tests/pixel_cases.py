"""Small sets of pixels for the model, solver and device tests: random SVBRDF parameters of nearly
flat pixels and a grid of lights, all float64."""

import torch

from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import normalize
from torchspec.model.lights import Kernel, Lights
from torchspec.simulate import LayoutConfig, layout


def random_svbrdf(count: int, generator: torch.Generator) -> SVBRDF:
    """``count`` pixels drawn from ``generator``: normals within a few degrees of +z, k_d in [0.2, 0.7],
    k_s in [0.1, 0.3], anisotropic roughness in [0.05, 0.15] and a rotation in [0, 1]."""
    f64 = torch.float64
    tilt = 0.1 * torch.randn(count, 2, generator=generator, dtype=f64)
    normal = normalize(torch.cat([tilt, torch.ones(count, 1, dtype=f64)], -1))
    kd = 0.2 + 0.5 * torch.rand(count, 3, generator=generator, dtype=f64)
    ks = 0.1 + 0.2 * torch.rand(count, 3, generator=generator, dtype=f64)
    alpha = 0.05 + 0.1 * torch.rand(count, 2, generator=generator, dtype=f64)
    return SVBRDF(normal, kd, ks, alpha, torch.rand(count, generator=generator, dtype=f64))


def grid_lights(kernel: Kernel, *, n: int = 6, extent: float = 0.6) -> Lights:
    """``n x n`` lights of ``kernel`` on a grid over ``[-extent, extent]^2`` of the l-plane (radius 0.8),
    unit irradiance and exposure."""
    centres = layout(LayoutConfig(kind="grid", nx=n, ny=n, extent=extent, radius=0.8))
    k = centres.shape[0]
    return Lights(centres, kernel, torch.ones(k, 1, dtype=torch.float64), torch.ones(k, dtype=torch.float64))
