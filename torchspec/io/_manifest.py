"""The manifest ``capture.json`` of ``docs/capture-format.md``: its records (:class:`Frame`,
:class:`LightSpec`), validation with errors that name the file and the key at fault, and its
JSON form. :mod:`torchspec.io.capture` reads and writes whole captures with it."""

from __future__ import annotations

import difflib
import itertools
import json
import math
import os
import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Protocol

import numpy as np
import torch

from ..errors import TorchspecError

FORMAT = "torchspec.capture"
VERSIONS = (1,)
MANIFEST = "capture.json"
_REQUIRED = ("width", "height", "channels", "camera", "light", "frames")
# Optional top-level keys read without a warning (kept in Capture.extra): "generator" records
# how a synthetic capture was made, by the development data's renderer and by torchspec simulate;
# "source" where an imported one came from (torchspec import: light file, images, transfer, clipping).
_OPTIONAL = ("generator", "source", "unknown")
# "unknown": what the capture does not know of its lights, a list of "irradiance" (the frames'
# irradiance is a placeholder: torchspec fit calibrates a gain per frame and channel) and
# "position" (the lights are near and their positions are to be found). Older readers ignore it.
UNKNOWN_VALUES = ("irradiance", "position")
_KNOWN = ("format", "version") + _REQUIRED
_FRAME_KEYS = ("file", "direction", "irradiance", "exposure")
_FRAME_OPTIONAL = ("position",)
# "position" (optional, every frame or none): a near light's position in object units (below); a
# reader that ignores it takes the direction, the light seen from the image's centre.
_LIGHT_KEYS = {"point": (), "gaussian": ("domain", "sigma"), "tabulated": ("file", "extent"), "unknown": ("symmetric",)}
_DOMAINS = ("projected", "angular")
_UNIT_TOLERANCE = 1e-3
"""A direction whose norm is further than this from 1 is an error."""
_UNIT_SILENT = 1e-6
"""Within this a direction is kept as written (float32 round-off); beyond, renormalised with a warning."""
_SAME_DIRECTION = 1e-9
"""Two frames whose directions differ by at most this in every coordinate are under the same light."""


class CaptureError(TorchspecError):
    """A capture that does not follow ``docs/capture-format.md``; the message names the file, and the
    key or frame at fault."""


@dataclass(frozen=True)
class Frame:
    """One photograph of a capture.

    Attributes:
        file: path of the EXR, relative to the capture directory.
        direction: unit vector from the surface to the centre of the light kernel (``z > 0``).
        irradiance: ``(C,)`` one value per capture channel. A single number is accepted when
            constructing and expanded to every channel by :class:`Capture`.
        exposure: scale of the recorded value.
        position: a near light's position ``(x, y, z)`` in object units (the image's width; origin
            at its centre, x right, y up, z towards the camera), or ``None`` for a distant light.
    """

    file: str
    direction: tuple[float, float, float]
    irradiance: tuple[float, ...]
    exposure: float
    position: tuple[float, float, float] | None = None

    def __post_init__(self):
        object.__setattr__(self, "direction", _floats(self.direction))
        object.__setattr__(self, "irradiance", _floats(self.irradiance))
        object.__setattr__(self, "exposure", _floats(self.exposure))


@dataclass(frozen=True)
class LightSpec:
    """The extended light source shared by all frames (``docs/capture-format.md``, table of kernels).

    Attributes:
        kernel: ``"point"``, ``"gaussian"``, ``"tabulated"`` or ``"unknown"``.
        domain: gaussian only: ``"projected"`` (``sigma`` in ``l`` units) or ``"angular"``
            (``sigma`` in radians).
        sigma: gaussian only: standard deviation, ``> 0``.
        file: tabulated only: the kernel EXR (channel ``Y``), relative to the capture directory.
        extent: tabulated only: the image covers ``l - l_k`` in ``[-extent, extent]^2``, ``> 0``.
        symmetric: unknown only: ``True``.
    """

    kernel: str
    domain: str | None = None
    sigma: float | None = None
    file: str | None = None
    extent: float | None = None
    symmetric: bool | None = None


# --- the manifest -------------------------------------------------------------------------------


class _Text(str):
    """A description shown as it is in an error, where a value would be shown as JSON."""


class Where:
    """Builds the :class:`CaptureError` of a manifest (or config) file ``source``, naming the key at fault."""

    def __init__(self, source: Path):
        self.source = source

    def error(self, key: str, condition: str, got: Any, fix: str = "") -> CaptureError:
        return CaptureError(f"{self.source}: {key} must {condition}; got {_show(got)}." + (f" {fix}" if fix else ""))


def parse_manifest(data: Any, source: Path, notes: list[str], *, extra_known: bool = False) -> dict[str, Any]:
    """Validate a manifest; the fields of :class:`Capture` but ``root``. Warnings go to ``notes``;
    with ``extra_known`` (a manifest made from :attr:`Capture.extra`) unknown top-level keys are
    not warned about."""
    where = Where(source)
    if not isinstance(data, dict):
        raise where.error("the manifest", "be a JSON object", data)
    if data.get("format") != FORMAT:
        raise where.error("format", f"be {FORMAT!r}", data.get("format"), "Is this a torchspec capture manifest?")
    version = data.get("version")
    if type(version) is not int or version not in VERSIONS:
        raise where.error(
            "version",
            f"be a supported version ({', '.join(map(str, VERSIONS))})",
            version,
            "Convert the capture to version 1, or use a torchspec that reads this version.",
        )
    require_keys(where, "the manifest", data, _REQUIRED, _KNOWN + _OPTIONAL, "See docs/capture-format.md.")
    unknown = [key for key in data if key not in _KNOWN]
    if [key for key in unknown if key not in _OPTIONAL] and not extra_known:
        strange = [key for key in unknown if key not in _OPTIONAL]
        notes.append(f"{source}: unknown top-level key(s) {strange} are kept in Capture.extra and not used.")
    if "unknown" in data:
        told = data["unknown"]
        if not isinstance(told, list) or not all(isinstance(v, str) and v in UNKNOWN_VALUES for v in told):
            raise where.error("unknown", f"be a list of {list(UNKNOWN_VALUES)}", told)
    width = _positive_int(where, "width", data["width"])
    height = _positive_int(where, "height", data["height"])
    channels = data["channels"]
    if (
        not isinstance(channels, list)
        or not channels
        or not all(isinstance(name, str) and name for name in channels)
        or len(set(channels)) != len(channels)
    ):
        raise where.error(
            "channels", "be a non-empty list of distinct channel names", channels, 'E.g. ["R", "G", "B"].'
        )
    return {
        "width": width,
        "height": height,
        "channels": tuple(channels),
        "view": _camera(where, data["camera"], notes),
        "light": parse_light(where, data["light"], notes),
        "frames": _frames(where, data["frames"], len(channels), notes),
        "extra": {key: data[key] for key in unknown},
    }


def _camera(where: Where, camera: Any, notes: list[str]) -> tuple[float, float, float]:
    if not isinstance(camera, dict):
        raise where.error("camera", "be an object", camera, 'E.g. {"model": "orthographic", "view": [0, 0, 1]}.')
    if camera.get("model") != "orthographic":
        raise where.error("camera.model", 'be "orthographic" (the only model of version 1)', camera.get("model"))
    if "view" not in camera:
        raise where.error(
            "camera.view", "be given", _Text("no such key"), "Give the unit direction towards the camera."
        )
    _unknown(where, "camera", camera, ("model", "view"), notes)
    return _direction(where, "camera.view", camera["view"], notes)


def parse_light(where: Where, light: Any, notes: list[str]) -> LightSpec:
    """The manifest's ``light`` block, validated; errors name ``where``'s file and the key, warnings
    (unknown keys) go to ``notes``."""
    if not isinstance(light, dict):
        raise where.error("light", "be an object", light, 'E.g. {"kernel": "point"}.')
    kernel = light.get("kernel")
    if not isinstance(kernel, str) or kernel not in _LIGHT_KEYS:
        raise where.error("light.kernel", f"be one of {list(_LIGHT_KEYS)}", kernel)
    keys = _LIGHT_KEYS[kernel]
    for key in keys:
        if key not in light:
            guesses = _guesses([name for name in light if name not in ("kernel",) + keys], [key])
            raise where.error(
                f"light.{key}",
                f"be given for kernel {kernel!r}",
                _Text("no such key"),
                f"{guesses.strip()} See docs/capture-format.md.".strip(),
            )
    _unknown(where, "light", light, ("kernel",) + keys, notes)
    values = {key: light[key] for key in keys}
    if kernel == "gaussian":
        if values["domain"] not in _DOMAINS:
            raise where.error("light.domain", f"be one of {list(_DOMAINS)}", values["domain"])
        values["sigma"] = _positive(where, "light.sigma", values["sigma"])
    elif kernel == "tabulated":
        values["file"] = _relative_file(where, "light.file", values["file"])
        values["extent"] = _positive(where, "light.extent", values["extent"])
    elif kernel == "unknown" and values["symmetric"] is not True:
        raise where.error(
            "light.symmetric", "be true (version 1 knows symmetric unknown kernels only)", light["symmetric"]
        )
    return LightSpec(kernel=kernel, **values)


def _frames(where: Where, frames: Any, count: int, notes: list[str]) -> tuple[Frame, ...]:
    if not isinstance(frames, list) or not frames:
        raise where.error("frames", "be a non-empty list of frame objects", frames)
    seen: dict[str, int] = {}
    out = []
    for k, raw in enumerate(frames):
        key = f"frames[{k}]"
        if not isinstance(raw, dict):
            raise where.error(
                key, "be an object", raw, 'E.g. {"file": ..., "direction": ..., "irradiance": 1, "exposure": 1}.'
            )
        require_keys(where, key, raw, _FRAME_KEYS, _FRAME_KEYS)
        _unknown(where, key, raw, _FRAME_KEYS + _FRAME_OPTIONAL, notes)
        file = _relative_file(where, f"{key}.file", raw["file"])
        normal = os.path.normpath(file)
        if normal in seen:
            raise where.error(
                f"{key}.file",
                f"differ from every other frame's file (frames[{seen[normal]}].file)",
                file,
                f"frames[{seen[normal]}] and frames[{k}] list the same file; list each frame once.",
            )
        seen[normal] = k
        direction = _direction(where, f"{key}.direction", raw["direction"], notes)
        irradiance = raw["irradiance"]
        if isinstance(irradiance, list):
            if len(irradiance) != count:
                raise where.error(f"{key}.irradiance", f"be a number or one number per channel ({count})", irradiance)
            irradiance = tuple(_positive(where, f"{key}.irradiance[{c}]", value) for c, value in enumerate(irradiance))
        else:
            irradiance = (_positive(where, f"{key}.irradiance", irradiance),) * count
        exposure = _positive(where, f"{key}.exposure", raw["exposure"])
        position = _position(where, f"{key}.position", raw["position"]) if "position" in raw else None
        out.append(Frame(file=file, direction=direction, irradiance=irradiance, exposure=exposure, position=position))
    placed = [frame.position is not None for frame in out]
    if any(placed) and not all(placed):
        first = placed.index(not placed[0])
        raise where.error(
            f"frames[{first}].position", "be given for every frame or for none", _raw_of(frames, first, "position")
        )
    _distinct_directions(where, out)
    return tuple(out)


def _distinct_directions(where: Where, frames: Sequence[Frame]) -> None:
    """Refuse two frames under the same light (directions within :data:`_SAME_DIRECTION` in every
    coordinate): a light position is one sample of the layout, and a repeated one is most often a
    slip in the manifest. Cells of that size in a dict keep this linear in the frame count."""
    cells: dict[tuple[int, ...], list[int]] = {}
    for k, frame in enumerate(frames):
        cell = tuple(math.floor(v / _SAME_DIRECTION) for v in frame.direction)
        for offset in itertools.product((-1, 0, 1), repeat=3):
            for j in cells.get(tuple(c + o for c, o in zip(cell, offset, strict=True)), ()):
                if all(
                    abs(u - v) <= _SAME_DIRECTION for u, v in zip(frames[j].direction, frame.direction, strict=True)
                ):
                    raise where.error(
                        f"frames[{k}].direction",
                        f"differ from every other frame's direction (frames[{j}].direction)",
                        list(frame.direction),
                        f"frames[{j}] and frames[{k}] are lit from the same direction; list each light position "
                        "once, or fix the direction.",
                    )
        cells.setdefault(cell, []).append(k)


def _direction(where: Where, key: str, value: Any, notes: list[str]) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3 or not all(_is_number(v) for v in value):
        raise where.error(key, "be a list of 3 finite numbers", value)
    norm = math.sqrt(sum(v * v for v in value))
    if abs(norm - 1) > _UNIT_TOLERANCE:
        raise where.error(
            key,
            f"be a unit vector (|d| within {_UNIT_TOLERANCE:g} of 1)",
            _Text(f"{value} of norm {norm:.6g}"),
            "Normalise it.",
        )
    if abs(norm - 1) > _UNIT_SILENT:
        notes.append(f"{where.source}: {key} has norm {norm:.9g}; renormalised to a unit vector.")
        value = [v / norm for v in value]
    if not value[2] > 0:
        raise where.error(
            key, "point above the surface (z > 0)", value, "A direction at or below the horizon sees or lights nothing."
        )
    return (float(value[0]), float(value[1]), float(value[2]))


def _position(where: Where, key: str, value: Any) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3 or not all(_is_number(v) for v in value):
        raise where.error(key, "be a list of 3 finite numbers (x, y, z in image widths)", value)
    if not value[2] > 0:
        raise where.error(key, "lie above the object (z > 0)", value)
    return (float(value[0]), float(value[1]), float(value[2]))


def _raw_of(frames: list, k: int, name: str) -> Any:
    """Frame ``k``'s ``name`` as written (a marker when absent)."""
    return frames[k].get(name, _Text("absent"))


def _unknown(where: Where, key: str, obj: dict, known: Sequence[str], notes: list[str]) -> None:
    unknown = [name for name in obj if name not in known]
    if unknown:
        notes.append(f"{where.source}: unknown key(s) {unknown} in {key} are ignored.{_guesses(unknown, known)}")


def _guesses(unknown: Sequence[str], known: Sequence[str]) -> str:
    """`` Did you mean 'direction' for 'directon'?`` for each unknown key close to a known one
    (:func:`difflib.get_close_matches`), or ``""``."""
    pairs = [
        (name, close[0])
        for name in unknown
        if isinstance(name, str) and (close := difflib.get_close_matches(name, list(known), n=1, cutoff=0.6))
    ]
    return "".join(f" Did you mean {right!r} for {wrong!r}?" for wrong, right in pairs)


def require_keys(
    where: Where, key: str, obj: dict, required: Sequence[str], known: Sequence[str], fix: str = ""
) -> None:
    """Raise the error of a ``key`` object (a mapping) that lacks some of ``required``, naming the
    missing keys and, for a misspelt one, the unknown key beside it and the key it resembles."""
    missing = [name for name in required if name not in obj]
    if not missing:
        return
    unknown = [name for name in obj if name not in known]
    guesses = _guesses(unknown, missing)
    got = f"{missing} missing" + (f", and the unknown key(s) {unknown}" if unknown else "")
    raise where.error(key, f"have the keys {list(required)}", _Text(got), (guesses.strip() + " " + fix).strip())


def _is_number(value: Any) -> bool:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an int beyond float range
        return False


def _positive(where: Where, key: str, value: Any) -> float:
    if not _is_number(value) or not value > 0:
        raise where.error(key, "be a positive number", value)
    return float(value)


def _positive_int(where: Where, key: str, value: Any) -> int:
    if type(value) is not int or value <= 0:
        raise where.error(key, "be a positive integer", value)
    return value


def _relative_file(where: Where, key: str, value: Any) -> str:
    if not isinstance(value, str) or not value or "\0" in value:
        raise where.error(key, "be a file name (a non-empty string without NUL characters)", value)
    if PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute():
        raise where.error(key, "be a path relative to the capture directory", value, "Make the path relative.")
    return value


class ManifestFields(Protocol):
    """What :func:`to_manifest` reads of a capture: the fields of a
    :class:`~torchspec.io.capture.Capture` that its manifest holds (typed here, as the module that
    reads captures imports this one)."""

    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...
    @property
    def channels(self) -> tuple[str, ...]: ...
    @property
    def view(self) -> tuple[float, float, float]: ...
    @property
    def light(self) -> LightSpec: ...
    @property
    def frames(self) -> tuple[Frame, ...]: ...
    @property
    def extra(self) -> dict: ...


def to_manifest(capture: ManifestFields, source: Path) -> dict[str, Any]:
    """The JSON manifest of ``capture`` (a :class:`~torchspec.io.capture.Capture`; validated by
    :func:`parse_manifest`, not here)."""
    clash = [key for key in capture.extra if key in _KNOWN]
    if clash:
        raise CaptureError(f"Capture.extra for {source} must not hold the format's keys; got {clash}. Set the fields.")
    light = {"kernel": capture.light.kernel}
    for name in ("domain", "sigma", "file", "extent", "symmetric"):
        value = getattr(capture.light, name)
        if value is not None:
            light[name] = value
    frames = []
    for frame in capture.frames:
        if not isinstance(frame, Frame):
            raise CaptureError(f"Capture.frames for {source} must hold Frame objects; got {type(frame).__name__}.")
        irradiance = list(frame.irradiance) if isinstance(frame.irradiance, tuple) else frame.irradiance
        if isinstance(irradiance, list) and irradiance and all(v == irradiance[0] for v in irradiance):
            irradiance = irradiance[0]
        direction = list(frame.direction) if isinstance(frame.direction, tuple) else frame.direction
        entry = {"file": frame.file, "direction": direction, "irradiance": irradiance, "exposure": frame.exposure}
        if getattr(frame, "position", None) is not None:
            entry["position"] = list(frame.position)
        frames.append(entry)
    view = list(capture.view) if isinstance(capture.view, tuple) else capture.view
    manifest = {
        "format": FORMAT,
        "version": VERSIONS[-1],
        "width": capture.width,
        "height": capture.height,
        "channels": list(capture.channels),
        "camera": {"model": "orthographic", "view": view},
        "light": light,
        "frames": frames,
        **capture.extra,
    }
    try:
        json.dumps(capture.extra)
    except (TypeError, ValueError) as error:
        raise CaptureError(f"Capture.extra for {source} must be JSON-serialisable; got {error}.") from error
    return manifest


def _floats(value: Any) -> Any:
    """``value`` as a float or a tuple of floats when it converts; as it is otherwise, for the
    manifest validation to report with the key's name."""
    try:
        if isinstance(value, (str, bytes)):
            return value
        if isinstance(value, (int, float, np.number)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, torch.Tensor) and value.dim() == 0:
            return float(value)
        return tuple(float(v) for v in _as_list(value))
    except (TypeError, ValueError):
        return value


def _as_list(values: Any) -> list:
    return values.tolist() if hasattr(values, "tolist") else list(values)


def _numpy(array: Any) -> np.ndarray:
    if isinstance(array, torch.Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def _show(value: Any) -> str:
    if isinstance(value, _Text):
        return str(value)
    try:
        text = json.dumps(value)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def not_a_capture(path: Path) -> None:
    """Refuse, in the user's terms, what is plainly not a capture: a folder that does not exist, a
    YAML config, an image."""
    try:
        exists, is_file = path.exists(), path.is_file()
    except OSError as error:
        raise CaptureError(f"the capture {path} must be a path the system can look up; got {error}.") from error
    if not exists:
        where = "" if path.parent.is_dir() else f" (nor does its folder {path.parent})"
        raise CaptureError(
            f"the capture folder {path} does not exist{where}. Pass a folder that holds {MANIFEST} and the "
            "frames (docs/capture-format.md); torchspec simulate or torchspec import makes one."
        )
    suffix = path.suffix.lower()
    if is_file and suffix in (".yaml", ".yml"):
        raise CaptureError(
            f"{path} is a YAML config, not a capture: a capture is a folder with {MANIFEST} and its frames "
            "(docs/capture-format.md). A simulation config makes one with: torchspec simulate CONFIG -o CAPTURE; "
            "a fit config goes to torchspec fit CAPTURE --config CONFIG."
        )
    if is_file and suffix in (".exr", ".jpg", ".jpeg", ".png", ".tif", ".tiff"):
        raise CaptureError(
            f"{path} is an image, not a capture: pass the folder that holds {MANIFEST} "
            "(photographs become a capture with: torchspec import SOURCE -o CAPTURE)."
        )
    rti = is_file and (suffix in RTI_LIGHT_FILES or path.name.lower() == "lights.txt")
    if not is_file and not (path / MANIFEST).exists():  # an RTI folder: photographs and their light file
        rti = any(p.suffix.lower() in RTI_LIGHT_FILES for p in path.iterdir() if p.is_file())
    if rti:
        raise CaptureError(
            f"{path} is an RTI capture (photographs and their light file), not yet a torchspec capture: import it "
            f"first with: torchspec import {shlex.quote(str(path))} -o CAPTURE, then: torchspec fit CAPTURE -o MAPS."
        )


RTI_LIGHT_FILES = (".lp", ".relight", ".dome")
"""The light files of RTI tools (``torchspec import`` reads them; so does a ``lights.txt``)."""
