"""A capture's photograph in ``torchspec view`` on a very large frame: how soon its tiles are
served, and the memory it takes.

Synthesizes a capture of one frame of ``size`` (height, width) pixels, RGB float32 ZIP, written
band by band of ``band_rows`` rows through OpenEXR's scanline writer (the texture of
``view_large.py``'s diffuse map; the script never holds the frame). Then, in a process of its own
for each way of reading the frame (``modes``: ``lazy``, the viewer's: bands of rows, the coarse
levels by a background pass; ``whole``: the frame read whole into memory, as the viewer read every
frame before, forced by ``keep_texels`` above its size), the viewer's :class:`~torchspec.view.Site`
with the capture (its maps a stand-in: only the photograph is served) is asked, as the page asks,
again while it answers "not made yet" (503; here every 0.05 s, the page every 0.5 s):

- a tile of full resolution at ``place`` (fractions of the width and height), as the page at 1:1
  asks first when the light snaps to the frame;
- then every tile of full resolution of a ``viewport`` at 1:1 about ``place``, one after the other;
- then the overview (the coarsest level's tile), the page's image of the whole photograph;

each timed from the site's creation; and the process's peak resident memory (``VmHWM``), its
resident memory after the first tile and at the end, and the load average (1, 5, 15 min) before
and after. The tiles' bytes are compared between the modes (the same, bit for bit).

    python experiments/view_photo_large.py [--config experiments/configs/view_photo_large.yaml] \
        [--output experiments/results]
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import ROOT, parse_args
from view_large import band, load, memory

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture
from torchspec.io.capture import FORMAT, VERSIONS
from torchspec.view.site import NotMade, Site
from torchspec.view.tiles import KEEP_TEXELS, PHOTO_TEXTURES, TILE, Pyramid


@dataclass(frozen=True)
class Settings:
    size: tuple[int, int]  # height, width of the frame
    band_rows: int  # rows written at a time
    folder: str  # the capture (kept: reused when its capture.json says the same size)
    viewport: tuple[int, int]  # width, height of the 1:1 view
    place: tuple[float, float]  # the 1:1 view's centre, as fractions of the width and height
    modes: tuple[str, ...] = ("lazy", "whole")
    keep_texels: int = KEEP_TEXELS  # the lazy mode's (the viewer's): frames of more pixels are read in bands


def synthesize(folder: Path, height: int, width: int, rows: int) -> float:
    """Write the frame (band by band) and ``capture.json`` (last); returns the seconds it took."""
    import Imath
    import OpenEXR

    manifest = folder / "capture.json"
    if manifest.exists() and [json.loads(manifest.read_text())[k] for k in ("height", "width")] == [height, width]:
        return 0.0
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    header = OpenEXR.Header(width, height)
    header["channels"] = {c: Imath.Channel(Imath.PixelType(Imath.PixelType.FLOAT)) for c in "RGB"}
    header["compression"] = Imath.Compression(Imath.Compression.ZIP_COMPRESSION)
    file = OpenEXR.OutputFile(str(folder / "frame.exr"), header)
    for first in range(0, height, rows):
        count = min(rows, height - first)
        planes = band(first, count, width, height)["diffuse"]
        file.writePixels({c: p.tobytes() for c, p in zip("RGB", planes, strict=True)}, count)
    file.close()
    frame = {"file": "frame.exr", "direction": [0.0, 0.0, 1.0], "irradiance": 0.5, "exposure": 2.0}
    write_json(manifest, {"format": FORMAT, "version": VERSIONS[-1], "width": width, "height": height,
                          "channels": ["R", "G", "B"], "camera": {"model": "orthographic", "view": [0.0, 0.0, 1.0]},
                          "light": {"kernel": "point"}, "frames": [frame]})  # fmt: skip
    return time.perf_counter() - start


def served(site: Site, path: str) -> bytes:
    """The tile at ``path``, asked again every 0.05 s while it is not made."""
    while True:
        try:
            return site.file(path, wait=False)
        except NotMade:
            time.sleep(0.05)


def session(settings: Settings, mode: str) -> dict:
    """One process's measurement (``--measure MODE``)."""
    import OpenEXR

    OpenEXR.set_global_thread_count(os.cpu_count() or 1)  # as torchspec view does
    capture = read_capture(settings.folder)
    height, width = settings.size
    stand_in = Pyramid.build({name: torch.zeros(1, 1) for name in "rgba"}, PHOTO_TEXTURES)
    keep = {"lazy": settings.keep_texels, "whole": height * width}[mode]
    before = load()
    start = time.perf_counter()
    site = Site(stand_in, {}, capture, keep_texels=keep)
    x, y = settings.place[0] * width, settings.place[1] * height
    row, column = int(y) // TILE, int(x) // TILE
    first = served(site, f"/photo/0/0/{row}_{column}.jpg")
    first_s = time.perf_counter() - start
    after_first = memory(os.getpid())
    (w, h), digest = settings.viewport, hashlib.sha256()
    rows = range(max(0, int(y - h / 2) // TILE), min(-(-height // TILE), -(-int(y + h / 2) // TILE)))
    columns = range(max(0, int(x - w / 2) // TILE), min(-(-width // TILE), -(-int(x + w / 2) // TILE)))
    for r in rows:
        for c in columns:
            digest.update(served(site, f"/photo/0/0/{r}_{c}.jpg"))
    view_s = time.perf_counter() - start
    top = len(site.photo(0).levels) - 1
    overview = served(site, f"/photo/0/{top}/0_0.jpg")
    overview_s = time.perf_counter() - start
    site.close()
    return {
        "mode": mode,
        "first_tile_1to1_s": first_s,
        "overview_tile_s": overview_s,
        "view_1to1_s": view_s,
        "view_tiles": len(rows) * len(columns),
        "memory_after_first_tile": after_first,
        "memory": memory(os.getpid()),
        "load_1_5_15min": {"start": before, "end": load()},
        "sha256": {
            "first": hashlib.sha256(first).hexdigest(),
            "overview": hashlib.sha256(overview).hexdigest(),
            "view": digest.hexdigest(),
        },
    }


def main(argv: list[str] | None = None) -> dict:
    def options(parser):
        parser.add_argument("--measure", help="run one mode's session and print its JSON (internal)")

    args = parse_args(__doc__, "view_photo_large.yaml", argv, options=options)
    settings = load_config(args.config, Settings)
    if args.measure:
        print(json.dumps(session(settings, args.measure)))
        return {}
    height, width = settings.size
    written = synthesize(Path(settings.folder), height, width, settings.band_rows)
    disk = (Path(settings.folder) / "frame.exr").stat().st_size
    print(f"{height}x{width} frame ({disk / 1e9:.2f} GB of EXR) written in {written:.0f} s (0: reused)")
    sessions = {}
    for mode in settings.modes:
        command = [sys.executable, __file__, "--config", str(args.config), "--measure", mode]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        line = subprocess.run(command, check=True, capture_output=True, text=True, env=env).stdout.splitlines()[-1]
        sessions[mode] = result = json.loads(line)
        print(f"{mode}: first tile at 1:1 {result['first_tile_1to1_s']:.2f} s, overview "
              f"{result['overview_tile_s']:.2f} s, "
              f"1:1 view ({result['view_tiles']} tiles) {result['view_1to1_s']:.2f} s; peak RSS "
              f"{result['memory']['peak_rss_mb']:.0f} MB (RSS after the first tile "
              f"{result['memory_after_first_tile']['rss_mb']:.0f} MB); load {result['load_1_5_15min']}")  # fmt: skip
    same = len({json.dumps(s["sha256"], sort_keys=True) for s in sessions.values()}) == 1
    result = {"settings": asdict(settings), "exr_bytes": disk, "synthesis_s": written, "sessions": sessions,
              "same_tiles": same}  # fmt: skip
    write_json(args.output / f"{Path(args.config).stem}.json", result)
    print(f"the modes' tiles are {'the same' if same else 'DIFFERENT'}; written to {args.output}")
    return result


if __name__ == "__main__":
    main()
