"""``torchspec view`` on a very large fit: how soon it shows, and the server's memory.

Synthesizes a fit's map folder of ``size`` (height, width) pixels, written band by band of
``band_rows`` rows through OpenEXR's scanline writer (the script never holds a whole map): the maps
(normal, diffuse, specular, roughness), the extra maps the viewer shows (model, quality, flags, the
standard deviations) and one it does not read (``residual``), smooth patterns with a fine texture,
float32, ZIP. Then runs ``python -m torchspec view FOLDER`` as its own process and, in headless
Chromium, measures:

- the server's start (the process launched until it prints its address: Python's imports, the
  folder's headers and a sample of its rows);
- a page opened at the fitted view: its first image (the coarsest level, made by the server's
  background pass over the rows), from the page's navigation; the view settled (every tile of the
  level that matches the zoom); then full resolution at 1:1 about ``place`` (every level-0 tile the
  window shows drawn);
- a page opened on a new server (``--no-cache``) and sent at once to 1:1 about ``place`` (its
  tiles read on demand while the background pass runs): from the page's navigation until every
  level-0 tile is drawn;
- reopening: a third server on the same maps once the first has cached the coarse levels
  (``FOLDER/.torchspec-view/``, removed before the first): its start, the overview (the coarsest
  level's tile) served, from the process's launch, then a page's first image of the whole painting
  and the fitted view settled, from its navigation;
- each server process's peak resident memory (``VmHWM``) and its resident memory, and the load
  average (1, 5, 15 min) at the start and end of each session.

    python experiments/view_large.py [--config experiments/configs/view_large.yaml] [--output experiments/results]
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.pipeline.flags import FLAGS, UNTRUSTED, bit
from torchspec.pipeline.settings import MODEL_CODES
from torchspec.view import cache
from torchspec.view.browser import Browser
from torchspec.view.tiles import levels_for


@dataclass(frozen=True)
class Settings:
    size: tuple[int, int]  # height, width of the synthetic fit
    band_rows: int  # rows written at a time
    folder: str  # where the maps are written (kept: reused when its svbrdf.json says the same size)
    viewport: tuple[int, int]
    place: tuple[float, float]  # the 1:1 view's centre, as fractions of the width and height


MAPS = {  # file: channels
    "normal": ("X", "Y", "Z"),
    "diffuse": ("R", "G", "B"),
    "specular": ("R", "G", "B"),
    "roughness": ("X", "Y"),
    "model": ("Y",),
    "quality": ("Y",),
    "flags": ("Y",),
    "std_normal_deg": ("Y",),
    "std_diffuse": ("R", "G", "B"),
    "std_specular": ("R", "G", "B"),
    "std_roughness": ("X", "Y"),
    "residual": ("R", "G", "B"),  # a fit's map that the viewer does not read
}


def band(first: int, rows: int, width: int, height: int) -> dict[str, np.ndarray]:
    """Every map's channels over rows ``first`` to ``first + rows - 1``, float32 ``(rows, W)``."""
    y = (np.arange(first, first + rows, dtype=np.float32)[:, None] / height) * np.ones((1, width), np.float32)
    x = np.arange(width, dtype=np.float32)[None, :] / width * np.ones((rows, 1), np.float32)
    fine = np.sin(np.float32(2000.0) * x) * np.cos(np.float32(1700.0) * y)  # brush-stroke scale texture
    gx, gy = 0.3 * np.sin(9 * x + 4 * y) + 0.05 * fine, 0.3 * np.cos(7 * y - 3 * x) + 0.05 * fine
    norm = np.sqrt(1 + gx * gx + gy * gy)
    out = {"normal": (-gx / norm, -gy / norm, 1 / norm)}
    out["diffuse"] = tuple(0.45 + 0.35 * np.sin(f * x + g * y) + 0.05 * fine for f, g in ((5, 2), (3, 6), (8, 1)))
    out["specular"] = tuple(0.1 + 0.08 * np.cos(3 * x + 5 * y) + 0 * fine for _ in range(3))
    alpha = 0.15 + 0.1 * np.sin(4 * x * y + 1) + 0.02 * fine
    out["roughness"] = (alpha, alpha)
    out["model"] = (np.where(alpha > 0.15, 1.0, 2.0).astype(np.float32),)
    out["quality"] = (0.5 + 0.5 * np.cos(6 * x) * np.sin(5 * y),)
    out["flags"] = (np.where(fine > 0.95, float(bit(UNTRUSTED[0])), 0.0).astype(np.float32),)
    out["std_normal_deg"] = (0.5 + 0.3 * np.abs(fine),)
    out["std_diffuse"] = tuple(0.01 + 0.005 * np.abs(fine) for _ in range(3))
    out["std_specular"] = tuple(0.02 + 0.01 * np.abs(fine) for _ in range(3))
    out["std_roughness"] = (0.01 + 0.005 * np.abs(fine), 0.01 + 0.005 * np.abs(fine))
    out["residual"] = tuple(0.001 * fine for _ in range(3))
    return {name: tuple(np.ascontiguousarray(c, dtype=np.float32) for c in value) for name, value in out.items()}


def synthesize(folder: Path, height: int, width: int, rows: int) -> float:
    """Write the maps (band by band) and ``svbrdf.json`` (last); returns the seconds it took."""
    import Imath
    import OpenEXR

    meta = folder / "svbrdf.json"
    if meta.exists() and json.loads(meta.read_text()).get("synthetic_size") == [height, width]:
        return 0.0
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    files = {}
    for name, channels in MAPS.items():
        header = OpenEXR.Header(width, height)
        header["channels"] = {c: Imath.Channel(Imath.PixelType(Imath.PixelType.FLOAT)) for c in channels}
        header["compression"] = Imath.Compression(Imath.Compression.ZIP_COMPRESSION)
        files[name] = OpenEXR.OutputFile(str(folder / f"{name}.exr"), header)
    for first in range(0, height, rows):
        count = min(rows, height - first)
        for name, planes in band(first, count, width, height).items():
            files[name].writePixels({c: p.tobytes() for c, p in zip(MAPS[name], planes, strict=True)}, count)
    for file in files.values():
        file.close()
    document = {
        "format": "torchspec.svbrdf",
        "version": 1,
        "model": "ward",
        "model_codes": list(MODEL_CODES),
        "flag_bits": {name: bit(name) for name in FLAGS},
        "untrusted_flags": list(UNTRUSTED),
        "synthetic_size": [height, width],
    }
    meta.write_text(json.dumps(document))
    return time.perf_counter() - start


def memory(pid: int) -> dict:
    """The process's peak and current resident memory, MB."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return {key: int(fields[name].split()[0]) / 1024 for key, name in (("peak_rss_mb", "VmHWM"), ("rss_mb", "VmRSS"))}


def one_to_one(browser: Browser, settings: Settings) -> float:
    height, width = settings.size
    centre = [settings.place[0] * width, settings.place[1] * height]
    start = time.perf_counter()
    browser.show(zoom=1, centre=centre)
    # every level-0 tile of the view drawn (the coarsest level's tile, drawn under them while they
    # load, may still be on its way: it waits for the server's background pass)
    browser.evaluate("new Promise(r => { const v = torchspecView.viewer, c = () => v.complete && !v.pending ? "
                     "r(0) : setTimeout(c, 5); setTimeout(c, 0); })")  # fmt: skip
    return time.perf_counter() - start


@contextmanager
def server(folder: Path, *options: str):
    """``torchspec view FOLDER [options]`` as its own process: ``(url, seconds to start, pid,
    launch time)``."""
    command = [sys.executable, "-m", "torchspec", "view", str(folder), "--port", "0", *options]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    start = time.perf_counter()
    process = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env)
    try:
        line = process.stdout.readline()
        yield line.split()[2], time.perf_counter() - start, process.pid, start
    finally:
        process.terminate()
        process.wait(timeout=30)


def wait_for(path: Path, timeout: float = 900.0) -> bool:
    """Whether ``path`` exists within ``timeout`` seconds (polled)."""
    end = time.perf_counter() + timeout
    while not path.exists() and time.perf_counter() < end:
        time.sleep(0.1)
    return path.exists()


def overview(url: str, settings: Settings) -> bytes:
    """The coarsest level's tile, asked again while the server answers 503 (not made yet)."""
    level = levels_for(*settings.size) - 1
    while True:
        try:
            with urllib.request.urlopen(f"{url}tiles/{level}/0_0.bin", timeout=600) as answer:
                return answer.read()
        except urllib.error.HTTPError as error:
            if error.code != 503:
                raise
            time.sleep(0.05)


def load() -> list[float]:
    return [round(value, 2) for value in os.getloadavg()]


def measure(settings: Settings, folder: Path) -> dict:
    """Three sessions, each with a server of its own: the page opened at the fitted view (its first
    image, the view settled, then 1:1; the server then caches the coarse levels), the page opened
    straight at 1:1 (during the pass, ``--no-cache``), and the reopening (with the cache)."""
    index = folder / cache.FOLDER / cache.INDEX
    if (folder / cache.FOLDER).exists():  # torchspec's own cache, made again below
        shutil.rmtree(folder / cache.FOLDER)
    loads = {"cold_start": load()}
    with server(folder) as (url, started, pid, launched), Browser(*settings.viewport, timeout=1800.0) as browser:
        after_start = memory(pid)
        opened = time.perf_counter()
        browser.open(url)
        browser.evaluate("torchspecView.settle()")
        fitted = time.perf_counter() - opened
        first = browser.evaluate("torchspecView.viewer.firstImage") / 1000
        level = browser.evaluate("torchspecView.viewer.level()")
        late = one_to_one(browser, settings)
        fitted_memory = memory(pid)
        if not wait_for(index):
            raise RuntimeError(f"the server did not write {index}")
        cached = time.perf_counter() - launched
    cache_bytes = sum(path.stat().st_size for path in index.parent.iterdir())
    loads["cold_end"] = load()
    with server(folder, "--no-cache") as (url, _, pid, _), Browser(*settings.viewport, timeout=1800.0) as browser:
        opened = time.perf_counter()
        browser.open(url)
        loaded = time.perf_counter() - opened
        early = loaded + one_to_one(browser, settings)  # from the page's navigation
        early_memory = memory(pid)
    loads["reopen_start"] = load()
    with server(folder) as (url, restarted, pid, launched):
        overview(url, settings)  # asked as soon as the server prints its address
        overview_s = time.perf_counter() - launched
        with Browser(*settings.viewport, timeout=1800.0) as browser:
            opened = time.perf_counter()
            browser.open(url)
            browser.evaluate("torchspecView.settle()")
            reopen = {
                "server_start_s": restarted,
                "overview_tile_from_launch_s": overview_s,
                "overview_tile_after_start_s": overview_s - restarted,
                "first_image_s": browser.evaluate("torchspecView.viewer.firstImage") / 1000,
                "fit_view_settled_s": time.perf_counter() - opened,
                "fit_view_level": browser.evaluate("torchspecView.viewer.level()"),
                "memory": memory(pid),
            }
    loads["reopen_end"] = load()
    return {
        "load_average_1min": loads["cold_start"][0],
        "load_average_1_5_15min": loads,
        "server_start_s": started,
        "memory_after_start": after_start,
        "first_image_s": first,
        "fit_view_settled_s": fitted,
        "fit_view_level": level,
        "one_to_one_after_s": late,
        "memory_fit_view_session": fitted_memory,
        "one_to_one_at_once_s": early,
        "memory_one_to_one_session": early_memory,
        "cache_written_after_launch_s": cached,
        "cache_bytes": cache_bytes,
        "reopen": reopen,
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "view_large.yaml", argv)
    settings = load_config(args.config, Settings)
    folder = Path(settings.folder)
    height, width = settings.size
    written = synthesize(folder, height, width, settings.band_rows)
    disk = sum(f.stat().st_size for f in folder.glob("*.exr"))
    print(f"{height}x{width} maps ({disk / 1e9:.2f} GB of EXR) written in {written:.0f} s (0: reused)")
    timing = measure(settings, folder)
    print(f"server start {timing['server_start_s']:.2f} s (RSS {timing['memory_after_start']['rss_mb']:.0f} MB); "
          f"1:1 at once {timing['one_to_one_at_once_s']:.2f} s; first image {timing['first_image_s']:.1f} s; "
          f"fit view settled {timing['fit_view_settled_s']:.1f} s (level {timing['fit_view_level']}); "
          f"1:1 after {timing['one_to_one_after_s']:.2f} s; server peak RSS "
          f"{timing['memory_fit_view_session']['peak_rss_mb']:.0f} MB (opened at 1:1: "
          f"{timing['memory_one_to_one_session']['peak_rss_mb']:.0f} MB)")  # fmt: skip
    reopen = timing["reopen"]
    print(f"reopen (cache of {timing['cache_bytes'] / 1e6:.0f} MB, written "
          f"{timing['cache_written_after_launch_s']:.1f} s after the first launch): server start "
          f"{reopen['server_start_s']:.2f} s; overview tile "
          f"{reopen['overview_tile_from_launch_s']:.2f} s from launch; first image {reopen['first_image_s']:.2f} s, "
          f"fit view settled {reopen['fit_view_settled_s']:.2f} s (level {reopen['fit_view_level']}); peak RSS "
          f"{reopen['memory']['peak_rss_mb']:.0f} MB; load {timing['load_average_1_5_15min']}")  # fmt: skip
    result = {"settings": asdict(settings), "exr_bytes": disk, "synthesis_s": written, "speed": timing}
    path = args.output / f"{Path(args.config).stem}.json"
    write_json(path, result)
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
