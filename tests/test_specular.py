import math

import pytest
import torch

from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import angle, from_plane, normalize
from torchspec.model.layout import layout_of
from torchspec.model.lights import Kernel, Lights, diffuse_directions
from torchspec.model.rendering import render
from torchspec.simulate import LayoutConfig, layout
from torchspec.start.specular import grid_search, locate_peak, naive_start, specular_residual

VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)


def _scene(config: LayoutConfig, count=24, seed=0, sigma=0.08):
    g = torch.Generator().manual_seed(seed)
    centres = layout(config)
    k = centres.shape[0]
    lights = Lights(
        centres,
        Kernel("gaussian", sigma=sigma),
        torch.ones(k, 1, dtype=torch.float64),
        torch.ones(k, dtype=torch.float64),
    )
    tilt = torch.rand(count, generator=g, dtype=torch.float64) * math.radians(8.0)
    phi = torch.rand(count, generator=g, dtype=torch.float64) * 2 * math.pi
    if config.kind == "line":  # normals in the plane of the line, which the samples can see
        phi = torch.full_like(phi, math.radians(config.azimuth_deg)) + math.pi * (torch.rand(count, generator=g) > 0.5)
        tilt = tilt * 0.6
    normal = torch.stack([tilt.sin() * phi.cos(), tilt.sin() * phi.sin(), tilt.cos()], -1)
    kd = torch.full((count, 3), 0.3, dtype=torch.float64)
    ks = 0.05 + 0.25 * torch.rand(count, 1, generator=g, dtype=torch.float64)
    alpha = 0.03 + 0.12 * torch.rand(count, 1, generator=g, dtype=torch.float64)
    truth = SVBRDF(normal, kd, ks, alpha.expand(-1, 2))
    samples = render(truth, lights, VIEW) / lights.scale
    return truth, lights, samples


def test_layout_of_grid_and_line():
    grid = layout_of(layout(LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8))[:, :2])
    assert grid.dims == 2 and grid.l.shape == (88, 2)
    assert grid.area.sum() == pytest.approx(math.pi * 0.8**2, rel=0.15)  # the disk the grid was clipped to
    line = layout_of(layout(LayoutConfig(kind="line", n=50, azimuth_deg=38.0))[:, :2])
    assert line.dims == 1
    assert (
        abs(
            abs(
                float(
                    line.axis
                    @ torch.tensor([math.cos(math.radians(38)), math.sin(math.radians(38))], dtype=torch.float64)
                )
            )
            - 1
        )
        < 1e-12
    )
    coords = line.coordinates()
    assert coords.min() > 0 and coords.max() < line.period[0]
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        layout_of(torch.zeros(2, 2))


@pytest.mark.parametrize("kernel", [None, "pooled"])
def test_fri_start_recovers_the_lobe_from_the_exact_residual(kernel):
    truth, lights, samples = _scene(LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8))
    d = diffuse_directions(lights)
    residual = specular_residual(samples, truth.normal, truth.diffuse, d)
    lay = layout_of(lights.directions[:, :2])
    start = locate_peak(residual, lay, VIEW, prior_normal=truth.normal, kernel_variance=0.08**2, kernel=kernel)
    error = torch.rad2deg(angle(start.normal.double(), truth.normal.double()))
    assert error.max() < 0.5 and error.median() < 0.15, (
        f"normal error median {error.median():.3g}, max {error.max():.3g} deg"
    )
    alpha = ((start.alpha - truth.roughness[:, 0]) / truth.roughness[:, 0]).abs()
    ks = ((start.specular - truth.specular[:, 0]) / truth.specular[:, 0]).abs()
    assert alpha.median() < 0.15, f"median alpha error {alpha.median():.3g}"
    assert ks.median() < 0.3, f"median k_s error {ks.median():.3g}"
    assert start.quality.min() > 0.5
    # The mirror point of the start is the peak found.
    mirror = (2 * (start.normal @ VIEW)[:, None] * start.normal - VIEW)[:, :2]
    assert torch.allclose(mirror, start.peak, atol=1e-9)


@pytest.mark.parametrize("kernel", [None, "pooled"])
def test_fri_start_on_a_line_takes_the_other_coordinate_from_the_prior(kernel):
    config = LayoutConfig(kind="line", n=50, azimuth_deg=38.0, theta_min_deg=-30.0, theta_max_deg=30.0)
    truth, lights, samples = _scene(config, sigma=0.03)
    d = diffuse_directions(lights)
    residual = specular_residual(samples, truth.normal, truth.diffuse, d)
    lay = layout_of(lights.directions[:, :2])
    start = locate_peak(residual, lay, VIEW, prior_normal=truth.normal, kernel_variance=0.03**2, kernel=kernel)
    error = torch.rad2deg(angle(start.normal.double(), truth.normal.double()))
    assert error.max() < 0.3, f"max normal error {error.max():.3g} deg"


def test_grid_search_and_naive_start():
    truth, lights, samples = _scene(LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8), count=6)
    d = diffuse_directions(lights)
    residual = specular_residual(samples, truth.normal, truth.diffuse, d)
    lay = layout_of(lights.directions[:, :2])
    prior = normalize(truth.normal + torch.tensor([0.03, -0.02, 0.0], dtype=torch.float64))
    found = grid_search(residual, lay, VIEW, prior_normal=prior, kernel_variance=0.08**2, step=0.02, radius=0.2)
    error = torch.rad2deg(angle(found.normal.double(), truth.normal.double()))
    assert error.max() < 0.6, f"max normal error {error.max():.3g} deg (the search step is 0.02 in l: ~0.3 deg)"
    naive = naive_start(residual, lay, VIEW, prior_normal=prior, alpha=0.1)
    assert torch.equal(naive.normal, prior) and torch.all(naive.alpha == 0.1)
    assert torch.all(naive.specular > 0)


def test_specular_residual_removes_the_diffuse_part_exactly():
    centres = from_plane(torch.tensor([[0.0, 0.0], [0.3, 0.1], [-0.2, 0.4], [0.1, -0.5]], dtype=torch.float64))
    lights = Lights(centres, Kernel("point"), torch.ones(4, 1, dtype=torch.float64), torch.ones(4, dtype=torch.float64))
    normal = normalize(torch.tensor([[0.1, 0.0, 1.0]], dtype=torch.float64))
    plain = SVBRDF(
        normal,
        torch.tensor([[0.2, 0.4, 0.6]], dtype=torch.float64),
        torch.zeros(1, 1, dtype=torch.float64),
        torch.zeros(1, 2, dtype=torch.float64),
    )
    samples = render(plain, lights, VIEW)
    residual = specular_residual(samples, plain.normal, plain.diffuse, centres)
    assert residual.abs().max() < 1e-15
