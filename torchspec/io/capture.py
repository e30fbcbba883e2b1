"""Capture directories of ``capture-format.md``: the manifest ``capture.json``, its frames and an
optional tabulated light kernel.

:func:`read_capture` validates the whole manifest and checks that every frame file exists, but
reads no pixels: :meth:`Capture.read_frames` reads (a subset of) the frames when asked, so a
caller can bound memory by the frames or tiles it holds. :func:`write_capture` writes the frames
first and ``capture.json`` last, so an interrupted write never leaves a manifest that lists
missing frames.
"""

from __future__ import annotations

import json
import math
import operator
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

import numpy as np
import torch

from .._atomic import write_json
from ..brdf import SVBRDF
from .exr import ExrError, read_exr, write_exr
from .svbrdf import Maps, write_svbrdf

__all__ = ["Capture", "CaptureError", "Frame", "LightSpec", "read_capture", "write_capture"]

FORMAT = "torchspec.capture"
VERSIONS = (1,)
MANIFEST = "capture.json"
_REQUIRED = ("width", "height", "channels", "camera", "light", "frames")
# Optional top-level keys read without a warning (kept in Capture.extra): "generator" records
# how a synthetic capture was made, by the development data's renderer and by torchspec simulate.
_OPTIONAL = ("generator",)
_KNOWN = ("format", "version") + _REQUIRED
_FRAME_KEYS = ("file", "direction", "irradiance", "exposure")
_LIGHT_KEYS = {"point": (), "gaussian": ("domain", "sigma"), "tabulated": ("file", "extent"), "unknown": ("symmetric",)}
_DOMAINS = ("projected", "angular")
_UNIT_TOLERANCE = 1e-3
"""A direction whose norm is further than this from 1 is an error."""
_UNIT_SILENT = 1e-6
"""Within this a direction is kept as written (float32 round-off); beyond, renormalised with a warning."""


class CaptureError(ValueError):
    """A capture that does not follow ``capture-format.md``; the message names the file, and the
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
    """

    file: str
    direction: tuple[float, float, float]
    irradiance: tuple[float, ...]
    exposure: float

    def __post_init__(self):
        object.__setattr__(self, "direction", _floats(self.direction))
        object.__setattr__(self, "irradiance", _floats(self.irradiance))
        object.__setattr__(self, "exposure", _floats(self.exposure))


@dataclass(frozen=True)
class LightSpec:
    """The extended light source shared by all frames (``capture-format.md``, table of kernels).

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


@dataclass(frozen=True)
class Capture:
    """A capture directory: its manifest, validated, and lazy access to its frames.

    Built by :func:`read_capture`; built by hand to describe a capture for :func:`write_capture`,
    which validates it like a manifest read from disk.

    Attributes:
        root: the capture directory; frame files are relative to it.
        width, height: ``W`` and ``H``, the size of every frame.
        channels: the ``C`` channel names read from every frame, in this order.
        view: unit direction towards the (orthographic) camera.
        light: the light kernel.
        frames: the ``K`` frames.
        extra: top-level manifest keys the format does not define, kept to be written back.
    """

    root: Path
    width: int
    height: int
    channels: tuple[str, ...]
    view: tuple[float, float, float]
    light: LightSpec
    frames: tuple[Frame, ...]
    extra: dict = field(default_factory=dict, hash=False)

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))
        channels = (self.channels,) if isinstance(self.channels, str) else tuple(self.channels)
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "view", _floats(self.view))
        object.__setattr__(self, "extra", dict(self.extra))
        for name in ("width", "height"):
            try:
                object.__setattr__(self, name, operator.index(getattr(self, name)))
            except TypeError:
                pass  # reported with the key's name by the manifest validation
        frames = tuple(self.frames)
        # A number is the same irradiance on every channel.
        frames = tuple(
            replace(frame, irradiance=(frame.irradiance,) * len(channels))
            if isinstance(frame, Frame) and isinstance(frame.irradiance, float)
            else frame
            for frame in frames
        )
        object.__setattr__(self, "frames", frames)

    @property
    def manifest(self) -> Path:
        """The path of ``capture.json``."""
        return self.root / MANIFEST

    def read_frames(
        self, indices: Sequence[int] | None = None, *, dtype: torch.dtype = torch.float32, device=None
    ) -> torch.Tensor:
        """Read frames as recorded (not divided by exposure or irradiance).

        Args:
            indices: the frames to read, in this order (negative indices count from the end);
                all ``K`` by default.
            dtype, device: of the result.

        Returns:
            ``(K, C, H, W)`` image stack, frames as the batch (kornia's layout), channels in the
            order of :attr:`channels`, row 0 at the top of the image.

        Raises:
            CaptureError: an index is out of range, or a frame is unreadable, has another size
                than the manifest's, lacks a channel, or holds NaN or Inf (the message names the
                frame index, the file and the count of bad pixels).

        Example:
            >>> capture = read_capture("painting-dev")  # doctest: +SKIP
            >>> capture.read_frames([0, 5]).shape
            torch.Size([2, 3, 48, 48])
        """
        count = len(self.frames)
        picked = range(count) if indices is None else [self._index(i) for i in _as_list(indices)]
        out = torch.empty((len(picked), len(self.channels), self.height, self.width), dtype=dtype, device=device)
        for j, k in enumerate(picked):
            out[j] = torch.from_numpy(self._read_frame(k)).permute(2, 0, 1)
        return out

    def _index(self, index) -> int:
        count = len(self.frames)
        try:
            k = operator.index(index)
        except TypeError:
            raise CaptureError(f"frame indices must be integers; got {index!r}.") from None
        if not -count <= k < count:
            raise CaptureError(f"frame index must be in [0, {count}) ({self.manifest} has {count} frames); got {k}.")
        return k % count

    def _read_frame(self, k: int) -> np.ndarray:
        file = self.root / self.frames[k].file
        try:
            image = read_exr(file, self.channels)
        except ExrError as error:
            raise CaptureError(
                f"{self.manifest}: frames[{k}] must be a readable EXR with channels {list(self.channels)}; got: {error}"
            ) from error
        if image.shape[:2] != (self.height, self.width):
            raise CaptureError(
                f"frames[{k}] {file} must be {self.height}x{self.width} (height x width, from {self.manifest}); "
                f"got {image.shape[0]}x{image.shape[1]}. Crop or resample the frame, or fix width and height."
            )
        bad = int((~np.isfinite(image)).any(axis=2).sum())
        if bad:
            raise CaptureError(
                f"frames[{k}] {file} must be finite; got {bad} pixel(s) with NaN or Inf (of "
                f"{self.height * self.width}). Re-export the frame, or replace those pixels with a finite value."
            )
        return image

    def read_kernel(self) -> torch.Tensor:
        """Read the image of a tabulated light kernel.

        Returns:
            ``(Hk, Wk)`` float32, channel ``Y`` of :attr:`LightSpec.file`, covering ``l - l_k`` in
            ``[-extent, extent]^2``, row 0 at the top (largest ``l_y``); not normalised.

        Raises:
            CaptureError: the light is not tabulated, or the file is unreadable, has no channel
                ``Y``, holds NaN or Inf, or has no positive mass.
        """
        if self.light.kernel != "tabulated":
            raise CaptureError(
                f"{self.manifest}: light.kernel must be 'tabulated' to read a kernel image; got "
                f"{self.light.kernel!r}. Only a tabulated light has a kernel file."
            )
        file = self.root / self.light.file
        try:
            image = read_exr(file, ["Y"])[:, :, 0]
        except ExrError as error:
            raise CaptureError(
                f"{self.manifest}: light.file must be a readable EXR with channel 'Y'; got: {error}"
            ) from error
        problem = _kernel_problem(image)
        if problem:
            raise CaptureError(f"{self.manifest}: light.file {file} {problem}")
        return torch.from_numpy(np.ascontiguousarray(image))

    def directions(self) -> torch.Tensor:
        """``(K, 3)`` float64 light centre directions."""
        return torch.tensor([frame.direction for frame in self.frames], dtype=torch.float64).reshape(-1, 3)

    def irradiance(self) -> torch.Tensor:
        """``(K, C)`` float64 irradiance per frame and channel."""
        values = [frame.irradiance for frame in self.frames]
        return torch.tensor(values, dtype=torch.float64).reshape(-1, len(self.channels))

    def exposure(self) -> torch.Tensor:
        """``(K,)`` float64 exposure per frame."""
        return torch.tensor([frame.exposure for frame in self.frames], dtype=torch.float64)


def read_capture(path: str | Path) -> Capture:
    """Read and validate a capture's manifest; the frames are read later by
    :meth:`Capture.read_frames`.

    Unknown keys are warned about (``warnings.warn``); unknown top-level keys are kept in
    :attr:`Capture.extra`. A direction whose norm is within ``1e-3`` of 1 is renormalised with a
    warning.

    Args:
        path: the capture directory, or its ``capture.json``.

    Returns:
        The capture, ``root`` its directory.

    Raises:
        CaptureError: ``capture.json`` is missing, not JSON, or breaks ``capture-format.md``
            (the message names the key, e.g. ``frames[3].direction``), or a listed frame or
            kernel file does not exist.

    Example:
        >>> capture = read_capture("../shared/data/painting-dev")  # doctest: +SKIP
        >>> len(capture.frames), capture.channels, capture.light.kernel
        (88, ('R', 'G', 'B'), 'gaussian')
    """
    path = Path(path)
    manifest = path if path.suffix.lower() == ".json" or path.is_file() else path / MANIFEST
    if not manifest.is_file():
        raise CaptureError(f"{manifest} must exist; got no such file. Pass a capture directory that holds {MANIFEST}.")
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except json.JSONDecodeError as error:
        raise CaptureError(
            f"{manifest} must be valid JSON; got {error.msg} at line {error.lineno} column {error.colno}. "
            "Fix the syntax."
        ) from error
    except (OSError, UnicodeDecodeError) as error:
        raise CaptureError(f"{manifest} must be a readable UTF-8 file; got {error}.") from error
    notes: list[str] = []
    capture = Capture(root=manifest.parent, **_parse(data, manifest, notes))
    for note in notes:
        warnings.warn(note, stacklevel=2)
    for k, frame in enumerate(capture.frames):
        file = capture.root / frame.file
        if not file.is_file():
            raise CaptureError(
                f"{manifest}: frames[{k}].file must exist; got {frame.file!r}, but {file} is missing "
                f"(the first of the missing frames). Restore the frame or remove it from {MANIFEST}."
            )
    if capture.light.kernel == "tabulated" and not (capture.root / capture.light.file).is_file():
        raise CaptureError(
            f"{manifest}: light.file must exist; got {capture.light.file!r}, but {capture.root / capture.light.file} "
            "is missing. Restore the kernel image."
        )
    return capture


def write_capture(
    path: str | Path,
    capture: Capture,
    frames: torch.Tensor | np.ndarray,
    *,
    kernel: torch.Tensor | np.ndarray | None = None,
    truth: SVBRDF | Maps | None = None,
) -> Capture:
    """Write a capture directory: frames, kernel, truth maps, then ``capture.json`` last.

    The manifest is validated like :func:`read_capture` does and the shapes checked before any
    file is written. An existing ``capture.json`` is removed first, so an interrupted write
    leaves no manifest over a mix of old and new frames; each file is written atomically.

    Args:
        path: the capture directory (created if needed).
        capture: the manifest; its ``root`` is where a tabulated kernel is copied from when
            ``kernel`` is not given.
        frames: ``(K, C, H, W)`` frames in the order of ``capture.frames``, channels in the order
            of ``capture.channels``; written as float32 EXRs at the frames' file names.
        kernel: ``(Hk, Wk)`` image of a tabulated light, written to ``light.file``.
        truth: ground-truth maps (leading dims ``(H, W)``), written to ``path/truth`` with
            :func:`~torchspec.io.write_svbrdf`.

    Returns:
        The capture as :func:`read_capture` will read it back, ``root = path``.

    Raises:
        CaptureError: the manifest is invalid, or the frames, kernel or truth do not match it.

    Example:
        >>> written = write_capture("out", capture, capture.read_frames())  # doctest: +SKIP
    """
    root = Path(path)
    if root.name == MANIFEST:
        root = root.parent
    manifest_path = root / MANIFEST
    notes: list[str] = []
    result = Capture(root=root, **_parse(_to_manifest(capture, manifest_path), manifest_path, notes, extra_known=True))
    for note in notes:
        warnings.warn(note, stacklevel=2)
    manifest = _to_manifest(result, manifest_path)
    size = (len(result.frames), len(result.channels), result.height, result.width)
    images = frames if isinstance(frames, torch.Tensor) else np.asarray(frames)
    if tuple(images.shape) != size:
        raise CaptureError(
            f"frames for {manifest_path} must have shape (K, C, H, W) = {size} ({size[0]} frames, channels "
            f"{list(result.channels)}, {size[2]}x{size[3]}); got {tuple(images.shape)}."
        )
    for k in range(size[0]):
        bad = int((~np.isfinite(_numpy(images[k]))).any(axis=0).sum())
        if bad:
            raise CaptureError(f"frames[{k}] for {manifest_path} must be finite; got {bad} pixel(s) with NaN or Inf.")
    kernel_image = _kernel_to_write(capture, result, kernel)
    if truth is not None:
        _check_truth(truth, result)

    root.mkdir(parents=True, exist_ok=True)
    manifest_path.unlink(missing_ok=True)
    for k, frame in enumerate(result.frames):
        try:
            write_exr(root / frame.file, _numpy(images[k]).transpose(1, 2, 0), result.channels)
        except ExrError as error:
            raise CaptureError(f"frames[{k}] of {manifest_path} could not be written: {error}") from error
    if kernel_image is not None:
        write_exr(root / result.light.file, kernel_image, ["Y"])
    if truth is not None:
        write_svbrdf(root / "truth", truth)
    write_json(manifest_path, manifest)
    return result


def _kernel_to_write(capture: Capture, result: Capture, kernel) -> np.ndarray | None:
    """The kernel image ``(Hk, Wk)`` to write, or ``None`` when there is nothing to write."""
    where = result.manifest
    if kernel is None:
        if result.light.kernel != "tabulated":
            return None
        source, target = capture.root / result.light.file, result.root / result.light.file
        if source.is_file() and source.resolve() != target.resolve():
            return capture.read_kernel().numpy()
        if target.is_file():
            return None
        raise CaptureError(
            f"kernel for {where} must be given for a tabulated light; got None, and neither {source} nor {target} "
            "exists. Pass kernel=(Hk, Wk) image."
        )
    if result.light.kernel != "tabulated":
        raise CaptureError(
            f"kernel for {where} must be None unless light.kernel is 'tabulated'; got a kernel with light.kernel "
            f"{result.light.kernel!r}. Drop the kernel or describe a tabulated light."
        )
    image = _numpy(kernel).astype(np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2 or 0 in image.shape:
        raise CaptureError(f"kernel for {where} must have shape (Hk, Wk) with Hk, Wk > 0; got {image.shape}.")
    problem = _kernel_problem(image)
    if problem:
        raise CaptureError(f"kernel for {where} {problem}")
    return image


def _kernel_problem(image: np.ndarray) -> str | None:
    bad = int((~np.isfinite(image)).sum())
    if bad:
        return f"must be finite; got {bad} pixel(s) with NaN or Inf. Recompute the kernel image."
    if not image.sum() > 0:
        return f"must have positive total mass; got sum {float(image.sum()):.3g}. Give a non-negative kernel image."
    return None


def _check_truth(truth, result: Capture) -> None:
    svbrdf = truth.svbrdf if isinstance(truth, Maps) else truth
    where = result.manifest
    if not isinstance(svbrdf, SVBRDF):
        raise CaptureError(f"truth for {where} must be an SVBRDF or Maps; got {type(truth).__name__}.")
    if tuple(svbrdf.shape) != (result.height, result.width):
        raise CaptureError(
            f"truth for {where} must have leading dims (H, W) = {(result.height, result.width)}; "
            f"got {tuple(svbrdf.shape)}."
        )
    if tuple(svbrdf.channels) != result.channels:
        raise CaptureError(
            f"truth for {where} must have the capture's channels {list(result.channels)}; got {list(svbrdf.channels)}."
        )


# --- the manifest -------------------------------------------------------------------------------


class _Text(str):
    """A description shown as it is in an error, where a value would be shown as JSON."""


class _Where:
    """Builds errors that name the manifest and a key."""

    def __init__(self, source: Path):
        self.source = source

    def error(self, key: str, condition: str, got: Any, fix: str = "") -> CaptureError:
        return CaptureError(f"{self.source}: {key} must {condition}; got {_show(got)}." + (f" {fix}" if fix else ""))


def _parse(data: Any, source: Path, notes: list[str], *, extra_known: bool = False) -> dict[str, Any]:
    """Validate a manifest; the fields of :class:`Capture` but ``root``. Warnings go to ``notes``;
    with ``extra_known`` (a manifest made from :attr:`Capture.extra`) unknown top-level keys are
    not warned about."""
    where = _Where(source)
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
    missing = [key for key in _REQUIRED if key not in data]
    if missing:
        raise where.error(
            "the manifest", f"have the keys {list(_REQUIRED)}", _Text(f"{missing} missing"), "See capture-format.md."
        )
    unknown = [key for key in data if key not in _KNOWN]
    if [key for key in unknown if key not in _OPTIONAL] and not extra_known:
        strange = [key for key in unknown if key not in _OPTIONAL]
        notes.append(f"{source}: unknown top-level key(s) {strange} are kept in Capture.extra and not used.")
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
        "light": _light(where, data["light"], notes),
        "frames": _frames(where, data["frames"], len(channels), notes),
        "extra": {key: data[key] for key in unknown},
    }


def _camera(where: _Where, camera: Any, notes: list[str]) -> tuple[float, float, float]:
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


def _light(where: _Where, light: Any, notes: list[str]) -> LightSpec:
    if not isinstance(light, dict):
        raise where.error("light", "be an object", light, 'E.g. {"kernel": "point"}.')
    kernel = light.get("kernel")
    if kernel not in _LIGHT_KEYS:
        raise where.error("light.kernel", f"be one of {list(_LIGHT_KEYS)}", kernel)
    keys = _LIGHT_KEYS[kernel]
    for key in keys:
        if key not in light:
            raise where.error(
                f"light.{key}", f"be given for kernel {kernel!r}", _Text("no such key"), "See capture-format.md."
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


def _frames(where: _Where, frames: Any, count: int, notes: list[str]) -> tuple[Frame, ...]:
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
        missing = [name for name in _FRAME_KEYS if name not in raw]
        if missing:
            raise where.error(key, f"have the keys {list(_FRAME_KEYS)}", _Text(f"{missing} missing"))
        _unknown(where, key, raw, _FRAME_KEYS, notes)
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
        out.append(Frame(file=file, direction=direction, irradiance=irradiance, exposure=exposure))
    return tuple(out)


def _direction(where: _Where, key: str, value: Any, notes: list[str]) -> tuple[float, float, float]:
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


def _unknown(where: _Where, key: str, obj: dict, known: Sequence[str], notes: list[str]) -> None:
    unknown = [name for name in obj if name not in known]
    if unknown:
        notes.append(f"{where.source}: unknown key(s) {unknown} in {key} are ignored.")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _positive(where: _Where, key: str, value: Any) -> float:
    if not _is_number(value) or not value > 0:
        raise where.error(key, "be a positive number", value)
    return float(value)


def _positive_int(where: _Where, key: str, value: Any) -> int:
    if type(value) is not int or value <= 0:
        raise where.error(key, "be a positive integer", value)
    return value


def _relative_file(where: _Where, key: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise where.error(key, "be a file name (a non-empty string)", value)
    if PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute():
        raise where.error(key, "be a path relative to the capture directory", value, "Make the path relative.")
    return value


def _to_manifest(capture: Capture, source: Path) -> dict[str, Any]:
    """The JSON manifest of ``capture`` (validated by :func:`_parse`, not here)."""
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
        frames.append(
            {"file": frame.file, "direction": direction, "irradiance": irradiance, "exposure": frame.exposure}
        )
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
