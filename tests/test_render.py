import importlib
import math

import pytest
import torch
from brute_force import pixel_tensors, random_case, reference_value
from kernel_cases import KERNELS

import torchspec as ts
from torchspec.model.brdf import SVBRDF, ward_cosine
from torchspec.model.geometry import normal_from_angles
from torchspec.model.lights import Kernel, Lights
from torchspec.model.quadrature import Quadrature
from torchspec.model.rendering import render

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


@pytest.mark.parametrize("path,tolerance", [("reference", 1e-4), ("fast", 1e-3)])
@pytest.mark.parametrize("name", list(KERNELS))
def test_render_matches_brute_force(name, path, tolerance):
    kernel, kernel_args, width = KERNELS[name]
    if path == "fast" and kernel.kind != "gaussian":
        pytest.skip("the fast path is for Gaussian kernels")
    for seed in range(8):
        normal, alpha, rotation, centre = random_case(seed, width)
        lights = Lights(centre[None], kernel, torch.ones(1, 1, dtype=F64), torch.ones(1, dtype=F64))
        expected, specular = reference_value(kernel_args, width, normal, alpha, rotation, centre, 0.3, 1.0)
        # the value, and in the cases that light the lobe up (even seeds) its specular part alone
        for k_d, target in ((0.3, expected), (0.0, specular))[: 2 - seed % 2]:
            maps = SVBRDF(*pixel_tensors(normal, k_d, alpha, rotation))
            value = render(maps, lights, VIEW, quadrature=Quadrature(path=path))[0, 0, 0].item()
            error = abs(value - target) / max(abs(target), 1e-12)
            assert error <= tolerance, (
                f"{name} {path} seed {seed} k_d {k_d}: relative error {error:.3g} ({value:.6g} vs {target:.6g})"
            )


def test_reference_when_the_product_lies_beyond_the_horizon():
    """A wide kernel low in the sky and a wide, anisotropic lobe: the product of their Gaussian
    approximations lies beyond the horizon, the integrand's mass just inside it."""
    from brute_force import integrate

    normal = torch.tensor([-0.06381024946133858, -0.47753684619145953, 0.8762915111954446], dtype=F64)
    centre = torch.tensor([-0.8330499634049361, -0.1374394189083045, 0.5358527452586039], dtype=F64)
    alpha, rotation = (0.3751243133162395, 0.052996693548681216), 2.75842955443195
    kernel = Kernel("gaussian", "projected", 0.08)
    maps = SVBRDF(
        normal[None],
        torch.zeros(1, 1, dtype=F64),
        torch.ones(1, 1, dtype=F64),
        torch.tensor([alpha], dtype=F64),
        torch.tensor([rotation], dtype=F64),
    )
    lights = Lights(centre[None], kernel, torch.ones(1, 1, dtype=F64), torch.ones(1, dtype=F64))
    _, expected = integrate(
        "gaussian-projected",
        centre,
        normal,
        k_d=0.0,
        k_s=1.0,
        alpha=alpha,
        rotation=rotation,
        box_centre=centre[:2],
        half=0.6,
        step=0.001,
        sigma=0.08,
    )
    for path, tolerance in (("reference", 1e-4), ("auto", 1e-3)):
        value = render(maps, lights, VIEW, quadrature=Quadrature(path=path))[0, 0, 0].item()
        assert abs(value - expected) <= tolerance * expected, (path, value, expected)


def test_point_light_is_exact():
    normal = normal_from_angles(torch.tensor([[0.2, -0.1], [0.0, 0.3]], dtype=F64))
    centre = torch.tensor([[0.3, 0.1, 0.0], [-0.2, 0.5, 0.0]], dtype=F64)
    centre[:, 2] = (1 - (centre[:, :2] ** 2).sum(-1)).sqrt()
    maps = SVBRDF(
        normal,
        torch.tensor([[0.2, 0.3, 0.4], [0.5, 0.1, 0.0]], dtype=F64),
        torch.tensor([[0.7], [0.2]], dtype=F64),
        torch.tensor([[0.1, 0.05], [0.3, 0.3]], dtype=F64),
    )
    irradiance = torch.tensor([[1.0, 2.0, 3.0], [0.5, 0.5, 0.5]], dtype=F64)
    lights = Lights(centre, Kernel("point"), irradiance, torch.tensor([2.0, 1.0], dtype=F64))
    value = render(maps, lights, VIEW)
    cos = (normal[:, None, :] * centre[None]).sum(-1).clamp(min=0)
    spec = ward_cosine(centre[None], VIEW, normal[:, None], maps.roughness[:, None])
    expected = maps.diffuse[:, None] / math.pi * cos[..., None] + maps.specular[:, None] * spec[..., None]
    expected = expected * (torch.tensor([2.0, 1.0], dtype=F64)[:, None] * irradiance)[None]
    torch.testing.assert_close(value, expected, rtol=1e-12, atol=0)


def test_shapes_chunks_and_devices():
    g = torch.Generator().manual_seed(0)
    normal = normal_from_angles(0.2 * torch.randn(4, 5, 2, generator=g))
    maps = SVBRDF(
        normal,
        torch.rand(4, 5, 3, generator=g),
        torch.rand(4, 5, 1, generator=g),
        0.02 + 0.2 * torch.rand(4, 5, 2, generator=g),
    )
    centre = normal_from_angles(0.4 * torch.randn(7, 2, generator=g))
    lights = Lights(centre, Kernel("gaussian", "projected", 0.05), torch.ones(7, 3), torch.ones(7))
    value = render(maps, lights, VIEW.float())
    assert value.shape == (4, 5, 7, 3) and value.dtype == torch.float32
    flat = render(maps.flatten(), lights, VIEW.float())
    torch.testing.assert_close(value.reshape(20, 7, 3), flat)
    module = importlib.import_module("torchspec.model.rendering")

    budget = module.BUDGET
    module.BUDGET = 64  # one pixel per chunk
    try:
        torch.testing.assert_close(render(maps, lights, VIEW.float()), value, rtol=1e-5, atol=1e-6)
    finally:
        module.BUDGET = budget


def test_bad_inputs():
    maps = SVBRDF(torch.tensor([[0.0, 0.0, 1.0]]), torch.ones(1, 3), torch.ones(1, 1), torch.ones(1, 2) * 0.1)
    lights = Lights(torch.tensor([[0.0, 0.0, 1.0]]), Kernel("unknown"), torch.ones(1, 1), torch.ones(1))
    with pytest.raises(ValueError, match="'unknown': rendering needs its shape"):
        render(maps, lights, VIEW.float())
    lights = Lights(
        torch.tensor([[0.0, 0.0, 1.0]]), Kernel("gaussian", "projected", 0.05), torch.ones(1, 2), torch.ones(1)
    )
    with pytest.raises(ValueError, match=r"irradiance must have 1 or 3 channels"):
        render(maps, lights, VIEW.float())
    lights = Lights(
        torch.tensor([[0.0, 0.0, 1.0]]), Kernel("supergaussian", "angular", 0.03, 6.0), torch.ones(1, 1), torch.ones(1)
    )
    with pytest.raises(ValueError, match="path 'fast' needs a Gaussian kernel"):
        render(maps, lights, VIEW.float(), quadrature=Quadrature(path="fast"))
    with pytest.raises(ValueError, match=r"view must have shape \(3,\)"):
        render(maps, lights, VIEW[:2].float())


@pytest.mark.parametrize(
    "kernel",
    [
        Kernel("point"),
        Kernel("gaussian", "projected", 0.05),
        Kernel("gaussian", "angular", 0.05),
        Kernel("supergaussian", "angular", 0.04, 6.0),
    ],
)
def test_gradcheck(kernel):
    """Every parameter, float64, with a grazing light and alpha = 0.005 among the cases."""
    angles = torch.tensor([[0.1, -0.2], [0.35, 0.1]], dtype=F64, requires_grad=True)
    k_d = torch.tensor([[0.3, 0.2], [0.5, 0.4]], dtype=F64, requires_grad=True)
    k_s = torch.tensor([[0.6, 0.4], [0.3, 0.2]], dtype=F64, requires_grad=True)
    alpha = torch.tensor([[0.005, 0.005], [0.12, 0.06]], dtype=F64, requires_grad=True)
    rotation = torch.tensor([0.3, 1.1], dtype=F64, requires_grad=True)
    theta = torch.tensor([0.2, 0.7, math.radians(86.0)], dtype=F64)  # the last grazes
    centre = torch.stack([torch.sin(theta), 0.1 * torch.ones_like(theta), torch.cos(theta)], -1)
    centre = centre / centre.norm(dim=-1, keepdim=True)
    lights = Lights(centre, kernel, torch.ones(3, 1, dtype=F64), torch.ones(3, dtype=F64))

    def forward(angles, k_d, k_s, alpha, rotation):
        maps = SVBRDF(normal_from_angles(angles), k_d, k_s, alpha, rotation)
        return render(maps, lights, VIEW)

    assert torch.autograd.gradcheck(forward, (angles, k_d, k_s, alpha, rotation), atol=1e-6, rtol=1e-4)


def test_top_level_exports():
    assert ts.render is render


@pytest.mark.parametrize("kernel", [Kernel("point"), Kernel("gaussian", "projected", 0.06)])
def test_a_second_lobe_renders_as_the_sum_of_the_lobes(kernel):
    """Two lobes render as the first lobe's SVBRDF plus the second alone (no k_d); pixels whose
    second lobe is 0 render as without it. Gradients reach the second lobe's parameters, also
    where its k_s is 0 (the lobe's value there)."""
    g = torch.Generator().manual_seed(7)
    n = normal_from_angles(0.15 * torch.randn(4, 2, dtype=F64, generator=g))
    kd, ks = torch.rand(4, 3, dtype=F64, generator=g), torch.rand(4, 1, dtype=F64, generator=g)
    ks2 = torch.tensor([[0.3], [0.0], [0.5], [0.2]], dtype=F64, requires_grad=True)
    alpha2 = torch.tensor([0.2, 0.3, 0.4, 0.1], dtype=F64)[:, None].expand(4, 2).clone().requires_grad_()
    alpha = torch.full((4, 2), 0.05, dtype=F64)
    theta = torch.tensor([0.0, 0.2, 0.5], dtype=F64)
    centre = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    lights = Lights(centre, kernel, torch.ones(3, 1, dtype=F64), torch.ones(3, dtype=F64))
    two = render(SVBRDF(n, kd, ks, alpha, None, None, ks2, alpha2), lights, VIEW)
    first = render(SVBRDF(n, kd, ks, alpha), lights, VIEW)
    second = render(SVBRDF(n, torch.zeros_like(kd), ks2, alpha2), lights, VIEW)
    torch.testing.assert_close(two, first + second, rtol=1e-12, atol=1e-14)
    assert torch.equal(two[1], first[1])
    grad_ks2, grad_alpha2 = torch.autograd.grad(two.sum(), (ks2, alpha2))
    assert bool((grad_ks2 > 0).all()) and bool((grad_alpha2[[0, 2, 3]] != 0).all())
    unit = SVBRDF(n[1:2], torch.zeros_like(kd[1:2]), torch.ones_like(ks[1:2]), alpha2[1:2].detach())
    torch.testing.assert_close(grad_ks2[1, 0], render(unit, lights, VIEW).sum())  # d/dk_s2 at k_s2 = 0
