"""Relighting under new lights: ``torchspec render MAPS --light X,Y,Z`` (repeatable) or
``--lights FILE.lp`` writes one image per light.

The maps are rendered as :func:`torchspec.relight.render_capture` renders a capture's frames (with
the fit's residual term, ``residual_term.exr``, unless ``term`` is false), under lights of the
capture's kernel from the new directions, seen from the capture's view. What a render needs of
the capture comes from the maps' ``svbrdf.json`` (``fit.scene``, which a fit records:
:func:`torchspec.pipeline.assembly.scene_record`), else from the capture (given, or the one the
fit names when it is still there, or the folder holding a ``truth/``). Maps fitted with cast
shadows (``height.exr``) are rendered times each light's visibility over that height
(:func:`torchspec.model.visibility.frame_visibility`).

Each new light has the irradiance ``irradiance`` (one value, or one per channel) and exposure 1;
by default the median over the fitted frames of ``exposure x irradiance x gain`` per channel
(``gain``: the per-frame gain the fit calibrated, where it did; 1 otherwise): a light at a
frame's direction renders that frame's prediction when the frame's scale is the median (an
imported capture's frames all have irradiance 1, exposure 1 unless EXIF says otherwise, and gains
whose geometric mean is 1). Near lights (a capture of positions, or a fit that calibrated a dome
radius or positions) are placed at the lights' distance from the image's centre along the new
directions (the fit's radius, else the median distance of the fitted frames' lights).

Images are 8-bit PNG (``light-000.png``, ...) where the capture came from photographs (its
manifest's ``source``), else float32 EXR (``light-000.exr``, negative values at 0); ``fmt``
chooses. A PNG holds the linear values clipped to ``[0, 1]`` (negative values to 0; 1: the
photographs' white) encoded as the photographs were (the transfer the import decoded them with:
sRGB, or the camera response it estimated), so that a light at a photograph's direction shows
that photograph as it was recorded, code for code where the maps predict it; ``srgb`` (and
captures not of photographs) encodes with the sRGB curve (IEC 61966-2-1). Beside them,
``lights.json`` lists each image's light (direction, where it was given), the irradiance and how
it was chosen and the encoding, and ``lights.lp`` the images and directions as an RTI light file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..atomic import atomic_path, write_json
from ..errors import TorchspecError
from ..export.arrays import code8
from ..io import Capture, Maps, read_capture, read_svbrdf, write_exr
from ..io.capture import light_kernel
from ..io.images import Transfer
from ..io.lp import light_entry
from ..io.rti import find_light_file, read_lights
from ..model.lights import Lights
from ..model.quadrature import Quadrature
from ..outputs import check_output
from ..pipeline.assembly import scene_record
from ..pipeline.plan import device_of
from . import (
    capture_for,
    capture_places,
    fitted_scales,
    residual_term_of,
    shaded_render,
    shadow_terms,
    softness_of,
)

__all__ = ["FORMATS", "LIGHTS_JSON", "LIGHTS_LP", "NewLight", "Scene", "parse_light", "read_new_lights",
           "render_lights", "scene_of"]  # fmt: skip

FORMATS = ("auto", "png", "exr")
"""``fmt`` of :func:`render_lights` (``--format``): ``auto`` is PNG for a capture of photographs."""
LIGHTS_JSON = "lights.json"
"""The record of the lights rendered, beside the images."""
LIGHTS_LP = "lights.lp"
"""The images and their directions as an RTI light file, beside the images."""
VALUES_PER_RENDER = 1 << 26
"""Values ``(pixels x lights x channels)`` rendered at once: lights are rendered in groups."""


class RenderError(TorchspecError):
    """New lights that cannot be rendered as asked; the message names the option at fault."""


@dataclass(frozen=True)
class NewLight:
    """A light to render: its unit ``direction`` (``z > 0``), where it was given (``--light
    0,0,1``, ``new.lp line 3``) and the image name the light file gives it (``None``: none)."""

    direction: tuple[float, float, float]
    given: str
    name: str | None = None


def parse_light(text: str, option: str = "--light") -> NewLight:
    """The light of ``--light X,Y,Z``: a direction towards the light (x right, y up, z towards the
    camera; any length, normalised).

    Raises:
        RenderError: not three numbers; a light file (read with ``--lights``), a path or a JSON
            file (the light description that was ``--light FILE`` is now ``--light-model FILE``);
            a zero direction or one below the horizon (:func:`torchspec.io.lp.light_entry`).
    """
    parts = [part.strip() for part in str(text).split(",")]
    try:
        vector = [float(part) for part in parts]
    except ValueError:
        vector = []
    if len(vector) != 3 or not all(math.isfinite(v) for v in vector):
        if str(text).lower().endswith((".lp", ".txt", ".relight", ".dome")):
            raise RenderError(
                f"{option} takes a direction X,Y,Z (e.g. {option} 0.5,0,0.87); got the light file {text!r}: "
                "a light file of new lights is read with --lights FILE."
            )
        if str(text).lower().endswith((".json", ".yaml", ".yml")) or Path(text).exists():
            raise RenderError(
                f"{option} takes a direction X,Y,Z (e.g. {option} 0.5,0,0.87); got the file {text!r}. A JSON light "
                "description (the light's kernel) is now given with --light-model FILE."
            )
        raise RenderError(
            f"{option} must be a direction X,Y,Z towards the light: three numbers, x right, y up, z towards the "
            f"camera (e.g. {option} 0.5,0,0.87); got {text!r}."
        )
    try:
        entry = light_entry(Path(option), vector, None, where=f"the direction {text!r}", remedy="give Z > 0")
    except TorchspecError as error:
        raise RenderError(str(error)) from None
    return NewLight(entry.direction, f"{option} {text}")


def read_new_lights(path: str | Path) -> tuple[list[NewLight], list[str]]:
    """The lights of a light file (an ``.lp``, a ``lights.txt`` of directions, a Relight
    ``.relight`` or ``.dome``: :func:`torchspec.io.rti.read_lights`, tolerant as an import is),
    and its notes (what was assumed to read it)."""
    lights = read_lights(find_light_file(path))
    found = [NewLight(entry.direction, f"{lights.path} {entry.place}", entry.name) for entry in lights.entries]
    return found, list(lights.notes)


@dataclass(frozen=True)
class Scene:
    """What rendering new lights takes of the capture the maps were fitted from.

    Attributes:
        view: unit direction towards the camera.
        light: the capture's ``light`` block (its kernel).
        irradiance: per channel: the default irradiance of a new light.
        chosen: how :attr:`irradiance` was chosen, in words.
        distance: near lights' distance from the image's centre, image widths (``None``: distant).
        photographs: whether the capture came from photographs (its manifest's ``source``).
        transfer: the tone curve the photographs were decoded with (``None``: not photographs).
        root: the capture's folder where known (a tabulated kernel's file is relative to it).
        source: where this came from, in words (``MAPS/svbrdf.json``, or the capture).
    """

    view: tuple[float, float, float]
    light: dict
    irradiance: tuple[float, ...]
    chosen: str
    distance: float | None
    photographs: bool
    transfer: Transfer | None
    root: Path | None
    source: str


def scene_of(maps: Maps, svbrdf_dir: Path | str, capture: Capture | None = None) -> Scene:
    """The :class:`Scene` of ``maps``: from ``svbrdf.json``'s ``fit.scene`` where the fit recorded
    it, else from ``capture``, else from the capture the fit names (``fit.capture``, as it was
    given to the fit or beside the maps' folder) or the folder holding ``truth/`` maps, when it is
    there (where a tabulated kernel's table is read too).

    Raises:
        RenderError: none of these says it (the message asks for ``--capture``).
    """
    svbrdf_dir = Path(svbrdf_dir)
    fit = maps.meta.get("fit") or {}
    record, root, source = fit.get("scene"), None, f"{svbrdf_dir / 'svbrdf.json'}"
    if capture is None and (record is None or record["light"].get("kernel") == "tabulated"):  # its table: there
        named = capture_places(fit["capture"], svbrdf_dir) if fit.get("capture") else []
        for folder in named + ([svbrdf_dir.resolve().parent] if svbrdf_dir.name == "truth" else []):
            if (folder / "capture.json").is_file():
                capture = read_capture(folder)
                break
    if capture is not None:
        capture = capture_for(maps, capture)
        root = capture.root
        if record is None:
            record = scene_record(capture, fit.get("frames") or list(range(len(capture.frames))))
            source = str(capture.manifest)
    if record is None:
        raise RenderError(
            f"{svbrdf_dir / 'svbrdf.json'} does not say the view and lights the maps were fitted under (no fit.scene: "
            "maps written before it, or not by a fit), and their capture is not beside them: pass --capture CAPTURE."
        )
    irradiance, chosen = _default_irradiance(record, fit.get("lights") or {})
    distance = _distance(record, fit.get("lights") or {})
    return Scene(tuple(record["view"]), dict(record["light"]), irradiance, chosen, distance,
                 bool(record.get("photographs")), Transfer.of_source(record.get("transfer")), root, source)  # fmt: skip


def _default_irradiance(record: dict, calibration: dict) -> tuple[tuple[float, ...], str]:
    """Per channel, the median over the fitted frames of ``exposure x irradiance x gain``, and
    how it was chosen, in words."""
    scale, gains = fitted_scales(record["exposure"], record["irradiance"], calibration)
    count = scale.shape[0]
    what = "exposure x irradiance x the calibrated gain" if gains else "exposure x irradiance"
    return tuple(float(v) for v in np.median(scale, axis=0)), f"the median over the fit's {count} frames of {what}"


def _distance(record: dict, calibration: dict) -> float | None:
    """The new lights' distance from the image's centre (:func:`torchspec.relight.fit_positions`'
    sources: a calibrated dome radius, calibrated positions, the capture's), ``None``: distant."""
    calibrated = calibration.get("calibrated") or []
    if "radius" in calibrated and calibration.get("radius") is not None:
        return float(calibration["radius"])
    if "position" in calibrated and calibration.get("positions") is not None:
        return float(np.median(np.linalg.norm(np.asarray(calibration["positions"], dtype=np.float64), axis=-1)))
    return record.get("distance")


def _irradiance(given, scene: Scene, channels: int) -> tuple[tuple[float, ...], str]:
    """The new lights' irradiance per channel (``given``: one value or one per channel) and how chosen."""
    if given is None:
        values, chosen = scene.irradiance, scene.chosen
    else:
        values, chosen = tuple(float(v) for v in np.atleast_1d(given)), "given (--irradiance)"
    if len(values) == 1:
        values = values * channels
    if len(values) != channels or not all(math.isfinite(v) and v >= 0 for v in values):
        raise RenderError(
            f"--irradiance must be one number or one per channel ({channels}), each >= 0; got {list(values)}."
        )
    return values, chosen


def render_lights(
    svbrdf_dir: Path | str,
    output_dir: Path | str,
    lights: list[NewLight],
    *,
    capture: Path | str | None = None,
    light_model: Path | str | None = None,
    irradiance: float | list[float] | None = None,
    fmt: str = "auto",
    srgb: bool = False,
    term: bool = True,
    path: str = "auto",
    dtype: torch.dtype = torch.float32,
    overwrite: bool = False,
    progress: bool = False,
    device: str | torch.device = "auto",
) -> dict:
    """Render the maps of ``svbrdf_dir`` under each of ``lights`` into ``output_dir`` (see the
    module's docstring): ``light-000.png`` (or ``.exr``), ..., ``lights.json`` and ``lights.lp``.

    Args:
        capture: the capture the maps were fitted from (:func:`scene_of`; needed when
            ``svbrdf.json`` does not record ``fit.scene`` and the capture is not where the fit was).
        light_model: a JSON light description replacing the capture's kernel (:meth:`Capture.lights`).
        irradiance: one value or one per channel (``None``: :attr:`Scene.irradiance`).
        fmt: ``png``, ``exr`` or ``auto`` (PNG for a capture of photographs, else EXR).
        srgb: PNG codes by the sRGB curve even where the photographs were decoded with another.
        term: add the fit's residual term where the maps have one.
        path: the quadrature path (:func:`torchspec.model.rendering.render`).

    Returns:
        ``{"files", "format", "irradiance", "irradiance_chosen", "clipped", "images", "scene"}``:
        ``clipped[k]`` counts image ``k``'s pixels above 1 in some channel (PNG: clipped to 1),
        ``images`` the rendered values ``(K, C, H, W)`` (linear, before any encoding).

    Raises:
        RenderError: no light, a bad ``fmt`` or ``irradiance``, PNG of channels other than RGB or
            Y, or maps that do not say their scene (:func:`scene_of`); OutputError: ``output_dir``
            holds files and not ``overwrite``; CaptureError: an unknown kernel and no ``light_model``.
    """
    if not lights:
        raise RenderError("no light to render: give --light X,Y,Z (repeatable) or --lights FILE.lp.")
    if fmt not in FORMATS:
        raise RenderError(f"--format must be one of {list(FORMATS)}; got {fmt!r}.")
    output = check_output(output_dir, overwrite=overwrite)
    maps = read_svbrdf(svbrdf_dir)
    scene = scene_of(maps, svbrdf_dir, None if capture is None else read_capture(capture))
    channels = tuple(maps.svbrdf.channels)
    values, chosen = _irradiance(irradiance, scene, len(channels))
    fmt = ("png" if scene.photographs else "exr") if fmt == "auto" else fmt
    if fmt == "png" and channels not in (("R", "G", "B"), ("Y",)):
        raise RenderError(f"--format png takes channels R, G, B or Y; the maps have {list(channels)}: use exr.")
    kernel = _kernel(scene, light_model)
    where = device_of(device)
    images = _render(maps, svbrdf_dir, scene, kernel, lights, values, where, dtype, term, Quadrature(path=path),
                     progress)  # fmt: skip
    curve = Transfer("srgb") if srgb or scene.transfer is None else scene.transfer
    encoding = f"8-bit codes of the linear values clipped to [0, 1], by the {_curve(curve)}" if fmt == "png" else (
        "float32 linear values, negative ones at 0"
    )
    files, clipped = _write_images(output, images, channels, fmt, curve)
    _write_record(output, lights, files, values, chosen, scene, encoding, term and "residual_term" in maps.extra)
    return {"files": files, "format": fmt, "encoding": encoding, "irradiance": values, "irradiance_chosen": chosen,
            "clipped": clipped, "images": images, "scene": scene}  # fmt: skip


def _curve(transfer: Transfer) -> str:
    """A PNG's tone curve in words."""
    if transfer.name == "response":
        return "camera response the import estimated from the photographs (as they were recorded)"
    return "sRGB curve" if transfer.name == "srgb" else f"photographs' transfer {transfer}"


def _kernel(scene: Scene, light_model: Path | str | None):
    """The new lights' kernel: the capture's (:attr:`Scene.light`), or ``light_model``'s."""
    if light_model is not None:
        return light_kernel(light_model, Path("."))
    kind = scene.light.get("kernel")
    if kind == "unknown":
        raise RenderError(
            f"{scene.source}: the light's kernel is 'unknown', so no light can be rendered; give its shape with "
            "--light-model FILE (e.g. the .json torchspec calibrate writes)."
        )
    if kind == "tabulated" and scene.root is None:
        raise RenderError(
            f"{scene.source}: the maps were fitted under a tabulated light, whose table ({scene.light.get('file')}) "
            "lies in the capture: pass --capture CAPTURE, or --light-model FILE."
        )
    return light_kernel(scene.light, scene.root or Path("."))


def _render(maps, svbrdf_dir, scene, kernel, lights, values, where, dtype, term, quadrature, progress):
    """``(K, C, H, W)`` on the CPU: the maps under each light, in groups of lights that keep a
    render within :data:`VALUES_PER_RENDER` values."""
    svbrdf = maps.svbrdf.to(where).to(dtype)
    height, width = svbrdf.shape
    found = residual_term_of(maps, svbrdf_dir, where) if term else None
    shape = maps.extra.get("height")  # cast shadows (height.exr): each light's visibility over it
    shape = None if shape is None else shape.to(where, dtype)
    share = maps.extra.get("indirect") if shape is not None else None  # its indirect light (indirect.exr)
    share = None if share is None else share.to(where, dtype)
    softness = softness_of(maps)  # the penumbra the fit chose
    view = torch.tensor(scene.view, dtype=dtype, device=where)
    directions = torch.tensor([light.direction for light in lights], dtype=dtype, device=where)
    scale = torch.tensor(values, dtype=dtype, device=where)
    group = max(1, VALUES_PER_RENDER // (height * width * len(values)))
    out = torch.empty((len(lights), len(values), height, width), dtype=torch.float32)  # CPU on purpose: written out
    for first in range(0, len(lights), group):
        part = directions[first : first + group]
        count = part.shape[0]
        here = Lights(part, kernel, scale.expand(count, -1), torch.ones(count, dtype=dtype, device=where))
        near = None if scene.distance is None else scene.distance * part  # as the capture's, at their distance
        seen = bounce = None
        if shape is not None:
            seen, bounce = shadow_terms(svbrdf, shape, share, softness, here, view, near, quadrature=quadrature)
        rendered = shaded_render(svbrdf, here, view, near, seen=seen, bounce=bounce, term=found,
                                 quadrature=quadrature, progress=progress)  # fmt: skip
        out[first : first + count] = rendered.permute(2, 3, 0, 1).float().cpu()
    return out


def _write_images(output: Path, images: torch.Tensor, channels: tuple[str, ...], fmt: str, curve: Transfer):
    """Each image of ``images (K, C, H, W)`` as ``light-NNN.png`` (8-bit codes of the values clipped
    to ``[0, 1]`` by ``curve``) or ``.exr`` (float32, negative values at 0): the file names and each
    image's count of pixels above 1."""
    files, clipped = [], []
    digits = max(3, len(str(len(images) - 1)))
    for k, image in enumerate(images):
        pixels = image.clamp(min=0).permute(1, 2, 0).numpy()  # (H, W, C)
        clipped.append(int((pixels > 1).any(-1).sum()))
        name = f"light-{k:0{digits}d}.{fmt}"
        if fmt == "exr":
            write_exr(output / name, pixels, channels)
        else:
            from PIL import Image

            codes = code8(curve.encode(torch.from_numpy(pixels).double().clamp(max=1)).numpy())
            with atomic_path(output / name) as tmp:
                Image.fromarray(codes[..., 0] if codes.shape[-1] == 1 else codes).save(tmp, format="PNG")
        files.append(name)
    return files, clipped


def _write_record(output: Path, lights, files, values, chosen, scene: Scene, encoding: str, term: bool) -> None:
    """``lights.json`` and ``lights.lp`` beside the images."""
    write_json(output / LIGHTS_JSON, {
        "lights": [
            {"file": file, "direction": list(light.direction), "given": light.given, "name": light.name}
            for file, light in zip(files, lights, strict=True)
        ],
        "irradiance": list(values),
        "irradiance_chosen": chosen,
        "exposure": 1.0,
        "distance": scene.distance,
        "view": list(scene.view),
        "light": scene.light,
        "residual_term": term,
        "encoding": encoding,
        "scene_from": scene.source,
    })  # fmt: skip
    lines = [str(len(files))] + [
        f"{file} {x:.9g} {y:.9g} {z:.9g}" for file, (x, y, z) in zip(files, (light.direction for light in lights),
                                                                        strict=True)
    ]  # fmt: skip
    with atomic_path(output / LIGHTS_LP) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
