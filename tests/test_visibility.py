"""Cast shadows (torchspec.model.visibility): the batched horizon against a brute-force ray march in
float64, soft visibility's derivatives, flat fields, extended kernels, shapes refused."""

import math

import pytest
import torch

from torchspec.errors import TorchspecError
from torchspec.model.lights import Kernel, Lights
from torchspec.model.visibility import (
    elevation,
    frame_visibilities,
    frame_visibility,
    horizon,
    kernel_visibility,
    marched_distances,
    marched_horizon,
    visibility,
)
from torchspec.simulate.relief import ReliefConfig, relief

F64 = torch.float64


def brute_horizon(height, directions, start=0.5, step=1.0 / 32):
    """The reference: :func:`marched_horizon`, every ray marched in fine steps."""
    return marched_horizon(height, directions, start, step)


def _lights(count, seed, low=10.0, high=60.0):
    g = torch.Generator().manual_seed(seed)
    phi = 2 * math.pi * torch.rand(count, generator=g, dtype=F64)
    el = torch.deg2rad(low + (high - low) * torch.rand(count, generator=g, dtype=F64))
    return torch.stack([el.cos() * phi.cos(), el.cos() * phi.sin(), el.sin()], -1)


@pytest.fixture(scope="module")
def field():
    return relief(ReliefConfig(bump_height=(3.0, 7.0), ridge_height=3.0, ridge_width=1.5, seed=0), 32, 32).height


@pytest.fixture(scope="module")
def reference(field):
    dirs = _lights(8, 0)
    return dirs, brute_horizon(field, dirs)


def test_horizon_matches_the_brute_force_march(field, reference):
    dirs, truth = reference
    fast = horizon(field, dirs)
    seen = truth > -1.5  # rays that stay in the image for some distance
    err = (fast - truth)[seen].abs()
    assert math.degrees(float(err.mean())) < 0.3 and math.degrees(float(err.max())) < 6.0
    assert bool((fast <= truth + 1e-9)[seen].all())  # the samples are a subset of the march's


def test_hard_visibility_agrees_away_from_the_shadow_edge(field, reference):
    dirs, truth = reference
    e = elevation(dirs).expand_as(truth)
    lit, fast_lit = e > truth, visibility(field, dirs) > 0.5
    away = (e - truth).abs() > math.radians(2.0)
    assert float((lit == fast_lit)[away].to(F64).mean()) > 0.98
    assert float((lit == fast_lit).to(F64).mean()) > 0.98
    assert 0.02 < float((~lit).to(F64).mean()) < 0.5  # the relief does cast shadows


def test_signs_of_the_azimuth():
    h = torch.zeros(7, 7, dtype=F64)
    h[3, 5] = 4.0  # east of the centre
    h[1, 3] = 4.0  # north of the centre (up the image: a smaller row)
    east, north, west = torch.tensor([[1.0, 0, 0.3], [0, 1.0, 0.3], [-1.0, 0, 0.3]], dtype=F64)
    v = visibility(h, torch.stack([east, north, west]))[3, 3]
    assert v[0] < 0.01 and v[1] < 0.01 and v[2] > 0.99


def test_flat_field_sees_every_light_above_the_softness(device):
    flat = torch.zeros(6, 8, dtype=torch.float32, device=device)
    dirs = _lights(5, 1, low=5.0).to(device=device, dtype=torch.float32)
    v = visibility(flat, dirs)
    assert v.shape == (6, 8, 5) and v.dtype == torch.float32 and v.device.type == device.type
    assert bool((v > 0.99).all())


def test_gradcheck_in_height_and_direction():
    g = torch.Generator().manual_seed(3)
    h = (2 * torch.rand(5, 6, generator=g, dtype=F64)).requires_grad_()
    d = torch.tensor([[0.6, 0.3, 0.4], [-0.5, 0.2, 0.5]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda h, d: visibility(h, d, softness=0.2, reach=4.0), (h, d))


def test_per_pixel_directions_equal_shared_ones(field):
    dirs = _lights(3, 2)
    shared = horizon(field[:12, :12], dirs)
    each = horizon(field[:12, :12], dirs.expand(12, 12, 3, 3))
    assert torch.allclose(shared, each, atol=1e-12)


def test_chunking_does_not_change_the_result(field, monkeypatch):
    import torchspec.model.visibility as module

    dirs = _lights(4, 4)
    whole = horizon(field, dirs)
    monkeypatch.setattr(module, "CHUNK_ELEMENTS", 3000)
    assert torch.allclose(horizon(field, dirs), whole, atol=1e-12)


@pytest.mark.parametrize("kernel", [Kernel("gaussian", "projected", 0.05), Kernel("gaussian", "angular", 0.08)])
def test_extended_kernel_probit_against_its_quadrature(field, kernel):
    dirs = _lights(4, 5, low=15.0, high=45.0)
    one = torch.ones(4, 1, dtype=F64)
    lights = Lights(dirs, kernel, one, one[:, 0])
    probit = kernel_visibility(field, lights)
    quadrature = kernel_visibility(field, lights, rule="nodes", order=4)
    point = visibility(field, dirs)
    assert float((probit - quadrature).abs().mean()) < 0.5 * float((point - quadrature).abs().mean())
    point_lights = Lights(dirs, Kernel("point"), one, one[:, 0])
    assert torch.equal(kernel_visibility(field, point_lights), point)


def test_marched_distances():
    t = marched_distances(0.5, 10.0)
    assert float(t[0]) == 0.5 and float(t[-1]) == 10.0 and bool((t[1:] > t[:-1]).all())
    assert {1.0, 2.0, 3.0, 4.0, 5.0} <= set(t.tolist())


@pytest.mark.parametrize(
    "height, dirs, match",
    [
        (torch.zeros(3, 4, 1), torch.ones(2, 3), r"\(H, W\).*\(3, 4, 1\)"),
        (torch.zeros(3, 4), torch.ones(2, 2), r"\(K, 3\).*\(2, 2\)"),
        (torch.zeros(3, 4), torch.ones(4, 3, 2, 3), r"\(H, W, K, 3\).*\(4, 3, 2, 3\)"),
    ],
)
def test_bad_shapes_are_refused(height, dirs, match):
    with pytest.raises(TorchspecError, match=match):
        horizon(height, dirs)


def test_a_ray_along_the_images_border_does_not_leave_it_by_a_rounding_error():
    height = torch.zeros(12, 6, dtype=torch.float64)
    height[9, :] = 4.0  # a ridge across the image, below the middle
    phi = math.radians(270.0)  # straight down the image: cos(phi) is -1.8e-16, not 0
    rounded = torch.tensor([[math.cos(phi), math.sin(phi), 0.3]], dtype=torch.float64)
    exact = torch.tensor([[0.0, -1.0, 0.3]], dtype=torch.float64)
    assert rounded[0, 0] < 0
    for found in (horizon(height, rounded), horizon(height, exact), marched_horizon(height, rounded)):
        assert torch.allclose(found[5, :, 0], torch.atan(torch.tensor(1.0, dtype=torch.float64)), atol=1e-6)


@pytest.mark.parametrize("light", ["point", "projected", "angular", "near"])
def test_one_horizon_gives_every_depth_and_penumbra_as_frame_visibility_does(light):
    rows, cols = torch.meshgrid(torch.arange(24.0, dtype=torch.float64), torch.arange(30.0, dtype=torch.float64),
                                indexing="ij")  # fmt: skip
    height = 6.0 * torch.exp(-((rows - 10) ** 2 + (cols - 14) ** 2) / 18.0) + 3.0 * (cols > 22)  # a bump and a step
    g = torch.Generator().manual_seed(1)
    directions = torch.randn(5, 3, generator=g, dtype=torch.float64)
    directions[:, 2] = directions[:, 2].abs() + 0.3
    directions = directions / directions.norm(dim=-1, keepdim=True)
    kernel = {"point": Kernel("point"), "projected": Kernel("gaussian", "projected", 0.05),
              "angular": Kernel("gaussian", "angular", 0.08), "near": Kernel("point")}[light]  # fmt: skip
    one = torch.ones(5, 1, dtype=torch.float64)
    lights = Lights(directions, kernel, one, one[:, 0])
    positions = 0.8 * directions if light == "near" else None
    depths, softnesses = (1.0, 1.5, 2.0), (math.radians(1.0), math.radians(2.0))
    pairs = list(frame_visibilities(height, lights, positions, depths, softnesses))
    assert [(d, s) for d, s, _ in pairs] == [(d, s) for d in depths for s in softnesses]
    for depth, softness, seen in pairs:
        expected = frame_visibility(height * depth, lights, positions, softness=softness)
        # a farther reach (the deepest height's, the widest penumbra's margin) moves it by < sigmoid(-8)
        assert torch.allclose(seen, expected, atol=3.4e-4, rtol=0), (depth, softness)
        assert float((seen - expected).abs().mean()) < 1e-6


def test_the_horizons_chunks_change_nothing(monkeypatch):
    import torchspec.model.visibility as module

    rows, cols = torch.meshgrid(torch.arange(20.0, dtype=F64), torch.arange(26.0, dtype=F64), indexing="ij")
    height = 5.0 * torch.exp(-((rows - 8) ** 2 + (cols - 12) ** 2) / 12.0)
    g = torch.Generator().manual_seed(4)
    directions = torch.randn(5, 3, generator=g, dtype=F64)
    directions[:, 2] = directions[:, 2].abs() + 0.2
    per_pixel = directions.expand(20, 26, 5, 3) + 0.05 * torch.randn(20, 26, 5, 3, generator=g, dtype=F64)
    whole = [horizon(height, directions), horizon(height, per_pixel)]
    for chunk in (4096, 300, 7):  # pixels, lights and samples split, down to a chunk of pixels at a time
        monkeypatch.setattr(module, "CHUNK_ELEMENTS", chunk)
        assert torch.equal(horizon(height, directions), whole[0]) and torch.equal(horizon(height, per_pixel), whole[1])
