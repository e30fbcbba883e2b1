"""The glTF 2.0 export (:func:`export_gltf`): ``scene.gltf``, ``scene.bin`` and 8-bit PNG textures
of a textured quad (or of the maps' height field, a mesh that casts the relief's shadows)."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._version import __version__
from ..atomic import atomic_path, write_json
from ..io import Maps, read_svbrdf
from ..model.brdf import SVBRDF
from ..outputs import check_output
from .arrays import (
    ISOTROPIC,
    ExportWarning,
    MapArrays,
    code8,
    height_array,
    map_arrays,
    relief_mesh,
    rgb,
    srgb,
    write_png,
)

__all__ = ["export_gltf"]


def export_gltf(
    maps: Maps | SVBRDF | str | Path, output: str | Path, *, overwrite: bool = False, height: np.ndarray | None = None
) -> Path:
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

    With a height (``height``, ``(H, W)`` in pixel pitches; default: the maps' ``height.exr``
    where a folder or :class:`~torchspec.io.Maps` has one, written by a fit with cast shadows) the
    quad is the height field's mesh (:func:`~torchspec.export.arrays.relief_mesh`: a vertex at
    each texel corner, ``z`` = height over ``max(W, H)``, 32-bit indices), its ``NORMAL`` and
    ``TANGENT`` still ``+z`` and ``+x`` so the normal map keeps the surface frame: a renderer that
    casts shadows casts the relief's.

    Args:
        maps: see :func:`export`.
        output: the folder to write.
        overwrite: replace what ``output`` holds.
        height: see above.

    Returns:
        The path of ``scene.gltf``.

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is not set (it replaces them), or cannot be written.
        ExportError: the maps are not ``(H, W)`` with channels ``R, G, B`` or ``Y``.

    Warns:
        ExportWarning: values outside what glTF holds were clipped (``baseColor > 1``, ``k_s > 1``,
            ``alpha > 1``); the message counts the pixels.

    Example:
        >>> export_gltf("fit", "fit-gltf")  # doctest: +SKIP
        PosixPath('fit-gltf/scene.gltf')
    """
    check_output(output, overwrite=overwrite)
    maps = read_svbrdf(maps) if isinstance(maps, (str, Path)) else maps  # read once: the maps and their height
    arrays = map_arrays(maps)
    relief = height_array(maps, arrays.size, height)
    rows, cols = arrays.size
    material = _material(arrays)
    folder = Path(output)
    manifest = folder / "scene.gltf"
    folder.mkdir(parents=True, exist_ok=True)
    manifest.unlink(missing_ok=True)
    for name, image in material.images.items():
        write_png(folder / "textures" / f"{name}.png", image, 8)
    if relief is None:
        buffer, views, accessors = _quad(cols / max(cols, rows), rows / max(cols, rows))
    else:
        mesh = relief_mesh(relief)
        buffer, views, accessors = _buffer(mesh.position, mesh.texel, mesh.triangles.reshape(-1).astype(np.uint32))
    with atomic_path(folder / "scene.bin") as tmp:
        tmp.write_bytes(buffer)
    document = _document(material)
    document["buffers"] = [{"uri": "scene.bin", "byteLength": len(buffer)}]
    document["bufferViews"] = views
    document["accessors"] = accessors
    write_json(manifest, document)
    return manifest


@dataclass(frozen=True)
class _Material:
    """The glTF material of the maps: its textures (name to 8-bit ``(H, W, C)`` image, in the
    document's order) and the factors that scale them."""

    images: dict[str, np.ndarray]
    specular_factor: float
    roughness_factor: float
    anisotropic: bool


def _material(arrays: MapArrays) -> _Material:
    """The material's textures and factors (see :func:`export_gltf`); warns about clipped values."""
    lobe = arrays.lobe
    clipped = {}
    specular = rgb(arrays.specular)
    strength = specular.max(axis=-1)
    clipped["k_s > 1"] = strength > 1
    strength = np.minimum(strength, 1.0)
    strength_factor = float(strength.max()) if lobe.any() else 0.0
    strength_code = code8(strength / strength_factor) if strength_factor > 0 else np.zeros(arrays.size, np.uint8)
    strength = strength_factor * strength_code / 255.0  # the weight a viewer applies
    color = np.where(strength[..., None] > 0, specular / np.maximum(strength, 1e-12)[..., None], 0.0)
    base = rgb(arrays.diffuse) / np.maximum(1.0 - strength, 1e-12)[..., None]
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
    anisotropic = bool((anisotropy > math.sqrt(ISOTROPIC)).any())
    rotation = np.zeros(arrays.size) if arrays.rotation is None else arrays.rotation
    angle = rotation + np.where(alpha[..., 1] > alpha[..., 0], math.pi / 2, 0.0)

    bad = {what: int(mask.sum()) for what, mask in clipped.items() if mask.any()}
    if bad:
        warnings.warn(
            "glTF cannot hold every value; clipped: " + ", ".join(f"{what} at {n} pixel(s)" for what, n in bad.items()),
            ExportWarning,
            stacklevel=3,
        )
    images = {
        "base_color": code8(srgb(base)),
        "metallic_roughness": np.stack(  # R unused (occlusion), G roughness, B metallic
            [np.full(arrays.size, 255, np.uint8), code8(roughness), np.zeros(arrays.size, np.uint8)], axis=-1
        ),
        "normal": code8((arrays.normal + 1.0) / 2.0),
        "specular": np.concatenate([code8(srgb(color)), strength_code[..., None]], axis=-1),
    }
    if anisotropic:
        direction = (np.stack([np.cos(angle), np.sin(angle)], axis=-1) + 1.0) / 2.0
        images["anisotropy"] = np.concatenate([code8(direction), code8(anisotropy)[..., None]], axis=-1)
    return _Material(images, strength_factor, rough_factor, anisotropic)


def _document(material: _Material) -> dict:
    """The glTF document of the quad (:func:`_quad`) with the material, but its buffer: the
    caller adds ``buffers``, ``bufferViews`` and ``accessors``."""
    images = material.images
    index = {name: k for k, name in enumerate(images)}
    extensions = {
        "KHR_materials_specular": {
            "specularFactor": material.specular_factor,
            "specularTexture": {"index": index["specular"]},
            "specularColorFactor": [25.0, 25.0, 25.0],
            "specularColorTexture": {"index": index["specular"]},
        }
    }
    if material.anisotropic:
        extensions["KHR_materials_anisotropy"] = {
            "anisotropyStrength": 1.0,
            "anisotropyTexture": {"index": index["anisotropy"]},
        }
    return {
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
                    "roughnessFactor": material.roughness_factor,
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
    }


def _quad(width: float, height: float) -> tuple[bytes, list[dict], list[dict]]:
    """The binary buffer, buffer views and accessors of a ``width x height`` quad facing ``+z``:
    indices, POSITION, NORMAL, TANGENT, TEXCOORD_0 (accessors 0 to 4)."""
    x, y = width / 2, height / 2
    # top-left, bottom-left, bottom-right, top-right; glTF's uv (0, 0) is the image's top-left.
    position = np.array([[-x, y, 0], [-x, -y, 0], [x, -y, 0], [x, y, 0]], np.float32)
    uv = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)  # counter-clockwise seen from +z
    return _buffer(position, uv, indices)


def _buffer(position: np.ndarray, uv: np.ndarray, indices: np.ndarray) -> tuple[bytes, list[dict], list[dict]]:
    """The binary buffer, buffer views and accessors of a mesh facing ``+z`` (``NORMAL`` ``+z``,
    ``TANGENT`` ``+x`` at every vertex): indices (16- or 32-bit), POSITION, NORMAL, TANGENT,
    TEXCOORD_0 (accessors 0 to 4)."""
    count = len(position)
    normal = np.tile(np.array([0, 0, 1], np.float32), (count, 1))
    tangent = np.tile(np.array([1, 0, 0, 1], np.float32), (count, 1))  # bitangent = n x t = +y
    parts = [
        (indices, 5123 if indices.dtype == np.uint16 else 5125, "SCALAR", 34963),
        (position.astype(np.float32), 5126, "VEC3", 34962),
        (normal, 5126, "VEC3", 34962),
        (tangent, 5126, "VEC4", 34962),
        (uv.astype(np.float32), 5126, "VEC2", 34962),
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


