import math

import pytest
import torch

from torchspec.model.brdf import SVBRDF, lambert, reflectance, ward, ward_cosine
from torchspec.model.geometry import normal_from_angles

F64 = torch.float64


def _dirs(n, seed, tilt=1.2):
    return normal_from_angles(tilt * (torch.rand(n, 2, dtype=F64, generator=torch.Generator().manual_seed(seed)) - 0.5))


def test_reciprocity():
    wi, wo, n = _dirs(40, 0), _dirs(40, 1), _dirs(40, 2, 0.5)
    alpha = torch.tensor([0.2, 0.07], dtype=F64).expand(40, 2)
    rot = torch.linspace(0, 3, 40, dtype=F64)
    ks = torch.rand(40, 3, dtype=F64)
    torch.testing.assert_close(ward(wi, wo, n, ks, alpha, rot), ward(wo, wi, n, ks, alpha, rot))


def test_isotropic_is_rotation_invariant_and_matches_closed_form():
    wi, wo, n = _dirs(30, 3), _dirs(30, 4), _dirs(30, 5, 0.5)
    alpha = torch.full((30, 2), 0.1, dtype=F64)
    a = ward(wi, wo, n, torch.ones(30, 1, dtype=F64), alpha, torch.zeros(30, dtype=F64))
    b = ward(wi, wo, n, torch.ones(30, 1, dtype=F64), alpha, torch.full((30,), 1.3, dtype=F64))
    torch.testing.assert_close(a, b)
    h = (wi + wo) / (wi + wo).norm(dim=-1, keepdim=True)
    cos_h = (h * n).sum(-1)
    ci, co = (n * wi).sum(-1), (n * wo).sum(-1)
    expected = torch.exp(-(1 / cos_h**2 - 1) / 0.01) / (4 * math.pi * 0.01 * torch.sqrt(ci * co))
    front = (ci > 0) & (co > 0)
    torch.testing.assert_close(a[..., 0], torch.where(front, expected, torch.zeros_like(expected)))


def test_energy_at_most_one():
    """Directional albedo of the lobe (k_s = 1), by quadrature over the hemisphere, for a view
    near the normal: Ward's normalisation keeps it below 1 for moderate roughness."""
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    theta = (torch.arange(400, dtype=F64) + 0.5) * (math.pi / 2 / 400)
    phi = (torch.arange(400, dtype=F64) + 0.5) * (2 * math.pi / 400)
    tt, pp = torch.meshgrid(theta, phi, indexing="ij")
    wi = torch.stack([torch.sin(tt) * torch.cos(pp), torch.sin(tt) * torch.sin(pp), torch.cos(tt)], -1)
    d_omega = torch.sin(tt) * (math.pi / 2 / 400) * (2 * math.pi / 400)
    for view_tilt in (0.0, 0.3, 0.6):
        wo = torch.tensor([math.sin(view_tilt), 0.0, math.cos(view_tilt)], dtype=F64)
        for a in (0.05, 0.1, 0.2, 0.3):
            lobe = ward_cosine(wi, wo, n, torch.tensor([a, a], dtype=F64))
            albedo = (lobe * d_omega).sum().item()
            assert albedo <= 1.0, f"albedo {albedo:.4f} at alpha {a}, view tilt {view_tilt}"
            if view_tilt == 0.0 and a <= 0.1:
                assert albedo > 0.95, f"a narrow lobe keeps its energy: {albedo:.4f}"


def test_back_facing_and_grazing_are_finite():
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    wo = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    for z in (-0.5, 0.0, 1e-12, 1e-6):
        wi = torch.tensor([[math.sqrt(1 - z * z), 0.0, z]], dtype=F64, requires_grad=True)
        alpha = torch.tensor([[0.3, 0.3]], dtype=F64, requires_grad=True)
        value = ward_cosine(wi, wo, n, alpha)
        value.sum().backward()
        assert torch.isfinite(value).all() and torch.isfinite(wi.grad).all() and torch.isfinite(alpha.grad).all()
        if z <= 0:
            assert value.item() == 0.0 and wi.grad.abs().sum().item() == 0.0


def test_zero_roughness_means_no_lobe():
    d = _dirs(5, 6)
    value = ward_cosine(d, d, d, torch.zeros(5, 2, dtype=F64))
    assert (value == 0).all()


def test_gradcheck_ward():
    wi = _dirs(3, 7).requires_grad_(True)
    wo = _dirs(3, 8).requires_grad_(True)
    n = _dirs(3, 9, 0.4).requires_grad_(True)
    alpha = torch.tensor([[0.005, 0.005], [0.1, 0.04], [0.5, 0.3]], dtype=F64, requires_grad=True)
    rot = torch.tensor([0.1, 0.5, 2.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(ward_cosine, (wi, wo, n, alpha, rot))


def test_reflectance_and_lambert():
    maps = SVBRDF(torch.tensor([[0.0, 0.0, 1.0]], dtype=F64), torch.tensor([[0.5, 0.2, 0.1]], dtype=F64),
                  torch.tensor([[0.0]], dtype=F64), torch.zeros(1, 2, dtype=F64))
    w = torch.tensor([[0.3, 0.0, math.sqrt(1 - 0.09)]], dtype=F64)
    torch.testing.assert_close(reflectance(w, w, maps), lambert(maps.diffuse))
    below = torch.tensor([[0.0, 0.0, -1.0]], dtype=F64)
    assert (reflectance(below, w, maps) == 0).all()


def test_svbrdf_container():
    maps = SVBRDF(torch.zeros(2, 3, 3), torch.zeros(2, 3, 3), torch.zeros(2, 3, 1), torch.zeros(2, 3, 2))
    assert maps.shape == (2, 3) and maps.channels == ("R", "G", "B")
    assert maps.flatten().shape == (6,) and maps.reshape(3, 2).diffuse.shape == (3, 2, 3)
    assert maps[0].shape == (3,) and maps.to(torch.float64).normal.dtype == F64
    assert SVBRDF(torch.zeros(1, 3), torch.zeros(1, 1), torch.zeros(1, 1), torch.zeros(1, 2)).channels == ("Y",)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(diffuse=torch.zeros(2, 3, 4), specular=torch.zeros(2, 3, 3)), r"specular must have shape \(2, 3, 4\)"),
        (dict(roughness=torch.zeros(2, 3, 1)), r"roughness must have shape \(2, 3, 2\)"),
        (dict(normal=torch.zeros(2, 3)), r"diffuse must have shape \(2, 3\)"),
        (dict(rotation=torch.zeros(3)), r"rotation must have shape \(2, 3\)"),
        (dict(channels=("R", "G")), "must name 3 channels"),
    ],
)
def test_svbrdf_shape_errors(kwargs, match):
    base = dict(normal=torch.zeros(2, 3, 3), diffuse=torch.zeros(2, 3, 3), specular=torch.zeros(2, 3, 1),
                roughness=torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match=match):
        SVBRDF(**{**base, **kwargs})


def test_a_second_lobe_adds_to_the_first():
    g = torch.Generator().manual_seed(4)
    n = normal_from_angles(0.2 * torch.randn(6, 2, dtype=F64, generator=g))
    kd, ks, ks2 = (torch.rand(6, c, dtype=F64, generator=g) for c in (3, 3, 1))
    alpha, alpha2 = torch.full((6, 2), 0.05, dtype=F64), torch.full((6, 2), 0.3, dtype=F64)
    one = SVBRDF(n, kd, ks, alpha)
    two = SVBRDF(n, kd, ks, alpha, None, None, ks2, alpha2)
    wi = normal_from_angles(0.4 * torch.randn(6, 2, dtype=F64, generator=g))
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(6, 3)
    torch.testing.assert_close(reflectance(wi, wo, two), reflectance(wi, wo, one) + ward(wi, wo, n, ks2, alpha2))
    assert two.second().specular is ks2 and one.second() is None
    assert two[1:3].specular2.shape == (2, 1) and two.reshape(2, 3).roughness2.shape == (2, 3, 2)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(specular2=torch.zeros(2, 3, 1)), "must be given together"),
        (dict(specular2=torch.zeros(2, 3, 2), roughness2=torch.zeros(2, 3, 2)), r"specular2 must have shape"),
        (dict(specular2=torch.zeros(2, 3, 1), roughness2=torch.zeros(2, 3)), r"roughness2 must have shape \(2, 3, 2\)"),
    ],
)
def test_second_lobe_shape_errors(kwargs, match):
    base = dict(normal=torch.zeros(2, 3, 3), diffuse=torch.zeros(2, 3, 3), specular=torch.zeros(2, 3, 1),
                roughness=torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match=match):
        SVBRDF(**{**base, **kwargs})
