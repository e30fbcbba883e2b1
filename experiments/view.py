"""The viewer (``torchspec view``) in headless Chromium, as a person's browser shows it.

1. Accuracy: the page's relit image against :func:`torchspec.render` (float64) of the same maps
   and point light, both 8-bit sRGB, for ``lights`` lights over the hemisphere, on synthetic maps of
   every model type (and a sharp-lobe set) and on the fits listed in the config. Largest difference
   in 8-bit steps, over all pixels and apart on the pixels whose lobe is narrower than a pixel's
   footprint (the mirror direction moves by more than the lobe's width, ``2 * angle(n, n') >
   min(alpha)``, to a neighbouring pixel), and the pixels where torch's own float32 render differs
   from float64 by more than a step (ill-conditioned in the page's float32). A fit whose capture
   has an extended kernel is also compared under that kernel (the page's default then) with
   render under the same kernel and centre (row ``NAME kernel``): the share of pixel-lights beyond
   one step, and apart the pixels whose lobe's half width at half maximum is below the fixed
   nodes' spacing (``torchspec.view.light``).
2. Screenshots of the page on each fit: relit at a grazing light, the normal layer, the quality
   layer (PNG in the output folder).
3. Speed on synthetic ``big x big`` maps: the server's start, the time from loading the page to
   its first image (the coarsest level), to the whole image fitted to the window (every tile of
   the level that matches the zoom), then to every tile drawn at full resolution (1:1), and the frame
   rate while the light moves: real mouse drags sent through the DevTools protocol (frames drawn
   per second) and the page's own loop (each frame finished before the next), the loop also
   under a projected Gaussian kernel of std ``speed_kernel_sigma`` (its 64 nodes a pixel).

    python experiments/view.py [--config experiments/configs/view.yaml] [--output experiments/results]

The fits of the config are made by ``torchspec demo -o D`` (``D/maps``, ``D/capture``) and by ``torchspec import
../shared/data/rti/realrti-item3 -o C && torchspec fit C -o F``.
"""

from __future__ import annotations

import math
import os
import threading
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_svbrdf
from torchspec.model.lights import Kernel
from torchspec.view import open_site, serve
from torchspec.view.browser import Browser
from torchspec.view.check import MODEL_TYPES, hemisphere_lights, lobe_width, model_maps, reference_srgb
from torchspec.view.light import light_quadrature


@dataclass(frozen=True)
class Settings:
    size: tuple[int, int]  # the synthetic maps, height and width
    lights: int
    max_zenith_deg: float
    sharp_alpha: tuple[float, float]  # the sharp-lobe set's alpha range
    fits: tuple[dict, ...]  # {name, maps, capture (or null)}: paths relative to the repository
    grazing_elevation_deg: float
    viewport: tuple[int, int]
    big: int
    drag_moves: int
    bench_frames: int
    speed_kernel_sigma: float
    speed_kernel_frames: int


@contextmanager
def page(browser: Browser, site):
    server = serve(site)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        start = time.perf_counter()
        browser.open(f"http://127.0.0.1:{server.server_address[1]}/")
        yield time.perf_counter() - start
    finally:
        server.shutdown()


def narrow_lobes(svbrdf) -> np.ndarray:
    """``(H, W)``: pixels whose lobe is narrower than the mirror direction's step to a neighbour."""
    n = svbrdf.normal.double()
    step = torch.zeros(n.shape[:2], dtype=torch.float64)
    for shift, dim in ((1, 0), (-1, 0), (1, 1), (-1, 1)):
        cos = (n * torch.roll(n, shift, dim)).sum(-1).clamp(-1, 1)
        step = torch.maximum(step, torch.acos(cos))
    alpha = svbrdf.roughness.double().amin(-1)
    lobe = (svbrdf.specular.amax(-1) > 0) & (alpha > 0)
    return (lobe & (2 * step > alpha)).numpy()


def compare(browser: Browser, svbrdf, view, lights, kernel=None, spacing: float = 0.0) -> dict:
    """The page against render on every light (a point, or ``kernel`` about the same centre):
    largest differences and pixel counts; under a kernel also apart on the pixels whose lobe's half
    width at half maximum is below the fixed nodes' ``spacing``."""
    height, width = svbrdf.shape
    narrow = narrow_lobes(svbrdf)
    between = lobe_width(svbrdf, tuple(view)) / 2 < spacing
    worst, worst_narrow, worst_rest, worst_between, above, ill = 0, 0, 0, 0, 0, 0
    for light in lights:
        browser.show(origin=True, light=light.tolist(), layer="relit", snap=False, compare=False, exposure=1,
                     extended=kernel is not None)  # fmt: skip
        shown = browser.read(0, 0, width, height)[..., :3].astype(int)
        expected = reference_srgb(svbrdf, tuple(light), tuple(view), kernel=kernel).astype(int)
        single = reference_srgb(svbrdf, tuple(light), tuple(view), dtype=torch.float32, kernel=kernel).astype(int)
        diff = np.abs(shown - expected).max(-1)
        worst = max(worst, int(diff.max()))
        worst_narrow = max(worst_narrow, int(diff[narrow].max(initial=0)))
        worst_rest = max(worst_rest, int(diff[~narrow].max(initial=0)))
        worst_between = max(worst_between, int(diff[between].max(initial=0)))
        above += int((diff > 1).sum())
        ill += int((np.abs(single - expected).max(-1) > 1).sum())
    extended = {}
    if kernel is not None:
        extended = {
            "kernel": kernel.kind,
            "sigma": kernel.sigma,
            "node_spacing": spacing,
            "lobe_between_nodes_pixels": int(between.sum()),
            "max_diff_8bit_lobe_between_nodes": worst_between,
            "share_pixel_lights_above_1": above / (height * width * len(lights)),
        }
    return {
        "pixels": height * width,
        "lights": len(lights),
        "max_diff_8bit": worst,
        "max_diff_8bit_narrow_lobe": worst_narrow,
        "max_diff_8bit_other": worst_rest,
        "narrow_lobe_pixels": int(narrow.sum()),
        "pixel_lights_above_1": above,
        "pixel_lights_float32_ill_conditioned": ill,
        **extended,
    }


def accuracy(settings: Settings, browser: Browser) -> dict:
    lights = hemisphere_lights(settings.lights, settings.max_zenith_deg)
    rows = {}
    for model in MODEL_TYPES:
        for label, alpha in (("", None), (" sharp", settings.sharp_alpha)):
            if model == "diffuse" and alpha is not None:
                continue
            maps = model_maps(model, *settings.size, seed=11, alpha=alpha)
            with page(browser, open_site(maps)):
                rows[model + label] = compare(browser, maps.svbrdf, (0.0, 0.0, 1.0), lights)
    for fit in settings.fits:
        folder = ROOT / fit["maps"]
        if not (folder / "svbrdf.json").exists():
            print(f"skipped {fit['name']}: no {folder}")
            continue
        maps = read_svbrdf(folder)
        site = open_site(maps, None if fit.get("capture") is None else ROOT / fit["capture"])
        with page(browser, site):
            rows[fit["name"]] = compare(browser, maps.svbrdf, site.manifest["view"], lights)
            if site.manifest["kernel_nodes"]:  # the capture's extended kernel, as the page shows it by default
                kernel, spacing = site.capture.lights().kernel, site.manifest["kernel_spacing"]
                rows[f"{fit['name']} kernel"] = compare(browser, maps.svbrdf, site.manifest["view"], lights, kernel,
                                                        spacing)  # fmt: skip
    return rows


def screenshots(settings: Settings, output: Path) -> dict:
    shots = {}
    elevation = math.radians(settings.grazing_elevation_deg)
    with Browser(*settings.viewport) as browser:
        for fit in settings.fits:
            folder = ROOT / fit["maps"]
            if not (folder / "svbrdf.json").exists():
                continue
            capture = None if fit.get("capture") is None else ROOT / fit["capture"]
            with page(browser, open_site(folder, capture, title=fit["name"])):
                light = [-math.cos(elevation) * math.sqrt(0.5), math.cos(elevation) * math.sqrt(0.5)]
                shown = browser.show(light=light, layer="relit", snap=False)  # the photograph: the nearest frame
                for layer in ("relit", "normal", "quality"):
                    browser.show(layer=layer)
                    path = output / f"view_{fit['name']}_{layer}.png"
                    browser.screenshot(path)
                    shots[f"{fit['name']} {layer}"] = path.name
                shots[f"{fit['name']} grazing light"] = shown["light"]
    return shots


def speed(settings: Settings) -> dict:
    big = settings.big
    maps = model_maps("ward-aniso", big, big, seed=2)
    start = time.perf_counter()
    site = open_site(maps)
    opened = time.perf_counter() - start
    site.manifest.update(light_quadrature(Kernel("gaussian", sigma=settings.speed_kernel_sigma)).describe())
    del maps
    with Browser(*settings.viewport) as browser, page(browser, site) as loaded:
        browser.show(extended=False)  # a point light but for the kernel's loop
        start = time.perf_counter()
        browser.evaluate("torchspecView.settle()")
        settled = loaded + time.perf_counter() - start
        first = browser.evaluate("torchspecView.viewer.firstImage") / 1000
        level = browser.evaluate("torchspecView.viewer.level()")
        start = time.perf_counter()
        state = browser.show(zoom=1, centre=[big / 2, big / 2])
        browser.evaluate("torchspecView.settle()")
        full = time.perf_counter() - start
        shown = state["width"] * state["height"]
        bench = browser.evaluate(f"torchspecView.bench({settings.bench_frames}, 1.0)")
        browser.show(extended=True)
        bench_kernel = browser.evaluate(f"torchspecView.bench({settings.speed_kernel_frames}, 1.0)")
        browser.show(extended=False)
        box = browser.evaluate("(() => { const r = torchspecView.viewer.canvas.getBoundingClientRect(); "
                               "return [r.left, r.top, r.width, r.height]; })()")  # fmt: skip
        cx, cy, radius = box[0] + box[2] / 2, box[1] + box[3] / 2, min(box[2], box[3]) * 0.4
        frames0 = browser.evaluate("torchspecView.viewer.frames")
        start = time.perf_counter()
        browser.call(
            "Input.dispatchMouseEvent", type="mousePressed", x=cx, y=cy, button="left", buttons=1, clickCount=1
        )
        for i in range(settings.drag_moves):
            phi = 2 * math.pi * i / settings.drag_moves
            x, y = cx + radius * math.cos(phi), cy + radius * math.sin(phi)
            browser.call("Input.dispatchMouseEvent", type="mouseMoved", x=x, y=y, button="left", buttons=1)
        browser.evaluate("new Promise(r => requestAnimationFrame(() => r(0)))")
        elapsed = time.perf_counter() - start
        browser.call("Input.dispatchMouseEvent", type="mouseReleased", x=cx, y=cy, button="left", buttons=0)
        frames = browser.evaluate("torchspecView.viewer.frames") - frames0
    return {
        "load_average_1min": os.getloadavg()[0],  # the machine is shared: what else ran
        "pixels": big * big,
        "server_start_s": opened,
        "first_image_s": first,
        "fit_view_settled_s": settled,
        "fit_view_level": level,
        "full_resolution_s": full,
        "canvas_pixels": shown,
        "drag_events": settings.drag_moves,
        "drag_seconds": elapsed,
        "drag_frames_per_s": frames / elapsed,
        "loop_frames_per_s": bench,
        "loop_frames_per_s_kernel": bench_kernel,
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "view.yaml", argv)
    settings = load_config(args.config, Settings)
    args.output.mkdir(parents=True, exist_ok=True)
    with Browser(1280, 800) as browser:
        rows = accuracy(settings, browser)
    print(f"page vs torchspec render, {settings.lights} point lights, 8-bit sRGB steps")
    print(
        f"{'maps':>18s} {'pixels':>7s} {'max':>4s} {'narrow':>7s} {'max@narrow':>10s} {'max@rest':>8s} "
        f"{'>1':>5s} {'f32ill':>6s}"
    )
    for name, r in rows.items():
        print(f"{name:>18s} {r['pixels']:7d} {r['max_diff_8bit']:4d} {r['narrow_lobe_pixels']:7d} "
              f"{r['max_diff_8bit_narrow_lobe']:10d} {r['max_diff_8bit_other']:8d} {r['pixel_lights_above_1']:5d} "
              f"{r['pixel_lights_float32_ill_conditioned']:6d}")  # fmt: skip
        if "kernel" in r:
            print(f"{'':>18s} under the capture's {r['kernel']} kernel (sigma {r['sigma']:g}): "
                  f"{r['share_pixel_lights_above_1']:.2e} of pixel-lights beyond 1 step; "
                  f"{r['lobe_between_nodes_pixels']} pixels whose lobe's half width is below the fixed nodes' spacing "
                  f"{r['node_spacing']:.3f}: max {r['max_diff_8bit_lobe_between_nodes']}")  # fmt: skip
    shots = screenshots(settings, args.output)
    timing = speed(settings)
    print(f"{settings.big}x{settings.big} maps: server start {timing['server_start_s']:.1f} s, first image "
          f"{timing['first_image_s']:.2f} s, the whole image {timing['fit_view_settled_s']:.2f} s, full resolution "
          f"(1:1) {timing['full_resolution_s']:.2f} s more; dragging "
          f"{timing['drag_frames_per_s']:.1f} frames/s, page loop {timing['loop_frames_per_s']:.1f} frames/s "
          f"({timing['loop_frames_per_s_kernel']:.2f} under a Gaussian kernel) "
          f"({timing['canvas_pixels']} canvas pixels)")  # fmt: skip
    with Browser(64, 64) as browser:
        version = browser.call("Browser.getVersion")["product"]
    result = {
        "settings": asdict(settings),
        "browser": version,
        "accuracy": rows,
        "screenshots": shots,
        "speed": timing,
    }
    name = Path(args.config).stem
    write_json(args.output / f"{name}.json", result)
    print(f"wrote {args.output / f'{name}.json'}")
    return result


if __name__ == "__main__":
    main()
