import math
from dataclasses import replace

import pytest
import torch

from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import normal_from_angles
from torchspec.model.jacobian import from_parameters, jacobian, parameters
from torchspec.model.least_squares import normal_equations, sandwich_terms
from torchspec.model.lights import Kernel, Lights
from torchspec.model.quadrature import Quadrature
from torchspec.model.registry import MODELS
from torchspec.model.rendering import render

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


def _problem(grey, kernel, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = 5
    maps = SVBRDF(
        normal_from_angles(0.3 * torch.randn(n, 2, dtype=F64, generator=g)),
        torch.rand(n, 3, dtype=F64, generator=g),
        torch.rand(n, 1 if grey else 3, dtype=F64, generator=g),
        torch.tensor([[0.005, 0.005], [0.05, 0.02], [0.1, 0.1], [0.3, 0.15], [0.5, 0.5]], dtype=F64),
        torch.rand(n, dtype=F64, generator=g) * 3,
    )
    theta = torch.tensor([0.0, 0.3, 0.6, 0.9, 1.3], dtype=F64)  # the last one grazes (75 deg)
    phi = torch.tensor([0.0, 1.0, 2.5, 4.0, 5.5], dtype=F64)
    centre = torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)], -1)
    irradiance = torch.tensor([[1.0, 0.5, 2.0]], dtype=F64).expand(5, 3)
    return maps, Lights(centre, kernel, irradiance, torch.linspace(0.5, 1.5, 5, dtype=F64))


def _autograd(maps, lights, path="auto"):
    params = parameters(maps)
    grey = maps.specular.shape[-1] == 1

    def forward(p):
        return render(from_parameters(p, maps.channels, grey), lights, VIEW, quadrature=Quadrature(path=path))

    full = torch.autograd.functional.jacobian(forward, params)  # (N, K, C, N, P)
    index = torch.arange(params.shape[0])
    return full[index, :, :, index]


@pytest.mark.parametrize("grey", [True, False])
@pytest.mark.parametrize("kernel", [Kernel("point"), Kernel("gaussian", "projected", 0.06)])
def test_forward_mode_is_the_exact_derivative(kernel, grey):
    maps, lights = _problem(grey, kernel)
    value, jac = jacobian(maps, lights, VIEW, mode="forward")
    torch.testing.assert_close(value, render(maps, lights, VIEW))
    torch.testing.assert_close(jac, _autograd(maps, lights), rtol=1e-9, atol=1e-12)
    assert jac.shape == (5, 5, 3, 2 + 3 + (1 if grey else 3) + 3)


@pytest.mark.parametrize("grey", [True, False])
def test_analytic_is_exact_for_point_lights(grey):
    maps, lights = _problem(grey, Kernel("point"))
    value, jac = jacobian(maps, lights, VIEW, mode="analytic")
    torch.testing.assert_close(value, render(maps, lights, VIEW), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(jac, _autograd(maps, lights), rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize("path", ["auto", "reference"])
@pytest.mark.parametrize(
    "kernel",
    [
        Kernel("gaussian", "projected", 0.06),
        Kernel("gaussian", "angular", 0.05),
        Kernel("supergaussian", "angular", 0.04, 6.0),
    ],
)
def test_analytic_matches_the_derivative_of_the_quadrature(kernel, path):
    """Fixed nodes: the quadrature of the derivative, within 1e-3 of each pixel's largest
    derivative (the derivative of the quadrature moves its nodes too)."""
    maps, lights = _problem(False, kernel, seed=1)
    quadrature = Quadrature(path=path)
    value, jac = jacobian(maps, lights, VIEW, mode="analytic", quadrature=quadrature)
    torch.testing.assert_close(value, render(maps, lights, VIEW, quadrature=quadrature), rtol=1e-10, atol=1e-12)
    exact = _autograd(maps, lights, path)
    scale = exact.abs().amax(dim=(1, 2, 3), keepdim=True)  # per pixel
    error = ((jac - exact).abs() / scale).max().item()
    assert error < 1e-3, f"largest relative difference {error:.3g}"


def test_bad_mode():
    maps, lights = _problem(False, Kernel("point"))
    with pytest.raises(ValueError, match="mode must be one of"):
        jacobian(maps, lights, VIEW, mode="reverse")


def test_shapes_follow_leading_dims():
    maps, lights = _problem(False, Kernel("point"))
    value, jac = jacobian(maps.reshape(5, 1), lights, VIEW)
    assert value.shape == (5, 1, 5, 3) and jac.shape == (5, 1, 5, 3, 11)
    assert math.isfinite(jac.abs().sum().item())


@pytest.mark.parametrize("mode", ["analytic", "forward"])
def test_no_pixels(mode):
    maps, lights = _problem(False, Kernel("gaussian", "projected", 0.05))
    value, jac = jacobian(maps[:0], lights, VIEW, mode=mode)
    assert value.shape == (0, 5, 3) and jac.shape == (0, 5, 3, 11)
    assert render(maps[:0], lights, VIEW).shape == (0, 5, 3)


@pytest.mark.parametrize("kernel", [Kernel("point"), Kernel("gaussian", "projected", 0.06)])
def test_isotropic_lobes_skip_the_tangent_frame(kernel):
    """All lobes isotropic: the frame-free derivative, the same as autograd's (exactly for a point
    light, within the fixed nodes' 1e-3 otherwise), and a rotation column of 0."""
    maps, lights = _problem(False, kernel, seed=2)
    alpha = torch.tensor([0.005, 0.05, 0.1, 0.3, 0.5], dtype=F64)[:, None].expand(5, 2)
    maps = SVBRDF(maps.normal, maps.diffuse, maps.specular, alpha.contiguous(), maps.rotation)
    value, jac = jacobian(maps, lights, VIEW)
    torch.testing.assert_close(value, render(maps, lights, VIEW), rtol=1e-10, atol=1e-12)
    exact = _autograd(maps, lights)
    scale = exact.abs().amax(dim=(1, 2, 3), keepdim=True)
    error = ((jac - exact).abs() / scale).max().item()
    assert error < (1e-9 if kernel.kind == "point" else 1e-3), f"largest relative difference {error:.3g}"
    assert (jac[..., -1] == 0).all()


def test_fast_clamp_is_close_to_the_exact_one():
    """The fit's clamp rule on normals tilted so that most frames reach behind their horizon:
    values within 5e-4 of each pixel's largest value, and the same derivatives to 1e-2."""
    g = torch.Generator().manual_seed(3)
    n = 64
    tilt = torch.linspace(0.0, 1.2, n, dtype=F64)
    az = torch.rand(n, dtype=F64, generator=g) * 2 * math.pi
    normal = torch.stack([torch.sin(tilt) * torch.cos(az), torch.sin(tilt) * torch.sin(az), torch.cos(tilt)], -1)
    maps = SVBRDF(
        normal,
        torch.rand(n, 3, dtype=F64, generator=g),
        torch.zeros(n, 3, dtype=F64),
        torch.full((n, 2), 0.1, dtype=F64),
    )
    x = torch.linspace(-0.8, 0.8, 7, dtype=F64)
    lx, ly = torch.meshgrid(x, x, indexing="ij")
    keep = lx**2 + ly**2 < 0.95
    plane = torch.stack([lx[keep], ly[keep]], -1)
    centre = torch.cat([plane, torch.sqrt(1 - (plane**2).sum(-1, keepdim=True))], -1)
    k = centre.shape[0]
    lights = Lights(
        centre, Kernel("gaussian", "projected", 0.08), torch.ones(k, 1, dtype=F64), torch.ones(k, dtype=F64)
    )
    value, jac = jacobian(maps, lights, VIEW, diffuse_only=True)
    fast, fast_jac = jacobian(maps, lights, VIEW, diffuse_only=True, quadrature=Quadrature(clamp="fast"))
    assert not torch.equal(value, fast)  # the rules differ where the clamp acts...
    scale = value.abs().amax(dim=(1, 2), keepdim=True)
    assert ((fast - value).abs() / scale).max() < 5e-4  # ...by little
    jac_scale = jac.abs().amax(dim=(1, 2, 3), keepdim=True)
    assert ((fast_jac - jac).abs() / jac_scale).max() < 1e-2
    with pytest.raises(ValueError, match="clamp must be one of"):
        jacobian(maps, lights, VIEW, quadrature=Quadrature(clamp="rough"))


@pytest.mark.parametrize(
    "kernel",
    [
        Kernel("gaussian", "projected", 0.06),
        Kernel("gaussian", "projected", 0.15),
        Kernel("gaussian", "angular", 0.05),
        Kernel("supergaussian", "angular", 0.04, 6.0),
    ],
)
def test_the_fits_quadrature_is_close_to_the_renderers(kernel):
    """``torchspec.fit``'s fewer nodes (3 x 3 per frame, 8 reference radii, the clamp's fast
    rule) on lobes from 0.005 to 0.5 and a frame at 75 deg: values within 1e-3 of each pixel's
    largest, derivatives within 1e-2."""
    maps, lights = _problem(False, kernel)
    value, jac = jacobian(maps, lights, VIEW, quadrature=Quadrature(order=3, reference_order=8, clamp="fast"))
    exact, exact_jac = jacobian(maps, lights, VIEW)
    assert ((value - exact).abs() / exact.abs().amax(dim=(1, 2), keepdim=True)).max() < 1e-3
    assert ((jac - exact_jac).abs() / exact_jac.abs().amax(dim=(1, 2, 3), keepdim=True)).max() < 1e-2


def test_compiled_is_eager():
    """``compile=True`` (torch.compile of the node integrations and of the normal equations' pass
    over the frames, as a large fit uses) gives the eager values, derivatives, normal equations and
    sandwich terms, to the rounding of sums taken in another order; so does the renderer's."""
    maps, lights = _problem(False, Kernel("gaussian", "projected", 0.08), seed=4)
    maps = maps.to(torch.float32)
    lights = lights.to(dtype=torch.float32)
    tilted = SVBRDF(
        normal_from_angles(torch.tensor([[0.9, 0.2]]).expand(5, 2)),
        maps.diffuse,
        maps.specular,
        maps.roughness,
        maps.rotation,
    )
    eager_rule = Quadrature(order=3, clamp="fast")
    fused_rule = replace(eager_rule, compile=True)
    for batch in (maps, tilted):  # the second reaches behind its horizon: the clamp's integral too
        plain = render(batch, lights, VIEW.float())
        compiled = render(batch, lights, VIEW.float(), quadrature=Quadrature(compile=True))
        torch.testing.assert_close(compiled, plain, rtol=1e-4, atol=1e-6)
        eager = jacobian(batch, lights, VIEW.float(), quadrature=eager_rule)
        fused = jacobian(batch, lights, VIEW.float(), quadrature=fused_rule)
        torch.testing.assert_close(fused, eager, rtol=1e-4, atol=1e-6)
        observed = eager[0] * 1.1
        weight = torch.ones_like(observed)
        select = torch.eye(eager[1].shape[-1])
        args = (batch, lights, VIEW.float(), observed, weight, select)
        plain = normal_equations(*args, quadrature=eager_rule)
        torch.testing.assert_close(
            normal_equations(*args, quadrature=fused_rule), plain, rtol=1e-4, atol=1e-7
        )
        args = (batch, lights, VIEW.float(), observed, weight / (0.1 + observed), weight, select)
        plain = sandwich_terms(*args, quadrature=eager_rule)
        fused = sandwich_terms(*args, quadrature=fused_rule)
        torch.testing.assert_close(fused, plain, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("name", list(MODELS))
def test_every_models_compiled_normal_equations(name):
    """Each model's normal equations as the solver gets them (:meth:`Model.residuals`), compiled
    (the Gram-matrix pass, in the model's own columns) and eager (the Jacobian, then its columns
    picked): equal to float rounding, on pixels that also reach behind their horizon, under
    coloured irradiance, with some samples dropped."""
    model = MODELS[name]
    maps, lights = _problem(model.grey, Kernel("gaussian", "projected", 0.08), seed=6)
    maps, lights = maps.to(torch.float32), lights.to(dtype=torch.float32)
    maps = SVBRDF(
        torch.cat([maps.normal, normal_from_angles(torch.tensor([[0.9, 0.2], [-0.7, 0.5]]))]),
        torch.cat([maps.diffuse, maps.diffuse[:2]]),
        torch.cat([maps.specular, maps.specular[:2]]),
        torch.cat([maps.roughness, maps.roughness[1:3]]),
        torch.cat([maps.rotation, maps.rotation[:2]]),
    )
    params = model.pack(maps)
    observed = render(model.unpack(params, maps.channels), lights, VIEW.float()) * 1.05 + 0.01
    g = torch.Generator().manual_seed(2)
    weight = (torch.rand(observed.shape[:2], generator=g) > 0.2).float() * 3.0  # (N, K): some dropped
    index = torch.arange(params.shape[0])
    args = (observed, weight, lights, VIEW.float(), maps.channels)
    eager_rule = Quadrature(order=3, reference_order=8, clamp="fast")
    eager = model.residuals(*args, quadrature=eager_rule, normal=True)(params, index)
    fused = model.residuals(*args, quadrature=replace(eager_rule, compile=True), normal=True)(params, index)
    assert fused.hess.shape == (params.shape[0], params.shape[1], params.shape[1])
    for got, expected in zip(fused, eager, strict=True):
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-6 * float(expected.abs().max()))


def _with_second_lobe(maps):
    """``maps`` with a broader grey second lobe (one pixel's k_s2 at 0)."""
    n = maps.shape[0]
    ks2 = torch.linspace(0.0, 0.6, n, dtype=maps.diffuse.dtype)[:, None]
    alpha2 = torch.linspace(0.1, 0.5, n, dtype=maps.diffuse.dtype)[:, None].expand(n, 2)
    return SVBRDF(maps.normal, maps.diffuse, maps.specular, maps.roughness, maps.rotation, maps.channels, ks2, alpha2)


@pytest.mark.parametrize("kernel", [Kernel("point"), Kernel("gaussian", "projected", 0.06)])
def test_a_second_lobes_columns(kernel):
    """With a second lobe: ``C_s2 + 2`` more columns (its k_s, alpha_x, alpha_y; the rotation is
    shared), exact for point lights and in forward mode, and the quadrature of the derivative
    (as for one lobe) on an extended light."""
    maps, lights = _problem(False, kernel, seed=3)
    maps = _with_second_lobe(maps)
    value, jac = jacobian(maps, lights, VIEW)
    assert jac.shape == (5, 5, 3, 2 + 3 + 3 + 3 + 1 + 2)
    torch.testing.assert_close(value, render(maps, lights, VIEW), rtol=1e-10, atol=1e-12)
    params = parameters(maps)

    def forward(p):
        return render(from_parameters(p, maps.channels, False, 1), lights, VIEW)

    full = torch.autograd.functional.jacobian(forward, params)
    index = torch.arange(params.shape[0])
    exact = full[index, :, :, index]
    torch.testing.assert_close(jacobian(maps, lights, VIEW, mode="forward")[1], exact, rtol=1e-9, atol=1e-12)
    if kernel.kind == "point":
        torch.testing.assert_close(jac, exact, rtol=1e-9, atol=1e-11)
    else:
        scale = exact.abs().amax(dim=(1, 2, 3), keepdim=True)
        assert float(((jac - exact).abs() / scale).max()) < 1e-3
    # The first lobe's columns are those of the first lobe alone, but for the shared normal and rotation.
    alone = jacobian(SVBRDF(maps.normal, maps.diffuse, maps.specular, maps.roughness, maps.rotation), lights, VIEW)[1]
    torch.testing.assert_close(jac[..., 2:10], alone[..., 2:10])


def test_the_lobe_snr_counts_both_lobes():
    maps, lights = _problem(True, Kernel("gaussian", "projected", 0.06), seed=3)
    two = _with_second_lobe(maps)
    observed = render(two, lights, VIEW)
    ones = torch.ones_like(observed)
    select = MODELS["ward-dual"].selection(3, observed)
    snr = sandwich_terms(two, lights, VIEW, observed, ones, ones, select, samples=True)[-1]
    matte = SVBRDF(two.normal, two.diffuse, 0 * two.specular, two.roughness)
    lobes = render(two, lights, VIEW) - render(matte, lights, VIEW)
    torch.testing.assert_close(snr, lobes.flatten(1).norm(dim=-1))
