"""The viewer's site: the page's static files, ``manifest.json`` and the tiles of
:mod:`torchspec.view.tiles`, served on 127.0.0.1 (``torchspec view``) or written to a folder any
web server can host (``torchspec export --to web``). Both lay the site out the same way:

    index.html, viewer.js, viewer.css   the page (package data: torchspec/view/static/)
    manifest.json                       size, channels, view, levels, textures, layers, lights,
                                        near lights' positions and the light kernel's nodes
                                        (:mod:`torchspec.view.light`),
                                        ``term``: the residual term's basis functions (0: none)
    tiles/L/R_C.bin                     the maps' tile at level L, row R, column C
    photo/K/L/R_C.jpg                   with a capture: frame K's photograph, the same tiling, a
                                        JPEG of the tile's own size (tiles.photo_jpeg)
"""

from __future__ import annotations

import json
import os
import re
import sys
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

import numpy as np
import OpenEXR
import torch

from ..atomic import atomic_path, write_json
from ..errors import TorchspecError
from ..io import Capture, Maps, read_capture, read_svbrdf
from ..io.exr import exr_size
from ..io.scale import capture_at
from ..model.brdf import SVBRDF
from ..model.lights import Kernel
from ..model.residual_term import MAP_NAME, TermDomain
from ..outputs import check_output
from ..progress import bar
from ..relight import softness_of
from ..report import MODEL_COLOURS, model_colours
from .cache import Stopped
from .light import light_quadrature, near_lights
from .shadows import shadow_manifest
from .tiles import EXTRA_MAPS, KEEP_TEXELS, PHOTO_QUALITY, Pyramid, frame_pyramid, photo_tile

__all__ = ["STATIC", "Site", "open_site", "export_web", "serve"]

STATIC = ("index.html", "viewer.js", "viewer.css")
"""The page's files, shipped in ``torchspec/view/static/``."""

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript", ".css": "text/css",
          ".json": "application/json", ".bin": "application/octet-stream", ".jpg": "image/jpeg"}  # fmt: skip
_TILE = re.compile(r"^/(?:tiles/(\d+)/(\d+)_(\d+)\.bin|photo/(\d+)/(\d+)/(\d+)_(\d+)\.jpg)$")
WAIT = 0.5
"""Seconds a tile request waits for its level before the server answers 503 (asked again later)."""
PHOTO_CACHE = 4
"""Photographs whose pyramids the server keeps (the frames last asked for; the others' background
passes are stopped)."""


SAMPLE_BANDS = (16, 16)
"""A folder's display ranges come from this many bands of this many rows, spread over the maps."""


def _quantile(values: list[np.ndarray], q: float = 0.99, samples: int = 1 << 18) -> float:
    """The ``q`` quantile of the positive finite values (of a regular subsample of ``samples``)."""
    value = np.concatenate([v.reshape(-1) for v in values])
    value = value[:: max(1, value.size // samples)]
    finite = value[np.isfinite(value) & (value > 0)]
    return float(np.quantile(finite, q)) if finite.size else 1.0


def term_encoding(meta: dict) -> dict:
    """The manifest's ``term_encoding``: the residual term's encoding (``svbrdf.json``'s
    ``residual_term.encoding``, :class:`torchspec.model.residual_term.TermDomain`), ``{"transfer":
    "srgb"}`` or a camera response's ``gamma``, ``offset``, ``contrast`` and ``slope`` at code 1
    for the page's three colour channels (a grey curve repeated)."""
    domain = TermDomain.from_json((meta.get(MAP_NAME) or {}).get("encoding"), f"svbrdf.json {MAP_NAME}.encoding")
    if domain.curve is None:
        return {"transfer": "srgb"}
    curve = domain.curve
    slope = curve.slope_at_one(torch.ones(curve.channels, dtype=torch.float64)).tolist()  # CPU on purpose: JSON
    three = {"gamma": curve.gamma, "offset": curve.offset, "contrast": curve.contrast, "slope": slope}
    return {"transfer": "response", **{k: [float(v[i % len(v)]) for i in range(3)] for k, v in three.items()}}


def _kernel(capture: Capture | None) -> Kernel | None:
    """The capture's light kernel (``None`` without a capture); an ``unknown`` one as such."""
    if capture is None:
        return None
    return Kernel("unknown") if capture.light.kernel == "unknown" else capture.lights().kernel


def _shadows(pyramid: Pyramid, head: Maps, capture: Capture | None) -> dict | None:
    """The manifest's ``shadows`` (:func:`~torchspec.view.shadows.shadow_manifest`) of maps with a
    height, else ``None``: the reach their horizons were made with (the pyramid's), the fit's
    penumbra, the capture's kernel."""
    if "height" not in head.extra:
        return None
    return shadow_manifest(softness_of(head), _kernel(capture), pyramid.shadow_reach)


class NotMade(Exception):
    """A tile whose level the background pass has not made yet."""


@dataclass
class Site:
    """A fit's viewer data: the maps' pyramid, the manifest, and the capture whose photographs
    show beside the relit fit (``None`` for none). Photographs' pyramids are made on demand, with
    the maps' tiling (:func:`~torchspec.view.tiles.frame_pyramid`: a frame of more than
    ``keep_texels`` pixels is read lazily, in bands of rows, as a map folder is)."""

    pyramid: Pyramid
    manifest: dict
    capture: Capture | None = None
    photos: OrderedDict = field(default_factory=OrderedDict)
    lock: threading.Lock = field(default_factory=threading.Lock)
    keep_texels: int = KEEP_TEXELS

    def file(self, path: str, wait: bool = True) -> bytes | None:
        """The bytes of the site's file at URL path ``path``; ``None`` for no such file.

        Raises:
            NotMade: ``wait`` is false and the tile's level is still being made (the server
                answers 503: the page asks again, and its connection serves other tiles meanwhile).
        """
        name = path.split("?", 1)[0]
        name = "/index.html" if name == "/" else name
        if name[1:] in STATIC:
            return resources.files(__package__).joinpath("static", name[1:]).read_bytes()
        if name == "/manifest.json":
            return json.dumps(self.manifest).encode()
        match = _TILE.match(name)
        if match is None:
            return None
        groups = match.groups()
        frame, level, row, column = (None, *groups[:3]) if groups[0] is not None else groups[3:]
        try:
            pyramid = self.pyramid if frame is None else self.photo(int(frame))
            if pyramid is not None and not wait and not pyramid.ready(int(level), timeout=WAIT):
                raise NotMade(path)
            if pyramid is None:
                return None
            if frame is not None:
                return photo_tile(pyramid, int(level), int(row), int(column))
            return pyramid.tile(int(level), int(row), int(column))
        except IndexError:
            return None
        except Stopped:  # a photograph dropped from the kept ones before its level was made
            if frame is None or self.photos.get(int(frame)) is pyramid:  # the site is closed
                raise
            if not wait:
                raise NotMade(path) from None
            return self.file(path, wait)  # its pyramid made again

    def photo(self, k: int) -> Pyramid | None:
        """Frame ``k``'s photograph as a pyramid (``None`` without a capture or such a frame)."""
        if self.capture is None or not 0 <= k < len(self.capture.frames):
            return None
        with self.lock:
            if k not in self.photos:
                tile = self.pyramid.tile_size
                self.photos[k] = frame_pyramid(self.capture, k, tile=tile, keep_texels=self.keep_texels)
                while len(self.photos) > PHOTO_CACHE:
                    self.photos.popitem(last=False)[1].close(timeout=0)  # its pass stops after its band
            self.photos.move_to_end(k)
            return self.photos[k]

    def close(self) -> None:
        """Stop the maps' background pass and cache write, and the photographs' passes
        (:meth:`Pyramid.close`)."""
        self.pyramid.close()
        with self.lock:
            photos = list(self.photos.values())
        for photo in photos:
            photo.close()


def _sample(folder: Path) -> tuple[list[Maps], tuple[int, int]]:
    """Bands of a map folder's rows spread over it (:data:`SAMPLE_BANDS`), and its ``(H, W)``."""
    first = read_svbrdf(folder, rows=(0, 1), extra_maps=EXTRA_MAPS)
    height, width = exr_size(folder / "normal.exr")
    count, rows = SAMPLE_BANDS
    starts = sorted({round(i * max(0, height - rows) / max(1, count - 1)) for i in range(count)})
    bands = [read_svbrdf(folder, rows=(a, min(height, a + rows)), extra_maps=EXTRA_MAPS) for a in starts]
    return [first] + bands, (height, width)


def open_site(
    maps: Maps | SVBRDF | str | Path,
    capture: Capture | str | Path | None = None,
    *,
    title: str = "",
    cache: bool = False,
    **options,
) -> Site:
    """The viewer data of maps (a folder or :class:`~torchspec.io.Maps`) and, optionally, the
    capture they were fitted from.

    A folder is read lazily (:meth:`Pyramid.of_folder`, its EXR blocks decoded on OpenEXR's worker
    threads, one a core, when the process has none): at start its headers and a sample of its
    rows (the display ranges); then each tile's rows when it is asked for, and the coarse levels in
    a background pass; a bad value (NaN, a normal off unit length) is found in the tile that holds
    it (its request fails, naming the file and row). ``cache``: a folder's coarse levels are read
    from the cache of :mod:`torchspec.view.cache` when it holds them for the maps as they are now
    (the whole painting shows at once), else written there once the pass has made them
    (``torchspec view`` without ``--no-cache``). A capture's frame is read when its photograph is
    first asked for: whole, or lazily as a folder (not cached on disk) when it has more than
    ``keep_texels`` pixels (:class:`Site`). ``options`` go to the :class:`Pyramid` (``tile``; for a
    folder also ``keep_texels``, ``cache_bytes``); ``tile`` and ``keep_texels`` to the photographs'.

    Raises:
        SVBRDFError, CaptureError: a folder that is not a valid map folder or capture.
        TorchspecError: a capture of another size than the maps.
    """
    source = str(maps) if isinstance(maps, (str, Path)) else ""
    if isinstance(maps, (str, Path)):
        folder = Path(maps)
        folder = folder.parent if folder.suffix.lower() == ".json" or folder.is_file() else folder
        if OpenEXR.global_thread_count() == 0:  # decode the files' blocks on every core (process-wide)
            OpenEXR.set_global_thread_count(os.cpu_count() or 1)
        bands, (height, width) = _sample(folder)
        pyramid = Pyramid.of_folder(folder, bands[0], (height, width), cache=cache, **options)
    else:
        bands = [Maps(maps) if isinstance(maps, SVBRDF) else maps]
        height, width = bands[0].svbrdf.shape
        pyramid = Pyramid.of_maps(bands[0], **options)
    if capture is not None and not isinstance(capture, Capture):
        capture = read_capture(capture)
    if capture is not None and (capture.height, capture.width) != (height, width):  # a fit at a crop or downsample
        capture = capture_at(capture, (bands[0].meta.get("fit") or {}).get("scale"))
    if capture is not None and (capture.height, capture.width) != (height, width):
        raise TorchspecError(
            f"{capture.manifest} is {capture.width}x{capture.height} but the maps are {width}x{height}: "
            "view a fit with the capture it was fitted from."
        )
    extra, meta, svbrdf = bands[0].extra, bands[0].meta, bands[0].svbrdf
    terms = sum(name.startswith("term_") and name.endswith("_r") for *_, names in pyramid.textures for name in names)
    layers = ["relit"] + (["physical"] if terms else []) + ["normal", "diffuse", "specular", "roughness"]
    layers += [name for name in ("model", "quality") if name in extra]
    layers += ["flags"] if "flags" in extra else []
    layers += ["std"] if any(name.startswith("std_") for name in extra) else []
    manifest = {
        "format": "torchspec.view",
        "version": 1,
        "title": title or source,
        "width": width,
        "height": height,
        "channels": list(svbrdf.channels),
        "view": list(capture.view) if capture is not None else [0.0, 0.0, 1.0],
        "layers": layers,
        "model_codes": meta.get("model_codes", []),
        "model_colours": list(model_colours(max(len(meta.get("model_codes", [])), len(MODEL_COLOURS)))),
        "flag_bits": meta.get("flag_bits", {}),
        "untrusted_flags": meta.get("untrusted_flags", []),
        "ranges": {
            "alpha": _quantile([band.svbrdf.roughness.numpy() for band in bands]),
            "specular": _quantile([band.svbrdf.specular.numpy() for band in bands]),
            **{n: _quantile([band.extra[n].numpy() for band in bands]) for n in extra if n.startswith("std_")},
        },
        "lights": [] if capture is None else capture.directions().tolist(),
        **near_lights(capture, meta, height, width),
        "term": terms,
        "term_encoding": term_encoding(meta) if terms else None,
        "shadows": _shadows(pyramid, bands[0], capture),
        **light_quadrature(_kernel(capture)).describe(),
        **pyramid.describe(),
        "photo": {
            "format": "jpeg",
            "files": "photo/K/L/R_C.jpg: frame K's tile, of its own size (not padded)",
            "values": "the frame over its exposure times irradiance: S times the sRGB-decoded codes, S the number "
            "after 'torchspec scale=' in the JPEG's comment",
            "quality": PHOTO_QUALITY,
        },
    }
    return Site(pyramid, manifest, capture, keep_texels=options.get("keep_texels", KEEP_TEXELS))


def export_web(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    capture: Capture | str | Path | None = None,
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Write the viewer as a static site to ``output`` (any web server can host it; browsers do
    not load ``file://`` tiles). With ``capture``, every frame's photograph is written too.
    A folder of maps is read lazily (:func:`open_site`), level by level and row by row of tiles:
    memory is bounded by the pyramid's bands and coarse levels, not by the maps. ``progress``: a
    bar over the tiles (on stderr).

    Returns:
        ``output / "index.html"``, written last (a folder with it holds the whole site).

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is false.
    """
    output = check_output(output, overwrite=overwrite)
    site = open_site(maps, capture)
    pyramids = [(Path("tiles"), site.pyramid)]
    if site.capture is not None:
        pyramids += [(Path("photo") / str(k), None) for k in range(len(site.capture.frames))]
    grids = [site.pyramid.grid(level) for level in range(len(site.pyramid.levels))]
    total = len(pyramids) * sum(rows * columns for rows, columns in grids)  # a photograph's: the maps' tiling
    with bar(total, desc="export web", unit="tile", enabled=progress) as shown:
        for folder, pyramid in pyramids:
            photo = pyramid is None
            pyramid = site.photo(int(folder.name)) if photo else pyramid
            for level in range(len(pyramid.levels)):
                rows, columns = pyramid.grid(level)
                (output / folder / str(level)).mkdir(parents=True, exist_ok=True)
                for row in range(rows):
                    for column in range(columns):
                        name = f"{row}_{column}.{'jpg' if photo else 'bin'}"
                        data = photo_tile(pyramid, level, row, column) if photo else pyramid.tile(level, row, column)
                        with atomic_path(output / folder / str(level) / name) as tmp:
                            tmp.write_bytes(data)
                        shown.update(1)
    write_json(output / "manifest.json", site.manifest)
    for name in STATIC:
        with atomic_path(output / name) as tmp:
            tmp.write_bytes(site.file(f"/{name}"))
    return output / "index.html"


class _Handler(BaseHTTPRequestHandler):
    def __init__(self, *args, site: Site, **kwargs):
        self.site = site
        super().__init__(*args, **kwargs)

    def do_GET(self):  # noqa: N802 (http.server's name)
        try:
            body = self.site.file(self.path, wait=False)
        except NotMade:
            self.send_response(503)
            self.send_header("Retry-After", "1")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        except TorchspecError as error:  # a lazily read tile's rows hold a bad value
            print(f"torchspec view: {self.path}: {error}", file=sys.stderr, flush=True)
            self.send_error(500, explain=str(error))
            return
        if body is None:
            self.send_error(404)
            return
        suffix = Path(self.path.split("?", 1)[0]).suffix or ".html"
        self.send_response(200)
        self.send_header("Content-Type", _TYPES.get(suffix, "application/octet-stream"))
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-cache" if suffix not in (".bin", ".jpg") else "max-age=3600")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):  # quiet: a page asks for hundreds of tiles
        pass


def serve(site: Site, port: int = 0) -> ThreadingHTTPServer:
    """An HTTP server of ``site`` on 127.0.0.1 (``port`` 0: a free one), not yet started: call
    its ``serve_forever()`` (or run it in a thread); ``server.server_address[1]`` is the port.

    Raises:
        TorchspecError: the port is taken or not allowed.
    """
    try:
        return ThreadingHTTPServer(("127.0.0.1", port), partial(_Handler, site=site))
    except OSError as error:
        raise TorchspecError(f"cannot serve on 127.0.0.1:{port}: {error.strerror}; choose another --port.") from error
