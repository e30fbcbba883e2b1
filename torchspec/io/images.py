"""Photographs as RTI captures hold them: JPEG, PNG and TIFF (8 or 16 bit, or float), and camera RAW
files, read to ``(H, W, C)`` values in ``[0, 1]`` as encoded, with the tone curve
(:class:`Transfer`) that turns them into linear radiance.

Readers: Pillow for JPEG, BMP and TGA; pypng for PNG (16-bit colour, which Pillow narrows to 8
bits); tifffile for TIFF; rawpy (``pip install "torchspec[raw]"``, imported only for a RAW file)
demosaics RAW files to linear 16-bit sRGB primaries. An integer image's largest code (255 or
65535) is a clipped sample: it reads as exactly 1, which every transfer keeps at 1, so a capture's
clipping level is 1 whatever the transfer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..calibration.response import ResponseCurve
from ..errors import TorchspecError
from .icc import ColourProfile, read_icc

__all__ = ["IMAGE_SUFFIXES", "RAW_SUFFIXES", "ImageError", "Photo", "Transfer", "read_photo", "exposure_value"]

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".tga")
RAW_SUFFIXES = (
    ".dng",
    ".cr2",
    ".cr3",
    ".crw",
    ".nef",
    ".nrw",
    ".arw",
    ".srf",
    ".sr2",
    ".orf",
    ".rw2",
    ".raf",
    ".pef",
    ".srw",
    ".3fr",
    ".iiq",
    ".erf",
    ".kdc",
    ".mrw",
    ".x3f",
    ".raw",
)
_EXIF_IFD = 0x8769
_EXIF_TAGS = {"exposure_time": 0x829A, "f_number": 0x829D, "iso": 0x8827}


class ImageError(TorchspecError):
    """A photograph that cannot be read or used; the message names the file."""


@dataclass(frozen=True)
class Transfer:
    """The tone curve of encoded values ``v`` in ``[0, 1]``: ``srgb`` (IEC 61966-2-1), ``linear``,
    ``gamma`` (``v ** gamma``), or ``response``: a camera response estimated from the photographs
    (:mod:`torchspec.calibration.response`, :attr:`curve`). ``auto`` asks for that estimate (``torchspec
    import`` makes it; :meth:`decode` refuses it).

    Example:
        >>> t = Transfer.parse("gamma:2.2")
        >>> str(t), round(float(t.decode(torch.tensor(0.5))), 4)
        ('gamma:2.2', 0.2176)
        >>> srgb = Transfer.parse("srgb")
        >>> round(float(srgb.encode(srgb.decode(torch.tensor(0.3)))), 6)
        0.3
    """

    name: str
    gamma: float | None = None
    curve: ResponseCurve | None = None

    @classmethod
    def parse(cls, text: str) -> Transfer:
        """``auto``, ``srgb``, ``linear`` or ``gamma:G`` (``G > 0``); :class:`ImageError` otherwise."""
        name, _, value = str(text).strip().lower().partition(":")
        if name in ("srgb", "linear", "auto") and not value:
            return cls(name)
        if name == "gamma":
            try:
                gamma = float(value)
            except ValueError:
                gamma = math.nan
            if math.isfinite(gamma) and gamma > 0:
                return cls("gamma", gamma)
        raise ImageError(
            f"the transfer must be 'auto', 'srgb', 'linear' or 'gamma:G' with G > 0 (e.g. gamma:2.2); got {text!r}."
        )

    def __str__(self) -> str:
        return f"gamma:{self.gamma:g}" if self.name == "gamma" else self.name

    @classmethod
    def of_source(cls, source: dict | None) -> Transfer | None:
        """The transfer an imported capture's frames were decoded with, from its manifest's
        ``source`` block (``transfer``, and ``response`` for an estimated one); ``None`` without
        one (a capture not imported from photographs)."""
        if not source or not source.get("transfer"):
            return None
        if source["transfer"] == "response":
            return cls("response", curve=ResponseCurve.from_json(source.get("response") or {}, "source.response"))
        return cls.parse(source["transfer"])

    def decode(self, values: torch.Tensor) -> torch.Tensor:
        """Encoded values in ``[0, 1]`` to linear, elementwise (a response curve per channel along
        the last dimension; dtype and device kept)."""
        if self.name == "auto":
            raise ImageError("the transfer 'auto' must be estimated from the photographs first (torchspec import).")
        if self.name == "response":
            return self.curve.decode(values)
        if self.name == "linear":
            return values
        if self.name == "gamma":
            return values.clamp(min=0) ** self.gamma
        return torch.where(values <= 0.04045, values / 12.92, ((values.clamp(min=0) + 0.055) / 1.055) ** 2.4)

    def encode(self, values: torch.Tensor) -> torch.Tensor:
        """Linear values to encoded ones, the inverse of :meth:`decode` on ``[0, 1]``."""
        if self.name == "auto":
            raise ImageError("the transfer 'auto' must be estimated from the photographs first (torchspec import).")
        if self.name == "response":
            return self.curve.encode(values)
        if self.name == "linear":
            return values
        if self.name == "gamma":
            return values.clamp(min=0) ** (1 / self.gamma)
        low = values * 12.92
        return torch.where(values <= 0.0031308, low, 1.055 * values.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


@dataclass(frozen=True)
class Photo:
    """A photograph as read.

    Attributes:
        pixels: ``(H, W, C)`` float32 encoded values (integer codes divided by the largest code),
            ``C`` 1 (grey) or 3 (RGB); an alpha channel is dropped.
        encoding: ``"8-bit"``, ``"16-bit"``, ``"float"`` or ``"raw"`` (linear 16-bit from rawpy).
        exif: ``exposure_time`` (s), ``f_number`` and ``iso`` where the file records them.
        notes: what was assumed or converted, naming the file.
        profile: the embedded ICC profile (:mod:`torchspec.io.icc`) when it is a matrix/TRC or
            grey one other than sRGB: it, not a :class:`Transfer`, decodes the pixels to linear
            sRGB primaries (:meth:`decode`). ``None`` without a profile, with an sRGB one, or when
            the image was converted to sRGB on reading (a CMYK or lookup-table profile; noted).
        tagged: whether the file says how it is encoded (an embedded ICC profile, sRGB included,
            or converted to sRGB on reading).
    """

    pixels: np.ndarray
    encoding: str
    exif: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    profile: ColourProfile | None = None
    tagged: bool = False

    def decode(self, pixels: torch.Tensor, transfer: Transfer | None) -> tuple[torch.Tensor, str]:
        """``pixels`` (this photo's ``(H, W, C)`` values, any dtype) to linear: with ``transfer``
        when given, else with the embedded profile, else with :attr:`default_transfer`. Returns
        the linear values and what decoded them (``"icc:DESCRIPTION"`` or the transfer's name)."""
        if transfer is None and self.profile is not None:
            return self.profile.decode(pixels), f"icc:{self.profile.description}"
        transfer = transfer or self.default_transfer
        return transfer.decode(pixels), str(transfer)

    @property
    def clipped(self) -> bool:
        """Whether the largest value is a clipping level (an integer image's largest code)."""
        return self.encoding != "float"

    @property
    def default_transfer(self) -> Transfer:
        """For 8 and 16-bit files sRGB where the file says so (:attr:`tagged`), else ``auto``
        (estimated from the photographs); linear for float and RAW files."""
        if self.encoding not in ("8-bit", "16-bit"):
            return Transfer("linear")
        return Transfer("srgb") if self.tagged else Transfer("auto")


def exposure_value(exif: dict[str, float]) -> float | None:
    """The relative exposure ``t * ISO / N^2`` of EXIF ``exposure_time``, ``iso`` and
    ``f_number`` (a missing ISO or f-number counts as equal between frames); ``None`` without
    an exposure time."""
    if "exposure_time" not in exif:
        return None
    return exif["exposure_time"] * exif.get("iso", 1.0) / exif.get("f_number", 1.0) ** 2


def _integer(array: np.ndarray, path: Path) -> tuple[np.ndarray, str]:
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0, "8-bit"
    if array.dtype == np.uint16:
        return array.astype(np.float32) / 65535.0, "16-bit"
    if array.dtype.kind == "f":
        return array.astype(np.float32), "float"
    raise ImageError(
        f"{path} must hold 8 or 16-bit integer or float samples; got {array.dtype}. Export it as 8 or 16-bit."
    )


def _channels(array: np.ndarray, path: Path, notes: list[str]) -> np.ndarray:
    """``(H, W, C)`` with ``C`` 1 or 3 from grey, grey + alpha, RGB or RGBA samples."""
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 2, 3, 4):
        raise ImageError(f"{path} must be a greyscale or RGB image; got samples of shape {array.shape}.")
    if array.shape[2] in (2, 4):
        notes.append(f"{path}: its alpha channel is not used.")
        array = array[:, :, :3] if array.shape[2] >= 3 else array[:, :, :1]
    return array


def _to_srgb(image, icc: bytes | None, path: Path, notes: list[str]):
    """A CMYK image, or one whose profile is not a matrix/TRC one, converted to 8-bit sRGB by
    littleCMS (Pillow's ImageCms) with its embedded profile; a CMYK image without one is an error."""
    import io

    from PIL import ImageCms

    if not icc:
        raise ImageError(
            f"{path} is a CMYK image without a colour profile; photographs for a fit must be RGB or greyscale. "
            "Convert it to RGB with its colour profile (e.g. `magick in.jpg -colorspace sRGB out.jpg`)."
        )
    try:
        source = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        name = (ImageCms.getProfileDescription(source) or "unnamed").strip()
        converted = ImageCms.profileToProfile(image, source, ImageCms.createProfile("sRGB"), outputMode="RGB")
    except (ImageCms.PyCMSError, OSError, ValueError) as error:
        raise ImageError(f"{path}: its {image.mode} colour profile cannot be applied: {error}.") from error
    notes.append(f"{path}: {image.mode} image converted to 8-bit sRGB with its ICC profile {name!r} (littleCMS).")
    return converted


_SRGB_TAG = b"converted to sRGB"
"""What stands for the profile of an image converted to sRGB on reading."""


def _profile(icc: bytes | None, path: Path, notes: list[str]) -> ColourProfile | None:
    """The embedded profile that decodes the pixels, or ``None`` (none, or sRGB)."""
    if not icc or icc == _SRGB_TAG:
        return None
    profile = read_icc(icc)
    if profile is None:
        raise ImageError(
            f"{path} embeds an ICC profile that is not a matrix/TRC one; convert it to sRGB or a matrix profile "
            "(e.g. Adobe RGB) first."
        )
    if profile.is_srgb:
        return None
    notes.append(f"{path}: decoded to linear sRGB primaries with its embedded ICC profile {profile.description!r}.")
    return profile


def _with_pillow(path: Path, notes: list[str]) -> tuple[np.ndarray, dict[str, float], bytes | None]:
    from PIL import Image

    try:
        with Image.open(path) as image:
            image.load()
            mode = image.mode
            exif = image.getexif().get_ifd(_EXIF_IFD)
            icc = image.info.get("icc_profile")
            if mode == "CMYK" or (icc and mode in ("RGB", "L") and read_icc(icc) is None):
                image, mode, icc = _to_srgb(image, icc, path, notes), "RGB", _SRGB_TAG
            if mode in ("P", "PA", "1", "YCbCr", "LAB", "HSV"):
                notes.append(f"{path}: {mode} image converted to RGB.")
                image = image.convert("RGBA" if mode == "PA" else "RGB")
            array = np.asarray(image)
            if mode.startswith("I;16"):
                array = array.astype(np.uint16)
    except ImageError:
        raise
    except Exception as error:  # Pillow's errors for a truncated or foreign file are of many kinds
        raise ImageError(f"{path} cannot be read as an image: {error}. Re-export or re-copy the file.") from error
    values = {name: float(exif[tag]) for name, tag in _EXIF_TAGS.items() if tag in exif and _positive(exif[tag])}
    return array, values, icc


def _positive(value) -> bool:
    try:
        number = float(value[0] if isinstance(value, tuple) else value)
    except (TypeError, ValueError, ZeroDivisionError):
        return False
    return math.isfinite(number) and number > 0


def _with_pypng(path: Path) -> np.ndarray:
    import png

    try:
        width, height, rows, info = png.Reader(filename=str(path)).asDirect()
        planes = info["planes"]
        dtype = np.uint16 if info["bitdepth"] > 8 else np.uint8
        array = np.vstack([np.asarray(row, dtype=dtype) for row in rows]).reshape(height, width, planes)
    except Exception as error:  # pypng's FormatError, ChunkError, and zlib's errors of a truncated file
        raise ImageError(f"{path} cannot be read as a PNG: {error}. Re-export or re-copy the file.") from error
    if info["bitdepth"] not in (8, 16):  # 1, 2, 4-bit grey: rescale to 8 bits
        array = (array.astype(np.float64) * 255 / (2 ** info["bitdepth"] - 1)).round().astype(np.uint8)
    return array


def _png_profile(path: Path) -> bytes | None:
    """The PNG's iCCP profile (pypng does not read it; Pillow reads the chunks only)."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            return image.info.get("icc_profile")
    except Exception:  # the pixels are read by pypng, which names the file's fault
        return None


def _with_tifffile(path: Path) -> tuple[np.ndarray, dict[str, float], bytes | None]:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            photometric = page.photometric
            array = page.asarray()
            axes = page.axes
            tags = page.tags.get("ExifTag")
            exif = dict(tags.value) if tags is not None else {}
            icc = page.tags.get(34675)  # InterColorProfile
            icc = bytes(icc.value) if icc is not None else None
    except Exception as error:  # tifffile's TiffFileError, and the codecs' errors of a truncated file
        raise ImageError(f"{path} cannot be read as a TIFF: {error}. Re-export or re-copy the file.") from error
    if photometric == tifffile.PHOTOMETRIC.SEPARATED:
        raise ImageError(f"{path} is a CMYK TIFF; photographs for a fit must be RGB or greyscale. Export it as RGB.")
    if axes.startswith("S") and array.ndim == 3:  # planar: samples first
        array = np.moveaxis(array, 0, -1)
    values = {}
    names = {"exposure_time": "ExposureTime", "f_number": "FNumber", "iso": "ISOSpeedRatings"}
    for name, key in names.items():
        value = exif.get(key)
        if isinstance(value, tuple) and len(value) == 2 and value[1]:
            value = value[0] / value[1]
        if value is not None and _positive(value):
            values[name] = float(value)
    return array, values, icc


def _with_rawpy(path: Path) -> np.ndarray:
    try:
        import rawpy
    except ImportError:
        raise ImageError(
            f"{path} is a camera RAW file; reading it needs rawpy, an optional dependency: "
            'pip install "torchspec[raw]" (or convert the RAW files to 16-bit TIFF).'
        ) from None
    try:
        with rawpy.imread(str(path)) as raw:
            return raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                use_camera_wb=True,
                user_flip=0,
                output_color=rawpy.ColorSpace.sRGB,
            )
    except Exception as error:  # libraw's errors of a truncated or unknown file
        raise ImageError(f"{path} cannot be read as a camera RAW file: {error}.") from error


def read_photo(path: str | Path) -> Photo:
    """Read a photograph (see the module's docstring for the formats).

    Raises:
        ImageError: the file is missing, truncated or of an unknown kind, a CMYK image, a RAW file
            without rawpy installed, or holds samples other than 8/16-bit integer or float.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise ImageError(f"{path} must be an image file; got no such file.")
    notes: list[str] = []
    exif: dict[str, float] = {}
    if suffix in RAW_SUFFIXES:
        array, encoding = _with_rawpy(path).astype(np.float32) / 65535.0, "raw"
        return Photo(pixels=_channels(array, path, notes), encoding=encoding, notes=tuple(notes))
    if suffix == ".png":
        array, icc = _with_pypng(path), _png_profile(path)
    elif suffix in (".tif", ".tiff"):
        array, exif, icc = _with_tifffile(path)
    elif suffix in IMAGE_SUFFIXES:
        array, exif, icc = _with_pillow(path, notes)
    else:
        raise ImageError(
            f"{path} must be an image of a known kind ({', '.join(IMAGE_SUFFIXES)}, or camera RAW); got "
            f"{suffix or 'no suffix'}."
        )
    pixels, encoding = _integer(array, path)
    pixels = _channels(pixels, path, notes)
    profile = _profile(icc, path, notes) if encoding != "float" else None
    if profile is not None and len(profile.curves) != pixels.shape[2]:
        raise ImageError(
            f"{path} embeds a {len(profile.curves)}-channel ICC profile for a {pixels.shape[2]}-channel image; "
            "re-export it with a matching profile."
        )
    tagged = bool(icc) and encoding != "float"
    return Photo(pixels=pixels, encoding=encoding, exif=exif, notes=tuple(notes), profile=profile, tagged=tagged)
