"""The viewer's site: the page's static files, ``manifest.json`` and the tiles of
:mod:`torchspec.view.tiles`, served on 127.0.0.1 (``torchspec view``) or written to a folder any
web server can host (``torchspec export --to web``). Both lay the site out the same way:

    index.html, viewer.js, viewer.css   the page (package data: torchspec/view/static/)
    manifest.json                       size, channels, view, levels, textures, layers, lights,
                                        the light kernel's nodes (:mod:`torchspec.view.light`),
                                        ``term``: the residual term's basis functions (0: none)
    tiles/L/R_C.bin                     the maps' tile at level L, row R, column C
    photo/K/L/R_C.bin                   with a capture: frame K's photograph, the same tiling
"""

from __future__ import annotations

import json
import re
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import partial
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_path, write_json
from ..brdf import SVBRDF
from ..errors import TorchspecError
from ..io import Capture, Maps, read_capture, read_svbrdf
from ..lights import Kernel
from ..outputs import check_output
from ..report import MODEL_COLOURS
from .light import light_quadrature
from .tiles import Pyramid, photo_pyramid

__all__ = ["STATIC", "Site", "open_site", "export_web", "serve"]

STATIC = ("index.html", "viewer.js", "viewer.css")
"""The page's files, shipped in ``torchspec/view/static/``."""

_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript", ".css": "text/css",
          ".json": "application/json", ".bin": "application/octet-stream"}  # fmt: skip
_TILE = re.compile(r"^/(?:tiles|photo/(\d+))/(\d+)/(\d+)_(\d+)\.bin$")
PHOTO_CACHE = 4
"""Photographs whose pyramids the server keeps (the frames last asked for)."""


def _quantile(value: np.ndarray, q: float = 0.99, samples: int = 1 << 18) -> float:
    """The ``q`` quantile of the positive finite values (of a regular subsample of ``samples``)."""
    value = value.reshape(-1)[:: max(1, value.size // samples)]
    finite = value[np.isfinite(value) & (value > 0)]
    return float(np.quantile(finite, q)) if finite.size else 1.0


def _kernel(capture: Capture | None) -> Kernel | None:
    """The capture's light kernel (``None`` without a capture); an ``unknown`` one as such."""
    if capture is None:
        return None
    return Kernel("unknown") if capture.light.kernel == "unknown" else capture.lights().kernel


@dataclass
class Site:
    """A fit's viewer data: the maps' pyramid, the manifest, and the capture whose photographs
    show beside the relit fit (``None`` for none). Photographs' pyramids are made on demand."""

    pyramid: Pyramid
    manifest: dict
    capture: Capture | None = None
    photos: OrderedDict = field(default_factory=OrderedDict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def file(self, path: str) -> bytes | None:
        """The bytes of the site's file at URL path ``path``; ``None`` for no such file."""
        name = path.split("?", 1)[0]
        name = "/index.html" if name == "/" else name
        if name[1:] in STATIC:
            return resources.files(__package__).joinpath("static", name[1:]).read_bytes()
        if name == "/manifest.json":
            return json.dumps(self.manifest).encode()
        match = _TILE.match(name)
        if match is None:
            return None
        frame, level, row, column = match.groups()
        try:
            pyramid = self.pyramid if frame is None else self.photo(int(frame))
            return pyramid.tile(int(level), int(row), int(column)) if pyramid is not None else None
        except IndexError:
            return None

    def photo(self, k: int) -> Pyramid | None:
        """Frame ``k``'s photograph as a pyramid (``None`` without a capture or such a frame)."""
        if self.capture is None or not 0 <= k < len(self.capture.frames):
            return None
        with self.lock:
            if k not in self.photos:
                frame = self.capture.read_frames([k], nonfinite="keep")[0]
                frame = torch.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0)
                scale = self.capture.exposure()[k] * self.capture.irradiance()[k]
                self.photos[k] = photo_pyramid(frame, scale)
                while len(self.photos) > PHOTO_CACHE:
                    self.photos.popitem(last=False)
            self.photos.move_to_end(k)
            return self.photos[k]


def open_site(
    maps: Maps | SVBRDF | str | Path, capture: Capture | str | Path | None = None, *, title: str = ""
) -> Site:
    """The viewer data of maps (a folder or :class:`~torchspec.io.Maps`) and, optionally, the
    capture they were fitted from.

    Raises:
        SVBRDFError, CaptureError: a folder that is not a valid map folder or capture.
        TorchspecError: a capture of another size than the maps.
    """
    source = str(maps) if isinstance(maps, (str, Path)) else ""
    maps = Maps(maps) if isinstance(maps, SVBRDF) else maps
    maps = read_svbrdf(maps) if not isinstance(maps, Maps) else maps
    if capture is not None and not isinstance(capture, Capture):
        capture = read_capture(capture)
    height, width = maps.svbrdf.shape
    if capture is not None and (capture.height, capture.width) != (height, width):
        raise TorchspecError(
            f"{capture.manifest} is {capture.width}x{capture.height} but the maps are {width}x{height}: "
            "view a fit with the capture it was fitted from."
        )
    pyramid = Pyramid.of_maps(maps)
    extra, meta = maps.extra, maps.meta
    svbrdf = maps.svbrdf
    terms = sum(name.startswith("term_") and name.endswith("_r") for *_, names in pyramid.textures for name in names)
    layers = ["relit"] + (["physical"] if terms else []) + ["normal", "diffuse", "specular", "roughness"]
    layers += [name for name in ("model", "quality") if name in extra]
    layers += ["flags"] if "flags" in extra else []
    layers += ["std"] if any(name.startswith("std_") for name in extra) else []
    alpha = svbrdf.roughness.numpy()
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
        "model_colours": list(MODEL_COLOURS),
        "flag_bits": meta.get("flag_bits", {}),
        "untrusted_flags": meta.get("untrusted_flags", []),
        "ranges": {
            "alpha": _quantile(alpha),
            "specular": _quantile(svbrdf.specular.numpy()),
            **{n: _quantile(extra[n].numpy()) for n in extra if n.startswith("std_")},
        },
        "lights": [] if capture is None else capture.directions().tolist(),
        "term": terms,
        **light_quadrature(_kernel(capture)).describe(),
        **pyramid.describe(),
    }
    return Site(pyramid, manifest, capture)


def export_web(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    capture: Capture | str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Write the viewer as a static site to ``output`` (any web server can host it; browsers do
    not load ``file://`` tiles). With ``capture``, every frame's photograph is written too.

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
    for folder, pyramid in pyramids:
        pyramid = pyramid if pyramid is not None else site.photo(int(folder.name))
        for level in range(len(pyramid.levels)):
            rows, columns = pyramid.grid(level)
            (output / folder / str(level)).mkdir(parents=True, exist_ok=True)
            for row in range(rows):
                for column in range(columns):
                    with atomic_path(output / folder / str(level) / f"{row}_{column}.bin") as tmp:
                        tmp.write_bytes(pyramid.tile(level, row, column))
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
        body = self.site.file(self.path)
        if body is None:
            self.send_error(404)
            return
        suffix = Path(self.path.split("?", 1)[0]).suffix or ".html"
        self.send_response(200)
        self.send_header("Content-Type", _TYPES.get(suffix, "application/octet-stream"))
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-cache" if suffix != ".bin" else "max-age=3600")
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
