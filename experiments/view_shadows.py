"""The viewer's cast shadows (``torchspec view`` of maps with a height, issue 39) in headless Chromium.

1. A fit with cast shadows (the config's ``fit``: its maps and capture), at each captured light:
   - the page's relit image (its residual term and shadows on) against the photograph the page
     shows beside it (its photo panel: the frame over exposure and irradiance), 8-bit PSNR, with
     the shadows on and off: what the shadows add to the viewer;
   - the page's physical layer against :func:`torchspec.view.check.reference_srgb` of the same
     maps with the visibility at the pixels' centres (what the page approximates: its horizons
     interpolated, float16, sparser far samples) and over each pixel's footprint as ``torchspec
     render`` takes it (``footprint=2``): the share of pixels within one 8-bit step, the share
     more than 10 steps off and the largest difference.
2. Speed, on synthetic reliefs of ``sizes`` (:func:`torchspec.view.check.with_height`, ``peak``
   pixels high): the horizon maps' making (:func:`torchspec.view.shadows.horizon_planes`, the CPU's
   ``threads``), and the page's frame rate with the shadows on and off (its own loop,
   ``torchspecView.bench``) on the largest.

    python experiments/view_shadows.py [--config experiments/configs/view_shadows.yaml] [--output experiments/results]

The fit: ``torchspec import ../shared/data/rti/synthrti-object3-m1 -o C && torchspec fit C -o F
--shadows on --downsample 4`` (``C`` and ``F`` in the config; missing: part 1 is skipped).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _common import ROOT, parse_args
from view import page

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.relight import softness_of
from torchspec.view import open_site
from torchspec.view.browser import Browser
from torchspec.view.check import model_maps, reference_srgb, with_height
from torchspec.view.shadows import AZIMUTHS, horizon_planes, view_reach


@dataclass(frozen=True)
class Settings:
    fit: dict | None  # {maps, capture}: paths relative to the repository (or absolute); missing: skipped
    viewport: tuple[int, int]
    sizes: tuple[int, ...]  # synthetic reliefs, size x size
    peak: float
    threads: int
    frames: int


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10.0 * math.log10(255.0**2 / max(mse, 1e-12))


def on_fit(browser: Browser, maps_dir: Path, capture_dir: Path) -> dict:
    maps = read_svbrdf(maps_dir)
    capture = read_capture(capture_dir)
    site = open_site(maps_dir, capture)
    height, width = maps.svbrdf.shape
    shadows = (maps.extra["height"], maps.extra.get("indirect"), softness_of(maps))
    rows = {"on": [], "off": []}
    within = {"centre": [], "footprint": []}
    over = {"centre": [], "footprint": []}
    worst = {"centre": 0, "footprint": 0}
    with page(browser, site):
        for k, light in enumerate(site.manifest["lights"]):
            for state in ("on", "off"):
                shown = browser.show(origin=True, light=light[:2], snap=True, compare=True, layer="relit",
                                     shadows=state == "on")  # fmt: skip
                assert shown["frame"] == k, (k, shown["frame"])
                relit = browser.read(0, 0, width, height)[..., :3]
                photo = browser.read(shown["panels"][1]["x"], 0, width, height)[..., :3]
                rows[state].append(psnr(relit, photo))
            browser.show(origin=True, layer="physical", shadows=True, compare=False)
            physical = browser.read(0, 0, width, height)[..., :3].astype(int)
            for name, footprint in (("centre", 1), ("footprint", 2)):
                expected = reference_srgb(maps.svbrdf, tuple(light), shadows=shadows, footprint=footprint).astype(int)
                difference = np.abs(physical - expected).max(-1)
                within[name].append(float((difference <= 1).mean()))
                over[name].append(float((difference > 10).mean()))
                worst[name] = max(worst[name], int(difference.max()))
    lowest = int(np.argmin([light[2] for light in site.manifest["lights"]]))
    return {
        "maps": str(maps_dir),
        "size": [height, width],
        "lights": len(site.manifest["lights"]),
        "depth": (maps.meta.get("height") or {}).get("depth"),
        "softness_deg": math.degrees(shadows[2]),
        "page_vs_photo_psnr_db": {state: float(np.mean(values)) for state, values in rows.items()},
        "page_vs_photo_psnr_db_lowest_light": {state: values[lowest] for state, values in rows.items()},
        "physical_within_1_step_share": {name: float(np.mean(values)) for name, values in within.items()},
        "physical_over_10_steps_share": {name: float(np.mean(values)) for name, values in over.items()},
        "physical_max_diff_8bit": worst,
    }


def speed(browser: Browser, sizes, peak: float, threads: int, frames: int) -> dict:
    torch.set_num_threads(threads)
    rows = []
    for size in sizes:
        maps = with_height(model_maps("ward-iso", size, size, seed=1), seed=2, peak=peak)
        height = maps.extra["height"]
        reach = view_reach(height)
        start = time.perf_counter()
        horizon_planes(height, 0, size, reach)
        seconds = time.perf_counter() - start
        per = seconds / size**2 * 1e6
        rows.append({"size": size, "reach_px": reach, "seconds": seconds, "seconds_per_megapixel": per})
    site = open_site(maps)
    fps = {}
    with page(browser, site):
        browser.evaluate("torchspecView.settle()")
        for state in (True, False):
            browser.show(origin=True, shadows=state, layer="relit")
            browser.evaluate("torchspecView.settle()")
            fps["on" if state else "off"] = browser.evaluate(f"torchspecView.bench({frames}, 1.0)")
    return {"azimuths": AZIMUTHS, "threads": threads, "horizons": rows, "page_fps": fps, "page_size": sizes[-1]}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "view_shadows.yaml", argv)
    settings = load_config(args.config, Settings)
    out = {"settings": asdict(settings)}
    with Browser(*settings.viewport) as browser:
        fit = settings.fit
        if fit and all((ROOT / fit[key]).exists() for key in ("maps", "capture")):
            out["fit"] = on_fit(browser, ROOT / fit["maps"], ROOT / fit["capture"])
        out["speed"] = speed(browser, settings.sizes, settings.peak, settings.threads, settings.frames)
    args.output.mkdir(parents=True, exist_ok=True)
    write_json(args.output / "view_shadows.json", out)
    print(out)
    return out


if __name__ == "__main__":
    main()
