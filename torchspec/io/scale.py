"""A quick look at a large capture: a crop and a box-average downsample (``--crop X,Y,W,H`` and
``--downsample N`` of ``torchspec import`` and ``torchspec fit``).

A :class:`Scale` takes the region ``X, Y, W, H`` of the full image (pixels, ``X, Y`` its top-left
corner; default: the whole image) and averages boxes of ``N x N`` of its pixels: the reduced image
is ``floor(W / N)`` by ``floor(H / N)`` pixels, its pixel (row ``r``, column ``c``) the mean of the
full image's rows ``Y + r N`` to ``Y + r N + N - 1`` and columns ``X + c N`` to ``X + c N + N - 1``
(the last ``W mod N`` columns and ``H mod N`` rows of the region are left out). Values are
averaged as they are given: linear radiance (an import reduces the photographs once decoded).

Clipping is kept conservatively: where a clipping level is given, a box holding a sample at or
above it in a channel reads, in that channel, as the box's largest value, so the reduced pixel is
clipped as well (the fit masks it as it would have masked the sample). A box holding NaN or Inf
reads NaN or Inf (the fit masks it).

Near lights (frames with a ``position``, in widths of the image from its centre) are moved to
the reduced image's frame: the origin at the reduced region's centre, the unit its width; each
frame's ``direction`` and ``irradiance`` are then those seen from the new centre
(:mod:`torchspec.model.near_lights`).

:class:`ScaledCapture` is a capture read this way: its frames are reduced as they are read, one
at a time (memory and the work after reading drop by ``N^2``).
"""

from __future__ import annotations

import functools
import math
import operator
from dataclasses import dataclass, replace

import numpy as np

from ..errors import TorchspecError
from .capture import Capture, CaptureError

__all__ = ["DOWNSAMPLE", "CROP", "Scale", "ScaleError", "ScaledCapture", "capture_at", "reduce_image", "scaled"]

DOWNSAMPLE = "--downsample"
"""The option that sets :attr:`Scale.downsample`, named by errors."""
CROP = "--crop"
"""The option that sets :attr:`Scale.crop`, named by errors."""


class ScaleError(TorchspecError):
    """A downsample factor or crop that cannot be applied; the message names the option and the
    image's size."""


def _integer(value, what: str) -> int:
    try:
        if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
            raise TypeError
        return operator.index(int(value) if isinstance(value, float) else value)
    except (TypeError, ValueError):
        raise ScaleError(f"{what} must be a whole number; got {value!r}.") from None


@dataclass(frozen=True)
class Scale:
    """A crop ``(X, Y, W, H)`` of the full image (``None``: all of it) and a box-average factor.

    Raises:
        ScaleError: ``downsample`` is not a whole number ``>= 1``, or ``crop`` not four whole
            numbers with ``X, Y >= 0`` and ``W, H >= 1`` (the message names :data:`DOWNSAMPLE` or
            :data:`CROP`).
    """

    downsample: int = 1
    crop: tuple[int, int, int, int] | None = None

    def __post_init__(self):
        n = _integer(self.downsample, f"{DOWNSAMPLE} N")
        if n < 1:
            raise ScaleError(f"{DOWNSAMPLE} N must be >= 1 (1: every pixel, 2: boxes of 2 x 2); got {n}.")
        object.__setattr__(self, "downsample", n)
        if self.crop is None:
            return
        if isinstance(self.crop, str) or len(self.crop) != 4:
            raise ScaleError(f"{CROP} must be four whole numbers X,Y,W,H, pixels of the full image; got {self.crop!r}.")
        x, y, w, h = (_integer(v, f"{CROP} X,Y,W,H") for v in self.crop)
        if x < 0 or y < 0 or w < 1 or h < 1:
            raise ScaleError(
                f"{CROP} X,Y,W,H must have X, Y >= 0 (the top-left corner) and W, H >= 1 (the size); "
                f"got {x},{y},{w},{h}."
            )
        object.__setattr__(self, "crop", (x, y, w, h))

    @classmethod
    def parse(cls, downsample: int | None = None, crop: str | None = None) -> Scale:
        """The scale of the options' text: ``downsample`` (``None``: 1) and ``crop`` ``X,Y,W,H``
        (``None``: the whole image)."""
        if crop is None:
            return cls(1 if downsample is None else downsample)
        parts = [part.strip() for part in str(crop).split(",")]
        if len(parts) != 4 or not all(part.lstrip("-").isdigit() for part in parts):
            raise ScaleError(
                f"{CROP} must be X,Y,W,H: four whole numbers, pixels of the full image (e.g. {CROP} 100,50,640,480); "
                f"got {crop!r}."
            )
        return cls(1 if downsample is None else downsample, tuple(int(part) for part in parts))

    @classmethod
    def from_record(cls, record: dict) -> Scale:
        """The scale :meth:`record` describes."""
        return cls(record.get("downsample", 1), None if record.get("crop") is None else tuple(record["crop"]))

    @property
    def identity(self) -> bool:
        """Every pixel as it is: no crop, no downsample."""
        return self.downsample == 1 and self.crop is None

    def region(self, width: int, height: int, what: str = "the image") -> tuple[int, int, int, int]:
        """``(X, Y, W, H)``: the pixels of a ``width x height`` image that the reduced image covers
        (the crop, less the rows and columns that do not fill a box).

        Raises:
            ScaleError: the crop reaches outside the image, or the region is smaller than one box
                (the message names the option, ``what`` and its size).
        """
        x, y, w, h = self.crop if self.crop is not None else (0, 0, width, height)
        if x + w > width or y + h > height:
            raise ScaleError(
                f"{CROP} {x},{y},{w},{h} reaches outside {what}, which is {width}x{height} (width x height): "
                f"X + W must be <= {width} and Y + H <= {height}."
            )
        n = self.downsample
        if w < n or h < n:
            named = f"{CROP} {x},{y},{w},{h}" if self.crop is not None else what
            raise ScaleError(
                f"{DOWNSAMPLE} {n} is larger than {named} ({w}x{h}): the reduced image would have no pixel. "
                f"Choose N <= {min(w, h)}."
            )
        return x, y, (w // n) * n, (h // n) * n

    def size(self, width: int, height: int, what: str = "the image") -> tuple[int, int]:
        """``(width, height)`` of the reduced image of a ``width x height`` one."""
        _, _, w, h = self.region(width, height, what)
        return w // self.downsample, h // self.downsample

    def record(self, width: int, height: int) -> dict:
        """What a manifest records of the scale of a ``width x height`` image: ``downsample``,
        ``crop`` (``[X, Y, W, H]``, the region the reduced image covers) and ``full_size``
        (``[width, height]``)."""
        return {"downsample": self.downsample, "crop": list(self.region(width, height)), "full_size": [width, height]}

    def reduce(self, image: np.ndarray, level: float | None = None) -> np.ndarray:
        """``(H, W, C)`` of an ``(H N, W N, C)`` image (the region, already cut): :func:`reduce_image`."""
        return reduce_image(image, self.downsample, level)


def compose(outer: dict | None, inner: dict) -> dict:
    """The scale :meth:`Scale.record` ``inner``, of an image itself reduced by ``outer`` (``None``:
    not reduced), as a record of the full image ``outer`` was reduced from."""
    if outer is None:
        return inner
    n, (x, y, _, _) = outer["downsample"], outer["crop"]
    ix, iy, iw, ih = inner["crop"]
    crop = [x + ix * n, y + iy * n, iw * n, ih * n]
    return {"downsample": n * inner["downsample"], "crop": crop, "full_size": list(outer["full_size"])}


def reduce_image(image: np.ndarray, n: int, level: float | None = None) -> np.ndarray:
    """``(H, W, C)`` float32: the means of the ``n x n`` boxes of ``image (H n, W n, C)`` (extra
    rows and columns left out); with a clipping ``level``, a box whose largest value in a channel
    is at or above it takes that largest value in that channel (still clipped). NaN or Inf in a
    box make its value NaN or Inf."""
    if n == 1:
        return np.ascontiguousarray(image, dtype=np.float32)
    h, w, c = image.shape[0] // n, image.shape[1] // n, image.shape[2]
    boxes = image[: h * n, : w * n].reshape(h, n, w, n, c)
    mean = boxes.mean(axis=(1, 3), dtype=np.float64)
    if level is not None:
        top = boxes.max(axis=(1, 3))
        mean = np.where(top >= level, top, mean)
    return mean.astype(np.float32)


def move_lights(frames, region: tuple[int, int, int, int], width: int, height: int) -> tuple:
    """``frames`` (:class:`~torchspec.io.Frame`) as seen from the reduced image of ``region`` of a
    ``width x height`` image: near lights' ``position`` in the reduced image's frame (origin at
    the region's centre, unit its width), their ``direction`` from that centre and ``irradiance``
    there (times ``(|p| / |p - c|)^2``); distant lights unchanged."""
    x, y, w, h = region
    if (x, y, w, h) == (0, 0, width, height) or not frames or frames[0].position is None:
        return tuple(frames)
    centre = np.array([(x + w / 2) / width - 0.5, (height / 2 - (y + h / 2)) / width, 0.0])
    moved = []
    for frame in frames:
        position = np.asarray(frame.position, dtype=np.float64)
        offset = position - centre
        distance = float(np.linalg.norm(offset))
        falloff = (float(np.linalg.norm(position)) / distance) ** 2
        irradiance = tuple(v * falloff for v in frame.irradiance) if isinstance(frame.irradiance, tuple) else (
            frame.irradiance * falloff
        )
        moved.append(
            replace(
                frame,
                position=tuple(float(v) for v in offset * (width / w)),
                direction=tuple(float(v) for v in offset / distance),
                irradiance=irradiance,
            )
        )
    return tuple(moved)


@dataclass(frozen=True)
class ScaledCapture(Capture):
    """A capture whose frames are read cropped and box-averaged (:class:`Scale`), as
    :func:`scaled` builds it: :attr:`width` and :attr:`height` are the reduced image's, the frames'
    files are the full capture's.

    Attributes:
        scale: the crop and downsample factor.
        full: ``(width, height)`` of the frame files.
        level: the clipping level kept conservatively (``None``: none).
    """

    scale: Scale = Scale()
    full: tuple[int, int] = (0, 0)
    level: float | None = None

    @functools.cached_property
    def whole(self) -> Capture:
        """The capture at full size, which reads the frame files."""
        width, height = self.full
        return Capture(self.root, width, height, self.channels, self.view, self.light, self.frames, self.extra)

    def record(self) -> dict:
        """:meth:`Scale.record` of the full frames, with ``photographs``: the same relative to the
        photographs an import reduced (:func:`compose`), where the capture's ``source`` records a
        scale."""
        own = self.scale.record(*self.full)
        source = self.extra.get("source")
        outer = source.get("scale") if isinstance(source, dict) else None
        return {**own, "photographs": compose(outer, own) if outer else None}

    def _read_frame(self, k: int, nonfinite: str = "raise", rows: tuple[int, int] | None = None) -> np.ndarray:
        """Frame ``k`` (its ``rows`` of the reduced image), read from the full frame's rows that
        hold them and reduced (:meth:`Capture.read_frames` reads through this)."""
        x, y, _, _ = self.scale.region(*self.full)
        n = self.scale.downsample
        first, stop = rows if rows is not None else (0, self.height)
        image = self.whole._read_frame(k, nonfinite, (y + first * n, y + stop * n))
        return reduce_image(image[:, x : x + self.width * n], n, self.level)


def scaled(capture: Capture, scale: Scale, level: float | None = None) -> Capture:
    """``capture`` read at ``scale`` (:class:`ScaledCapture`; ``capture`` itself when
    :attr:`Scale.identity`), clipping kept at ``level``.

    Raises:
        ScaleError: :meth:`Scale.region` of the capture's size (naming its ``capture.json``).
    """
    if scale.identity:
        return capture
    if isinstance(capture, ScaledCapture):
        raise ScaleError(f"{capture.manifest}: a capture read at one scale cannot be scaled again.")
    width, height = capture.width, capture.height
    region = scale.region(width, height, f"the frames of {capture.manifest}")
    reduced = scale.size(width, height)
    level = None if level is None or not math.isfinite(level) else float(level)
    return ScaledCapture(
        root=capture.root,
        width=reduced[0],
        height=reduced[1],
        channels=capture.channels,
        view=capture.view,
        light=capture.light,
        frames=move_lights(capture.frames, region, width, height),
        extra=capture.extra,
        scale=scale,
        full=(width, height),
        level=level,
    )


def capture_at(capture: Capture, record: dict | None) -> Capture:
    """``capture`` read at the scale ``record`` (``svbrdf.json``'s ``fit.scale``: a crop and
    downsample, :mod:`torchspec.io.scale`), clipped boxes kept at the level the capture records; the
    capture itself for ``None``.

    Raises:
        CaptureError: the record is of a capture of another size.
    """
    if not record:
        return capture
    if list(record["full_size"]) != [capture.width, capture.height]:
        width, height = record["full_size"]
        raise CaptureError(
            f"the maps were fitted from a {width}x{height} capture at --downsample {record['downsample']}, but "
            f"{capture.manifest} is {capture.width}x{capture.height}: give the capture they were fitted from."
        )
    return scaled(capture, Scale.from_record(record), capture.saturation)
