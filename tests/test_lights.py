import math

import pytest
import torch
from brute_force import integrate, kernel_density

from torchspec.model.diffuse import clamped_diffuse
from torchspec.model.lights import Kernel, Lights, diffuse_directions, nodes

F64 = torch.float64


def _lights(kernel, thetas, phi=0.3):
    theta = torch.tensor(thetas, dtype=F64)
    centre = torch.stack([torch.sin(theta) * math.cos(phi), torch.sin(theta) * math.sin(phi), torch.cos(theta)], -1)
    return Lights(centre, kernel, torch.ones(len(thetas), 1, dtype=F64), torch.ones(len(thetas), dtype=F64))


def _brute_moments(kind, centre, **kw):
    """Mass and first moment of the kernel above the horizon by a fine Cartesian grid."""
    step = 0.0015
    offsets = (torch.arange(int(1.0 / step), dtype=F64) + 0.5) * step - 0.5
    gx, gy = torch.meshgrid(centre[0] + offsets, centre[1] + offsets, indexing="ij")
    l = torch.stack([gx, gy], -1).reshape(-1, 2)
    l = l[(l * l).sum(-1) < 1.0]
    w = torch.cat([l, torch.sqrt(1.0 - (l * l).sum(-1))[:, None]], -1)
    d = kernel_density(kind, w, centre, **kw) * step * step
    return d.sum().item(), (d[:, None] * w).sum(0)


KERNELS = [
    (Kernel("gaussian", "projected", 0.08), "gaussian-projected", dict(sigma=0.08)),
    (Kernel("gaussian", "angular", 0.06), "gaussian-angular", dict(sigma=0.06)),
    (Kernel("supergaussian", "angular", 0.05, 6.0), "supergaussian", dict(sigma=0.05, power=6.0)),
]


@pytest.mark.parametrize("kernel,kind,kw", KERNELS)
def test_mass_and_diffuse_direction(kernel, kind, kw):
    lights = _lights(kernel, [0.0, 0.6, 1.2])
    _, weight = nodes(lights, order=32)
    direction = diffuse_directions(lights)
    for k in range(3):
        mass, moment = _brute_moments(kind, lights.directions[k], **kw)
        assert abs(weight[k].sum().item() - mass) < 2e-4, f"frame {k}: mass {weight[k].sum().item():.6f} vs {mass:.6f}"
        torch.testing.assert_close(direction[k], moment, atol=2e-4, rtol=0)
    assert abs(weight[0].sum().item() - 1.0) < 1e-7  # at the zenith nothing is lost


def test_mass_below_the_horizon_is_lost():
    lights = _lights(Kernel("gaussian", "projected", 0.08), [math.asin(0.97)])
    _, weight = nodes(lights, order=32)
    mass, _ = _brute_moments("gaussian-projected", lights.directions[0], sigma=0.08)
    assert 0.5 < weight.sum().item() < 0.8 and abs(weight.sum().item() - mass) < 2e-4


def test_tabulated_kernel_is_normalised_and_oriented():
    table = torch.zeros(9, 9, dtype=F64)
    table[1, 6] = 1.0  # one bright pixel up and to the right
    kernel = Kernel("tabulated", table=table, extent=0.1)
    lights = _lights(kernel, [0.0])
    directions, weight = nodes(lights, order=40)
    assert abs(weight.sum().item() - 1.0) < 1e-6
    mean = (weight[0, :, None] * directions[0]).sum(0)
    assert mean[0] > 0.03 and mean[1] > 0.03  # +x is column right, +y is row 0


def test_point_light_nodes():
    lights = _lights(Kernel("point"), [0.1, 0.5])
    directions, weight = nodes(lights)
    torch.testing.assert_close(directions[:, 0], lights.directions)
    assert (weight == 1).all()


@pytest.mark.parametrize("tilt_deg,theta_deg", [(30, 70), (20, 75), (10, 80)])
def test_clamped_diffuse_matches_brute_force(tilt_deg, theta_deg):
    """A kernel across the horizon of a normal tilted away from it: in front and behind."""
    kernel = Kernel("gaussian", "projected", 0.08)
    theta, tilt = math.radians(theta_deg), math.radians(tilt_deg)
    centre = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=F64)
    normal = torch.tensor([[-math.sin(tilt), 0.0, math.cos(tilt)]], dtype=F64)
    expected, _ = integrate("gaussian-projected", centre[0], normal[0], k_d=math.pi, k_s=0.0, alpha=(0.1, 0.1),
                            rotation=0.0, box_centre=centre[0, :2], half=0.56, step=0.0008, sigma=0.08)
    linear = diffuse_directions(_lights(kernel, [theta], 0.0)) @ normal[0]
    value = clamped_diffuse(kernel, centre, normal, linear).item()
    assert value > linear.item()  # the clamp removes negative contributions
    assert abs(value / expected - 1) < 1e-4, f"{value:.8g} vs {expected:.8g}"


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(kind="disk"), "kind must be one of"),
        (dict(kind="gaussian", sigma=0.0), "needs sigma"),
        (dict(kind="gaussian", domain="planar", sigma=0.1), "domain must be"),
        (dict(kind="tabulated", extent=0.1), r"needs a \(Hk, Wk\) table"),
        (dict(kind="tabulated", table=-torch.ones(3, 3), extent=0.1), "finite, >= 0"),
    ],
)
def test_bad_kernels(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Kernel(**kwargs)


def test_lights_validation():
    with pytest.raises(ValueError, match="above the horizon"):
        Lights(torch.tensor([[0.0, 0.0, -1.0]]), Kernel("point"), torch.ones(1, 1), torch.ones(1))
    with pytest.raises(ValueError, match=r"irradiance must have shape \(1, C\)"):
        Lights(torch.tensor([[0.0, 0.0, 1.0]]), Kernel("point"), torch.ones(2, 1), torch.ones(1))


def test_from_spec():
    assert Kernel.from_spec({"kernel": "gaussian", "domain": "projected", "sigma": 0.08}).sigma == 0.08
    disk = Kernel.from_spec({"kind": "supergaussian", "domain": "angular", "radius": 0.035, "power": 6.0})
    assert disk.kind == "supergaussian" and disk.sigma == 0.035 and disk.power == 6.0
    assert Kernel.from_spec({"kernel": "unknown", "symmetric": True}).kind == "unknown"


def test_an_angular_kernel_compiles_without_a_graph_break():
    """The angular kernel's normaliser is a number fixed per kernel: under torch.compile its density
    is one graph (a Gauss-Legendre rule built in each call split it, and compiled fits of angular
    kernels ran at eager speed), with the eager values."""
    import torch._dynamo

    from torchspec.model.brdf import SVBRDF
    from torchspec.model.geometry import normal_from_angles
    from torchspec.model.quadrature import Quadrature
    from torchspec.model.rendering import render

    kernel = Kernel("gaussian", "angular", 0.05)
    assert kernel._radial_normaliser() == pytest.approx(2 * math.pi * 0.05**2, rel=2e-3)  # small angles: planar
    theta = torch.tensor([0.1, 0.4, 0.8])
    centre = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    lights = Lights(centre, kernel, torch.ones(3, 1), torch.ones(3))
    g = torch.Generator().manual_seed(0)
    maps = SVBRDF(normal_from_angles(0.2 * torch.randn(6, 2, generator=g)), torch.rand(6, 3, generator=g),
                  torch.rand(6, 1, generator=g), torch.full((6, 2), 0.1))
    view = torch.tensor([0.0, 0.0, 1.0])
    torch._dynamo.utils.counters.clear()
    compiled = render(maps, lights, view, quadrature=Quadrature(compile=True))
    assert not torch._dynamo.utils.counters["graph_break"], dict(torch._dynamo.utils.counters["graph_break"])
    torch.testing.assert_close(compiled, render(maps, lights, view), rtol=1e-4, atol=1e-6)


def test_lights_pick_frames():
    centre = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8]], dtype=torch.float64)
    lights = Lights(centre, Kernel("gaussian", sigma=0.05), torch.tensor([[1.0], [2.0], [3.0]]), torch.ones(3))
    for index in ([2, 0], torch.tensor([2, 0])):
        picked = lights[index]
        assert torch.equal(picked.directions, centre[[2, 0]]) and picked.irradiance[:, 0].tolist() == [3.0, 1.0]
        assert picked.kernel is lights.kernel
    assert lights[torch.tensor([True, False, True])].irradiance[:, 0].tolist() == [1.0, 3.0]
    assert lights[1].directions.shape == (1, 3) and lights[-1].irradiance.tolist() == [[3.0]]
    assert lights[1:].exposure.shape == (2,)
