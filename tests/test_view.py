"""torchspec view: the tiles, the site, the command, and the page itself in headless Chromium
(skipped, with the reason, where no browser or websocket client is installed)."""

from __future__ import annotations

import functools
import http.server
import io
import json
import math
import subprocess
import sys
import threading
import urllib.error
import urllib.request

import numpy as np
import pytest
import torch
from conftest import served_page

from torchspec.cli import main
from torchspec.errors import TorchspecError
from torchspec.export import ExportError, export
from torchspec.io import Capture, Frame, LightSpec, Maps, read_svbrdf, write_capture, write_svbrdf
from torchspec.io import svbrdf as svbrdf_io
from torchspec.model.lights import Kernel, Lights
from torchspec.model.near_lights import image_points, near_light
from torchspec.model.rendering import TILE_PIXELS, render_image
from torchspec.model.residual_term import MAP_NAME, WEIGHT_MAP, ResidualTerm, encode
from torchspec.outputs import OutputError
from torchspec.pipeline.tiling import BLOCK_ANGLE, LEAST_BLOCK, near_block
from torchspec.relight import render_capture, render_near
from torchspec.view import TEXTURES, TILE, Pyramid, export_web, open_site, serve
from torchspec.view.browser import find_chromium
from torchspec.view.check import MODEL_TYPES, hemisphere_lights, lobe_width, model_maps, reference_srgb, with_term
from torchspec.view.light import MAX_NODES, light_quadrature, near_lights
from torchspec.view.tiles import levels_for, read_photo_jpeg

CHROMIUM, WHY = find_chromium()
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason=f"no headless Chromium: {WHY}")


def _decode(data: bytes, textures=TEXTURES) -> dict[str, np.ndarray]:
    """A tile's planes, ``(TILE, TILE)`` float32 each, as the page reads them."""
    planes, offset = {}, 0
    for _, dtype, names in textures:
        size = TILE * TILE * 4 * np.dtype(dtype).itemsize
        values = np.frombuffer(data[offset : offset + size], dtype=np.dtype(dtype).newbyteorder("<"))
        values = values.reshape(TILE, TILE, 4).astype(np.float32)
        planes.update({name: values[..., j] for j, name in enumerate(names)})
        offset += size
    assert offset == len(data)
    return planes


def test_pyramid_tiles_hold_the_maps():
    maps = model_maps("ward-dual", height=300, width=520, seed=1)
    pyramid = Pyramid.of_maps(maps)
    assert levels_for(300, 520) == len(pyramid.levels) == 3
    assert pyramid.levels == [(300, 520), (150, 260), (75, 130)]
    assert pyramid.grid(0) == (2, 3) and pyramid.grid(2) == (1, 1)
    svbrdf = maps.svbrdf
    tile = _decode(pyramid.tile(0, 1, 2))  # rows 256..299, columns 512..519
    assert np.array_equal(tile["normal_z"][:44, :8], svbrdf.normal[256:, 512:, 2].numpy())  # float32: exact
    assert np.array_equal(tile["alpha2_x"][:44, :8], svbrdf.roughness2[256:, 512:, 0].numpy())
    assert np.allclose(tile["kd_g"][:44, :8], svbrdf.diffuse[256:, 512:, 1].numpy(), rtol=1e-3, atol=0)  # float16
    assert np.allclose(tile["ks2_b"][:44, :8], svbrdf.specular2[256:, 512:, 0].numpy(), rtol=1e-3, atol=0)  # grey
    assert not tile["normal_z"][44:].any() and not tile["normal_z"][:, 8:].any()  # padding
    # Level 1: 2 x 2 averages, normals renormalised; codes from the top-left texel.
    tile = _decode(pyramid.tile(1, 0, 0))
    block = svbrdf.normal[:2, :2].double().mean((0, 1))
    assert np.allclose(tile["normal_x"][0, 0], (block / block.norm())[0].item(), atol=1e-6)
    assert tile["model"][0, 0] == maps.extra["model"][0, 0].item()
    with pytest.raises(IndexError):
        pyramid.tile(0, 2, 0)


def test_site_routes_and_refuses_other_paths():
    site = open_site(model_maps("ward-iso", 20, 30))
    assert b"viewer.js" in site.file("/") and b"WebGL2" in site.file("/viewer.js")
    manifest = json.loads(site.file("/manifest.json"))
    assert (manifest["width"], manifest["height"], manifest["levels"]) == (30, 20, [[20, 30]])
    assert "flags" in manifest["layers"] and manifest["lights"] == []
    assert len(site.file("/tiles/0/0_0.bin")) == TILE * TILE * 64
    for bad in (
        "/tiles/1/0_0.bin",
        "/tiles/0/0_1.bin",
        "/../pyproject.toml",
        "/static/viewer.js",
        "/photo/0/0/0_0.bin",
        "/photo/0/0/0_0.jpg",  # no capture
    ):
        assert site.file(bad) is None, bad


def test_export_web_writes_a_static_site(tmp_path):
    maps = model_maps("diffuse", 40, 300)
    index = export(maps.svbrdf, tmp_path / "web", to="web")
    assert index == tmp_path / "web" / "index.html"
    files = {p.relative_to(tmp_path / "web").as_posix() for p in (tmp_path / "web").rglob("*") if p.is_file()}
    assert files == {"index.html", "viewer.js", "viewer.css", "manifest.json", "tiles/0/0_0.bin", "tiles/0/0_1.bin",
                     "tiles/1/0_0.bin"}  # fmt: skip
    with pytest.raises(OutputError, match="overwrite"):
        export_web(maps, tmp_path / "web")
    with pytest.raises(ExportError, match="web or rti export"):
        export(maps.svbrdf, tmp_path / "gltf", to="gltf", capture=tmp_path)


class _Terminal(io.StringIO):
    """A stderr that says it is a terminal (progress bars show there only)."""

    def isatty(self) -> bool:
        return True


def test_the_web_export_command_shows_a_bar_unless_quiet(tmp_path, monkeypatch, capsys):
    write_svbrdf(tmp_path / "maps", model_maps("diffuse", 40, 300))
    for quiet, folder in ((False, "loud"), (True, "quiet")):
        terminal = _Terminal()
        monkeypatch.setattr(sys, "stderr", terminal)
        argv = ["export", str(tmp_path / "maps"), "--to", "web", "-o", str(tmp_path / folder)]
        assert main(argv + ["--quiet"] * quiet) == 0
        assert f"wrote {tmp_path / folder / 'index.html'}" in capsys.readouterr().out
        assert ("export web" in terminal.getvalue()) is not quiet, terminal.getvalue()  # 3 tiles: 3/3
        assert ("3/3" in terminal.getvalue()) is not quiet


def _capture(folder, maps, exposure=2.0, irradiance=0.5, sigma=None):
    """A capture of ``maps`` rendered under 12 point lights (its photographs are the model's); with
    ``sigma``, its manifest's light is a Gaussian of that std in the l-plane (the photographs stay
    the point lights': rendering them under the kernel takes seconds, and the tests that give one
    look at the page's relit side only)."""
    height, width = maps.svbrdf.shape
    directions = torch.tensor(hemisphere_lights(12, 70.0))
    frames = [Frame(f"f{k:02d}.exr", tuple(d.tolist()), irradiance, exposure) for k, d in enumerate(directions)]
    spec = LightSpec("point") if sigma is None else LightSpec("gaussian", "projected", sigma)
    capture = Capture(folder, width, height, ("R", "G", "B"), (0.0, 0.0, 1.0), spec, frames)
    lights = Lights(directions, Kernel("point"), torch.full((12, 3), irradiance, dtype=torch.float64),
                    torch.full((12,), exposure, dtype=torch.float64))  # fmt: skip
    values = render_image(maps.svbrdf.to(torch.float64), lights, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return write_capture(folder, capture, values.permute(2, 3, 0, 1).float())


def test_a_web_export_with_its_capture_holds_every_photograph(tmp_path):
    maps = model_maps("ward-iso", 8, 12)
    capture = _capture(tmp_path / "c", maps, exposure=2.0, irradiance=0.5)
    export(maps, tmp_path / "web", to="web", capture=tmp_path / "c")
    manifest = json.loads((tmp_path / "web" / "manifest.json").read_text())
    assert np.allclose(manifest["lights"], capture.directions().numpy())
    assert manifest["photo"]["format"] == "jpeg"
    photos = sorted(p.relative_to(tmp_path / "web").as_posix() for p in (tmp_path / "web" / "photo").rglob("*.*"))
    assert photos == [f"photo/{k}/0/0_0.jpg" for k in sorted(range(12), key=str)]  # one tile each, a JPEG
    photo, scale = read_photo_jpeg((tmp_path / "web" / "photo" / "11" / "0" / "0_0.jpg").read_bytes())
    assert photo.shape == (8, 12, 3)  # the photograph's own size, not a padded 256 x 256 tile
    light = capture.directions()[11:12]
    one = torch.ones(1, 3, dtype=torch.float64)
    unit = render_image(maps.svbrdf.to(torch.float64), Lights(light, Kernel("point"), one, one[0, :1]),
                        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))[:, :, 0]  # fmt: skip
    assert scale == pytest.approx(float(unit.max()), rel=1e-6)  # the frame over exposure * irradiance: its top
    codes = encode(torch.from_numpy(photo / scale)).numpy() * 255
    exact = np.round(encode((unit / scale).clamp(0, 1)).numpy() * 255)
    error = np.abs(codes - exact)
    print(f"photograph's JPEG against the frame's sRGB codes: {error.mean():.2f} on average, {error.max():.0f} at "
          f"most; mean {photo.mean():.5f} against {float(unit.mean()):.5f}")  # fmt: skip
    assert abs(codes.mean() - exact.mean()) < 0.5  # random pixels, JPEG's worst case: their noise off, not their level


def test_a_capture_of_another_size_is_refused(tmp_path):
    capture = _capture(tmp_path / "c", model_maps("diffuse", 8, 12))
    with pytest.raises(TorchspecError, match="12x8 but the maps are 13x8"):
        open_site(model_maps("diffuse", 8, 13), capture)


@pytest.mark.parametrize("quiet", [[], ["--quiet"]], ids=["", "quiet"])
def test_the_view_command_serves_on_localhost(tmp_path, quiet):
    write_svbrdf(tmp_path / "maps", model_maps("ward-iso", 16, 16))
    command = [sys.executable, "-m", "torchspec", "view", str(tmp_path / "maps"), "--port", "0", *quiet]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        line = process.stdout.readline()
        assert line.startswith("torchspec view: http://127.0.0.1:"), line
        url = line.split()[2]
        with urllib.request.urlopen(url + "manifest.json", timeout=10) as answer:
            assert json.load(answer)["title"] == "maps"
    finally:
        process.terminate()
        process.wait(timeout=10)


@needs_browser
@pytest.mark.parametrize("model", MODEL_TYPES)
def test_the_page_relights_as_render_does(browser, model):
    maps = model_maps(model, 48, 64, seed=3)
    with served_page(browser, open_site(maps)):
        for light in hemisphere_lights(3, 75.0):
            browser.show(origin=True, light=light.tolist(), layer="relit")
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light)).astype(int)
            assert np.abs(page - expected).max() <= 1, (model, light)
            assert expected.std() > 10  # not a blank image


@needs_browser
def test_the_static_export_works_from_a_plain_web_server(browser, tmp_path):
    maps = model_maps("ward-aniso", 40, 300, seed=7)  # two tiles wide
    export_web(maps, tmp_path / "web")

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):
            pass

    handler = functools.partial(Quiet, directory=str(tmp_path / "web"))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        browser.open(f"http://127.0.0.1:{server.server_address[1]}/")
        light = hemisphere_lights(5, 60.0)[3]
        browser.show(origin=True, light=light.tolist(), layer="relit")
        page = browser.read(0, 0, 300, 40)[..., :3].astype(int)
        assert np.abs(page - reference_srgb(maps.svbrdf, tuple(light)).astype(int)).max() <= 1
    finally:
        server.shutdown()


@needs_browser
def test_layers_show_the_maps(browser):
    maps = model_maps("ward-aniso", 32, 40, seed=4)
    with served_page(browser, open_site(maps)):
        browser.show(origin=True, layer="normal")
        page = browser.read(0, 0, 40, 32)[..., :3].astype(int)
        expected = np.round((maps.svbrdf.normal.numpy() * 0.5 + 0.5) * 255)
        assert np.abs(page - expected).max() <= 1
        browser.show(layer="diffuse")
        page = browser.read(0, 0, 40, 32)[..., :3].astype(int)
        expected = torch.round(encode(maps.svbrdf.diffuse.double()) * 255).numpy()
        assert np.abs(page - expected).max() <= 1
        browser.show(layer="flags")
        red = browser.read(0, 0, 40, 32)[..., 0] > 200
        assert np.array_equal(red, maps.extra["flags"].numpy() > 0)  # model_maps flags only untrusted bits


@needs_browser
def test_the_origin_is_placed_in_the_canvas_as_laid_out_now(browser):
    maps = model_maps("ward-iso", 16, 24, seed=2)
    with served_page(browser, open_site(maps)):
        browser.evaluate("torchspecView.settle()")
        browser.evaluate("document.getElementById('bar').style.paddingTop = '37px'")  # the canvas shrinks, no frame yet
        browser.show(origin=True, layer="normal")
        page = browser.read(0, 0, 24, 16)[..., :3].astype(int)
        assert np.abs(page - np.round((maps.svbrdf.normal.numpy() * 0.5 + 0.5) * 255)).max() <= 1


def _jpeg_shown(site, frame: int) -> np.ndarray:
    """What the page shows of frame ``frame``'s photograph at 1:1 (its level-0 tile 0_0, at
    exposure 1): the JPEG's sRGB codes decoded, times its scale, encoded again and clipped."""
    values, _ = read_photo_jpeg(site.file(f"/photo/{frame}/0/0_0.jpg"))
    return np.round(encode(torch.from_numpy(values).clamp(0, 1)).numpy() * 255).astype(int)


@needs_browser
def test_with_a_capture_the_light_snaps_and_the_photograph_shows(browser, tmp_path):
    maps = model_maps("ward-iso", 24, 32, seed=5)
    capture = _capture(tmp_path / "c", maps)
    site = open_site(maps, capture)
    with served_page(browser, site):
        target = capture.directions()[7]
        state = browser.show(origin=True, light=(target[:2] + 0.02).tolist(), layer="relit")
        assert state["frame"] == 7 and np.allclose(state["light"], target.tolist())
        relit = browser.read(0, 0, 32, 24)[..., :3].astype(int)
        photo = browser.read(state["panels"][1]["x"], 0, 32, 24)[..., :3].astype(int)
        assert np.abs(relit - reference_srgb(maps.svbrdf, tuple(target.tolist())).astype(int)).max() <= 1
        assert np.abs(photo - _jpeg_shown(site, 7)).max() <= 1
        print(f"photograph panel against the relit one: {np.abs(photo - relit).mean():.2f} codes on average (JPEG)")


@needs_browser
def test_dragging_on_the_hemisphere_moves_the_light_and_a_click_reads_a_pixel(browser):
    maps = model_maps("ward-dual", 24, 32, seed=6)
    with served_page(browser, open_site(maps)):
        browser.show(origin=True)
        box = browser.evaluate("(() => { const r = document.getElementById('hemi').getBoundingClientRect(); "
                               "return [r.left, r.top, r.width]; })()")  # fmt: skip
        left, top, size = box
        radius, centre = size / 2 - 6, (left + size / 2, top + size / 2)
        for kind, x, y in (("mousePressed", 0.0, 0.0), ("mouseMoved", 0.3, 0.1), ("mouseReleased", 0.6, 0.2)):
            browser.call("Input.dispatchMouseEvent", type=kind, x=centre[0] + x * radius, y=centre[1] - y * radius,
                         button="left", buttons=0 if kind == "mouseReleased" else 1, clickCount=1)  # fmt: skip
        light = browser.evaluate("torchspecView.viewer.light")
        assert np.allclose(light[:2], [0.3, 0.1], atol=0.02)  # the last move; the release does not move it
        canvas = browser.evaluate("(() => { const r = torchspecView.viewer.canvas.getBoundingClientRect(); "
                                  "return [r.left, r.top]; })()")  # fmt: skip
        count = browser.evaluate("torchspecView.viewer.readouts")
        for kind in ("mousePressed", "mouseReleased"):
            browser.call("Input.dispatchMouseEvent", type=kind, x=canvas[0] + 5.5, y=canvas[1] + 9.5,
                         button="left", buttons=1, clickCount=1)  # fmt: skip
        # The readout fetches the pixel's tile: wait for the page to say the table is filled (a
        # fixed delay fails whenever the tile takes longer, as on a loaded machine).
        browser.evaluate(f"torchspecView.readout({count + 1})")
        rows = browser.evaluate("[...document.querySelectorAll('#info tr')].map(t => t.innerText)")
        assert rows[0].split() == ["pixel", "5,", "9"]
        k_s2 = maps.svbrdf.specular2[9, 5, 0].item()
        shown = {row.split("\t")[0]: row.split("\t")[1] for row in rows}
        assert np.allclose([float(v) for v in shown["k_s2"].split()], k_s2, rtol=1e-3), rows


def test_a_captures_kernel_becomes_the_pages_nodes(tmp_path):
    maps = model_maps("ward-iso", 8, 12)
    manifest = open_site(maps, _capture(tmp_path / "c", maps, sigma=0.08)).manifest
    nodes = np.array(manifest["kernel_nodes"])
    assert manifest["kernel"] == "gaussian" and nodes.shape == (64, 3) and not manifest["kernel_angular"]
    assert np.isclose(nodes[:, 2].sum(), 1.0) and np.allclose(nodes[:, 2] @ nodes[:, :2], 0.0, atol=1e-15)
    variance = nodes[:, 2] @ (nodes[:, :2] ** 2)  # Gauss-Hermite: the kernel's moments exactly
    assert np.allclose(variance, 0.08**2, rtol=1e-12)
    assert "gaussian kernel (sigma 0.08, projected), 64 nodes" in manifest["kernel_label"]
    assert open_site(maps).manifest["kernel_nodes"] == [] and open_site(maps).manifest["kernel"] == "point"
    for kernel in (Kernel("gaussian", "angular", 0.1), Kernel("supergaussian", "angular", 0.1, power=6.0),
                   Kernel("tabulated", table=torch.rand(16, 16, generator=torch.Generator().manual_seed(0)),
                          extent=0.2)):  # fmt: skip
        rule = light_quadrature(kernel)
        assert len(rule.weights) <= MAX_NODES and np.isclose(rule.weights.sum(), 1.0, atol=2e-4), kernel.kind
        mean = rule.weights @ rule.offsets
        assert np.allclose(mean, kernel.offset(torch.zeros(3, dtype=torch.float64)).numpy(), atol=1e-3), kernel.kind


DEMO_SIGMA = 0.08  # torchspec demo's light: a projected Gaussian kernel


@needs_browser
def test_the_page_relights_under_the_captures_kernel_as_render_does(browser, tmp_path):
    maps = model_maps("ward-iso", 48, 64, seed=9, alpha=(0.03, 0.2))  # the demo's range of alpha
    capture = _capture(tmp_path / "c", maps, sigma=DEMO_SIGMA)
    kernel = capture.lights().kernel
    site = open_site(maps, capture)
    # Pixels whose lobe's half width at half maximum is below the fixed nodes' spacing (23 % of
    # them): fixed nodes would fall on either side of its peak; the page places them on each
    # lobe's product with the kernel, so these match too.
    narrow = lobe_width(maps.svbrdf) / 2 < site.manifest["kernel_spacing"]
    assert narrow.mean() > 0.2
    with served_page(browser, site):
        for light in hemisphere_lights(4, 60.0):
            state = browser.show(origin=True, light=light.tolist(), layer="relit", snap=False, compare=False)
            assert state["extended"]
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel).astype(int)
            difference = np.abs(page - expected).max(-1)
            assert difference[~narrow].max() <= 1 and difference[narrow].max() <= 1, light
            assert expected.std() > 10
            point = reference_srgb(maps.svbrdf, tuple(light)).astype(int)
            assert np.abs(point - expected).max() > 10  # the kernel matters here
        assert "gaussian kernel" in browser.evaluate("document.getElementById('kernel').textContent")
        browser.show(extended=False)  # the point light, on request
        page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
        assert np.abs(page - point).max() <= 1
        assert browser.evaluate("document.getElementById('kernel').textContent") == "point light"


def _table_kernel() -> Kernel:
    """A tabulated kernel whose mass sits off its centre (8 x 8 over +-0.2: render's reference
    rule takes two radii a pixel, a larger table costs seconds)."""
    y, x = torch.meshgrid(*[torch.linspace(-1, 1, 8, dtype=torch.float64)] * 2, indexing="ij")
    return Kernel("tabulated", table=torch.exp(-((x - 0.2) ** 2 + y**2) / 0.3), extent=0.2)


@needs_browser
@pytest.mark.parametrize("kernel", [Kernel("gaussian", "angular", 0.1), _table_kernel()], ids=["angular", "tabulated"])
def test_the_page_sums_other_kernels_on_their_fixed_nodes(browser, kernel):
    maps = model_maps("ward-iso", 16, 24, seed=9, alpha=(0.2, 0.45))  # lobes broader than the nodes' spacing
    site = open_site(maps)
    rule = light_quadrature(kernel)
    site.manifest.update(rule.describe())  # as a capture with this kernel gives it
    assert rule.lobe_rule.size == 0 and (lobe_width(maps.svbrdf) / 2 > rule.spacing).all()
    with served_page(browser, site):
        for light in hemisphere_lights(2, 60.0):  # render of a tabulated kernel takes a second
            browser.show(origin=True, light=light.tolist(), layer="relit")
            page = browser.read(0, 0, 24, 16)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel).astype(int)
            assert np.abs(page - expected).max() <= 1, light
            assert np.abs(reference_srgb(maps.svbrdf, tuple(light)).astype(int) - expected).max() > 5


def _term(maps) -> ResidualTerm:
    """The maps' residual term as ``torchspec render`` reads it (torchspec.relight.render_capture)."""
    extra, encoding = maps.extra, (maps.meta.get(MAP_NAME) or {}).get("encoding")
    channels = len(maps.svbrdf.channels)
    return ResidualTerm.from_map(extra[MAP_NAME], channels, weight=extra.get(WEIGHT_MAP), encoding=encoding)


def test_the_web_export_holds_the_residual_terms_planes(tmp_path):
    maps = with_term(model_maps("ward-iso", 40, 300, seed=8), order=2, seed=1)
    export_web(maps, tmp_path / "web")
    manifest = json.loads((tmp_path / "web" / "manifest.json").read_text())
    assert manifest["term"] == 4 and manifest["layers"][:2] == ["relit", "physical"]
    textures = [(t["name"], t["dtype"], t["planes"]) for t in manifest["textures"]]
    assert textures[: len(TEXTURES)] == [(n, d, list(p)) for n, d, p in TEXTURES] and len(textures) == len(TEXTURES) + 4
    tile = _decode((tmp_path / "web" / "tiles" / "0" / "0_1.bin").read_bytes(), textures)  # columns 256..299
    term = _term(maps)
    for j in range(4):
        for c, name in enumerate("rgb"):
            expected = term.coefficients[:, 256:, j, c].numpy()
            assert np.allclose(tile[f"term_{j}_{name}"][:40, :44], expected, rtol=1e-3, atol=1e-7)  # float16
    assert np.allclose(tile["term_weight"][:40, :44], term.weight[:, 256:].numpy(), rtol=1e-3, atol=0)
    assert not tile["term_pad_0"].any() and not tile["term_0_r"][40:].any()
    assert "term" not in open_site(model_maps("ward-iso", 8, 8)).manifest["layers"]


@needs_browser
@pytest.mark.parametrize("order", [3, 2])
def test_the_page_adds_the_residual_term_as_render_does(browser, order):
    maps = with_term(model_maps("ward-dual" if order == 3 else "ward-aniso", 48, 64, seed=11), order, seed=2)
    term = _term(maps)
    lights = hemisphere_lights(20 if order == 3 else 4, 80.0)
    with served_page(browser, open_site(maps)):
        for light in lights:
            browser.show(origin=True, light=light.tolist(), layer="relit")
            page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), term=term).astype(int)
            assert np.abs(page - expected).max() <= 1, light
            physical = reference_srgb(maps.svbrdf, tuple(light)).astype(int)
            assert np.abs(physical - expected).max() > 20  # the term matters here
        assert browser.evaluate("document.getElementById('shown').textContent") == "relit: model + residual term"
        browser.show(layer="physical")  # the term off: the maps alone
        page = browser.read(0, 0, 64, 48)[..., :3].astype(int)
        assert np.abs(page - physical).max() <= 1
        assert "physical maps only" in browser.evaluate("document.getElementById('shown').textContent")


CURVES = {  # a film-like S curve per channel, and a grey power: torchspec.calibration.response's family
    "film": {
        "transfer": "response",
        "response": {"gamma": [1.3, 2.0, 0.9], "offset": [0.0, 0.05, 0.2], "contrast": [4.0, -3.0, 0.0]},
    },
    "power": {"transfer": "response", "response": {"gamma": [1.25], "offset": [0.0], "contrast": [0.0]}},  # one for all
}


@needs_browser
@pytest.mark.parametrize("curve", sorted(CURVES))
def test_the_page_adds_a_term_in_the_photographs_encoding_as_render_does(browser, curve):
    maps = with_term(model_maps("ward-iso", 32, 48, seed=14), 3, seed=7, size=0.3, encoding=CURVES[curve])
    term = _term(maps)
    assert term.domain.curve is not None
    srgb = ResidualTerm(term.coefficients, term.chosen, term.weight)  # the same term added in sRGB
    with served_page(browser, open_site(maps)):
        assert browser.evaluate("torchspecView.viewer.m.term_encoding.transfer") == "response"
        for light in hemisphere_lights(6, 75.0):
            browser.show(origin=True, light=light.tolist(), layer="relit")
            page = browser.read(0, 0, 48, 32)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), term=term).astype(int)
            assert np.abs(page - expected).max() <= 1, light
            other = reference_srgb(maps.svbrdf, tuple(light), term=srgb).astype(int)
            assert np.abs(other - expected).max() > 10  # the encoding matters here


@needs_browser
def test_under_a_kernel_the_term_is_taken_at_its_effective_direction(browser, tmp_path):
    maps = with_term(model_maps("ward-iso", 24, 32, seed=12, alpha=(0.2, 0.45)), 3, seed=3)
    capture = _capture(tmp_path / "c", maps, sigma=DEMO_SIGMA)
    kernel, term = capture.lights().kernel, _term(maps)
    with served_page(browser, open_site(maps, capture)):
        for light in hemisphere_lights(4, 60.0):  # as the kernel's test above: lower, the maps alone differ by 2
            state = browser.show(origin=True, light=light.tolist(), layer="relit", snap=False, compare=False)
            assert state["extended"]
            page = browser.read(0, 0, 32, 24)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel, term=term).astype(int)
            assert np.abs(page - expected).max() <= 1, light
            assert np.abs(reference_srgb(maps.svbrdf, tuple(light), kernel=kernel).astype(int) - expected).max() > 20


@needs_browser
def test_under_a_kernel_without_a_table_the_term_is_taken_at_the_nodes_mean(browser):
    maps = with_term(model_maps("ward-iso", 16, 24, seed=9, alpha=(0.2, 0.45)), 3, seed=4)
    kernel, term = _table_kernel(), _term(maps)
    site = open_site(maps)
    site.manifest.update(light_quadrature(kernel).describe())  # as a capture with this kernel gives it
    assert site.manifest["kernel_diffuse"] == []  # no table of effective directions: the nodes' sum
    with served_page(browser, site):
        for light in hemisphere_lights(2, 60.0):  # render of a tabulated kernel takes a second
            browser.show(origin=True, light=light.tolist(), layer="relit")
            page = browser.read(0, 0, 24, 16)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, tuple(light), kernel=kernel, term=term).astype(int)
            assert np.abs(page - expected).max() <= 1, light


def _near_capture(folder, maps, exposure=2.0, irradiance=0.5, last=2.0):
    """A capture of ``maps`` under 12 point lights 1.2 to 2 image widths away (the last ``last``
    away; each frame's ``position``), its photographs rendered as ``torchspec render`` renders near
    lights (block by block: torchspec.relight.render_near); and the positions ``(12, 3)``."""
    height, width = maps.svbrdf.shape
    directions = torch.tensor(hemisphere_lights(12, 75.0))
    radii = torch.cat([torch.linspace(1.2, 2.0, 12, dtype=torch.float64)[:11], torch.tensor([last]).double()])
    positions = directions * radii[:, None]
    frames = [Frame(f"f{k:02d}.exr", tuple(d.tolist()), irradiance, exposure, position=tuple(p.tolist()))
              for k, (d, p) in enumerate(zip(directions, positions, strict=True))]  # fmt: skip
    capture = Capture(folder, width, height, ("R", "G", "B"), (0.0, 0.0, 1.0), LightSpec("point"), frames)
    lights = Lights(directions, Kernel("point"), torch.full((12, 3), irradiance, dtype=torch.float64),
                    torch.full((12,), exposure, dtype=torch.float64))  # fmt: skip
    values = render_near(maps.svbrdf.to(torch.float64), lights, positions, torch.tensor([0.0, 0.0, 1.0]).double())
    return write_capture(folder, capture, values.permute(2, 3, 0, 1).float()), positions


def test_the_manifest_gives_the_near_lights_positions(tmp_path):
    maps = model_maps("ward-iso", 8, 12)
    capture, positions = _near_capture(tmp_path / "near", maps)
    manifest = open_site(maps, capture).manifest
    assert np.allclose(manifest["positions"], positions.numpy())
    assert manifest["near_block"] == near_block(8, 12, TILE_PIXELS, positions)  # render_capture's, all the lights'
    rule = {"block_angle": BLOCK_ANGLE, "least_block": LEAST_BLOCK, "most_block": math.isqrt(TILE_PIXELS)}
    assert {key: manifest[key] for key in rule} == rule  # for the page's own light
    assert np.isclose(manifest["near_radius"], positions.norm(dim=-1).median().item())
    assert "the capture's positions" in manifest["near_source"]
    distant = _capture(tmp_path / "distant", maps)
    for shown in (open_site(maps, distant).manifest, open_site(maps).manifest):  # no positions: no block
        assert shown["positions"] == [] and shown["near_radius"] is None and shown["near_block"] is None
        assert {key: shown[key] for key in rule} == rule
    # A fit that calibrated one dome radius (svbrdf.json's fit.lights): every frame at it along its direction.
    dome = {"frames": list(range(12)), "lights": {"calibrated": ["irradiance", "radius"], "radius": 2.5, "gains": []}}
    manifest = open_site(Maps(maps.svbrdf, {"fit": dome}), distant).manifest
    assert np.allclose(manifest["positions"], 2.5 * distant.directions().numpy()) and manifest["near_radius"] == 2.5
    assert manifest["near_block"] == near_block(8, 12, TILE_PIXELS, 2.5 * distant.directions())
    assert "dome radius" in manifest["near_source"]
    # On a larger image the block grows with the nearest light's distance: the capture's block is
    # its nearest light's, smaller than its farthest light's alone.
    large = near_lights(capture, {}, 450, 690)["near_block"]
    alone = [near_block(450, 690, TILE_PIXELS, positions[k : k + 1]) for k in range(12)]
    assert large == near_block(450, 690, TILE_PIXELS, positions) == min(alone) < max(alone)
    assert large > LEAST_BLOCK
    # A fit that calibrated the positions of the frames it fitted: those, the others the capture's.
    found = positions[::2] * 1.1
    fitted = {"frames": list(range(0, 12, 2)), "lights": {"calibrated": ["irradiance", "position"],
                                                          "positions": found.tolist()}}  # fmt: skip
    shown = np.array(open_site(Maps(maps.svbrdf, {"fit": fitted}), capture).manifest["positions"])
    assert np.allclose(shown[::2], found.numpy()) and np.allclose(shown[1::2], positions[1::2].numpy())
    fitted["frames"] = list(range(2, 14, 2))  # frame 12: not the capture's
    with pytest.raises(TorchspecError, match="fit.lights.positions"):
        open_site(Maps(maps.svbrdf, {"fit": fitted}), capture)


NEAR_POSITIONS = ([0.3, 0.2, 1.0], [1.2, 0.0, 0.5], [-1.4, 1.3, 0.35], [0.0, -0.6, 1.9], [0.6, -0.4, 4.4])
"""Near lights 1.1 to 2 image widths away, 70, 23, 10 and 72 degrees above the horizon (from the
centre), and one 4.4 widths away, 81 degrees above it, whose blocks in render are wider than
LEAST_BLOCK over a 69 pixel wide image (``near_block``) and do not divide it."""


def _block(height, width, position):
    """render_near's block for one light at ``position`` (torchspec.pipeline.tiling.near_block)."""
    return near_block(height, width, TILE_PIXELS, torch.tensor([position], dtype=torch.float64))


@needs_browser
@pytest.mark.parametrize("model", MODEL_TYPES)
def test_the_page_relights_under_a_near_light_as_render_does(browser, model):
    maps = model_maps(model, 45, 69, seed=3)
    site = open_site(maps)
    assert site.manifest["near_block"] is None  # no capture: the page takes render's block of its own light
    blocks = [_block(45, 69, position) for position in NEAR_POSITIONS]
    assert max(blocks) > LEAST_BLOCK and 69 % max(blocks) and 45 % max(blocks)  # narrower last blocks
    with served_page(browser, site):
        for position, block in zip(NEAR_POSITIONS, blocks, strict=True):
            at = np.array(position)
            direction, distance = at / np.linalg.norm(at), float(np.linalg.norm(at))
            # as torchspec render: one direction a block of pixels (render_near); and at each pixel
            for each in (False, True):
                shown = {"light": direction.tolist(), "distance": distance, "pixel": each, "layer": "relit"}
                state = browser.show(origin=True, **shown)
                assert np.allclose(state["position"], position, atol=1e-12) and state["block"] == (1 if each else block)
                page = browser.read(0, 0, 69, 45)[..., :3].astype(int)
                expected = reference_srgb(maps.svbrdf, None, position=position, each_pixel=each).astype(int)
                assert np.abs(page - expected).max() <= 1, (model, position, each)
            distant = reference_srgb(maps.svbrdf, tuple(direction)).astype(int)
            # the position matters (more than the tolerance: over a Lambertian surface, the farthest
            # light's falloff varies by 9 % over the image)
            assert np.abs(distant - expected).max() > (10 if distance < 4 else 1)
        state = browser.show(origin=True, distance=None)  # infinite: the distant light of the same direction
        assert state["position"] is None
        assert np.abs(browser.read(0, 0, 69, 45)[..., :3].astype(int) - distant).max() <= 1


@needs_browser
def test_under_a_near_light_the_kernel_and_the_term_follow_each_blocks_direction(browser, tmp_path):
    maps = with_term(model_maps("ward-iso", 24, 32, seed=9, alpha=(0.03, 0.2)), 3, seed=6)
    capture, _ = _near_capture(tmp_path / "c", maps)
    site = open_site(maps, capture)
    kernel = Kernel("gaussian", "projected", DEMO_SIGMA)
    site.manifest.update(light_quadrature(kernel).describe())  # as a capture with this kernel gives it
    narrow = lobe_width(maps.svbrdf) / 2 < site.manifest["kernel_spacing"]  # fixed nodes would straddle these
    assert narrow.mean() > 0.2
    term = _term(maps)
    # Where the kernel comes within about 30 degrees of the horizon, render integrates on its
    # reference nodes (the product of kernel and lobe reaches the horizon) and the page does not,
    # near or distant (the distant tests above keep within 60 degrees of the zenith): so do these
    # lights, at every pixel.
    positions = ([0.3, 0.2, 1.0], [0.6, 0.4, 1.2], [0.0, -0.6, 1.9])
    directions, _ = near_light(torch.tensor(positions, dtype=torch.float64), image_points(24, 32))
    assert float(torch.rad2deg(torch.acos(directions[..., 2])).max()) < 60.0
    with served_page(browser, site):
        for position in positions:
            direction = (np.array(position) / np.linalg.norm(position)).tolist()
            state = browser.show(origin=True, light=direction, distance=float(np.linalg.norm(position)), snap=False,
                                 compare=False, layer="relit")  # fmt: skip
            assert state["extended"] and np.allclose(state["position"], position, atol=1e-12)
            page = browser.read(0, 0, 32, 24)[..., :3].astype(int)
            expected = reference_srgb(maps.svbrdf, None, kernel=kernel, term=term, position=position).astype(int)
            difference = np.abs(page - expected).max(-1)
            assert difference[~narrow].max() <= 1 and difference[narrow].max() <= 1, position
            distant = reference_srgb(maps.svbrdf, tuple(direction), kernel=kernel, term=term).astype(int)
            assert np.abs(distant - expected).max() > 10


@needs_browser
def test_on_a_near_capture_the_light_snaps_to_a_frames_position(browser, tmp_path):
    maps = model_maps("ward-iso", 24, 32, seed=5)
    capture, positions = _near_capture(tmp_path / "c", maps, exposure=2.0, irradiance=0.5, last=12.0)
    write_svbrdf(tmp_path / "maps", maps)
    predicted = render_capture(tmp_path / "maps", capture.root, None, dtype=torch.float64)["predicted"]
    site = open_site(maps, capture)
    with served_page(browser, site):
        target = capture.directions()[7]
        state = browser.show(origin=True, light=(target[:2] + 0.02).tolist(), layer="relit")
        assert state["distance"] == site.manifest["near_radius"] != np.linalg.norm(state["position"])
        assert state["frame"] == 7 and np.allclose(state["position"], positions[7].tolist(), atol=1e-12)
        assert state["block"] == site.manifest["near_block"] == near_block(24, 32, TILE_PIXELS, positions)
        relit = browser.read(0, 0, 32, 24)[..., :3].astype(int)
        photo = browser.read(state["panels"][1]["x"], 0, 32, 24)[..., :3].astype(int)
        rendered = (predicted[7] / (2.0 * 0.5)).permute(1, 2, 0).clamp(0.0, 1.0)  # torchspec render, at unit light
        assert np.abs(relit - torch.round(encode(rendered) * 255).numpy()).max() <= 1
        assert np.abs(photo - _jpeg_shown(site, 7)).max() <= 1  # the photograph's JPEG tile, at unit light
        assert "frame 7's position (the capture's positions)" in browser.evaluate(
            "document.getElementById('near').textContent"
        )
        distant = reference_srgb(maps.svbrdf, tuple(target.tolist())).astype(int)
        assert np.abs(distant - relit).max() > 10  # the frame's light taken as distant: another image
        # The distance control's last step: a distant light, snapped to the frame's direction.
        browser.evaluate("(() => { const d = document.getElementById('distance'); d.value = d.max; "
                         "d.dispatchEvent(new Event('input')); })()")  # fmt: skip
        state = browser.show(origin=True)  # the control's label changed: the canvas may have moved
        assert state["position"] is None and state["frame"] == 7
        assert np.abs(browser.read(0, 0, 32, 24)[..., :3].astype(int) - distant).max() <= 1
        # The farthest frame, 12 widths away: render_capture lights it in the capture's blocks (its
        # nearest light's), not in the wider ones of that light alone; which the page's own light
        # there takes.
        far = capture.directions()[11].tolist()
        alone = near_block(24, 32, TILE_PIXELS, positions[11:])
        state = browser.show(origin=True, light=far, distance=2.0, snap=True)
        assert state["frame"] == 11 and np.allclose(state["position"], positions[11].tolist(), atol=1e-12)
        assert state["block"] == site.manifest["near_block"] < alone
        rendered = (predicted[11] / (2.0 * 0.5)).permute(1, 2, 0).clamp(0.0, 1.0)
        relit = browser.read(0, 0, 32, 24)[..., :3].astype(int)
        assert np.abs(relit - torch.round(encode(rendered) * 255).numpy()).max() <= 1
        block = state["block"]
        assert f"block of {block} x {block} pixels, as torchspec render takes it for the capture's lights" in (
            browser.evaluate("document.getElementById('near').textContent")
        )
        state = browser.show(origin=True, light=far, distance=12.0, snap=False)
        assert np.allclose(state["position"], positions[11].tolist(), atol=1e-12) and state["block"] == alone


@needs_browser
def test_the_pages_block_for_its_own_light_is_renders(browser, tmp_path):
    """The block the page lights a light of its own in (torchspec view's JavaScript) is
    ``near_block`` of that one light, in landscape and portrait images: at LEAST_BLOCK, in between,
    and at a tile's side; a frame's direction at a chosen distance, in a capture without positions,
    is such a light too."""
    # [0, 2.13, 3] and [0, 2.5, 5]: the image's half height (not half its width) puts them on the
    # floor's other side, in landscape and in portrait
    free = ([0.3, 0.2, 1.0], [0.6, -0.4, 4.4], [0.0, 2.13, 3.0], [0.0, 2.5, 5.0], [-2.0, 0.3, 9.0], [1.5, 1.0, 25.0],
            [3.0, -2.0, 80.0])  # fmt: skip
    for height, width in ((45, 69), (69, 45)):
        maps = model_maps("ward-iso", height, width, seed=2)
        blocks = []
        with served_page(browser, open_site(maps)):
            for position in free:
                at = np.array(position)
                shown = {
                    "light": (at / np.linalg.norm(at)).tolist(),
                    "distance": float(np.linalg.norm(at)),
                    "pixel": False,
                }
                state = browser.show(**shown)
                assert np.allclose(state["position"], position, atol=1e-12)
                blocks.append(_block(height, width, state["position"]))
                assert state["block"] == blocks[-1], (height, width, position)
                assert f"block of {blocks[-1]} x {blocks[-1]} pixels" in browser.evaluate(
                    "document.getElementById('near').textContent"
                )
            assert browser.show(distance=None)["block"] is None and browser.show(distance=2.0, pixel=True)["block"] == 1
        assert blocks[0] == LEAST_BLOCK and blocks[-1] == math.isqrt(TILE_PIXELS)  # the least, a tile's side
        assert len({block for block in blocks if LEAST_BLOCK < block < math.isqrt(TILE_PIXELS)}) >= 2  # between
    distant = _capture(tmp_path / "c", maps)  # 69 x 45, directions without positions
    with served_page(browser, open_site(maps, distant)):
        state = browser.show(light=distant.directions()[3].tolist(), distance=30.0, snap=True, pixel=False)
        assert state["frame"] == 3 and np.allclose(state["position"], 30.0 * distant.directions()[3].numpy())
        assert state["block"] == _block(69, 45, state["position"]) > LEAST_BLOCK


def _lazy_and_in_memory(folder):
    """A map folder's pyramid read lazily (64-texel tiles, levels 0 and 1 made on demand, 2 in memory
    from a pass over the rows, 3 reduced from it) and the pyramid of its maps read whole."""
    lazy = open_site(folder, tile=64, keep_texels=5000).pyramid
    return lazy, Pyramid.of_maps(read_svbrdf(folder), tile=64)


def test_tiles_read_lazily_equal_the_tiles_in_memory_bit_for_bit(tmp_path):
    write_svbrdf(tmp_path / "maps", with_term(model_maps("ward-dual", 200, 300, seed=13), 2, seed=5))
    lazy, whole = _lazy_and_in_memory(tmp_path / "maps")
    assert (
        lazy.kept == 2
        and whole.kept == 0
        and lazy.levels == whole.levels == [(200, 300), (100, 150), (50, 75), (25, 38)]
    )
    assert lazy.textures == whole.textures and len(lazy.textures) == len(TEXTURES) + 4
    for level in range(4):
        rows, columns = whole.grid(level)
        for row in range(rows):
            for column in range(columns):
                assert lazy.tile(level, row, column) == whole.tile(level, row, column), (level, row, column)


def test_a_tile_request_reads_only_its_rows(tmp_path, monkeypatch):
    write_svbrdf(tmp_path / "maps", model_maps("ward-iso", 200, 300, seed=14))
    lazy = _lazy_and_in_memory(tmp_path / "maps")[0]
    lazy.made[lazy.kept].wait()  # the background pass over the rows is done
    read, real = [], svbrdf_io._read_band
    monkeypatch.setattr(
        svbrdf_io, "_read_band", lambda path, channels, rows: read.append(rows) or real(path, channels, rows)
    )
    lazy.tile(0, 1, 2)
    assert read and set(read) == {(64, 128)}  # every map's file, those rows only
    read.clear()
    lazy.tile(0, 1, 0)  # the same rows: kept
    lazy.tile(2, 0, 0)  # a level held in memory
    assert read == []
    lazy.tile(1, 1, 1)  # level 1: rows 128..199 of level 0
    assert set(read) == {(128, 192), (192, 200)}


def test_a_tile_of_a_level_not_yet_made_is_asked_again_later(tmp_path):
    write_svbrdf(tmp_path / "maps", model_maps("ward-iso", 200, 300, seed=15))
    site = open_site(tmp_path / "maps", tile=64, keep_texels=5000)
    site.pyramid.made[3].wait()
    site.pyramid.made[3].clear()  # as while the background pass runs
    server = serve(site)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/tiles"
    try:
        with pytest.raises(urllib.error.HTTPError) as answer:
            urllib.request.urlopen(f"{url}/3/0_0.bin", timeout=10)
        assert answer.value.code == 503 and answer.value.headers["Retry-After"] == "1"
        with urllib.request.urlopen(f"{url}/0/2_3.bin", timeout=10) as tile:  # level 0: read on demand
            assert tile.read() == site.pyramid.tile(0, 2, 3)
        site.pyramid.made[3].set()
        with urllib.request.urlopen(f"{url}/3/0_0.bin", timeout=10) as tile:
            assert tile.read() == site.pyramid.tile(3, 0, 0)
    finally:
        server.shutdown()


@needs_browser
def test_the_page_asks_again_for_a_tile_not_yet_made(browser, tmp_path):
    maps = model_maps("ward-iso", 40, 300, seed=16)
    write_svbrdf(tmp_path / "maps", maps)
    site = open_site(tmp_path / "maps")  # levels (40, 300) and (20, 150)
    site.pyramid.made[1].wait()
    site.pyramid.made[1].clear()  # as while the background pass runs
    with served_page(browser, site):
        browser.show(layer="normal", zoom=0.5, centre=[150, 20])  # level 1
        # the tiles' states once one was answered 503 (to be asked again), polled: the answer takes the
        # server's 0.5 s wait plus however long a loaded machine needs (at most 30 s here)
        waited = """new Promise(resolve => {
            const start = performance.now();
            const poll = () => {
                const states = [...torchspecView.viewer.tiles.values()].map(t => t.state);
                if (states.includes("later") || performance.now() - start > 30000) resolve(states);
                else setTimeout(poll, 20);
            };
            poll();
        })"""
        assert "later" in browser.evaluate(waited)
        site.pyramid.made[1].set()
        browser.evaluate("torchspecView.settle()")  # resolves once the level's tile is drawn
        assert browser.evaluate("torchspecView.viewer.tiles.get('tiles/1/0_0.bin').state") == "ready"
        state = browser.show()
        x, y = state["width"] // 2 - 75, state["height"] // 2 - 10  # the image's top left (150 x 20 on screen)
        page = browser.read(x + 1, y + 1, 148, 18)[..., :3].astype(int)
        assert (np.abs(page - 32).max(-1) > 0).all()  # no background (grey 32) where the image is
