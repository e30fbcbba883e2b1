"""Light files of Relight (cnr-isti-vclab/relight): a RelightLab project (``.relight``) and a dome
(``.dome``), both JSON, read as a :class:`~torchspec.io.lp.LightFile`.

A dome holds ``directions`` (``{"x", "y", "z"}`` per light, the image frame of an ``.lp``: x
right, y up, z towards the camera), and, by its ``lightConfiguration``, light positions:
``"directional"`` (none), ``"spherical"`` (``positionsSphere``, or the directions scaled to
``domeDiameter / 2`` and raised by ``verticalOffset``) or ``"lights3d"`` (``positions3d``; the
directions are their normalised vectors where the file gives none). Positions are in the unit
of ``imageWidth`` (mm; cm in older files), origin at the image's centre; they are returned in
units of the image's width (divided by ``imageWidth``; as written when it is 0, which Relight
takes as a width of 1). A ``.dome`` names no images: its lights are matched to the photographs
of its folder by order.

A project holds ``folder`` (the images' folder, relative to the project), ``images``
(``filename``, ``skip``, and in older files each image's ``direction`` and ``position``) and a
``dome``. The dome's lights pair with the images by index (all images, or the ones not skipped
when the counts say so); skipped images are left out, with a note.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from .lp import LightFile, LightFileError, direction_notes, light_entry

__all__ = ["RELIGHT_SUFFIXES", "read_relight"]

RELIGHT_SUFFIXES = (".relight", ".dome")


def _load(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as error:
        raise LightFileError(f"{path}: cannot be read: {error}.") from error
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise LightFileError(
            f"{path}: line {error.lineno} column {error.colno} is not valid JSON ({error.msg}); a Relight "
            "project or dome file is JSON."
        ) from error
    if not isinstance(data, dict):
        raise LightFileError(f"{path} must hold a JSON object (a Relight project or dome); got {type(data).__name__}.")
    return data


def _vectors(path: Path, values, key: str) -> list[tuple[float, float, float]]:
    if values is None:
        return []
    if not isinstance(values, list):
        raise LightFileError(f"{path}: {key} must be a list of {{x, y, z}} objects; got {type(values).__name__}.")
    vectors = []
    for k, value in enumerate(values):
        try:
            vector = tuple(float(value[axis]) for axis in "xyz")
        except (KeyError, TypeError, ValueError):
            raise LightFileError(f"{path}: {key}[{k}] must be an object with numbers x, y, z; got {value!r}.") from None
        vectors.append(vector)
    return vectors


def _number(path: Path, dome: dict, key: str, where: str) -> float:
    value = dome.get(key, 0.0)
    try:
        value = float(value or 0.0)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value):
        raise LightFileError(f"{path}: {where}{key} must be a number; got {dome.get(key)!r}.")
    return value


def _dome_lights(path: Path, dome: dict, where: str, notes: list[str]):
    """``(directions, positions or None)`` of a dome object, positions in image widths."""
    directions = _vectors(path, dome.get("directions"), f"{where}directions")
    configuration = str(dome.get("lightConfiguration", "directional")).lower()
    width = _number(path, dome, "imageWidth", where)
    diameter = _number(path, dome, "domeDiameter", where)
    offset = _number(path, dome, "verticalOffset", where)
    positions = None
    if configuration == "lights3d":
        positions = _vectors(path, dome.get("positions3d"), f"{where}positions3d") or None
        if positions and not directions:
            directions = positions
    elif configuration == "spherical":
        positions = _vectors(path, dome.get("positionsSphere"), f"{where}positionsSphere") or None
        if positions is None and diameter > 0:
            scaled = [[c * diameter / 2 / (math.hypot(*d) or 1.0) for c in d] for d in directions]
            positions = [(x, y, z + offset) for x, y, z in scaled]
    elif configuration != "directional":
        raise LightFileError(
            f"{path}: {where}lightConfiguration must be 'directional', 'spherical' or 'lights3d'; got "
            f"{dome.get('lightConfiguration')!r}."
        )
    if positions is not None:
        if len(positions) != len(directions):
            raise LightFileError(
                f"{path}: {where}lists {len(directions)} directions but {len(positions)} positions; they must pair."
            )
        scale = width if width > 0 else 1.0
        positions = [tuple(c / scale for c in p) for p in positions]
        notes.append(
            f"{path}: a {configuration} dome: light positions read "
            + (f"(imageWidth {width:g}: in image widths)." if width > 0 else "(no imageWidth: taken as image widths).")
        )
    return directions, positions


def _project_images(path: Path, data: dict, directions: list, notes: list[str]):
    """The project's ``(names, directions, keep)`` paired by index: every image, or those not skipped."""
    images = data.get("images")
    if not isinstance(images, list) or not images:
        raise LightFileError(f"{path}: images must list the project's photographs; got {images!r}.")
    names, skips, own = [], [], []
    for k, image in enumerate(images):
        if not isinstance(image, dict) or not isinstance(image.get("filename"), str):
            raise LightFileError(f"{path}: images[{k}] must be an object with a filename; got {image!r}.")
        names.append(image["filename"])
        skips.append(bool(image.get("skip", False)))
        own.append(_vectors(path, [image["direction"]], f"images[{k}].direction")[0] if "direction" in image else None)
    if not directions and all(vector is not None for vector in own):  # older projects: per image
        directions = own
    kept = [k for k, skip in enumerate(skips) if not skip]
    if len(directions) == len(images):
        pairs = [(k, directions[k]) for k in kept]
    elif len(directions) == len(kept):
        pairs = list(zip(kept, directions, strict=True))
    else:
        raise LightFileError(
            f"{path}: its dome lists {len(directions)} light directions for {len(images)} images ({len(kept)} not "
            "skipped); they must pair one to one. Recompute the lights in RelightLab, or export an .lp."
        )
    if len(kept) < len(images):
        skipped = [names[k] for k, skip in enumerate(skips) if skip]
        notes.append(f"{path}: {len(skipped)} image(s) marked skip are left out ({', '.join(skipped[:5])}).")
    return names, pairs


def read_relight(path: str | Path) -> LightFile:
    """Read a RelightLab project (``.relight``) or dome (``.dome``) file; see the module's docstring.

    Raises:
        LightFileError: invalid JSON (the line and column), a missing or malformed key, a zero or
            below-the-horizon direction (which image or light), directions that do not pair with
            the images or positions.
    """
    path = Path(path)
    data = _load(path)
    notes: list[str] = []
    is_project = "images" in data or path.suffix.lower() == ".relight"
    dome = data.get("dome", {}) if is_project else data
    if not isinstance(dome, dict):
        raise LightFileError(f"{path}: dome must be an object; got {type(dome).__name__}.")
    directions, positions = _dome_lights(path, dome, "dome." if is_project else "", notes)
    folder = None
    if is_project:
        names, pairs = _project_images(path, data, directions, notes)
        folder = (path.parent / str(data.get("folder") or ".")).resolve()
        if positions is not None:
            positions = [
                positions[k] if len(positions) == len(names) else positions[j] for j, (k, _) in enumerate(pairs)
            ]
        entries = [
            light_entry(path, vector, names[k], where=f"images[{k}] ({names[k]})", remedy="mark the image skip")
            for k, vector in pairs
        ]
    else:
        entries = [light_entry(path, vector, None, where=f"directions[{k}]") for k, vector in enumerate(directions)]
    if not entries:
        raise LightFileError(f"{path} must hold at least one light direction; got none.")
    notes += direction_notes(path, entries)
    return LightFile(
        path=path,
        entries=tuple(entries),
        declared=None,
        notes=tuple(notes),
        folder=folder,
        positions=None if positions is None else tuple(tuple(p) for p in positions),
    )
