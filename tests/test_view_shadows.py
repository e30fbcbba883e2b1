"""torchspec view of maps with a height: the horizon maps (torchspec.view.shadows), their tiles,
and the page's cast shadows against torchspec's own visibility in headless Chromium (skipped, with
the reason, where no browser is installed)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import served_page

from torchspec.io import Capture, Frame, LightSpec, read_svbrdf, write_capture, write_svbrdf
from torchspec.model.lights import Kernel, Lights
from torchspec.model.visibility import frame_visibility, horizon, marched_distances
from torchspec.relight import shaded_render, shadow_terms
from torchspec.view import Pyramid, open_site
from torchspec.view.browser import find_chromium
from torchspec.view.check import model_maps, reference_srgb, with_height, with_term
from torchspec.view.light import light_quadrature
from torchspec.view.shadows import (
    AZIMUTHS,
    BAND,
    SHADOW_TEXTURES,
    horizon_planes,
    shadow_manifest,
    view_distances,
    view_reach,
)
from torchspec.view.tiles import TEXTURES

CHROMIUM, WHY = find_chromium()
SOFTNESS = math.radians(2.0)


def _azimuths() -> torch.Tensor:
    phi = torch.arange(AZIMUTHS, dtype=torch.float64) * (2.0 * math.pi / AZIMUTHS)
    return torch.stack([phi.cos(), phi.sin(), torch.zeros_like(phi)], -1)


def test_the_views_distances_are_the_fits_near_the_pixel_and_sparser_beyond():
    fit = marched_distances(0.5, 200.0)
    view = view_distances(200.0)
    assert torch.equal(view[view < 4.0], fit[fit < 4.0])  # the same samples within 4 pixels
    assert (view.diff() > 0).all() and view[-1] == 200.0
    far = view[view >= 4.0]
    assert torch.allclose(far[:-1].diff(), torch.clamp(far[:-2] / 32.0, min=0.5))  # each 1/32 farther
    assert len(view) < len(fit) / 3
    assert torch.equal(view_distances(3.0), fit.new_tensor(marched_distances(0.5, 3.0).tolist()))


def test_the_views_horizons_are_the_fits_in_bands_bit_for_bit_and_within_a_fraction_of_a_degree():
    maps = with_height(model_maps("diffuse", 280, 16, seed=1), seed=2, peak=10.0)
    height = maps.extra["height"].double()
    reach = view_reach(height)
    whole = horizon_planes(height, 0, 280, reach)
    assert set(whole) == {f"horizon_{j}" for j in range(AZIMUTHS)}
    for start, stop in ((0, 64), (250, 280), (BAND - 10, BAND + 5)):  # bands across the blocks' border
        band = horizon_planes(height, start, stop, reach)
        assert all(torch.equal(band[name], whole[name][start:stop]) for name in whole), (start, stop)
    fit = horizon(height, _azimuths(), reach=reach)  # the fit's samples: every half pixel
    view = torch.stack([whole[f"horizon_{j}"] for j in range(AZIMUTHS)], -1).double()
    # where a light above the plane meets it (a horizon below the plane hides none): a far narrow
    # bump may fall between the sparser samples, rarely and by little
    error = torch.rad2deg((view.clamp(min=0) - fit.clamp(min=0)).abs())
    assert float(error.max()) < 1.5 and float(error.mean()) < 0.01 and float((error > 0.25).double().mean()) < 0.005
    # as far as a light 5 degrees above the plane can be hidden: the full length sees no more there
    low = torch.deg2rad(torch.tensor(5.0, dtype=torch.float64))
    far = horizon(height, _azimuths(), reach=math.hypot(280, 16))
    assert torch.equal(fit >= low, far >= low)


def test_maps_with_a_height_carry_the_shadow_textures_and_the_manifest_says_how(tmp_path):
    plain = model_maps("ward-iso", 24, 32, seed=4)
    assert open_site(plain).manifest["shadows"] is None
    maps = with_height(plain, seed=3)
    site = open_site(maps)
    names = [texture["name"] for texture in site.manifest["textures"]]
    assert names == [name for name, *_ in TEXTURES + SHADOW_TEXTURES]
    shadows = site.manifest["shadows"]
    assert shadows["azimuths"] == AZIMUTHS and shadows["softness_deg"] == 2.0 and not shadows["angular"]
    assert shadows["covariance"] == [[0.0, 0.0], [0.0, 0.0]] and shadows["reach"] == view_reach(maps.extra["height"])
    block = site.pyramid.block(0, 0, 0)  # level 0's planes, as the tiles send them
    index = {name: i for i, name in enumerate(site.pyramid.names)}
    expected = horizon_planes(maps.extra["height"], 0, 24, shadows["reach"])
    assert torch.equal(block[index["horizon_5"], :24, :32], expected["horizon_5"])
    assert torch.equal(block[index["indirect"], :24, :32], maps.extra["indirect"])
    angular = shadow_manifest(SOFTNESS, Kernel("gaussian", "angular", 0.1), 10.0)
    assert angular["angular"] and np.allclose(angular["covariance"], np.eye(2) * 0.01)


def test_a_folder_with_a_height_read_lazily_gives_the_tiles_in_memory_bit_for_bit(tmp_path):
    write_svbrdf(tmp_path / "maps", with_height(model_maps("ward-iso", 280, 40, seed=13), seed=5))
    lazy = open_site(tmp_path / "maps", tile=64, keep_texels=5000).pyramid
    whole = Pyramid.of_maps(read_svbrdf(tmp_path / "maps"), tile=64)
    assert lazy.kept > 0 and lazy.textures == whole.textures and lazy.shadow_reach == whole.shadow_reach
    for level in range(len(whole.levels)):
        rows, columns = whole.grid(level)
        for row in range(rows):
            for column in range(columns):
                assert lazy.tile(level, row, column) == whole.tile(level, row, column), (level, row, column)


def _light(elevation_deg: float, azimuth_deg: float) -> list[float]:
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return [math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]


def _assert_on_grid(difference, where):
    """On one of the maps' azimuths the page's horizon is the fit's but for float16 and the
    sparser far samples: ``difference`` (codes) at most 1 on all but 0.2 % of the pixels, at most 3."""
    assert (difference <= 1).mean() > 0.998 and difference.max() <= 3, (where, (difference > 1).sum(), difference.max())


def _assert_off_only_at_edges(difference, maps, light, position=None):
    """``difference`` (codes, ``(H, W)``) is at most 1 but within two pixels of the reference's
    shadow edges (where its visibility varies by more than 0.2 over 5 x 5 pixels), on all but 1 %
    of the pixels, over 10 on under 1 % and at most 32."""
    one = torch.ones(1, 1, dtype=torch.float64)
    at = None if position is None else torch.tensor([position], dtype=torch.float64)
    centre = torch.tensor([light], dtype=torch.float64) if position is None else at / at.norm()
    seen = frame_visibility(maps.extra["height"].double(), Lights(centre, Kernel("point"), one, one[0]), at,
                            footprint=1, softness=SOFTNESS)[None, ..., 0]  # fmt: skip
    spread = F.max_pool2d(seen, 5, 1, 2) + F.max_pool2d(-seen, 5, 1, 2)
    edge = (spread[0] > 0.2).numpy()
    off = difference > 1
    assert (off & ~edge).mean() < 0.01 and (difference > 10).mean() < 0.01 and difference.max() <= 32, (
        light, position, (off & ~edge).mean(), (difference > 10).mean(), difference.max())


def _shadows(maps):
    return maps.extra["height"], maps.extra["indirect"], SOFTNESS


@pytest.mark.skipif(CHROMIUM is None, reason=f"no headless Chromium: {WHY}")
def test_the_page_casts_the_heights_shadows_as_render_does(browser):
    maps = with_height(model_maps("ward-iso", 48, 64, seed=3), seed=1, peak=12.0)
    step = 360.0 / AZIMUTHS
    with served_page(browser, open_site(maps)):
        assert "with their cast shadows" in browser.evaluate("document.getElementById('shown').textContent")
        for elevation, azimuth, on_grid in ((25, 0, True), (35, 7 * step, True), (20, 21 * step, True), (30, 180, True),
                                            (25, 100, False), (30, 200, False), (20, 281, False)):  # fmt: skip
            light = _light(elevation, azimuth)
            if azimuth in (0, 180):  # y = -0.0, as a capture's light file may give it (its atan2 is -0 or -pi)
                light[1] = -0.0
            browser.show(origin=True, light=light[:2], layer="relit")
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), shadows=_shadows(maps)).astype(int)
            difference = np.abs(page - expected).max(-1)
            if on_grid:
                _assert_on_grid(difference, (elevation, azimuth))
            else:  # between two, interpolated: the shadows' edges move by up to two pixels
                _assert_off_only_at_edges(difference, maps, light)
            unshadowed = reference_srgb(maps.svbrdf, tuple(light)).astype(int)
            assert (np.abs(unshadowed - expected).max(-1) > 20).mean() > 0.03  # the shadows matter here
        browser.show(shadows=False)  # off: the maps alone
        page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
        assert np.abs(page - unshadowed).max() <= 1
        assert "cast shadows off" in browser.evaluate("document.getElementById('shown').textContent")


@pytest.mark.skipif(CHROMIUM is None, reason=f"no headless Chromium: {WHY}")
def test_the_page_applies_the_term_after_the_shadows_as_render_does(browser):
    maps = with_term(with_height(model_maps("ward-dual", 48, 64, seed=11), seed=4), 3, seed=2)
    from torchspec.model.residual_term import MAP_NAME, WEIGHT_MAP, ResidualTerm

    term = ResidualTerm.from_map(maps.extra[MAP_NAME], 3, weight=maps.extra[WEIGHT_MAP])
    with served_page(browser, open_site(maps)):
        for azimuth in (3, 12, 25):
            light = _light(25, azimuth * 360.0 / AZIMUTHS)
            browser.show(origin=True, light=light[:2], layer="relit", shadows=True)
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), term=term, shadows=_shadows(maps)).astype(int)
            assert np.abs(page - expected).max() <= 1, azimuth
            browser.show(layer="physical")
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            physical = reference_srgb(maps.svbrdf, tuple(light), shadows=_shadows(maps)).astype(int)
            assert np.abs(page - physical).max() <= 1 and np.abs(physical - expected).max() > 20, azimuth
            browser.show(layer="relit")


@pytest.mark.skipif(CHROMIUM is None, reason=f"no headless Chromium: {WHY}")
@pytest.mark.parametrize("kernel", [Kernel("gaussian", "projected", 0.08), Kernel("gaussian", "angular", 0.1)],
                         ids=["projected", "angular"])  # fmt: skip
def test_under_a_kernel_the_penumbra_widens_as_render_does(browser, kernel):
    maps = with_height(model_maps("ward-iso", 32, 48, seed=9, alpha=(0.2, 0.45)), seed=6, softness_deg=1.0, peak=14.0)
    site = open_site(maps)
    site.manifest.update(light_quadrature(kernel).describe())  # as a capture with this kernel gives it
    site.manifest["shadows"] = shadow_manifest(math.radians(1.0), kernel, site.pyramid.shadow_reach)
    with served_page(browser, site):
        # 40 degrees up: nearer the horizon render integrates the kernel on its reference nodes
        # (test_view's kernel tests keep within 60 degrees of the zenith), with or without shadows
        for azimuth in (5, 18):
            light = _light(40, azimuth * 360.0 / AZIMUTHS)
            assert browser.show(origin=True, light=light[:2], layer="relit")["extended"]
            page = browser.read(0, 0, 48, 32)[..., :3].astype(int)
            shadows = (maps.extra["height"], maps.extra["indirect"], math.radians(1.0))
            expected = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel, shadows=shadows).astype(int)
            _assert_on_grid(np.abs(page - expected).max(-1), azimuth)
            point = reference_srgb(maps.svbrdf, tuple(light), shadows=shadows).astype(int)
            assert np.abs(point - expected).max() > 5  # the kernel matters here
            browser.show(extended=False)  # a point light: its penumbra not widened
            _assert_on_grid(np.abs(browser.read(0, 0, 48, 32)[..., :3].astype(int) - point).max(-1), azimuth)
            browser.show(extended=True)
            unshadowed = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel).astype(int)
            assert (np.abs(unshadowed - expected).max(-1) > 20).mean() > 0.01  # and the shadows


@pytest.mark.skipif(CHROMIUM is None, reason=f"no headless Chromium: {WHY}")
def test_under_a_near_light_each_pixel_sees_it_from_its_own_centre(browser):
    maps = with_height(model_maps("ward-iso", 45, 69, seed=3), seed=8)
    with served_page(browser, open_site(maps)):
        for position in ([1.2, 0.0, 0.5], [-0.9, 0.8, 0.45]):
            at = np.array(position)
            direction, distance = (at / np.linalg.norm(at)).tolist(), float(np.linalg.norm(at))
            state = browser.show(origin=True, light=direction, distance=distance, layer="relit")
            assert np.allclose(state["position"], position, atol=1e-12)
            page = browser.read(0, 0, 69, 45)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, None, position=position, shadows=_shadows(maps)).astype(int)
            difference = np.abs(page - expected).max(-1)
            _assert_off_only_at_edges(difference, maps, None, position)  # each pixel's azimuth: interpolated
            unshadowed = reference_srgb(maps.svbrdf, None, position=position).astype(int)
            assert (np.abs(unshadowed - expected).max(-1) > 20).mean() > 0.03


def test_the_view_shadows_experiment_runs(tmp_path, browser):
    import sys

    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    import view_shadows

    maps = with_height(model_maps("ward-iso", 24, 32, seed=2), seed=3, peak=10.0)
    write_svbrdf(tmp_path / "maps", maps)
    directions = torch.tensor([_light(20, a) for a in (10, 100, 190, 280)] + [[0.0, 0.0, 1.0]], dtype=torch.float64)
    count = directions.shape[0]
    lights = Lights(directions, Kernel("point"), torch.ones(count, 3, dtype=torch.float64),
                    torch.ones(count, dtype=torch.float64))  # fmt: skip
    view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    svbrdf = maps.svbrdf.to(torch.float64)
    seen, bounce = shadow_terms(svbrdf, maps.extra["height"].double(), maps.extra["indirect"].double(), SOFTNESS,
                                lights, view)  # fmt: skip
    values = shaded_render(svbrdf, lights, view, seen=seen, bounce=bounce)  # the photographs: with their shadows
    frames = [Frame(f"f{k}.exr", tuple(d.tolist()), 1.0, 1.0) for k, d in enumerate(directions)]
    capture = Capture(tmp_path / "capture", 32, 24, ("R", "G", "B"), (0.0, 0.0, 1.0), LightSpec("point"), frames)
    write_capture(tmp_path / "capture", capture, values.permute(2, 3, 0, 1).float())
    config = tmp_path / "config.yaml"
    config.write_text(f"fit: {{maps: {tmp_path / 'maps'}, capture: {tmp_path / 'capture'}}}\nviewport: [640, 480]\n"
                      "sizes: [32, 48]\npeak: 6\nthreads: 1\nframes: 2\n")  # fmt: skip
    out = view_shadows.main(["--config", str(config), "--output", str(tmp_path / "out")])
    fit = out["fit"]
    assert fit["lights"] == count and fit["page_vs_photo_psnr_db"]["on"] > fit["page_vs_photo_psnr_db"]["off"] + 3
    assert fit["physical_within_1_step_share"]["centre"] > 0.95
    assert [row["size"] for row in out["speed"]["horizons"]] == [32, 48] and out["speed"]["page_fps"]["on"] > 0
    assert (tmp_path / "out" / "view_shadows.json").exists()
