"""Capture directories of ``docs/capture-format.md``: the manifest ``capture.json``, its frames and an
optional tabulated light kernel.

:func:`read_capture` validates the whole manifest and checks that every frame file exists, but
reads no pixels: :meth:`Capture.read_frames` reads (a subset of) the frames when asked, so a
caller can bound memory by the frames or tiles it holds. :func:`write_capture` writes the frames
first and ``capture.json`` last, so an interrupted write never leaves a manifest that lists
missing frames.
"""

from __future__ import annotations

import operator
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..atomic import read_json, write_json
from ..errors import TorchspecError
from ..model.brdf import SVBRDF
from ..model.lights import Kernel, Lights
from ..outputs import check_output
from ._manifest import (
    FORMAT,
    MANIFEST,
    VERSIONS,
    CaptureError,
    Frame,
    LightSpec,
    Where,
    _as_list,
    _floats,
    _numpy,
    _show,
    not_a_capture,
    parse_light,
    parse_manifest,
    to_manifest,
)
from .exr import ExrError, _read_rows, read_exr, write_exr
from .svbrdf import Maps, write_svbrdf

__all__ = [
    "Capture",
    "CaptureError",
    "Frame",
    "LightSpec",
    "FORMAT",
    "VERSIONS",
    "light_kernel",
    "read_capture",
    "write_capture",
]


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

    @property
    def saturation(self) -> float | None:
        """The clipping level the capture records, ``None`` when it records none: an imported
        capture's ``source.saturation`` (``torchspec import``: 1, an integer photograph's largest
        code). A fit whose ``FitConfig.masks.saturation`` is ``None`` masks at it instead of detecting a
        plateau (a flat region repeats a frame's largest value without clipping)."""
        source = self.extra.get("source")
        level = source.get("saturation") if isinstance(source, dict) else None
        if isinstance(level, (int, float)) and not isinstance(level, bool) and level > 0:
            return float(level)
        return None

    def read_frames(
        self,
        indices: Sequence[int] | None = None,
        *,
        rows: tuple[int, int] | None = None,
        dtype: torch.dtype = torch.float32,
        device=None,
        nonfinite: str = "raise",
    ) -> torch.Tensor:
        """Read frames as recorded (not divided by exposure or irradiance).

        Args:
            indices: the frames to read, in this order (negative indices count from the end);
                all ``K`` by default.
            rows: ``(start, stop)``: only these rows of every frame, reading only the blocks of
                each file that hold them (:func:`~torchspec.io.exr.read_exr`); all by default.
            dtype, device: of the result.
            nonfinite: ``raise`` (a frame with NaN, Inf or negative pixels is an error),
                ``keep`` (they are returned as they are, with a warning naming the frame, for a
                caller that masks them, as :func:`torchspec.pipeline.fit` does) or ``ignore`` (the same
                without the warning, for a caller that counts and reports them itself).

        Returns:
            ``(K, C, H, W)`` image stack (``H = stop - start`` with ``rows``), frames as the batch
            (kornia's layout), channels in the order of :attr:`channels`, row 0 at the top of the
            image.

        Raises:
            CaptureError: an index is out of range, or a frame is unreadable, has another size
                than the manifest's, lacks a channel, or holds NaN, Inf or (with ``raise``)
                negative values (the message names the frame index, the file and the count of bad
                pixels, and the most negative value).

        Example:
            >>> from tempfile import mkdtemp
            >>> from torchspec.demo import scene
            >>> from torchspec.simulate import simulate, write_simulation
            >>> folder = f"{mkdtemp()}/sim"  # a simulated 8 x 8 painting, 88 frames
            >>> _ = write_simulation(folder, simulate(scene(size=8), root=folder))
            >>> capture = read_capture(folder)
            >>> capture.read_frames([0, 5]).shape
            torch.Size([2, 3, 8, 8])
        """
        if nonfinite not in ("raise", "keep", "ignore"):
            raise TorchspecError(f"nonfinite must be 'raise', 'keep' or 'ignore'; got {nonfinite!r}.")
        count = len(self.frames)
        picked = range(count) if indices is None else [self._index(i) for i in _as_list(indices)]
        out = torch.empty((0, len(self.channels), self.height, self.width), dtype=dtype, device=device)
        for j, k in enumerate(picked):
            image = torch.from_numpy(self._read_frame(k, nonfinite, rows)).permute(2, 0, 1)
            if j == 0:  # allocated once a frame has the manifest's size: a wrong one allocates nothing
                out = torch.empty((len(picked), *image.shape), dtype=dtype, device=device)
            out[j] = image
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

    def _read_frame(self, k: int, nonfinite: str = "raise", rows: tuple[int, int] | None = None) -> np.ndarray:
        """Frame ``k`` (its ``rows``) as ``(H, W, C)``, checked; NaN, Inf and negative values
        raise unless ``nonfinite`` is ``keep``, which warns instead, or ``ignore``."""
        file = self.root / self.frames[k].file
        keep_bad, warn = nonfinite != "raise", nonfinite == "keep"
        try:
            if rows is None:
                image = read_exr(file, self.channels)
                size = image.shape[:2]
            else:
                image, size = _read_rows(file, self.channels, rows)
        except ExrError as error:
            raise CaptureError(
                f"{self.manifest}: frames[{k}] (an EXR with channels {list(self.channels)}): {error}"
            ) from error
        if size != (self.height, self.width):
            raise CaptureError(
                f"frames[{k}] {file} must be {self.height}x{self.width} (height x width, from {self.manifest}); "
                f"got {size[0]}x{size[1]}. Crop or resample the frame, or fix width and height."
            )
        finite = np.isfinite(image)
        bad = int((~finite).any(axis=2).sum())
        read = image.shape[0] * image.shape[1]  # the pixels read: the frame's, or its rows'
        if bad and not keep_bad:
            raise CaptureError(
                f"frames[{k}] {file} must be finite; got {bad} pixel(s) with NaN or Inf (of "
                f"{read}). Re-export the frame, or replace those pixels with a finite value."
            )
        if bad and warn:
            warnings.warn(
                f"frames[{k}] {file}: {bad} pixel(s) with NaN or Inf (of {read}) are returned as they are: mask them.",
                stacklevel=3,
            )
        below = (image < 0) & finite  # -Inf is counted above
        negative = int(below.any(axis=2).sum())
        if negative:
            lowest = float(image[below].min())
            if not keep_bad:
                raise CaptureError(
                    f"frames[{k}] {file} must be non-negative (linear radiance); got {negative} pixel(s) with a "
                    f"negative value (of {read}), the most negative {lowest:.3g}. Re-export the "
                    "frame without a black-level offset, or read it with nonfinite='keep' and mask them."
                )
            if warn:
                warnings.warn(
                    f"frames[{k}] {file}: {negative} pixel(s) with a negative value (of {read}; "
                    f"the most negative {lowest:.3g}) are kept as they are.",
                    stacklevel=3,
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
        return read_kernel_table(self.root / self.light.file, f"{self.manifest}: light.file")

    def directions(self) -> torch.Tensor:
        """``(K, 3)`` float64 light centre directions."""
        # CPU on purpose: a small table from the manifest (JSON); callers move it with .to(...)
        return torch.tensor([frame.direction for frame in self.frames], dtype=torch.float64).reshape(-1, 3)

    def irradiance(self) -> torch.Tensor:
        """``(K, C)`` float64 irradiance per frame and channel."""
        values = [frame.irradiance for frame in self.frames]
        # CPU on purpose: a small table from the manifest (JSON); callers move it with .to(...)
        return torch.tensor(values, dtype=torch.float64).reshape(-1, len(self.channels))

    def positions(self) -> torch.Tensor | None:
        """``(K, 3)`` float64 near-light positions (``Frame.position``), or ``None`` for distant lights."""
        if not self.frames or self.frames[0].position is None:
            return None
        # CPU on purpose: a small table from the manifest (JSON); callers move it with .to(...)
        return torch.tensor([frame.position for frame in self.frames], dtype=torch.float64).reshape(-1, 3)

    @property
    def unknown(self) -> tuple[str, ...]:
        """What the manifest's ``unknown`` key says the capture does not know (``irradiance``, ``position``)."""
        return tuple(self.extra.get("unknown", ()))

    def exposure(self) -> torch.Tensor:
        """``(K,)`` float64 exposure per frame."""
        # CPU on purpose: a small table from the manifest (JSON); callers move it with .to(...)
        return torch.tensor([frame.exposure for frame in self.frames], dtype=torch.float64)

    def lights(self, *, light: str | Path | dict | None = None, dtype: torch.dtype = torch.float64) -> Lights:
        """The :class:`~torchspec.model.lights.Lights` of the capture's frames (``K`` of them), in ``dtype``.

        Args:
            light: a JSON file, or a mapping, with the keys of the format's ``light`` block, or
                with that block under ``light`` (the ``.json`` that ``torchspec calibrate`` writes
                beside its kernel), or a development capture's ``truth/light.json``: replaces the
                manifest's kernel, which an ``unknown`` kernel requires. A tabulated light's
                ``file`` is relative to the JSON file (to the capture for a mapping).
            dtype: of the directions, irradiance and exposure.

        Raises:
            CaptureError: the manifest's kernel is ``unknown`` and no ``light`` is given, or
                ``light`` is an unreadable file, breaks the format's light block or names an
                unreadable kernel image.
        """
        if light is None:
            spec = self.light
            if spec.kernel == "unknown":
                raise CaptureError(
                    f"{self.manifest}: light.kernel is 'unknown', so the frames cannot be predicted. Give the "
                    "light's shape with --light-model FILE (e.g. a calibrated or known light JSON)."
                )
            table = self.read_kernel() if spec.kernel == "tabulated" else None
            kernel = Kernel.from_spec(spec, table=table)
        else:
            kernel = self._given_kernel(light)
        return Lights(self.directions().to(dtype), kernel, self.irradiance().to(dtype), self.exposure().to(dtype))

    def _given_kernel(self, light: str | Path | Mapping) -> Kernel:
        """The kernel of a light description given instead of the manifest's (:meth:`lights`)."""
        return light_kernel(light, self.root)


def light_kernel(light: str | Path | Mapping, folder: Path, option: str = "--light-model") -> Kernel:
    """The kernel of a light description (:meth:`Capture.lights`' ``light``): a JSON file, or a
    mapping whose tabulated ``file`` is relative to ``folder``; ``option`` is what gave the file
    (named when it is unreadable).

    Raises:
        CaptureError: an unreadable file, a block that breaks the format, an ``unknown`` kernel or
            an unreadable kernel image.
    """
    source = None
    if not isinstance(light, Mapping):
        source = Path(light)
        hint = f"The light description ({option}) is a JSON file, e.g. the .json torchspec calibrate writes."
        light = read_json(source, CaptureError, hint)
        if not isinstance(light, Mapping):
            raise CaptureError(f"the light description {source} must be a JSON object; got {_show(light)}.")
    if isinstance(light.get("light"), Mapping):  # calibrate's kernel.json: {"light": ..., "calibration": ...}
        light = light["light"]
    if light.get("kind", light.get("kernel")) in ("supergaussian", "disk"):  # a simulation's truth/light.json
        return Kernel.from_spec(light)
    where = Where(source if source is not None else Path("the light description"))
    notes: list[str] = []
    spec = parse_light(where, dict(light), notes)
    for note in notes:
        warnings.warn(note, stacklevel=3)
    if spec.kernel == "unknown":
        raise where.error("light.kernel", "give the light's shape (not 'unknown') to predict frames", spec.kernel)
    table = None
    if spec.kernel == "tabulated":
        folder = source.parent if source is not None else folder
        table = read_kernel_table(folder / spec.file, f"{where.source}: light.file")
    return Kernel.from_spec(spec, table=table)


def read_kernel_table(file: Path, key: str) -> torch.Tensor:
    """The ``(Hk, Wk)`` float32 table of a tabulated kernel: channel ``Y`` of ``file``, checked
    (finite, positive mass); ``key`` names the file in an error (e.g. ``capture.json: light.file``)."""
    try:
        image = read_exr(file, ["Y"])[:, :, 0]
    except ExrError as error:
        raise CaptureError(f"{key} must be a readable EXR with channel 'Y'; got: {error}") from error
    problem = _kernel_problem(image)
    if problem:
        raise CaptureError(f"{key} {file} {problem}")
    return torch.from_numpy(np.ascontiguousarray(image))


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
        CaptureError: ``capture.json`` is missing, not JSON, or breaks ``docs/capture-format.md``
            (the message names the key, e.g. ``frames[3].direction``), or a listed frame or
            kernel file does not exist.

    Example:
        >>> from tempfile import mkdtemp
        >>> from torchspec.demo import scene
        >>> from torchspec.simulate import simulate, write_simulation
        >>> folder = f"{mkdtemp()}/sim"  # a simulated 8 x 8 painting, 88 frames
        >>> _ = write_simulation(folder, simulate(scene(size=8), root=folder))
        >>> capture = read_capture(folder)
        >>> len(capture.frames), capture.channels, capture.light.kernel
        (88, ('R', 'G', 'B'), 'gaussian')
    """
    path = Path(path)
    not_a_capture(path)
    manifest = path if path.suffix.lower() == ".json" or path.is_file() else path / MANIFEST
    data = read_json(manifest, CaptureError, f"Pass a capture directory that holds {MANIFEST}.")
    notes: list[str] = []
    capture = Capture(root=manifest.parent, **parse_manifest(data, manifest, notes))
    for note in notes:
        warnings.warn(note, stacklevel=2)
    for k, frame in enumerate(capture.frames):
        file = capture.root / frame.file
        if not _is_file(file, f"{manifest}: frames[{k}].file"):
            raise CaptureError(
                f"{manifest}: frames[{k}].file must exist; got {frame.file!r}, but {file} is missing "
                f"(the first of the missing frames). Restore the frame or remove it from {MANIFEST}."
            )
    kernel = capture.root / capture.light.file if capture.light.kernel == "tabulated" else None
    if kernel is not None and not _is_file(kernel, f"{manifest}: light.file"):
        raise CaptureError(
            f"{manifest}: light.file must exist; got {capture.light.file!r}, but {kernel} "
            "is missing. Restore the kernel image."
        )
    return capture


def _is_file(path: Path, key: str) -> bool:
    """``path.is_file()``, with a :class:`CaptureError` naming ``key`` for a path the system
    refuses (a name too long, a folder without permission)."""
    try:
        return path.is_file()
    except OSError as error:
        raise CaptureError(
            f"{key} must be a file the system can look up; got {path}: {error.strerror or error}."
        ) from error


def write_capture(
    path: str | Path,
    capture: Capture,
    frames: torch.Tensor | np.ndarray,
    *,
    kernel: torch.Tensor | np.ndarray | None = None,
    truth: SVBRDF | Maps | None = None,
    overwrite: bool = False,
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
        overwrite: write into a folder that already holds files (those of the same names are
            replaced); without it such a folder is refused (:func:`torchspec.outputs.check_output`).

    Returns:
        The capture as :func:`read_capture` will read it back, ``root = path``.

    Raises:
        OutputError: ``path`` holds files and ``overwrite`` is not set, or cannot be written.
        CaptureError: the manifest is invalid, or the frames, kernel or truth do not match it.

    Example:
        >>> from tempfile import mkdtemp
        >>> from torchspec.demo import scene
        >>> from torchspec.simulate import simulate, write_simulation
        >>> folder = f"{mkdtemp()}/sim"  # a simulated 8 x 8 painting, 88 frames
        >>> _ = write_simulation(folder, simulate(scene(size=8), root=folder))
        >>> capture = read_capture(folder)
        >>> copy = write_capture(f"{folder}-copy", capture, capture.read_frames())
        >>> copy.root.name, len(copy.frames)
        ('sim-copy', 88)
    """
    root = Path(path)
    if root.name == MANIFEST:
        root = root.parent
    check_output(root, overwrite=overwrite)
    manifest_path = root / MANIFEST
    notes: list[str] = []
    data = to_manifest(capture, manifest_path)
    result = Capture(root=root, **parse_manifest(data, manifest_path, notes, extra_known=True))
    for note in notes:
        warnings.warn(note, stacklevel=2)
    manifest = to_manifest(result, manifest_path)
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
        write_svbrdf(root / "truth", truth, overwrite=overwrite)
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
