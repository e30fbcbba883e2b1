"""SVBRDF maps for other tools (``torchspec export``): a Mitsuba 3 scene, a glTF 2.0 quad, or
16-bit PNG maps. Each mapping and what it cannot carry is stated in ``docs/export.md``.

- :func:`export_mitsuba`: ``scene.xml`` and EXR textures; the painting is a rectangle under an
  orthographic camera, its material ``normalmap(blendbsdf(0.5, diffuse(2 k_d),
  roughconductor(beckmann, alpha_u, alpha_v, 2 k_s, F = 1))) = k_d / pi + k_s Beckmann``; an
  optional directional emitter reproduces a point-light frame.
- :func:`export_gltf`: ``scene.gltf``, ``scene.bin`` and 8-bit PNG textures of a textured quad:
  metallic 0, ``roughness = sqrt(alpha)`` (glTF's GGX takes ``alpha = roughness^2``), ``k_s`` through
  ``KHR_materials_specular`` and anisotropy through ``KHR_materials_anisotropy``.
- :func:`export_png16`: the four maps as 16-bit PNG with their decoding in ``png16.json``.

Every file is written atomically and each export's manifest (``scene.xml``, ``scene.gltf``,
``png16.json``) last, so a folder with a manifest holds all of its files.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path, write_json
from ._version import __version__
from .brdf import SVBRDF
from .errors import TorchspecError
from .io import Maps, read_svbrdf, write_exr

__all__ = ["ExportError", "ExportWarning", "FORMATS", "export", "export_gltf", "export_mitsuba", "export_png16"]

FORMATS = ("mitsuba", "gltf", "png16")
MIN_ALPHA = 1e-4
"""Mitsuba's own floor on a microfacet alpha; a lobe with ``alpha = 0`` is exported with it."""
_ISOTROPIC = 1e-3  # relative difference of alpha_x, alpha_y below which a lobe counts as isotropic
_ANGLE = 1e-3  # radians: a rotation this close to a quarter turn is one
_CODE16 = 65535


class ExportError(TorchspecError):
    """Maps or options that cannot be exported as asked; the message names what and why."""


class ExportWarning(UserWarning):
    """An export that had to change values its target cannot hold (clipped, rounded)."""


@dataclass(frozen=True)
class _Arrays:
    """The maps as float64 numpy arrays, ``(H, W, ...)``; ``specular`` broadcast to ``C``."""

    normal: np.ndarray
    diffuse: np.ndarray
    specular: np.ndarray
    roughness: np.ndarray
    rotation: np.ndarray | None
    channels: tuple[str, ...]

    @property
    def size(self) -> tuple[int, int]:
        return self.normal.shape[0], self.normal.shape[1]

    @property
    def lobe(self) -> np.ndarray:
        """``(H, W)``: the pixels with a specular lobe (``k_s > 0`` on some channel)."""
        return (self.specular > 0).any(axis=-1)


def export(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    to: str,
    light: Sequence[float] | None = None,
    irradiance: float | Sequence[float] | None = None,
) -> Path:
    """Export maps to one of :data:`FORMATS` (``"mitsuba"``, ``"gltf"``, ``"png16"``).

    Args:
        maps: a folder of SVBRDF maps (read with :func:`~torchspec.io.read_svbrdf`), its
            :class:`~torchspec.io.Maps` or an :class:`~torchspec.SVBRDF` with leading dims ``(H, W)``.
        output: the folder to write (created if needed).
        to: the format.
        light, irradiance: ``mitsuba`` only: see :func:`export_mitsuba` (irradiance 1 by default).

    Returns:
        The export's manifest: ``scene.xml``, ``scene.gltf`` or ``png16.json``.

    Raises:
        ExportError: an unknown format, a light for a format other than ``mitsuba``, an
            irradiance without a light, or maps that the format cannot take (see each format).
        SVBRDFError: ``maps`` is a folder that is missing or not a valid map folder.

    Example:
        >>> export("fit", "fit-gltf", to="gltf")  # doctest: +SKIP
        PosixPath('fit-gltf/scene.gltf')
    """
    if to not in FORMATS:
        raise ExportError(f"the export format must be one of {', '.join(FORMATS)}; got {to!r}.")
    if light is None and irradiance is not None:
        raise ExportError(f"an irradiance needs a light to apply to; got {irradiance!r} and no light. Add the light.")
    if to == "mitsuba":
        return export_mitsuba(maps, output, light=light, irradiance=1.0 if irradiance is None else irradiance)
    if light is not None:
        raise ExportError(f"a light can only be added to a mitsuba export; got one for {to!r}. Drop the light.")
    return export_gltf(maps, output) if to == "gltf" else export_png16(maps, output)


def export_mitsuba(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    light: Sequence[float] | None = None,
    irradiance: float | Sequence[float] = 1.0,
    spp: int = 16,
    shadowing: bool = False,
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
            grazing light, e.g. by 0.6 % for a 12-degree tilt lit at 65 degrees). Off, the material is
            exactly ``k_d / pi + k_s Beckmann``; on, it is what Mitsuba renders by default for a
            normal-mapped surface (as the development captures were rendered).

    Returns:
        The path of ``scene.xml``.

    Raises:
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``, or the light
            or irradiance is invalid.

    Warns:
        ExportWarning: an anisotropic lobe's rotation is not a multiple of 90 degrees (Mitsuba's
            lobe axes follow the surface's ``x`` and ``y``): it is rounded to the nearest one.

    Example:
        >>> export_mitsuba("truth", "scene", light=[0.3, -0.5, 0.8])  # doctest: +SKIP
        PosixPath('scene/scene.xml')
    """
    arrays = _arrays(maps)
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise ExportError(f"spp must be an integer >= 1; got {spp!r}.")
    emitter = None if light is None else _emitter(light, irradiance, arrays.channels)
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
    write_exr(textures / "diffuse_x2.exr", 2.0 * _rgb(arrays.diffuse), ["R", "G", "B"])
    write_exr(textures / "specular_x2.exr", 2.0 * _rgb(arrays.specular), ["R", "G", "B"])
    write_exr(textures / "alpha_u.exr", alpha_u, ["Y"])
    write_exr(textures / "alpha_v.exr", alpha_v, ["Y"])
    text = _scene_xml(arrays.size, spp, emitter, shadowing)
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


def _scene_xml(size: tuple[int, int], spp: int, emitter: tuple[np.ndarray, np.ndarray] | None, shadowing: bool) -> str:
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
    <shape type="rectangle">
        <transform name="to_world">
            <scale x="{half_w:.9g}" y="{half_h:.9g}" z="1"/>
        </transform>
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
    return direction, np.broadcast_to(values, (3,)) if values.size == 1 else _rgb(values)


def _quarter_turns(arrays: _Arrays) -> tuple[np.ndarray, np.ndarray]:
    """``alpha_u, alpha_v`` along the surface ``x`` and ``y``: the lobe's rotation rounded to a
    quarter turn (odd ones swap the axes), with a warning where that changes an anisotropic lobe."""
    alpha_x, alpha_y = arrays.roughness[..., 0], arrays.roughness[..., 1]
    if arrays.rotation is None:
        return alpha_x, alpha_y
    turns = np.round(arrays.rotation / (math.pi / 2))
    residual = np.abs(arrays.rotation - turns * (math.pi / 2))
    anisotropic = np.abs(alpha_x - alpha_y) > _ISOTROPIC * np.maximum(alpha_x, alpha_y)
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


def export_gltf(maps: Maps | SVBRDF | str | Path, output: str | Path) -> Path:
    """Write a glTF 2.0 textured quad of the maps: ``scene.gltf``, ``scene.bin`` and 8-bit PNG
    textures in ``textures/``.

    The quad is the rectangle of :func:`export_mitsuba` (longer side 1 m, in the ``z = 0`` plane,
    facing ``+z``: glTF's ``+y`` up matches the format's), with ``NORMAL`` and ``TANGENT = +x``,
    texture row 0 at the top. Material, per texel (``m = max_c k_s``):

    - ``baseColor = k_d / (1 - m)`` (sRGB PNG): glTF weighs the diffuse by ``1 - m`` here;
    - metallic 0, ``roughness = sqrt(alpha)`` (glTF's GGX uses ``alpha = roughness^2``), of the
      smaller ``alpha`` when anisotropic;
    - ``KHR_materials_specular``: ``specular = m``, ``specularColor = k_s / m`` with factor 25
      (``0.04 x 25 = 1``), so ``F0 = k_s`` and ``F90 = m``: ``F = k_s`` exactly for grey ``k_s``;
    - ``KHR_materials_anisotropy`` when some lobe is anisotropic: direction ``A`` (or ``A + 90``
      degrees when ``alpha_y > alpha_x``), ``strength^2 = (alpha_max - alpha_min) / (1 - alpha_min)``;
    - the normal map in glTF's convention (tangent space, ``+y`` up, ``RGB = (n + 1) / 2``).

    Args:
        maps: see :func:`export`.
        output: the folder to write.

    Returns:
        The path of ``scene.gltf``.

    Raises:
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``.

    Warns:
        ExportWarning: values outside what glTF holds were clipped (``baseColor > 1``, ``k_s > 1``,
            ``alpha > 1``); the message counts the pixels.

    Example:
        >>> export_gltf("fit", "fit-gltf")  # doctest: +SKIP
        PosixPath('fit-gltf/scene.gltf')
    """
    arrays = _arrays(maps)
    height, width = arrays.size
    lobe = arrays.lobe
    clipped = {}
    specular = _rgb(arrays.specular)
    strength = specular.max(axis=-1)
    clipped["k_s > 1"] = strength > 1
    strength = np.minimum(strength, 1.0)
    strength_factor = float(strength.max()) if lobe.any() else 0.0
    strength_code = _code8(strength / strength_factor) if strength_factor > 0 else np.zeros(arrays.size, np.uint8)
    strength = strength_factor * strength_code / 255.0  # the weight a viewer applies
    color = np.where(strength[..., None] > 0, specular / np.maximum(strength, 1e-12)[..., None], 0.0)
    base = _rgb(arrays.diffuse) / np.maximum(1.0 - strength, 1e-12)[..., None]
    clipped["base color > 1"] = (base > 1).any(axis=-1)

    alpha = arrays.roughness
    alpha_min, alpha_max = alpha.min(axis=-1), alpha.max(axis=-1)
    clipped["alpha > 1"] = lobe & (alpha_max > 1)
    alpha_min, alpha_max = np.minimum(alpha_min, 1.0), np.minimum(alpha_max, 1.0)
    roughness = np.sqrt(alpha_min)
    rough_factor = float(roughness[lobe].max()) if lobe.any() else 1.0
    rough_factor = rough_factor if rough_factor > 0 else 1.0
    roughness = np.where(lobe, roughness / rough_factor, 1.0)
    anisotropy = np.where(
        lobe & (alpha_min < 1), np.sqrt(np.clip((alpha_max - alpha_min) / np.maximum(1 - alpha_min, 1e-12), 0, 1)), 0.0
    )
    anisotropic = bool((anisotropy > math.sqrt(_ISOTROPIC)).any())
    rotation = np.zeros(arrays.size) if arrays.rotation is None else arrays.rotation
    angle = rotation + np.where(alpha[..., 1] > alpha[..., 0], math.pi / 2, 0.0)

    bad = {what: int(mask.sum()) for what, mask in clipped.items() if mask.any()}
    if bad:
        warnings.warn(
            "glTF cannot hold every value; clipped: " + ", ".join(f"{what} at {n} pixel(s)" for what, n in bad.items()),
            ExportWarning,
            stacklevel=2,
        )

    folder = Path(output)
    manifest = folder / "scene.gltf"
    folder.mkdir(parents=True, exist_ok=True)
    manifest.unlink(missing_ok=True)
    images = {
        "base_color": _code8(_srgb(base)),
        "metallic_roughness": np.stack(  # R unused (occlusion), G roughness, B metallic
            [np.full(arrays.size, 255, np.uint8), _code8(roughness), np.zeros(arrays.size, np.uint8)], axis=-1
        ),
        "normal": _code8((arrays.normal + 1.0) / 2.0),
        "specular": np.concatenate([_code8(_srgb(color)), strength_code[..., None]], axis=-1),
    }
    if anisotropic:
        direction = (np.stack([np.cos(angle), np.sin(angle)], axis=-1) + 1.0) / 2.0
        images["anisotropy"] = np.concatenate([_code8(direction), _code8(anisotropy)[..., None]], axis=-1)
    for name, image in images.items():
        _write_png(folder / "textures" / f"{name}.png", image, 8)
    index = {name: k for k, name in enumerate(images)}
    buffer, views, accessors = _quad(width / max(width, height), height / max(width, height))
    with atomic_path(folder / "scene.bin") as tmp:
        tmp.write_bytes(buffer)

    extensions = {
        "KHR_materials_specular": {
            "specularFactor": strength_factor,
            "specularTexture": {"index": index["specular"]},
            "specularColorFactor": [25.0, 25.0, 25.0],
            "specularColorTexture": {"index": index["specular"]},
        }
    }
    if anisotropic:
        extensions["KHR_materials_anisotropy"] = {
            "anisotropyStrength": 1.0,
            "anisotropyTexture": {"index": index["anisotropy"]},
        }
    document = {
        "asset": {"version": "2.0", "generator": f"torchspec {__version__} export"},
        "extensionsUsed": sorted(extensions),
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "painting"}],
        "meshes": [
            {
                "name": "painting",
                "primitives": [
                    {
                        "attributes": {"POSITION": 1, "NORMAL": 2, "TANGENT": 3, "TEXCOORD_0": 4},
                        "indices": 0,
                        "material": 0,
                        "mode": 4,
                    }
                ],
            }
        ],
        "materials": [
            {
                "name": "svbrdf",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": index["base_color"]},
                    "metallicFactor": 0.0,
                    "roughnessFactor": rough_factor,
                    "metallicRoughnessTexture": {"index": index["metallic_roughness"]},
                },
                "normalTexture": {"index": index["normal"]},
                "extensions": extensions,
            }
        ],
        # Texels are measurements: magnified nearest, as the maps are pixels.
        "samplers": [{"magFilter": 9728, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071}],
        "images": [{"uri": f"textures/{name}.png", "mimeType": "image/png"} for name in images],
        "textures": [{"source": k, "sampler": 0} for k in range(len(images))],
        "buffers": [{"uri": "scene.bin", "byteLength": len(buffer)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    write_json(manifest, document)
    return manifest


def _quad(width: float, height: float) -> tuple[bytes, list[dict], list[dict]]:
    """The binary buffer, buffer views and accessors of a ``width x height`` quad facing ``+z``:
    indices, POSITION, NORMAL, TANGENT, TEXCOORD_0 (accessors 0 to 4)."""
    x, y = width / 2, height / 2
    # top-left, bottom-left, bottom-right, top-right; glTF's uv (0, 0) is the image's top-left.
    position = np.array([[-x, y, 0], [-x, -y, 0], [x, -y, 0], [x, y, 0]], np.float32)
    normal = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    tangent = np.tile(np.array([1, 0, 0, 1], np.float32), (4, 1))  # bitangent = n x t = +y
    uv = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)  # counter-clockwise seen from +z
    parts = [
        (indices, 5123, "SCALAR", 34963),
        (position, 5126, "VEC3", 34962),
        (normal, 5126, "VEC3", 34962),
        (tangent, 5126, "VEC4", 34962),
        (uv, 5126, "VEC2", 34962),
    ]
    buffer, views, accessors = b"", [], []
    for k, (data, component, kind, target) in enumerate(parts):
        raw = data.astype(data.dtype.newbyteorder("<")).tobytes()
        views.append({"buffer": 0, "byteOffset": len(buffer), "byteLength": len(raw), "target": target})
        accessor = {"bufferView": k, "componentType": component, "count": len(data), "type": kind}
        if kind == "VEC3" and k == 1:  # POSITION must carry its bounds
            accessor["min"], accessor["max"] = data.min(axis=0).tolist(), data.max(axis=0).tolist()
        accessors.append(accessor)
        buffer += raw + b"\0" * (-len(raw) % 4)  # every view starts 4-byte aligned
    return buffer, views, accessors


def export_png16(maps: Maps | SVBRDF | str | Path, output: str | Path) -> Path:
    """Write the maps as 16-bit PNG with their decoding in ``png16.json``.

    ``normal.png`` (RGB ``= (n + 1) / 2``), ``diffuse.png`` and ``specular.png`` (RGB, or grey for
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
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``.

    Example:
        >>> export_png16("fit", "fit-png")  # doctest: +SKIP
        PosixPath('fit-png/png16.json')
    """
    arrays = _arrays(maps)
    height, width = arrays.size
    rotation = np.zeros(arrays.size) if arrays.rotation is None else np.mod(arrays.rotation, math.pi)
    alpha_scale = _scale(arrays.roughness)
    entries = {
        "normal": (arrays.normal, ["X", "Y", "Z"], [2.0] * 3, [-1.0] * 3),
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
        _write_png(folder / f"{name}.png", np.round(np.clip(code, 0, 1) * _CODE16).astype(np.uint16), 16)
        described[name] = {"file": f"{name}.png", "channels": channels, "scale": scale, "offset": offset}
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


def _arrays(maps) -> _Arrays:
    if isinstance(maps, (str, Path)):
        maps = read_svbrdf(maps)
    svbrdf = maps.svbrdf if isinstance(maps, Maps) else maps
    if not isinstance(svbrdf, SVBRDF):
        raise ExportError(f"maps must be a map folder, Maps or an SVBRDF; got {type(maps).__name__}.")
    if len(svbrdf.shape) != 2:
        raise ExportError(
            f"the SVBRDF must have leading dims (H, W); got {tuple(svbrdf.shape)}. Reshape it: svbrdf.reshape(H, W)."
        )
    channels = tuple(svbrdf.channels)
    if channels not in (("R", "G", "B"), ("Y",)):
        raise ExportError(
            f"the maps must have channels R, G, B or Y to export; got {list(channels)}. "
            "Other channel sets have no colour meaning in Mitsuba, glTF or PNG."
        )

    def array(value):
        return value.detach().cpu().double().numpy()

    diffuse = array(svbrdf.diffuse)
    values = {
        "normal": array(svbrdf.normal),
        "diffuse": diffuse,
        "specular": np.broadcast_to(array(svbrdf.specular), diffuse.shape),
        "roughness": array(svbrdf.roughness),
        "rotation": None if svbrdf.rotation is None else array(svbrdf.rotation),
    }
    for name, value in values.items():
        if value is not None and not np.isfinite(value).all():
            raise ExportError(
                f"SVBRDF.{name} must be finite; got {int((~np.isfinite(value)).sum())} NaN or Inf value(s)."
            )
    for name in ("diffuse", "specular", "roughness"):
        if (values[name] < 0).any():
            raise ExportError(f"SVBRDF.{name} must be >= 0; got a minimum of {values[name].min():.3g}.")
    if svbrdf.specular2 is not None and bool((svbrdf.specular2 > 0).any()):
        count = int((svbrdf.specular2 > 0).any(-1).sum())
        warnings.warn(
            f"{count} pixel(s) have a second lobe (ward-dual: specular2.exr, roughness2.exr), which no export "
            "carries: they are exported with their first (sharper) lobe only (docs/export.md).",
            ExportWarning,
            stacklevel=3,
        )
    return _Arrays(channels=channels, **values)


def _rgb(value: np.ndarray) -> np.ndarray:
    """``(..., 3)``: a single channel replicated (grey)."""
    return np.repeat(value, 3, axis=-1) if value.shape[-1] == 1 else value


def _srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of values clipped to ``[0, 1]``."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _code8(value: np.ndarray) -> np.ndarray:
    return np.round(np.clip(value, 0.0, 1.0) * 255).astype(np.uint8)


def _write_png(path: Path, image: np.ndarray, bitdepth: int) -> None:
    """An ``(H, W)`` or ``(H, W, C)`` (C = 1 to 4) integer image as PNG, atomically."""
    import png

    image = image[..., None] if image.ndim == 2 else image
    height, width, count = image.shape
    writer = png.Writer(width, height, greyscale=count <= 2, alpha=count in (2, 4), bitdepth=bitdepth, compression=9)
    with atomic_path(path) as tmp, open(tmp, "wb") as file:
        writer.write(file, image.reshape(height, width * count).tolist())
