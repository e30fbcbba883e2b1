"""The Mitsuba 3 export (:func:`export_mitsuba`): ``scene.xml`` and EXR textures of a rectangle
(or of the maps' height field, a mesh that casts the relief's shadows) under an orthographic camera."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._version import __version__
from ..atomic import atomic_path
from ..io import Maps, read_svbrdf, write_exr
from ..model.brdf import SVBRDF
from ..outputs import check_output
from .arrays import ISOTROPIC, ExportError, ExportWarning, MapArrays, height_array, map_arrays, relief_mesh, rgb

__all__ = ["export_mitsuba", "height_ply", "MESH", "MIN_ALPHA"]

MESH = "height.ply"
"""The height field's mesh beside ``scene.xml`` (maps with a height)."""

MIN_ALPHA = 1e-4
"""Mitsuba's own floor on a microfacet alpha; a lobe with ``alpha = 0`` is exported with it."""
_ANGLE = 1e-3  # radians: a rotation this close to a quarter turn is one


def export_mitsuba(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    light: Sequence[float] | None = None,
    irradiance: float | Sequence[float] = 1.0,
    spp: int = 16,
    shadowing: bool = False,
    overwrite: bool = False,
    height: np.ndarray | None = None,
) -> Path:
    """Write a Mitsuba 3 scene of the maps (for the RGB variants, e.g. ``scalar_rgb``).

    The painting is the rectangle ``|x| <= W / (2 M)``, ``|y| <= H / (2 M)`` (``M = max(W, H)``:
    the longer side is 1) in the plane ``z = 0``, world axes = the format's surface frame, seen
    by an orthographic camera on ``+z`` (the format's view ``(0, 0, 1)``) whose ``W x H`` film
    has one pixel per texel (box filter, textures looked up nearest), so a render is pixel for
    pixel the maps' prediction. Files: ``scene.xml``; ``textures/normal.exr`` (``(n + 1) / 2``,
    Mitsuba's ``normalmap`` encoding), ``diffuse_x2.exr`` and ``specular_x2.exr`` (``2 k_d``,
    ``2 k_s``: the blend's weight 0.5 halves them back), ``alpha_u.exr``, ``alpha_v.exr``.

    Args:
        maps: see :func:`export`.
        output: the folder to write.
        light: ``(3,)`` direction towards a light (surface frame, normalised here, ``z > 0``): adds
            a ``directional`` emitter, which renders a point-light frame of that direction.
        irradiance: the emitter's irradiance, one number or one per channel; for a capture's
            frame pass ``irradiance * exposure``, so the render is the recorded value.
        spp: the sampler's default sample count (``mitsuba -D spp=N`` overrides it).
        shadowing: keep Mitsuba's default ``normalmap`` shadowing function (Estevez et al. 2019,
            against the shading terminator: a factor ``<= 1`` that darkens tilted normals under
            grazing light). Off, the material is exactly ``k_d / pi + k_s Beckmann``; on, it is
            what Mitsuba renders by default for a normal-mapped surface (the development captures
            are rendered so).
        height: ``(H, W)`` the surface's height in pixel pitches (``height.exr``, written by a fit
            with cast shadows); default: the maps' own, where a folder or :class:`~torchspec.io.Maps`
            has one. With a height the shape is ``height.ply``, the height field as a triangle
            mesh (a vertex at each texel corner, the mean height of the texels around it, times
            ``1 / M``: one pixel pitch), its shading normals ``(0, 0, 1)`` so the normal map
            keeps the surface frame; the orthographic camera sees each texel at its pixel, and
            Mitsuba casts the relief's shadows.

    Returns:
        The path of ``scene.xml``.

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is not set (it replaces them), or cannot be written.
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``, or the light
            or irradiance is invalid.

    Warns:
        ExportWarning: an anisotropic lobe's rotation is not a multiple of 90 degrees (Mitsuba's
            lobe axes follow the surface's ``x`` and ``y``): it is rounded to the nearest one.

    Example:
        >>> export_mitsuba("truth", "scene", light=[0.3, -0.5, 0.8])  # doctest: +SKIP
        PosixPath('scene/scene.xml')
    """
    check_output(output, overwrite=overwrite)
    maps = read_svbrdf(maps) if isinstance(maps, (str, Path)) else maps  # read once: the maps and their height
    arrays = map_arrays(maps)
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise ExportError(f"spp must be an integer >= 1; got {spp!r}.")
    emitter = None if light is None else _emitter(light, irradiance, arrays.channels)
    relief = height_array(maps, arrays.size, height)
    alpha_u, alpha_v = _quarter_turns(arrays)
    lobe = arrays.lobe
    # alpha = 0 is the format's "no lobe": any alpha renders k_s = 0 as 0, and 1 keeps it finite.
    alpha_u, alpha_v = (np.where(lobe, np.maximum(a, MIN_ALPHA), 1.0) for a in (alpha_u, alpha_v))
    folder = Path(output)
    scene = folder / "scene.xml"
    folder.mkdir(parents=True, exist_ok=True)
    scene.unlink(missing_ok=True)
    textures = folder / "textures"
    write_exr(textures / "normal.exr", (arrays.normal + 1.0) / 2.0, ["R", "G", "B"])
    write_exr(textures / "diffuse_x2.exr", 2.0 * rgb(arrays.diffuse), ["R", "G", "B"])
    write_exr(textures / "specular_x2.exr", 2.0 * rgb(arrays.specular), ["R", "G", "B"])
    write_exr(textures / "alpha_u.exr", alpha_u, ["Y"])
    write_exr(textures / "alpha_v.exr", alpha_v, ["Y"])
    (folder / MESH).unlink(missing_ok=True)
    if relief is not None:
        with atomic_path(folder / MESH) as tmp:
            tmp.write_bytes(height_ply(relief))
    text = _scene_xml(arrays.size, spp, emitter, shadowing, relief is not None)
    with atomic_path(scene) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return scene


def _bitmap(name: str, file: str) -> str:
    # Mitsuba's rectangle has v = 0 at y = -1 (the bottom) and a bitmap's row 0 at v = 0: to_uv
    # flips v so that row 0 of every texture is the top of the painting, as in the maps.
    return f"""<texture type="bitmap" name="{name}">
    <string name="filename" value="textures/{file}"/>
    <boolean name="raw" value="true"/>
    <string name="filter_type" value="nearest"/>
    <transform name="to_uv">
        <scale x="1" y="-1"/>
        <translate x="0" y="1"/>
    </transform>
</texture>"""


def _indent(text: str, spaces: int) -> str:
    return "\n".join(" " * spaces + line for line in text.splitlines())


def height_ply(height: np.ndarray) -> bytes:
    """A binary PLY of the height field ``height (H, W)`` (pixel pitches) over the rectangle of
    :func:`export_mitsuba` (:func:`~torchspec.export.arrays.relief_mesh`: a vertex at each texel
    corner, two triangles per texel), shading normals ``(0, 0, 1)``, ``(u, v)`` as Mitsuba's
    rectangle has them (``v = 0`` at the bottom)."""
    mesh = relief_mesh(height)
    count = len(mesh.position)
    vertex = np.zeros(count, dtype=[(name, "<f4") for name in ("x", "y", "z", "nx", "ny", "nz", "u", "v")])
    for k, name in enumerate("xyz"):
        vertex[name] = mesh.position[:, k]
    vertex["nz"], vertex["u"], vertex["v"] = 1.0, mesh.texel[:, 0], 1.0 - mesh.texel[:, 1]
    face = np.zeros(len(mesh.triangles), dtype=[("count", "u1"), ("index", "<i4", (3,))])
    face["count"], face["index"] = 3, mesh.triangles
    header = "\n".join([
        "ply", "format binary_little_endian 1.0", f"comment torchspec {__version__}: height field",
        f"element vertex {count}", *(f"property float {name}" for name in vertex.dtype.names),
        f"element face {len(face)}", "property list uchar int vertex_indices", "end_header",
    ]) + "\n"  # fmt: skip
    return header.encode("ascii") + vertex.tobytes() + face.tobytes()


def _scene_xml(
    size: tuple[int, int], spp: int, emitter: tuple[np.ndarray, np.ndarray] | None, shadowing: bool, mesh: bool = False
) -> str:
    height, width = size
    half_w, half_h = width / (2 * max(size)), height / (2 * max(size))
    if emitter is None:
        # No "--" in an XML comment: the option is named without its dashes.
        light = "    <!-- no emitter: add one, or export with the light option (torchspec export, light X Y Z) -->"
    else:
        direction, rgb = emitter
        light = (
            '    <emitter type="directional">\n'
            f'        <vector name="direction" value="{", ".join(f"{-d:.9g}" for d in direction)}"/>\n'
            f'        <rgb name="irradiance" value="{rgb[0]:.9g}, {rgb[1]:.9g}, {rgb[2]:.9g}"/>\n'
            "    </emitter>"
        )
    terminator = (
        "normalmap use_shadowing_function true: Mitsuba's shadow-terminator factor (<= 1) is kept."
        if shadowing
        else "normalmap use_shadowing_function false: the BRDF is exactly the above."
    )
    if mesh:  # the height field (height.ply), already in world units
        shape = (
            '    <shape type="ply">\n'
            f'        <string name="filename" value="{MESH}"/>\n'
            '        <boolean name="face_normals" value="false"/>'
        )
    else:
        shape = (
            '    <shape type="rectangle">\n'
            '        <transform name="to_world">\n'
            f'            <scale x="{half_w:.9g}" y="{half_h:.9g}" z="1"/>\n'
            "        </transform>"
        )
    return f"""<?xml version="1.0" encoding="utf-8"?>
<!-- Written by torchspec {__version__} (torchspec export; mappings in docs/export.md).
     World axes = the maps' surface frame: x right, y up, z towards the camera. Material:
     k_d / pi + k_s * Beckmann(alpha_u, alpha_v), Fresnel 1, as the blend of 0.5 * diffuse(2 k_d)
     and 0.5 * roughconductor(2 k_s) under the normal map. The maps' Ward alpha is used as the
     Beckmann alpha one to one: the lobes agree within 2 % at the peak, not in the tails.
     {terminator}
     For the RGB variants (scalar_rgb, llvm_ad_rgb, cuda_ad_rgb). -->
<scene version="3.0.0">
    <default name="spp" value="{spp}"/>
    <integrator type="direct"/>
    <sensor type="orthographic">
        <transform name="to_world">
            <scale x="{half_w:.9g}" y="{half_w:.9g}" z="1"/>
            <lookat origin="0, 0, 1" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/>
            <integer name="height" value="{height}"/>
            <string name="pixel_format" value="rgb"/>
            <rfilter type="box"/>
        </film>
    </sensor>
{shape}
        <bsdf type="normalmap">
            <boolean name="use_shadowing_function" value="{str(bool(shadowing)).lower()}"/>
{_indent(_bitmap("normalmap", "normal.exr"), 12)}
            <bsdf type="blendbsdf">
                <float name="weight" value="0.5"/>
                <bsdf type="diffuse">
{_indent(_bitmap("reflectance", "diffuse_x2.exr"), 20)}
                </bsdf>
                <bsdf type="roughconductor">
                    <string name="material" value="none"/>
                    <string name="distribution" value="beckmann"/>
{_indent(_bitmap("alpha_u", "alpha_u.exr"), 20)}
{_indent(_bitmap("alpha_v", "alpha_v.exr"), 20)}
{_indent(_bitmap("specular_reflectance", "specular_x2.exr"), 20)}
                </bsdf>
            </bsdf>
        </bsdf>
    </shape>
{light}
</scene>
"""


def _emitter(light, irradiance, channels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    direction = np.asarray(light, dtype=np.float64).reshape(-1)
    if direction.shape != (3,) or not np.isfinite(direction).all() or np.linalg.norm(direction) == 0:
        raise ExportError(f"the light must be a finite non-zero direction (x, y, z); got {list(direction)}.")
    direction = direction / np.linalg.norm(direction)
    if direction[2] <= 0:
        raise ExportError(f"the light must be above the surface (z > 0 in the surface frame); got {list(direction)}.")
    values = np.asarray(irradiance, dtype=np.float64).reshape(-1)
    if values.size not in (1, len(channels)) or not np.isfinite(values).all() or (values < 0).any():
        raise ExportError(
            f"the irradiance must be one number >= 0 or one per channel {list(channels)}; got {list(values)}."
        )
    return direction, np.broadcast_to(values, (3,)) if values.size == 1 else rgb(values)


def _quarter_turns(arrays: MapArrays) -> tuple[np.ndarray, np.ndarray]:
    """``alpha_u, alpha_v`` along the surface ``x`` and ``y``: the lobe's rotation rounded to a
    quarter turn (odd ones swap the axes), with a warning where that changes an anisotropic lobe."""
    alpha_x, alpha_y = arrays.roughness[..., 0], arrays.roughness[..., 1]
    if arrays.rotation is None:
        return alpha_x, alpha_y
    turns = np.round(arrays.rotation / (math.pi / 2))
    residual = np.abs(arrays.rotation - turns * (math.pi / 2))
    anisotropic = np.abs(alpha_x - alpha_y) > ISOTROPIC * np.maximum(alpha_x, alpha_y)
    lossy = anisotropic & arrays.lobe & (residual > _ANGLE)
    if lossy.any():
        warnings.warn(
            f"Mitsuba's anisotropic lobe follows the surface x and y axes: {int(lossy.sum())} pixel(s) with a "
            f"rotation that is not a multiple of 90 degrees were rounded to the nearest one (up to "
            f"{math.degrees(float(residual[lossy].max())):.3g} degrees off).",
            ExportWarning,
            stacklevel=3,
        )
    odd = np.mod(turns, 2) == 1
    return np.where(odd, alpha_y, alpha_x), np.where(odd, alpha_x, alpha_y)


