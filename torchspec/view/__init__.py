"""Relight a fit in the browser (``torchspec view``, ``torchspec export --to web``).

The page (``static/``: plain JavaScript and WebGL2, nothing from the network) relights the maps
with the fit's own model, Lambert plus Ward (isotropic, anisotropic, two lobes), under a point
light or the capture's extended kernel (:mod:`.light`), per pixel as :func:`torchspec.render`
does, with the fit's residual term where it has one (the ``physical`` layer without it);
:mod:`.tiles` cuts the maps into a pyramid of binary tiles (a capture's photographs into JPEG
tiles), :mod:`.site` serves them on 127.0.0.1 or writes them as a static site, and :mod:`.browser`
drives the page in headless Chromium (the tests and ``experiments/view.py``).
"""

from .site import STATIC, Site, export_web, open_site, serve
from .tiles import TEXTURES, TILE, Pyramid

__all__ = ["STATIC", "TEXTURES", "TILE", "Pyramid", "Site", "export_web", "open_site", "serve"]
