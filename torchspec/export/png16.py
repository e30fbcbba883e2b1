"""The 16-bit PNG export (:func:`export_png16`): the four maps with their decoding in ``png16.json``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._version import __version__
from ..atomic import write_json
from ..io import Maps
from ..model.brdf import SVBRDF
from ..outputs import check_output
from .arrays import map_arrays, write_png

__all__ = ["NORMAL_FILES", "export_png16"]

_CODE16 = 65535
NORMAL_FILES = {"normal": "normal_opengl.png", "normal_directx": "normal_directx.png"}
"""The normal map's two files: OpenGL's convention (``+y`` up, green ``= (n_y + 1) / 2``) and
DirectX's (``+y`` down, green ``= (1 - n_y) / 2``); red and blue are the same in both."""


def export_png16(maps: Maps | SVBRDF | str | Path, output: str | Path, *, overwrite: bool = False) -> Path:
    """Write the maps as 16-bit PNG with their decoding in ``png16.json``.

    ``normal_opengl.png`` (RGB ``= (n + 1) / 2``, ``+y`` up) and ``normal_directx.png`` (the same
    with green ``= (1 - n_y) / 2``, ``+y`` down; ``png16.json``'s ``normal_directx`` entry decodes it
    to the same ``n``), ``diffuse.png`` and ``specular.png`` (RGB, or grey for
    maps of channel ``Y``), ``roughness.png`` (RGB: ``alpha_x, alpha_y`` and the rotation ``A``
    modulo pi, which leaves the lobe unchanged; 0 without a rotation map). Every channel decodes
    as ``value = offset + scale * code / 65535`` with the ``offset`` and ``scale`` per channel in
    ``png16.json``; ``k_d``, ``k_s`` and ``alpha`` are scaled by their map's maximum, so each map
    uses the full range (the error is at most ``scale / 131070``).

    Args:
        maps: see :func:`export`.
        output: the folder to write.

    Returns:
        The path of ``png16.json``.

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is not set (it replaces them), or cannot be written.
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``.

    Example:
        >>> export_png16("fit", "fit-png")  # doctest: +SKIP
        PosixPath('fit-png/png16.json')
    """
    check_output(output, overwrite=overwrite)
    arrays = map_arrays(maps)
    height, width = arrays.size
    rotation = np.zeros(arrays.size) if arrays.rotation is None else np.mod(arrays.rotation, math.pi)
    alpha_scale = _scale(arrays.roughness)
    entries = {
        "normal": (arrays.normal, ["X", "Y", "Z"], [2.0] * 3, [-1.0] * 3),
        "normal_directx": (arrays.normal, ["X", "Y", "Z"], [2.0, -2.0, 2.0], [-1.0, 1.0, -1.0]),
        "diffuse": (arrays.diffuse, list(arrays.channels), [_scale(arrays.diffuse)] * len(arrays.channels), None),
        "specular": (arrays.specular, list(arrays.channels), [_scale(arrays.specular)] * len(arrays.channels), None),
        "roughness": (
            np.concatenate([arrays.roughness, rotation[..., None]], axis=-1),
            ["alpha_x", "alpha_y", "rotation"],
            [alpha_scale, alpha_scale, math.pi],
            None,
        ),
    }
    folder = Path(output)
    manifest = folder / "png16.json"
    folder.mkdir(parents=True, exist_ok=True)
    manifest.unlink(missing_ok=True)
    described = {}
    for name, (value, channels, scale, offset) in entries.items():
        offset = offset or [0.0] * len(channels)
        code = (value - np.asarray(offset)) / np.asarray(scale)
        file = NORMAL_FILES.get(name, f"{name}.png")
        write_png(folder / file, np.round(np.clip(code, 0, 1) * _CODE16).astype(np.uint16), 16)
        described[name] = {"file": file, "channels": channels, "scale": scale, "offset": offset}
    described["roughness"]["rotation_map"] = arrays.rotation is not None
    write_json(
        manifest,
        {
            "format": "torchspec.png16",
            "version": 1,
            "generator": f"torchspec {__version__} export",
            "width": width,
            "height": height,
            "decode": "value = offset + scale * code / 65535, per channel",
            "maps": described,
        },
    )
    return manifest


def _scale(value: np.ndarray) -> float:
    """The largest value, the full scale of a 16-bit code (1 for an all-zero map)."""
    top = float(value.max())
    return top if top > 0 else 1.0
