"""The OpenLIME export (:func:`export_openlime`): the maps of OpenLIME's BRDF layer (``LayerBRDF``,
shader ``ShaderBRDF``; cnr-isti-vclab/openlime, ``src/LayerBRDF.js`` and ``src/ShaderBRDF.js``)
and ``info.json``, the layer's options.

The layer renders ``(k_d / pi + k_s ward(alpha)) <n, l>`` (plus a small ambient ``k_d / pi``
times its ``kAmbient``) with the isotropic Ward lobe
``exp(-tan^2(theta_h) / alpha^2) / (4 pi alpha^2 sqrt(<n, l> <n, v>))``, torchspec's own for
``alpha_x = alpha_y``. Its gloss texture ``g`` in ``[0, 1]`` maps to ``alpha`` through the layer's
``alphaLimits = [a_min, a_max]``:

    alpha = (1 - g (G_max - G_min) - G_min)^4,  G_min = 1 - a_max^(1/4),  G_max = 1 - a_min^(1/4)

(:func:`alpha_from_gloss`), whose inverse (:func:`gloss_from_alpha`) is
``g = (a_max^(1/4) - alpha^(1/4)) / (a_max^(1/4) - a_min^(1/4))``; the export sets ``alphaLimits``
to the smallest and largest ``alpha`` of the maps, so the conversion is exact up to the 8-bit
gloss code.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .._version import __version__
from ..atomic import write_json
from ..io import Maps
from ..model.brdf import SVBRDF
from ..outputs import check_output
from .arrays import ISOTROPIC, ExportWarning, code8, map_arrays, rgb, write_png

__all__ = ["WARD_EXPONENT", "MIN_ALPHA_SHOWN", "alpha_from_gloss", "export_openlime", "gloss_from_alpha"]

WARD_EXPONENT = 4.0
"""ShaderBRDF's ``ISO_WARD_EXPONENT``: gloss is linear in ``alpha^(1/4)``."""
MIN_ALPHA_SHOWN = 1e-5**0.5
"""ShaderBRDF's ``ward()`` returns 0 where ``(alpha <n, h>)^2 < 1e-5``: a lobe with ``alpha``
below ``sqrt(1e-5) = 0.0032`` is not shown at all."""


def gloss_from_alpha(alpha: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """OpenLIME's gloss ``g`` of roughness ``alpha`` for ``alphaLimits = limits``: the inverse of
    :func:`alpha_from_gloss` (``g = 0`` at ``a_max``, ``1`` at ``a_min``; ``0`` when they are equal)."""
    low, high = (limit ** (1 / WARD_EXPONENT) for limit in limits)
    if high == low:
        return np.zeros_like(alpha)
    return (high - np.power(alpha, 1 / WARD_EXPONENT)) / (high - low)


def alpha_from_gloss(gloss: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """The roughness ``alpha`` ShaderBRDF takes from gloss ``g`` for ``alphaLimits = limits``:
    ``(1 - g (G_max - G_min) - G_min)^4`` with ``G_min = 1 - a_max^(1/4)``, ``G_max = 1 - a_min^(1/4)``."""
    min_gloss = 1 - limits[1] ** (1 / WARD_EXPONENT)
    max_gloss = 1 - limits[0] ** (1 / WARD_EXPONENT)
    return np.power(1 - gloss * (max_gloss - min_gloss) - min_gloss, WARD_EXPONENT)


def export_openlime(maps: Maps | SVBRDF | str | Path, output: str | Path, *, overwrite: bool = False) -> Path:
    """Write the maps of OpenLIME's BRDF layer: ``kd.png``, ``ks.png``, ``normals.png``,
    ``gloss.png`` (8-bit) and ``info.json``, the layer's options (``new OpenLIME.Layer(info)``
    with the URLs made relative to the page).

    - ``kd.png``: ``k_d`` (the layer divides by pi), linear (``colorspaces.kd = "linear"``);
    - ``ks.png``: ``k_s``, linear; 0 where there is no lobe;
    - ``normals.png``: ``(n + 1) / 2``, the image frame (``x`` right, ``y`` up, OpenGL's convention);
    - ``gloss.png``: :func:`gloss_from_alpha` of ``alpha = sqrt(alpha_x alpha_y)`` (the layer's lobe
      is isotropic; the geometric mean keeps the lobe's peak and its integral), with
      ``alphaLimits`` the smallest and largest such ``alpha`` of the pixels with a lobe.

    Args:
        maps: see :func:`export`.
        output: the folder to write.

    Returns:
        The path of ``info.json`` (written last).

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is not set, or cannot be written.
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``.

    Warns:
        ExportWarning: values the layer cannot hold: ``k_d > 1`` or ``k_s > 1`` (clipped),
            anisotropic lobes (made isotropic), lobes narrower than :data:`MIN_ALPHA_SHOWN`
            (the shader shows nothing); each message counts the pixels.
    """
    check_output(output, overwrite=overwrite)
    arrays = map_arrays(maps)
    height, width = arrays.size
    lobe = arrays.lobe
    alpha_x, alpha_y = arrays.roughness[..., 0], arrays.roughness[..., 1]
    alpha = np.sqrt(alpha_x * alpha_y)
    limits = (float(alpha[lobe].min()), float(alpha[lobe].max())) if lobe.any() else (0.01, 0.5)
    gloss = np.where(lobe, gloss_from_alpha(np.where(lobe, alpha, limits[1]), limits), 0.0)
    anisotropic = lobe & (np.abs(alpha_x - alpha_y) > ISOTROPIC * alpha)
    _warn(arrays.diffuse, arrays.specular, anisotropic, lobe & (alpha < MIN_ALPHA_SHOWN))
    folder = Path(output)
    manifest = folder / "info.json"
    folder.mkdir(parents=True, exist_ok=True)
    manifest.unlink(missing_ok=True)
    images = {
        "kd": rgb(arrays.diffuse),
        "ks": rgb(np.where(lobe[..., None], arrays.specular, 0.0)),
        "normals": (arrays.normal + 1) / 2,
        "gloss": gloss,
    }
    for name, image in images.items():
        write_png(folder / f"{name}.png", code8(image), 8)
    write_json(
        manifest,
        {
            "type": "brdf",
            "layout": "image",
            "channels": {name: f"{name}.png" for name in images},
            "colorspaces": {"kd": "linear", "ks": "linear"},
            "alphaLimits": list(limits),
            "width": width,
            "height": height,
            "generator": f"torchspec {__version__} export",
            "note": "OpenLIME LayerBRDF options: new OpenLIME.Layer(info), channel URLs relative to this file",
        },
    )
    return manifest


def _warn(diffuse: np.ndarray, specular: np.ndarray, anisotropic: np.ndarray, invisible: np.ndarray) -> None:
    """One :class:`ExportWarning` listing what the layer cannot hold, with pixel counts."""
    counts = {
        "k_d > 1 (clipped)": int((diffuse > 1).any(-1).sum()),
        "k_s > 1 (clipped)": int((specular > 1).any(-1).sum()),
        "an anisotropic lobe (exported isotropic, alpha = sqrt(alpha_x alpha_y))": int(anisotropic.sum()),
        f"alpha < {MIN_ALPHA_SHOWN:.4f} (the layer's shader shows no lobe)": int(invisible.sum()),
    }
    found = [f"{what} at {count} pixel(s)" for what, count in counts.items() if count]
    if found:
        warnings.warn(
            "OpenLIME's BRDF layer cannot hold " + "; ".join(found) + " (docs/export.md).", ExportWarning, stacklevel=3
        )
