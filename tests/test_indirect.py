"""Indirect light in a relief's shadows (torchspec.model.indirect) and the visibility averaged over a
pixel's footprint: the flat diffuse against its closed form, the indirect share's least squares
against a brute-force float64 reference and its clamps, the footprint average against its
definition, ``simulate``'s indirect light, and ``torchspec render`` adding indirect.exr's light."""

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.errors import TorchspecError
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import from_plane
from torchspec.model.indirect import MAX_SHARE, bound, flat_maps, indirect_share
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render, render_image
from torchspec.model.visibility import frame_visibility, kernel_visibility, sky_view, visibility
from torchspec.simulate import LayoutConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.relief import ReliefConfig, relief
from torchspec.simulate.synth import PaintingConfig

F64 = torch.float64


def _lights(count: int = 7, seed: int = 0, kernel: Kernel | None = None) -> Lights:
    g = torch.Generator().manual_seed(seed)
    d = from_plane(1.2 * (torch.rand(count, 2, generator=g, dtype=F64) - 0.5))  # |l_xy| < 0.85
    irradiance = 0.5 + torch.rand(count, 3, generator=g, dtype=F64)
    return Lights(d, kernel or Kernel("point"), irradiance, 0.5 + torch.rand(count, generator=g, dtype=F64))


def _maps(n: int = 9, seed: int = 1) -> SVBRDF:
    g = torch.Generator().manual_seed(seed)
    normal = torch.cat([0.6 * (torch.rand(n, 2, generator=g, dtype=F64) - 0.5), torch.ones(n, 1, dtype=F64)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    diffuse = torch.rand(n, 3, generator=g, dtype=F64)
    specular = 0.3 * torch.rand(n, 1, generator=g, dtype=F64)
    roughness = torch.full((n, 2), 0.15, dtype=F64)
    return SVBRDF(normal, diffuse, specular, roughness)


def test_flat_diffuse_is_the_albedo_on_the_mean_plane():
    maps, lights = _maps(), _lights()
    flat = flat_maps(maps)
    assert torch.equal(flat.diffuse, maps.diffuse) and float(flat.specular.abs().max()) == 0.0
    got = render(flat, lights, torch.tensor([0.0, 0.0, 1.0], dtype=F64))  # (n, K, C)
    scale = lights.irradiance * lights.exposure[:, None]  # (K, C)
    expected = maps.diffuse[:, None, :] / math.pi * lights.directions[None, :, 2:3] * scale[None]
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-14)


def _brute_share(residual, flat, weight):
    """One pixel's share by a dense 1-D search of the weighted squared error (float64)."""
    grid = torch.linspace(0.0, MAX_SHARE, 20001, dtype=F64)
    error = (weight[None] * (residual[None] - grid[:, None, None] * flat[None]) ** 2).sum((1, 2))
    return float(grid[error.argmin()])


def test_indirect_share_is_the_weighted_least_squares_and_is_clamped():
    g = torch.Generator().manual_seed(3)
    k, c, n = 11, 3, 6
    flat = torch.rand(k, c, n, generator=g, dtype=F64)
    truth = torch.tensor([0.0, 0.05, 0.3, 0.9, -0.4, 1.7], dtype=F64)
    residual = truth * flat + 0.01 * torch.randn(k, c, n, generator=g, dtype=F64)
    weight = (torch.rand(k, n, generator=g, dtype=F64) > 0.3).to(F64)
    got = indirect_share(residual, flat, weight)
    for p in range(n):
        w = weight[:, p, None].expand(k, c)
        assert abs(float(got[p]) - _brute_share(residual[..., p], flat[..., p], w)) <= 1e-4
    assert float(got[4]) == 0.0 and float(got[5]) == MAX_SHARE  # clamped to [0, MAX_SHARE]
    none = indirect_share(residual, flat, torch.zeros(k, n, dtype=F64))
    assert torch.equal(none, torch.zeros(n, dtype=F64))  # no samples: no indirect light


def test_the_share_is_bounded_by_the_hidden_sky():
    g = torch.Generator().manual_seed(5)
    flat = 0.1 + torch.rand(9, 3, 4, generator=g, dtype=F64)
    sky = torch.tensor([1.0, 0.9, 0.6, 0.0], dtype=F64)
    torch.testing.assert_close(bound(sky), MAX_SHARE * (1.0 - sky))
    got = indirect_share(0.3 * flat, flat, torch.ones(9, 4, dtype=F64), bound(sky))
    # open to the sky: none; partly hidden: at most the hidden share; deep: the least squares
    torch.testing.assert_close(got, torch.tensor([0.0, 0.1, 0.3, 0.3], dtype=F64), rtol=1e-12, atol=1e-12)


def test_sky_view_is_one_on_a_plane_and_falls_in_a_pit():
    flat = sky_view(torch.zeros(9, 9, dtype=F64))
    assert float(flat.min()) > 0.999
    pit = torch.zeros(9, 9, dtype=F64)
    pit[:, :3] = pit[:, 6:] = 6.0  # a groove 3 pixels wide between walls 6 pixels high
    groove = sky_view(pit)
    assert float(groove[4, 4]) < 0.6 and float(groove[4, 4]) < float(groove[4, 1])
    # the brute force: the cosine-weighted mean of visibility over a fine hemisphere grid
    theta = (torch.arange(90, dtype=F64) + 0.5) / 90 * (math.pi / 2)
    phi = (torch.arange(180, dtype=F64) + 0.5) / 180 * (2 * math.pi)
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    directions = torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], -1).reshape(-1, 3)
    weight = (t.cos() * t.sin()).reshape(-1)
    seen = visibility(pit, directions)[4, 4]
    assert abs(float((seen * weight).sum() / weight.sum()) - float(groove[4, 4])) < 0.03


def test_visibility_softness_follows_the_setting():
    shape = relief(ReliefConfig(seed=6, bumps=2, bump_height=(5.0, 6.0)), 10, 10)
    lights = _lights(5, seed=4)
    for soft in (0.5, 4.0):
        got = frame_visibility(shape.height, lights, footprint=1, softness=math.radians(soft))
        torch.testing.assert_close(got, visibility(shape.height, lights.directions, softness=math.radians(soft)))


@settings(max_examples=25, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(1e-3, 1e3), st.integers(0, 10_000))
def test_indirect_share_recovers_an_exact_bounce_at_any_brightness(share, scale, seed):
    g = torch.Generator().manual_seed(seed)
    flat = scale * (0.1 + torch.rand(8, 3, 2, 2, generator=g, dtype=F64))
    got = indirect_share(share * flat, flat, torch.ones(8, 2, 2, dtype=F64))
    torch.testing.assert_close(got, torch.full((2, 2), share, dtype=F64), rtol=1e-10, atol=1e-12)


def test_footprint_average_is_the_mean_over_a_finer_height():
    shape = relief(ReliefConfig(seed=4, bumps=2, bump_height=(4.0, 5.0), ridge_height=3.0), 12, 10)
    lights = _lights(5, seed=2)
    one = frame_visibility(shape.height, lights, footprint=1)
    torch.testing.assert_close(one, visibility(shape.height, lights.directions), rtol=0, atol=0)
    fine = F.interpolate((3 * shape.height)[None, None], scale_factor=3, mode="bicubic", align_corners=False)[0, 0]
    expected = F.avg_pool2d(visibility(fine, lights.directions).permute(2, 0, 1)[None], 3)[0].permute(1, 2, 0)
    torch.testing.assert_close(frame_visibility(shape.height, lights, footprint=3), expected, rtol=1e-12, atol=1e-12)
    flat = frame_visibility(torch.zeros(6, 5, dtype=F64), lights)
    assert float(flat.min()) > 0.999  # nothing casts a shadow on a plane
    with pytest.raises(TorchspecError, match="footprint"):
        frame_visibility(shape.height, lights, footprint=0)


def test_footprint_follows_the_kernel_and_near_lights():
    shape = relief(ReliefConfig(seed=5, bumps=2), 8, 8)
    lights = _lights(4, seed=3, kernel=Kernel("gaussian", sigma=0.05))
    fine = F.interpolate((2 * shape.height)[None, None], scale_factor=2, mode="bicubic", align_corners=False)[0, 0]
    expected = F.avg_pool2d(kernel_visibility(fine, lights).permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
    torch.testing.assert_close(frame_visibility(shape.height, lights, footprint=2), expected, rtol=1e-12, atol=1e-12)
    near = frame_visibility(shape.height, lights, 3.0 * lights.directions, footprint=2)
    assert near.shape == (8, 8, 4) and bool(((near >= 0) & (near <= 1)).all())


def _simulation(indirect: float, size: int = 16):
    shape = ReliefConfig(seed=2, bumps=3, bump_height=(4.0, 6.0), ridge_height=0.0, indirect=indirect)
    return SimulationConfig(
        name="indirect",
        scene=SceneConfig(painting=PaintingConfig(width=size, height=size, strokes=3), relief=shape),
        layout=LayoutConfig(kind="grid", nx=4, ny=4, extent=0.95, radius=1.0),
    )


def test_simulate_adds_the_indirect_light_of_the_sky_it_cannot_see(tmp_path):
    plain, bounced = simulate(_simulation(0.0)), simulate(_simulation(0.6))
    assert plain.indirect is None
    share = 0.6 * (1.0 - sky_view(bounced.height.double()))
    torch.testing.assert_close(bounced.indirect, share.float())
    assert float(share.max()) > 0.02  # the bumps hide some of the sky
    written = write_simulation(tmp_path / "relief", bounced)
    lights = written.lights(dtype=F64)
    flat = render_image(flat_maps(bounced.truth.to(F64)), lights, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    added = (share[..., None, None] * flat).permute(2, 3, 0, 1)
    sensed = bounced.frames.double() - plain.frames.double()  # same seeds: the sensor's noise cancels
    assert float((sensed - added).abs().max()) < 1e-3 * float(bounced.frames.abs().max())
    from torchspec.io import read_svbrdf

    assert torch.equal(read_svbrdf(tmp_path / "relief" / "truth").extra["indirect"], bounced.indirect)
    with pytest.raises(TorchspecError, match="indirect"):
        ReliefConfig(indirect=1.5)


def test_render_adds_the_indirect_light_of_indirect_exr(tmp_path):
    from torchspec.io import read_capture, write_svbrdf
    from torchspec.relight import render_capture

    sim = simulate(_simulation(0.0, size=12))
    write_simulation(tmp_path / "relief", sim)
    truth = sim.truth.to(torch.float32)
    share = torch.linspace(0.0, 0.4, 144).reshape(12, 12)
    write_svbrdf(tmp_path / "shadowed", truth, extra={"height": sim.height.float()})
    write_svbrdf(tmp_path / "bounced", truth, extra={"height": sim.height.float(), "indirect": share})
    shadowed = render_capture(tmp_path / "shadowed", tmp_path / "relief", None)["predicted"]
    bounced = render_capture(tmp_path / "bounced", tmp_path / "relief", None)["predicted"]
    lights = read_capture(tmp_path / "relief").lights(dtype=torch.float32)
    flat = render_image(flat_maps(truth), lights, torch.tensor([0.0, 0.0, 1.0])).permute(2, 3, 0, 1)
    torch.testing.assert_close(bounced, shadowed + share * flat, rtol=1e-5, atol=1e-6)
    write_svbrdf(tmp_path / "soft", truth, extra={"height": sim.height.float()}, meta={"height": {"softness_deg": 4.0}})
    soft = render_capture(tmp_path / "soft", tmp_path / "relief", None)["predicted"]
    plain = render_capture(tmp_path / "soft", tmp_path / "relief", None, shadows=False)["predicted"]
    seen = frame_visibility(sim.height.float(), lights, softness=math.radians(4.0)).permute(2, 0, 1)[:, None]
    torch.testing.assert_close(soft, plain * seen, rtol=1e-5, atol=1e-6)  # the fit's softness, from svbrdf.json
    off = render_capture(tmp_path / "bounced", tmp_path / "relief", None, shadows=False)["predicted"]
    plain = render_capture(tmp_path / "shadowed", tmp_path / "relief", None, shadows=False)["predicted"]
    assert torch.equal(off, plain)  # without shadows, no indirect light either
