"""OpenEXR images as ``(H, W, C)`` float32 arrays, with errors that name the file.

OpenEXR's Python binding (``import OpenEXR``, version 3) has traps this module hides:

- it does not raise for a truncated file: the file opens with zero parts (and prints a warning
  on stdout), so the part count is checked here;
- its writer ignores numpy strides, so a transposed or sliced array is written scrambled:
  every channel is passed through :func:`numpy.ascontiguousarray`;
- it cannot write float64: images are written as 32-bit float channels;
- its reports go to ``sys.stdout`` and the C library's to file descriptor 2: both are redirected
  around each call to keep them for the error, and the redirection is process-wide, so it is held
  by one thread at a time (:data:`_REDIRECT`): reading from several threads at once is safe.

Corrupted bytes inside a compressed block may still decode without an error (EXR has no
checksum): readers further up check what they can (finite values, sizes).
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import OpenEXR

from ..atomic import atomic_path
from ..errors import TorchspecError

__all__ = ["ExrError", "exr_size", "read_exr", "write_exr"]

_GROUPS = (("R", "G", "B"), ("X", "Y", "Z"))
_REDIRECT = threading.RLock()
"""Held while ``sys.stdout`` or descriptor 2 is redirected: another thread's redirection in
between would restore the wrong target (descriptor 2 left on a closed file, ``sys.stdout`` on a
buffer), and two threads' library lines would mix."""


class ExrError(TorchspecError):
    """An EXR file that cannot be read or written as asked; the message names the file."""


def _channel_order(names: Sequence[str]) -> list[str]:
    """The order :func:`read_exr` gives a file's channels by default.

    ``R, G, B`` in that order when present, then ``X, Y, Z`` likewise, then the others sorted.

    Example:
        >>> _channel_order(["B", "A", "G", "R"])
        ['R', 'G', 'B', 'A']
    """
    grouped = [name for group in _GROUPS for name in group if name in names]
    return grouped + sorted(set(names) - set(grouped))


def _open(path: Path, header_only: bool = False) -> OpenEXR.File:
    """Open ``path`` with every channel separate (or its header only), raising :class:`ExrError`
    for any failure."""
    try:
        exists = path.is_file()
    except OSError as error:  # a name too long, a folder without permission
        raise ExrError(f"EXR file {path} must be a path the system can look up; got {error}.") from error
    if not exists:
        raise ExrError(f"EXR file {path} must exist; got no such file. Check the path.")
    kind = _not_exr(path)
    if kind:
        raise ExrError(
            f"{path} is {kind}, not an EXR: torchspec reads linear (HDR) OpenEXR frames. Convert photographs "
            "into a capture with: torchspec import SOURCE -o CAPTURE (docs/capture-format.md, 'Your own photographs')."
        )
    # The binding reports a failed pixel read (e.g. a truncated file) by printing on stdout and
    # returning zero parts, and the library prints its own lines (EXR_ERR_...) on stderr: keep
    # them for the error instead of showing the user a library's raw lines.
    printed = io.StringIO()
    try:
        with _REDIRECT, contextlib.redirect_stdout(printed), _library_stderr() as library:
            file = OpenEXR.File(str(path), separate_channels=True, header_only=header_only)
    except Exception as error:
        raise ExrError(
            f"{path} cannot be read as an OpenEXR image: it is truncated, damaged or not an EXR "
            f"({_detail(path, library.text or str(error))}). Write or copy the file again."
        ) from error
    notes = printed.getvalue().strip()
    if not file.parts:
        raise ExrError(
            f"{path} is truncated or corrupt: the OpenEXR library could not read its pixels "
            f"({_detail(path, library.text or notes)}). Write or copy the file again."
        )
    if notes:  # not ours to swallow when the read went well
        sys.stdout.write(printed.getvalue())
    if library.text:
        sys.stderr.write(library.text)
    if len(file.parts) > 1:
        raise ExrError(f"{path} must be a single-part EXR; got {len(file.parts)} parts. Save one part per file.")
    return file


_MAGIC = (
    (b"\xff\xd8\xff", "a JPEG"),
    (b"\x89PNG", "a PNG"),
    (b"II*\x00", "a TIFF (or a camera raw file)"),
    (b"MM\x00*", "a TIFF (or a camera raw file)"),
    (b"GIF8", "a GIF"),
    (b"#?RADIANCE", "a Radiance HDR"),
    (b"#?RGBE", "a Radiance HDR"),
)
_EXR_MAGIC = b"\x76\x2f\x31\x01"


def _not_exr(path: Path) -> str | None:
    """What ``path`` is when its first bytes say it is not an EXR (``"a JPEG"``, ...), else ``None``
    (an EXR, or a file too short or unknown: the library's error then says what is wrong)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(16)
    except OSError:
        return None
    if head.startswith(_EXR_MAGIC) or len(head) < 4:
        return None
    for magic, kind in _MAGIC:
        if head.startswith(magic):
            return kind
    return "a text file" if head.isascii() else None


class _Captured:
    text = ""


@contextlib.contextmanager
def _library_stderr():
    """Capture what C code writes on file descriptor 2 (OpenEXR's ``EXR_ERR_...`` lines) while the
    block runs; ``.text`` holds it after. Where descriptor 2 cannot be redirected (no such
    descriptor), nothing is captured. Holds :data:`_REDIRECT` throughout (other threads' writes
    on descriptor 2 meanwhile are captured too)."""
    captured = _Captured()
    with _REDIRECT:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError):
            yield captured
            return
        with tempfile.TemporaryFile() as sink:
            os.dup2(sink.fileno(), 2)
            try:
                yield captured
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                sink.seek(0)
                captured.text = sink.read().decode("utf-8", "replace")


def _detail(path: Path, text: str) -> str:
    """The library's first line about ``path``, without the path and the error code: a detail for
    the user's sentence, not the sentence."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if not lines:
        return "no detail given"
    line = lines[0].replace(f"{path}: ", "").replace(str(path), "the file")
    line = re.sub(r"^\(EXR_ERR_[A-Z_]+\)\s*", "", line)
    line = re.sub(r"^Warning:\s*", "", line)
    return f"OpenEXR says: {line}"


def read_exr(
    path: str | Path, channels: Sequence[str] | None = None, *, rows: tuple[int, int] | None = None
) -> np.ndarray:
    """Read channels of an EXR file.

    Args:
        path: the ``.exr`` file.
        channels: the channel names to read, in this order; a single string is one name. By
            default every channel of the file: ``R, G, B`` in that order when present, then
            ``X, Y, Z`` likewise, then the others sorted.
        rows: ``(start, stop)``: only rows ``start`` to ``stop - 1`` (``0 <= start < stop <= H``).
            Only the file's blocks that hold them are read and decoded (a block is 1 to 256 rows,
            by compression: 16 for ZIP), so a band of a large image costs about its share of the
            file; the rest of the file is not checked.

    Returns:
        ``(H, W, C)`` (``H = stop - start`` with ``rows``) C-contiguous float32 array, row 0 at
        the top of the image (half, float and uint channels are converted).

    Raises:
        ExrError: the file is missing, unreadable, truncated, multi-part, lacks a requested
            channel (the message lists those it has), holds channels that are not 2D images of
            one size, or ``rows`` are not rows of the image.

    Example:
        >>> import shutil, tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> write_exr(folder / "0000.exr", np.ones((48, 32, 3)), ["B", "G", "R"])
        >>> read_exr(folder / "0000.exr").shape  # R, G, B, whatever the order written
        (48, 32, 3)
        >>> read_exr(folder / "0000.exr", ["G"], rows=(8, 24)).shape
        (16, 32, 1)
        >>> shutil.rmtree(folder)
    """
    if rows is None:
        return _read(Path(path), channels)[1]
    return _read_rows(Path(path), channels, rows)[0]


def _read(path: Path, channels: Sequence[str] | None) -> tuple[list[str], np.ndarray]:
    """:func:`read_exr` that also returns the names of the channels read, in order."""
    file = _open(path)
    try:
        found = {name: channel.pixels for name, channel in file.channels().items()}
    except Exception as error:
        raise ExrError(f"{path} must be a readable OpenEXR file; got {type(error).__name__}: {error}.") from error
    if not found:
        raise ExrError(f"{path} must have at least one channel; got none. Write it again.")
    if isinstance(channels, str):
        channels = [channels]
    names = _channel_order(list(found)) if channels is None else list(channels)
    if not names:
        raise ExrError(f"channels to read from {path} must name at least one channel; got {channels!r}.")
    missing = [name for name in names if name not in found]
    if missing:
        raise ExrError(
            f"{path} must have channel(s) {missing}; it has {_channel_order(list(found))}. "
            "Ask for channels the file has, or rewrite it with these channel names."
        )
    shapes = {name: getattr(found[name], "shape", None) for name in names}
    for name, shape in shapes.items():
        if shape is None or len(shape) != 2:
            raise ExrError(f"{path}: channel {name!r} must be a 2D image; got pixel data of shape {shape}.")
    if len(set(shapes.values())) > 1:
        raise ExrError(
            f"{path}: channels must all have one size (no subsampling); got {shapes}. Resample the channels."
        )
    image = np.stack([np.asarray(found[name], dtype=np.float32) for name in names], axis=-1)
    return names, np.ascontiguousarray(image)


def _read_rows(path: Path, channels: Sequence[str] | None, rows: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int]]:
    """:func:`read_exr` of a band of rows: the band ``(stop - start, W, C)`` and the image's
    ``(H, W)``. Reads the header, then the band through the binding's scanline interface
    (``InputFile``; deprecated in OpenEXR 3.3, so a binding without it reads the whole image)."""
    return _read_band(path, channels, rows)[1:]


def exr_size(path: str | Path) -> tuple[int, int]:
    """``(H, W)`` of an EXR image, from its header (its pixels are not read).

    Raises:
        ExrError: the file is missing or not a readable EXR.
    """
    return _size(_open(Path(path), header_only=True).header())


def _size(header) -> tuple[int, int]:
    """``(H, W)`` of a header's data window."""
    low, high = header["dataWindow"]
    return int(high[1] - low[1] + 1), int(high[0] - low[0] + 1)


def _read_band(
    path: Path, channels: Sequence[str] | None, rows: tuple[int, int]
) -> tuple[list[str], np.ndarray, tuple[int, int]]:
    """:func:`_read_rows` that also returns the names of the channels read, in order, first."""
    header = _open(path, header_only=True).header()
    low = header["dataWindow"][0]
    size = _size(header)
    found = {channel.name: channel for channel in header["channels"]}
    if isinstance(channels, str):
        channels = [channels]
    names = _channel_order(list(found)) if channels is None else list(channels)
    missing = [name for name in names if name not in found]
    if missing or not names:
        raise ExrError(
            f"{path} must have channel(s) {missing or names}; it has {_channel_order(list(found))}. "
            "Ask for channels the file has, or rewrite it with these channel names."
        )
    sampled = {name: (found[name].xSampling, found[name].ySampling) for name in names}
    if any(sampling != (1, 1) for sampling in sampled.values()):
        raise ExrError(f"{path}: channels must all have one size (no subsampling); got {sampled}. Resample them.")
    start, stop = (int(row) for row in rows)
    if not 0 <= start < stop <= size[0]:
        raise ExrError(
            f"rows of {path} must satisfy 0 <= start < stop <= {size[0]} (the image is {size[0]}x{size[1]}); "
            f"got {start}:{stop}."
        )
    if not hasattr(OpenEXR, "InputFile"):
        return names, np.ascontiguousarray(_read(path, names)[1][start:stop]), size
    import Imath  # shipped with the binding, beside the InputFile it describes

    try:
        legacy = OpenEXR.InputFile(str(path))
        try:
            first = int(low[1]) + start  # the binding's scanlines count from the data window's top
            data = legacy.channels(names, Imath.PixelType(Imath.PixelType.FLOAT), first, first + stop - start - 1)
        finally:
            legacy.close()
    except Exception as error:
        raise ExrError(
            f"{path} must be a readable OpenEXR file; rows {start}:{stop} could not be read ({type(error).__name__}: "
            f"{error}): the file is truncated or corrupt. Write it again."
        ) from error
    band = np.empty((stop - start, size[1], len(names)), dtype=np.float32)
    for c, buffer in enumerate(data):
        band[:, :, c] = np.frombuffer(buffer, dtype=np.float32).reshape(stop - start, size[1])
    return names, band, size


def _to_numpy(image) -> np.ndarray:
    if hasattr(image, "detach"):  # a torch tensor, without importing torch here
        image = image.detach().cpu().numpy()
    return np.asarray(image)


def write_exr(path: str | Path, image, channels: Sequence[str]) -> None:
    """Write an image as an EXR of 32-bit float channels with ZIP compression, atomically.

    The file is written under a temporary name (``.<name>.*.part.exr``) in the same folder and
    renamed into place, so an interruption never leaves a half-written file under ``path``.
    Missing parent folders are created.

    Args:
        path: the ``.exr`` file to write (replaced if it exists).
        image: ``(H, W, C)`` numpy array or torch tensor (any strides, dtype, device), or
            ``(H, W)`` with one channel name.
        channels: the ``C`` channel names, in the order of the last axis; a single string is one
            name.

    Raises:
        ExrError: the image is not ``(H, W, C)`` with ``C = len(channels)`` and ``H, W > 0``, a
            channel name is repeated or empty, or OpenEXR fails to write.

    Example:
        >>> import shutil, tempfile, torch
        >>> folder = Path(tempfile.mkdtemp())
        >>> write_exr(folder / "normal.exr", torch.zeros(48, 64, 3), ["X", "Y", "Z"])
        >>> sorted(path.name for path in folder.iterdir())  # no temporary file is left
        ['normal.exr']
        >>> shutil.rmtree(folder)
    """
    path = Path(path)
    if isinstance(channels, str):
        channels = [channels]
    channels = list(channels)
    array = _to_numpy(image)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[0] == 0 or array.shape[1] == 0:
        raise ExrError(f"image for {path} must have shape (H, W, C) or (H, W) with H, W > 0; got {array.shape}.")
    if len(channels) != array.shape[2]:
        raise ExrError(
            f"channels for {path} must name one channel per image channel ({array.shape[2]}); "
            f"got {len(channels)}: {channels}. Pass {array.shape[2]} names, e.g. ['R', 'G', 'B'] or ['Y']."
        )
    if len(set(channels)) != len(channels) or not all(isinstance(name, str) and name for name in channels):
        raise ExrError(f"channels for {path} must be distinct non-empty strings; got {channels}.")
    if not (np.issubdtype(array.dtype, np.number) or array.dtype == np.bool_) or np.iscomplexobj(array):
        raise ExrError(f"image for {path} must be real numbers; got dtype {array.dtype}.")
    # The binding reads the buffer as if it were C-contiguous: strides are not honoured.
    pixels = {
        name: OpenEXR.Channel(np.ascontiguousarray(array[:, :, c], dtype=np.float32)) for c, name in enumerate(channels)
    }
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, pixels).write(str(tmp))
        except Exception as error:
            raise ExrError(f"{path} could not be written; got {type(error).__name__}: {error}.") from error
