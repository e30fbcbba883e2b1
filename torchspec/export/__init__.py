"""SVBRDF maps for other tools (``torchspec export``): a Mitsuba 3 scene, a glTF 2.0 quad, or
16-bit PNG maps. Each mapping and what it cannot carry is stated in ``docs/export.md``.

- :func:`export_mitsuba` (:mod:`torchspec.export.mitsuba`): ``scene.xml`` and EXR textures;
  the painting is a rectangle under an orthographic camera, its material
  ``normalmap(blendbsdf(0.5, diffuse(2 k_d), roughconductor(beckmann, alpha_u, alpha_v, 2 k_s,
  F = 1))) = k_d / pi + k_s Beckmann``; an optional directional emitter reproduces a point-light
  frame.
- :func:`export_gltf` (:mod:`torchspec.export.gltf`): ``scene.gltf``, ``scene.bin`` and 8-bit PNG
  textures of a textured quad: metallic 0, ``roughness = sqrt(alpha)`` (glTF's GGX takes
  ``alpha = roughness^2``), ``k_s`` through ``KHR_materials_specular`` and anisotropy through
  ``KHR_materials_anisotropy``.
- :func:`export_png16` (:mod:`torchspec.export.png16`): the four maps as 16-bit PNG with their
  decoding in ``png16.json``; the normal map in OpenGL's and DirectX's conventions.
- :func:`export_openlime` (:mod:`torchspec.export.openlime`): the maps of OpenLIME's BRDF layer
  (``kd``, ``ks``, ``normals``, ``gloss``) and its options in ``info.json``; Ward's ``alpha`` to
  the layer's gloss exactly.
- :func:`export_rti` (:mod:`torchspec.export.rti`): an HSH ``.rti`` that RTIViewer opens, fitted
  to the maps' renders over the hemisphere, described in ``rti.json``.
- ``web``: the relighting page of :mod:`torchspec.view` as a static site (:func:`torchspec.view.export_web`).

:mod:`torchspec.export.arrays` holds what they share: the checked maps as numpy arrays, the
value encodings, :class:`ExportError` and :class:`ExportWarning`.

Every file is written atomically and each export's manifest (``scene.xml``, ``scene.gltf``,
``png16.json``, ``info.json``, ``rti.json``) last, so a folder with a manifest holds all of its files.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from ..io import Maps
from ..model.brdf import SVBRDF
from .arrays import ExportError, ExportWarning
from .gltf import export_gltf
from .mitsuba import MESH, MIN_ALPHA, export_mitsuba
from .openlime import export_openlime
from .png16 import export_png16
from .rti import export_rti

__all__ = [
    "ExportError",
    "ExportWarning",
    "DEFAULT_LIGHT",
    "FORMATS",
    "MIN_ALPHA",
    "export",
    "export_gltf",
    "export_mitsuba",
    "MESH",
    "export_openlime",
    "export_png16",
    "export_rti",
]

FORMATS = ("mitsuba", "gltf", "png16", "openlime", "rti", "web")
DEFAULT_LIGHT = (-0.5, 0.5, 0.5**0.5)
"""The Mitsuba export's light when none is given: a directional light at 45 degrees elevation from
the upper left (azimuth 135 degrees from the surface's +x towards +y), a painting's usual light,
so that the scene renders the maps instead of black."""


def export(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    to: str,
    light: Sequence[float] | None = None,
    irradiance: float | Sequence[float] | None = None,
    overwrite: bool = False,
    capture: str | Path | None = None,
    progress: bool = False,
) -> Path:
    """Export maps to one of :data:`FORMATS` (``"mitsuba"``, ``"gltf"``, ``"png16"``, ``"openlime"``, ``"rti"``,
    ``"web"``).

    Args:
        maps: a folder of SVBRDF maps (read with :func:`~torchspec.io.read_svbrdf`), its
            :class:`~torchspec.io.Maps` or an :class:`~torchspec.SVBRDF` with leading dims ``(H, W)``.
        output: the folder to write (created if needed).
        to: the format.
        light, irradiance: ``mitsuba`` only: see :func:`export_mitsuba` (irradiance 1 by
            default); without a light the scene is lit by :data:`DEFAULT_LIGHT` (a scene without
            an emitter, to light in Mitsuba, is :func:`export_mitsuba`'s ``light=None``). ``rti``
            takes one irradiance, its fitted lights' (default: the photographs', as bright as they
            are; pi for maps without their capture: :func:`export_rti`).
        overwrite: write into a folder that already holds files; refused otherwise
            (:func:`torchspec.outputs.check_output`).
        capture: ``web``: the capture the maps were fitted from, whose photographs the page shows
            beside the relit fit (:func:`torchspec.view.export_web`); ``rti``: the capture whose
            photographs' brightness and encoding the .rti takes (default: the one ``svbrdf.json``
            names, :func:`~torchspec.export.rti.rti_lighting`).
        progress: ``web`` only: a bar over the tiles written (on stderr).

    Returns:
        The export's manifest: ``scene.xml``, ``scene.gltf``, ``png16.json``, ``info.json``, ``rti.json``
        or (web) ``index.html``.

    Raises:
        ExportError: an unknown format, a light for a format other than ``mitsuba``, an
            irradiance for one other than ``mitsuba`` or ``rti``, or maps that the format cannot
            take (see each format).
        SVBRDFError: ``maps`` is a folder that is missing or not a valid map folder.

    Example:
        >>> export("fit", "fit-gltf", to="gltf")  # doctest: +SKIP
        PosixPath('fit-gltf/scene.gltf')
    """
    if to not in FORMATS:
        raise ExportError(f"the export format must be one of {', '.join(FORMATS)}; got {to!r}.")
    if capture is not None and to not in ("web", "rti"):
        raise ExportError(f"a capture can only be given to a web or rti export; got one for {to!r}. Drop it.")
    if to == "web" and light is None and irradiance is None:
        from ..view import export_web  # the viewer's page, tiled maps (torchspec.view)

        return export_web(maps, output, capture=capture, overwrite=overwrite, progress=progress)
    if to == "mitsuba":
        light = DEFAULT_LIGHT if light is None else light
        irradiance = 1.0 if irradiance is None else irradiance
        return export_mitsuba(maps, output, light=light, irradiance=irradiance, overwrite=overwrite)
    if light is not None:
        raise ExportError(f"a light can only be added to a mitsuba export; got one for {to!r}. Drop the light.")
    if to == "rti":
        return export_rti(maps, output, irradiance=_one_irradiance(irradiance), capture=capture, overwrite=overwrite)
    if irradiance is not None:
        raise ExportError(f"an irradiance can only be given to a mitsuba or rti export; got one for {to!r}. Drop it.")
    writer = {"gltf": export_gltf, "png16": export_png16, "openlime": export_openlime}[to]
    return writer(maps, output, overwrite=overwrite)


def _one_irradiance(irradiance: float | Sequence[float] | None) -> float | None:
    """The rti export's single irradiance (``None``: the photographs', :func:`export_rti`)."""
    if irradiance is None:
        return None
    values = [irradiance] if isinstance(irradiance, (int, float)) else list(irradiance)
    if len(values) != 1:
        raise ExportError(f"an rti export takes one irradiance (its lights are white); got {values}.")
    return float(values[0])
