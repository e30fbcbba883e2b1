"""Embedded ICC colour profiles of photographs: decode encoded values to linear values in sRGB
primaries (D65 white), the working space of an imported capture.

A matrix/TRC profile (Adobe RGB, ProPhoto, Display P3, sRGB, a camera's or scanner's RGB
profile; ``GRAY`` profiles with one curve) is read from its tags and applied in floating point:
each channel's tone curve (``curv``: identity, gamma or table; ``para``: the ICC parametric
functions 0-4), then the profile's colorants (``rXYZ``, ``gXYZ``, ``bXYZ``, the D50-adapted
connection space) followed by the inverse of sRGB's D50-adapted colorants, as a colour-management
module does for the relative colorimetric intent between two matrix profiles. Nothing is clipped:
colours outside the sRGB gamut keep negative or above-one components. A profile equal to sRGB
(within :data:`SRGB_TOLERANCE`) is reported as such, so the usual sRGB decoding applies.

Profiles of other kinds (lookup-table ``A2B`` profiles, CMYK) are not read here;
:func:`torchspec.io.images.read_photo` converts such images to sRGB with Pillow's littleCMS.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["SRGB_TOLERANCE", "ColourProfile", "read_icc"]

SRGB_TOLERANCE = 2e-3
"""Largest difference (matrix entries, and curve values on ``[0, 1]``) of a profile taken as sRGB."""

SRGB_D50 = np.array(
    [
        [0.4360747, 0.3850649, 0.1430804],
        [0.2225045, 0.7168786, 0.0606169],
        [0.0139322, 0.0971045, 0.7141733],
    ]
)
"""sRGB's colorants adapted to D50 (Bradford), columns R, G, B: linear sRGB to the ICC connection space."""


@dataclass(frozen=True)
class Curve:
    """One channel's tone curve: ``kind`` ``"table"`` (``values`` sampled on ``[0, 1]``) or
    ``"para"`` (ICC parametric function ``function`` with ``values`` ``g, a, b, c, d, e, f``)."""

    kind: str
    values: tuple[float, ...]
    function: int = 0

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """Encoded ``x`` in ``[0, 1]`` to linear, elementwise (dtype and device kept)."""
        if self.kind == "table":
            table = torch.tensor(self.values, dtype=x.dtype, device=x.device)
            if len(table) == 1:  # a gamma
                return x.clamp(min=0) ** table[0]
            position = x.clamp(0, 1) * (len(table) - 1)
            low = position.floor().clamp(max=len(table) - 2).long()
            t = position - low
            return table[low] * (1 - t) + table[low + 1] * t
        g, a, b, c, d, e, f = (self.values + (0.0,) * 7)[:7]
        if self.function == 0:
            return x.clamp(min=0) ** g
        if self.function in (1, 2):
            offset = 0.0 if self.function == 1 else c
            cut = -b / a
            return torch.where(x >= cut, (a * x + b).clamp(min=0) ** g + offset, torch.full_like(x, offset))
        if self.function in (3, 4):
            high_offset, low_offset = (0.0, 0.0) if self.function == 3 else (e, f)
            return torch.where(x >= d, (a * x + b).clamp(min=0) ** g + high_offset, c * x + low_offset)
        raise ValueError(f"ICC parametric curve function {self.function} is not defined")


SRGB_CURVE = Curve("para", (2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045), function=3)


@dataclass(frozen=True)
class ColourProfile:
    """A matrix/TRC (or grey) ICC profile as read.

    Attributes:
        description: the profile's description tag (or ``"unnamed"``).
        curves: one tone curve per channel (1 for a grey profile, 3 for RGB).
        matrix: ``(3, 3)`` the profile's linear RGB to linear sRGB (identity for grey).
    """

    description: str
    curves: tuple[Curve, ...]
    matrix: np.ndarray

    @property
    def is_srgb(self) -> bool:
        """Whether the profile is sRGB within :data:`SRGB_TOLERANCE` (matrix and curves)."""
        x = torch.linspace(0, 1, 256, dtype=torch.float64)  # CPU on purpose: a check of the profile read from a file
        curves = max(float((curve(x) - SRGB_CURVE(x)).abs().max()) for curve in self.curves)
        return curves < SRGB_TOLERANCE and float(np.abs(self.matrix - np.eye(3)).max()) < SRGB_TOLERANCE

    def decode(self, values: torch.Tensor) -> torch.Tensor:
        """``(..., C)`` encoded values in ``[0, 1]`` (``C`` = the profile's channels) to linear
        sRGB primaries (dtype and device kept)."""
        if len(self.curves) == 1:
            return self.curves[0](values)
        linear = torch.stack([curve(values[..., k]) for k, curve in enumerate(self.curves)], -1)
        matrix = torch.as_tensor(self.matrix, dtype=values.dtype, device=values.device)
        return linear @ matrix.T


def _tags(data: bytes) -> dict[str, bytes]:
    (count,) = struct.unpack_from(">I", data, 128)
    tags = {}
    for k in range(count):
        signature, offset, size = struct.unpack_from(">4sII", data, 132 + 12 * k)
        tags[signature.decode("latin-1")] = data[offset : offset + size]
    return tags


def _s15(data: bytes, offset: int, count: int) -> tuple[float, ...]:
    return tuple(v / 65536 for v in struct.unpack_from(f">{count}i", data, offset))


def _curve(tag: bytes) -> Curve:
    kind = tag[:4]
    if kind == b"curv":
        (count,) = struct.unpack_from(">I", tag, 8)
        if count == 0:
            return Curve("para", (1.0,), function=0)
        if count == 1:
            return Curve("table", (struct.unpack_from(">H", tag, 12)[0] / 256,))
        return Curve("table", tuple(v / 65535 for v in struct.unpack_from(f">{count}H", tag, 12)))
    if kind == b"para":
        (function,) = struct.unpack_from(">H", tag, 8)
        sizes = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}
        if function not in sizes:
            raise ValueError(f"parametric curve function {function}")
        return Curve("para", _s15(tag, 12, sizes[function]), function=function)
    raise ValueError(f"curve of type {kind!r}")


def _description(tags: dict[str, bytes]) -> str:
    tag = tags.get("desc", b"")
    try:
        if tag[:4] == b"desc":  # ICC v2 textDescriptionType: ASCII
            (length,) = struct.unpack_from(">I", tag, 8)
            return tag[12 : 12 + length].split(b"\0")[0].decode("latin-1").strip() or "unnamed"
        if tag[:4] == b"mluc":  # ICC v4: the first record, UTF-16BE
            length, offset = struct.unpack_from(">II", tag, 20)
            return tag[offset : offset + length].decode("utf-16-be").strip("\0 ") or "unnamed"
    except (struct.error, UnicodeDecodeError):
        pass
    return "unnamed"


def read_icc(data: bytes) -> ColourProfile | None:
    """The matrix/TRC or grey profile of ICC ``data``; ``None`` for a profile of another kind
    (lookup tables only, CMYK, Lab) or one that cannot be parsed.

    Example:
        >>> from PIL import ImageCms
        >>> srgb = read_icc(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
        >>> srgb.description, srgb.is_srgb
        ('sRGB built-in', True)
    """
    try:
        space = data[16:20]
        tags = _tags(data)
        description = _description(tags)
        if space == b"GRAY" and "kTRC" in tags:
            return ColourProfile(description, (_curve(tags["kTRC"]),), np.eye(3))
        if space != b"RGB " or not all(key in tags for key in ("rXYZ", "gXYZ", "bXYZ", "rTRC", "gTRC", "bTRC")):
            return None
        colorants = np.array([_s15(tags[key], 8, 3) for key in ("rXYZ", "gXYZ", "bXYZ")]).T  # columns
        curves = tuple(_curve(tags[key]) for key in ("rTRC", "gTRC", "bTRC"))
    except (struct.error, ValueError, IndexError):
        return None
    return ColourProfile(description, curves, np.linalg.solve(SRGB_D50, colorants))
