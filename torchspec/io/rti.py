"""``torchspec import``: an RTI capture (photographs and a light file) to a capture of
``capture-format.md``.

The light file (:mod:`torchspec.io.lp`) is an ``.lp`` (SOURCE, or the one ``.lp`` of the folder
SOURCE), or a ``lights.txt`` of directions only. Each light's image is found by name (as written,
then its file name in the light file's folder, in any case, then the same name with another image
suffix); when no name matches and the folder holds as many photographs as lights, by order; a
file of directions only is matched by order (names in natural order: ``2`` before ``10``; files
whose name holds ``mask`` or ``normal`` are not photographs). Otherwise each missing image is named;
but an ``.lp``'s lines beyond its count that name missing images, where the counted lines' images
are all found, are ignored with a note (:func:`read_lights`).

Every photograph (:mod:`torchspec.io.images`) is decoded to linear values with one recorded transfer
(or, without ``--transfer``, with its embedded ICC profile when that is not sRGB: to linear sRGB
primaries, colours outside sRGB's gamut clipped at 0 with a note; the manifest's
``source.icc_profiles`` names each frame's profile). 8 and 16-bit photographs that do not say
their encoding (no ICC profile), or ``--transfer auto``, are decoded with the camera's response
estimated from the stack itself (:func:`torchspec.calibration.response.estimate_response`, on
:data:`RESPONSE_PIXELS` pixels under the light file's directions), recorded with its uncertainty
as ``source.response``. Each frame is written as a float32 EXR: point lights (the
light file's directions), irradiance 1, exposure 1, or the EXIF exposure ``t ISO / N^2`` relative to
the median frame's where it differs between frames. A clipped sample (an integer image's largest
code) reads as exactly 1, the clipping level the fit detects (``FitConfig.masks.saturation``); the
manifest's ``source`` records the light file, the images, the transfer, that level and what was
assumed.

The capture is written to a temporary folder beside OUTPUT and renamed to it once complete: a
failure leaves nothing behind, and an OUTPUT that holds files is replaced only with ``overwrite``.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass, replace
from pathlib import Path, PureWindowsPath

import numpy as np
import torch
from tqdm.auto import tqdm

from .._version import __version__
from ..calibration.response import ResponseError, ResponseEstimate, estimate_response, response_samples
from ..errors import TorchspecError
from ..outputs import check_output
from .capture import Capture, Frame, LightSpec, read_capture, write_capture
from .images import IMAGE_SUFFIXES, RAW_SUFFIXES, ImageError, Transfer, exposure_value, read_photo
from .lp import LightFile, keep_counted, read_light_file
from .relight import RELIGHT_SUFFIXES, read_relight
from .scale import Scale, move_lights

__all__ = ["RTIImportError", "Imported", "find_light_file", "import_rti", "match_images", "photographs", "read_lights"]

CLIP = 1.0
"""The linear value of a clipped sample, whatever the transfer."""
_NOT_FRAMES = ("mask", "normal")
GLARE = 25.0
"""Degrees about each pixel's mirror direction whose samples one candidate curve leaves out."""
JUDGE_MARGIN = 1.0
"""dB by which another candidate curve must predict left-out photographs better than the curve
estimated from every sample to replace it: the fit's score of a small crop moves by a fraction of a
dB with what the Ward lobes make of the highlights (on a simulated painting encoded as sRGB it
preferred a power curve, 0.05 off in linear units, to sRGB itself)."""
RESPONSE_PIXELS = 2048
"""Pixels the camera's response is estimated from (``--transfer auto``)."""
_MEMORY = 1 << 30
"""A frame stack larger than this (bytes) is held in a temporary file instead of memory."""


class RTIImportError(TorchspecError):
    """An RTI capture that cannot be imported; the message names the file (and line)."""


@dataclass(frozen=True)
class Imported:
    """The result of :func:`import_rti`.

    Attributes:
        capture: the capture as written (``root`` the output folder).
        light_file: the light file read.
        images: each frame's photograph, in frame order.
        matched: ``"name"`` or ``"order"``.
        transfer: the tone curve the photographs were decoded with (``response``: estimated).
        response: the estimate behind a ``response`` transfer, else ``None``.
        saturated: clipped pixels (any channel at the clipping level; with a downsample, boxes
            holding a clipped sample), per frame.
        notes: what was assumed (also warned about, and kept in the manifest's ``source``).
        positions: ``(K, 3)`` float64 light positions in image widths (origin at the image's
            centre, x right, y up, z towards the camera) when the light file gives them (a Relight
            spherical or lights3d dome), in frame order; ``None`` otherwise. Each frame's
            ``position`` in the manifest (``source.positions``: as the light file gives them,
            before a crop moves them to the cropped image's frame).
    """

    capture: Capture
    light_file: LightFile
    images: tuple[Path, ...]
    matched: str
    transfer: Transfer
    saturated: tuple[int, ...]
    notes: tuple[str, ...]
    positions: torch.Tensor | None = None
    response: ResponseEstimate | None = None


def find_light_file(source: str | Path) -> Path:
    """The light file of SOURCE: the file itself, or the folder's one ``.lp`` (else its one
    Relight ``.relight`` project, else its one ``.dome``, else its ``lights.txt``).
    :class:`RTIImportError` when there is none, or several of the first kind found."""
    source = Path(source)
    if source.is_file():
        return source
    if not source.is_dir():
        raise RTIImportError(f"{source} must be an .lp light file or a folder holding one; got no such file or folder.")
    for suffix in (".lp", *RELIGHT_SUFFIXES):
        found = sorted(path for path in source.iterdir() if path.suffix.lower() == suffix and path.is_file())
        if len(found) > 1:
            raise RTIImportError(
                f"{source} must hold one {suffix} light file; got {len(found)} ({', '.join(p.name for p in found)}). "
                "Pass the one to use as SOURCE."
            )
        if found:
            return found[0]
    if (source / "lights.txt").is_file():
        return source / "lights.txt"
    raise RTIImportError(
        f"{source} must hold an .lp light file (or a Relight .relight or .dome file, or a lights.txt of "
        "directions); got none. Pass the light file as SOURCE."
    )


def read_lights(path: Path) -> LightFile:
    """The light file ``path``: a Relight ``.relight`` or ``.dome`` (:mod:`torchspec.io.relight`),
    else an ``.lp`` or a file of directions (:mod:`torchspec.io.lp`).

    An ``.lp`` whose count (its first line) is below its lines is cut to the counted lights
    (:func:`~torchspec.io.lp.keep_counted`, with a note naming the lines ignored) where the count and
    the folder agree: every counted line's image is found and no image of a line beyond the count is
    (RTI tools read only the counted lines). Otherwise every line is kept, and an image missing among
    them is an error of :func:`match_images`."""
    if path.suffix.lower() in RELIGHT_SUFFIXES:
        return read_relight(path)
    lights = read_light_file(path)
    declared, folder = lights.declared, lights.image_folder
    if not (lights.named and declared is not None and 0 < declared < len(lights.entries)):
        return lights
    find = _finder(folder)
    found = [find(entry.name) is not None for entry in lights.entries]
    if not all(found[:declared]) or any(found[declared:]):
        return lights
    extra = lights.entries[declared:]
    names = ", ".join(repr(entry.name) for entry in extra[:5]) + (" ..." if len(extra) > 5 else "")
    return keep_counted(lights, f"they name images that {folder} does not hold ({names})")


def _natural(name: str) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def photographs(folder: Path) -> list[Path]:
    """The folder's image files that may be frames, in natural order (``2`` before ``10``); files
    whose name holds ``mask`` or ``normal`` are not frames."""
    suffixes = IMAGE_SUFFIXES + RAW_SUFFIXES
    files = [
        path
        for path in folder.iterdir()
        if path.suffix.lower() in suffixes
        and path.is_file()
        and not path.name.startswith(".")
        and not any(word in path.stem.lower() for word in _NOT_FRAMES)
    ]
    return sorted(files, key=lambda path: _natural(path.name))


def _finder(folder: Path):
    """A function ``name -> Path | None``: the image a light file's ``name`` names in ``folder``
    (as written, then its file name in any case, then the same stem with another image suffix)."""
    listing = {path.name.lower(): path for path in folder.iterdir() if path.is_file()}
    stems: dict[str, list[Path]] = {}
    for path in photographs(folder):
        stems.setdefault(path.stem.lower(), []).append(path)
    return lambda name: _by_name(folder, name, listing, stems)


def _by_name(folder: Path, name: str, listing: dict[str, Path], stems: dict[str, list[Path]]) -> Path | None:
    written = name.replace("\\", "/")
    if not PureWindowsPath(name).is_absolute() and not written.startswith("/") and (folder / written).is_file():
        return folder / written
    base = PureWindowsPath(name).name
    if base.lower() in listing:
        return listing[base.lower()]
    same = stems.get(Path(base).stem.lower(), [])
    return same[0] if len(same) == 1 else None


def match_images(lights: LightFile) -> tuple[list[Path], str, list[str]]:
    """Each light's photograph: ``(paths, "name" or "order", notes)``; see the module's docstring.

    Raises:
        RTIImportError: an image cannot be found; the message names each missing one and its line.
    """
    folder = lights.image_folder
    found_photos = photographs(folder)
    if lights.named:
        find = _finder(folder)
        found = [find(entry.name) for entry in lights.entries]
        if all(path is not None for path in found):
            return found, "name", []
        if not any(found) and len(found_photos) == len(lights.entries):
            note = (
                f"{lights.path}: no image is named as in the light file; the {len(found_photos)} photographs of "
                f"{folder} are matched by order ({found_photos[0].name} to {lights.entries[0].place}, ...)."
            )
            return found_photos, "order", [note]
        missing = [entry for entry, path in zip(lights.entries, found, strict=True) if path is None]
        shown = "; ".join(f"{entry.name!r} ({entry.place})" for entry in missing)
        raise RTIImportError(
            f"{lights.path}: {len(missing)} of {len(lights.entries)} images are missing from {folder}: {shown}. "
            "Restore them, or fix their names in the light file."
        )
    if len(found_photos) != len(lights.entries):
        raise RTIImportError(
            f"{lights.path} lists {len(lights.entries)} directions without image names, so the images are matched by "
            f"order; but {folder} holds {len(found_photos)} photographs. Keep exactly one photograph per light."
        )
    note = (
        f"{lights.path} names no images: its {len(found_photos)} directions are matched by order to the photographs "
        f"of {folder} in natural order ({', '.join(path.name for path in found_photos[:2])} ...)."
    )
    return found_photos, "order", [note]


def _exposures(exifs: list[dict[str, float]], images: list[Path], notes: list[str]) -> list[float]:
    """Per-frame exposure relative to the median frame's where EXIF says it differs; else 1."""
    values = [exposure_value(exif) for exif in exifs]
    known = [value for value in values if value is not None]
    if not known or max(known) <= min(known) * (1 + 1e-6):
        return [1.0] * len(images)
    if len(known) < len(values):
        absent = [images[k].name for k, value in enumerate(values) if value is None]
        notes.append(
            f"EXIF exposures differ between frames, but {len(absent)} frame(s) record none ({', '.join(absent[:5])}"
            f"{' ...' if len(absent) > 5 else ''}): every frame is given exposure 1."
        )
        return [1.0] * len(images)
    median = float(np.median(known))
    notes.append(
        f"EXIF exposures (t ISO / N^2) differ between frames, {min(known):.4g} to {max(known):.4g}: recorded as "
        "each frame's exposure relative to the median frame's."
    )
    return [value / median for value in values]


def _check_output(output: Path, overwrite: bool) -> None:
    if output.exists() and not output.is_dir():
        raise RTIImportError(f"{output} must be a folder to write the capture in; got a file.")
    # A file where a parent folder must be, or a folder that takes no new file: named (the content
    # rule is import's own: an output that holds files is replaced whole, only with overwrite).
    check_output(output, overwrite=True)
    if output.is_dir() and any(output.iterdir()) and not overwrite:
        raise RTIImportError(
            f"{output} already holds files; refusing to replace them. Choose an empty or new folder, or pass "
            "--overwrite to replace it."
        )


def _frame_name(k: int, image: Path) -> str:
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", image.stem)
    return f"frames/{k:04d}_{stem}.exr"


def _read_stack(images, transfer, dtype, scratch: Path, progress: bool, directions: torch.Tensor, scale: Scale):
    """Decode every photograph into a ``(K, C, H, W)`` float32 array, cropped and downsampled
    (``scale``, :mod:`torchspec.io.scale`) once decoded to linear: ``(stack, transfer, encoding,
    exifs, notes, saturated, profiles, response, size)``; ``profiles[k]`` names the ICC profile
    that decoded frame ``k`` (``transfer`` None: an embedded non-sRGB profile decodes its frame);
    ``response`` the estimate of an ``auto`` transfer (:func:`_decode_auto`, on the crop's codes at
    full size); ``saturated[k]`` counts frame ``k``'s clipped pixels (boxes holding a clipped
    sample); ``size`` is the photographs' ``(width, height)``."""
    stack, size, first, exifs, notes, saturated = None, None, None, [], [], []
    given, profiles, region, n = transfer, [None] * len(images), None, scale.downsample
    for k, image in enumerate(tqdm(images, unit="image", desc="import", disable=not progress)):
        photo = read_photo(image)
        notes += photo.notes
        pixels = torch.from_numpy(photo.pixels)
        if stack is None:
            first = photo
            transfer = transfer or (photo.default_transfer if photo.profile is None else None)
            if transfer is not None and transfer.name == "auto" and photo.encoding not in ("8-bit", "16-bit"):
                raise ImageError(
                    f"{image} holds {photo.encoding} samples, which are linear: --transfer auto is for 8 or 16-bit "
                    "photographs. Leave --transfer out (or pass linear)."
                )
            size = photo.pixels.shape
            region = scale.region(size[1], size[0], f"the photographs ({image.name})")
            codes = transfer is not None and transfer.name == "auto"  # kept at full size until decoded
            m = 1 if codes else n
            stack = _stack(scratch, (len(images), size[2], region[3] // m, region[2] // m))
        _check_alike(image, images[0], photo, first, size)
        if photo.pixels.shape[2] != size[2]:  # grey among colour frames: the grey replicated
            notes.append(f"{image}: a greyscale photograph among colour ones; its grey is used for R, G and B.")
            pixels = pixels.expand(-1, -1, 3)
        pixels = pixels[region[1] : region[1] + region[3], region[0] : region[0] + region[2]]
        # CPU on purpose: with the photograph's pixels, decoded from its file into a numpy stack
        clipped = (pixels >= CLIP).any(-1) if first.clipped else torch.zeros(pixels.shape[:2], dtype=bool)
        saturated.append(int(clipped.reshape(region[3] // n, n, region[2] // n, n).any(3).any(1).sum()))
        clipped = clipped[..., None]
        if codes:  # codes kept: decoded once the curve is known
            if photo.profile is not None:
                notes.append(f"{image}: its ICC profile is not used (--transfer auto).")
            stack[k] = pixels.permute(2, 0, 1).numpy()
            exifs.append(photo.exif)
            continue
        # an untagged frame in a stack whose first frame says its encoding: sRGB, as before the estimate
        untagged = photo.profile is None and photo.default_transfer.name == "auto"
        linear, decoder = photo.decode(pixels.to(dtype), Transfer("srgb") if given is None and untagged else given)
        if decoder.startswith("icc:"):  # the matrix moves a clipped sample off 1: keep it at the level
            linear = torch.where(clipped, linear.clamp(min=CLIP), linear)
            profiles[k] = decoder[4:]
            outside = int((linear < 0).any(-1).sum())
            if outside:  # radiance is non-negative: a colour outside sRGB's gamut is clipped to it
                notes.append(
                    f"{image}: {outside} pixel(s) outside the sRGB gamut after its ICC profile; their negative "
                    "components are set to 0."
                )
                linear = linear.clamp(min=0)
        level = CLIP if first.clipped else None  # a box holding a clipped sample stays clipped
        stack[k] = scale.reduce(linear.numpy(), level).transpose(2, 0, 1)
        exifs.append(photo.exif)
    transfer = transfer or first.default_transfer
    response = None
    if transfer.name == "auto":
        transfer, response = _decode_auto(stack, directions, notes)
        if n > 1:  # decoded to linear: now averaged
            count, c, h, w = stack.shape
            reduced = _stack(scratch, (count, c, h // n, w // n), "small")
            for frame in range(count):
                reduced[frame] = scale.reduce(stack[frame].transpose(1, 2, 0), CLIP).transpose(2, 0, 1)
            stack = reduced
    return stack, transfer, first.encoding, exifs, notes, saturated, profiles, response, (size[1], size[0])


def _stack(scratch: Path, shape: tuple[int, ...], name: str = "stack") -> np.ndarray:
    """An empty float32 array of ``shape``: in a temporary file of ``scratch`` when it is larger
    than :data:`_MEMORY`."""
    if np.prod(shape) * 4 > _MEMORY:
        return np.lib.format.open_memmap(scratch / f"{name}.npy", mode="w+", dtype=np.float32, shape=shape)
    return np.empty(shape, dtype=np.float32)


def _check_alike(image: Path, first_image: Path, photo, first, size) -> None:
    """Every photograph of a stack must match the first one's size, encoding and kind (a grey
    one among colour ones is allowed: its grey serves R, G and B)."""
    if photo.pixels.shape[:2] != size[:2]:
        raise ImageError(
            f"{image} must be {size[1]}x{size[0]} (width x height) like {first_image.name}; got "
            f"{photo.pixels.shape[1]}x{photo.pixels.shape[0]}. Crop or resize the photographs to one size."
        )
    if photo.encoding != first.encoding:
        raise ImageError(
            f"{image} must be encoded like {first_image.name} ({first.encoding}) to share one transfer; got "
            f"{photo.encoding}. Export every photograph the same way."
        )
    if photo.pixels.shape[2] != size[2] and photo.pixels.shape[2] != 1:
        raise ImageError(
            f"{image} must be greyscale like {first_image.name}; got a colour photograph. Convert every "
            "photograph to the same kind (or the first one to colour)."
        )


def _decode_auto(stack: np.ndarray, directions: torch.Tensor, notes: list[str]):
    """The codes of ``stack (K, C, H, W)`` decoded in place with the camera's response: ``(transfer,
    estimate)``. Candidates: the curve estimated from every sample, the one estimated without the
    samples near a highlight (:data:`GLARE`), and sRGB, judged by the fit's prediction of left-out
    frames (:func:`torchspec.calibration.response_judge.judge_curves`) where the capture has 10 frames or more:
    the first is kept unless another predicts better by :data:`JUDGE_MARGIN`;
    where no curve can be estimated, sRGB (noted)."""
    k, c, h, w = stack.shape
    generator = torch.Generator().manual_seed(0)  # CPU on purpose: a seeded draw, reproducible, indexes numpy
    drawn = torch.randperm(h * w, generator=generator)[: 8 * RESPONSE_PIXELS].sort().values
    rows, cols = (drawn // w).numpy(), (drawn % w).numpy()
    codes = torch.from_numpy(np.ascontiguousarray(stack[:, :, rows, cols])).double()  # (K, C, N)
    picked = response_samples(codes, RESPONSE_PIXELS)
    try:
        estimates = {
            "estimated": estimate_response(codes[..., picked], directions.double()),
            "estimated without glare": estimate_response(codes[..., picked], directions.double(), glare=GLARE),
        }
    except ResponseError as error:
        notes.append(f"the camera's response could not be estimated ({error}); the photographs are decoded as sRGB.")
        estimates = {}
    candidates = {name: Transfer("response", curve=e.curve) for name, e in estimates.items()}
    chosen, estimate = "srgb", None
    if candidates:
        chosen, estimate = "estimated", estimates["estimated"]
    if candidates and k >= 10 and min(h, w) >= 8:
        from ..calibration.response_judge import judge_curves  # the fit judges the curves: imported where it does

        candidates["srgb"] = Transfer("srgb")
        scores = judge_curves(torch.from_numpy(np.asarray(stack)), directions, candidates)
        best = max(scores, key=scores.get)
        chosen = best if scores[best] > scores["estimated"] + JUDGE_MARGIN else "estimated"
        estimate = replace(estimates.get(chosen, estimates["estimated"]), judged=scores)
        if chosen == "srgb":
            notes.append(
                "the camera's responses estimated from the photographs predicted left-out photographs less well than "
                f"sRGB ({', '.join(f'{n} {v:.2f} dB' for n, v in scores.items())}): decoded as sRGB."
            )
    transfer = candidates.get(chosen, Transfer("srgb"))
    for frame in range(k):
        encoded = torch.from_numpy(stack[frame]).double().permute(1, 2, 0)
        stack[frame] = transfer.decode(encoded).permute(2, 0, 1).float().numpy()
    return transfer, estimate


def _source_record(lights, matched, images, encoding, transfer, response, profiles, saturated, exifs, notes) -> dict:
    """The manifest's ``source`` block of an import (docs/capture-format.md)."""
    return {
        "importer": f"torchspec {__version__} import",
        "light_file": str(lights.path),
        "matched": matched,
        "images": [os.path.relpath(image, lights.path.parent) for image in images],
        "lines": [entry.where or entry.line for entry in lights.entries],
        "encoding": encoding,
        "transfer": str(transfer),
        "response": None if response is None else response.to_json(),
        "icc_profiles": profiles if any(profiles) else None,
        "positions": None if lights.positions is None else [list(p) for p in lights.positions],
        "saturation": CLIP if encoding != "float" else None,
        "saturated_pixels": saturated,
        "exif": exifs if any(exifs) else None,
        "notes": notes,
    }


def import_rti(
    source: str | Path,
    output: str | Path,
    *,
    transfer: str | Transfer | None = None,
    overwrite: bool = False,
    progress: bool = False,
    scale: Scale | None = None,
) -> Imported:
    """Import an RTI capture (see the module's docstring) into ``output``.

    Args:
        source: an ``.lp`` file (or ``lights.txt``), or a folder holding one.
        output: the capture folder to write; new, empty, or replaced with ``overwrite``.
        transfer: ``auto``, ``srgb``, ``linear`` or ``gamma:G``; ``None``: for 8 and 16-bit
            photographs their ICC profile where they embed one, else ``auto`` (the camera's
            response estimated from the photographs); linear for float and RAW ones.
        overwrite: replace an ``output`` that holds files (only once the new capture is complete).
        progress: a tqdm bar over the photographs.
        scale: a crop of the photographs and a downsample factor (:class:`~torchspec.io.scale.Scale`,
            ``--crop``, ``--downsample``; ``None``: every pixel), applied once they are decoded to linear values (boxes
            averaged; a box holding a clipped sample is clipped); recorded as ``source.scale``.
            Near lights' positions are moved to the cropped image's frame.

    Returns:
        :class:`Imported`. Notes (what was assumed) are also warned about.

    Raises:
        TorchspecError: :class:`~torchspec.io.lp.LightFileError` (the file and line),
            :class:`RTIImportError` (missing images, each named; an output that holds files),
            :class:`~torchspec.io.images.ImageError` (an unreadable, CMYK or odd-sized photograph),
            :class:`~torchspec.io.scale.ScaleError` (a crop outside the photographs, naming their size);
            nothing is written then.
    """
    output = Path(output)
    lights = read_lights(find_light_file(source))
    images, matched, notes = match_images(lights)
    notes = list(lights.notes) + notes
    _check_output(output, overwrite)
    inside = [path for path in (lights.path, *images) if path.resolve().is_relative_to(output.resolve())]
    if inside:
        raise RTIImportError(
            f"{output} must not hold the capture's own files; got {inside[0]} inside it. Write the capture to "
            "another folder."
        )
    if isinstance(transfer, str):
        transfer = Transfer.parse(transfer)
    scale = scale or Scale()
    output.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".{output.name}.import-", dir=output.parent))
    try:
        # CPU on purpose: parsed from the light file, written to the capture's files
        directions = torch.tensor([entry.direction for entry in lights.entries], dtype=torch.float64)
        directions = directions / directions.norm(dim=-1, keepdim=True)
        stack, transfer, encoding, exifs, image_notes, saturated, profiles, response, size = _read_stack(
            images, transfer, torch.float64, scratch, progress, directions, scale
        )
        notes += image_notes
        exposures = _exposures(exifs, images, notes)
        frames = _frames(images, lights, exposures, scale, size)
        record = _source_record(
            lights, matched, images, encoding, transfer, response, profiles, saturated, exifs, notes
        )
        record["scale"] = None if scale.identity else scale.record(*size)
        channels = ("Y",) if stack.shape[1] == 1 else ("R", "G", "B")
        capture = Capture(
            root=scratch / "capture",
            width=stack.shape[3],
            height=stack.shape[2],
            channels=channels,
            view=(0.0, 0.0, 1.0),
            light=LightSpec(kernel="point"),
            frames=frames,
            # A light file gives no light's intensity: the fit calibrates a gain per frame and channel.
            extra={"source": record, "unknown": ["irradiance"]},
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # directions are unit to float round-off: renormalised silently
            write_capture(scratch / "capture", capture, stack)
        del stack
        _replace(scratch / "capture", output, scratch)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    for note in notes:
        warnings.warn(note, stacklevel=2)
    written = read_capture(output)
    positions = written.positions()  # as the capture holds them: in the cropped image's frame
    return Imported(
        written, lights, tuple(images), matched, transfer, tuple(saturated), tuple(notes), positions, response
    )


def _frames(images: list[Path], lights: LightFile, exposures: list[float], scale: Scale, size) -> tuple[Frame, ...]:
    """Each photograph's frame: the light file's direction (and position, moved to the frame of
    the image ``scale`` reduces a photograph of ``size`` to: :func:`torchspec.io.scale.move_lights`),
    irradiance 1 (unknown), its exposure."""
    places = lights.positions if lights.positions is not None else [None] * len(images)
    frames = tuple(
        Frame(
            file=_frame_name(k, image),
            direction=entry.direction,
            irradiance=1.0,
            exposure=exposure,
            position=None if place is None else tuple(float(v) for v in place),
        )
        for k, (image, entry, exposure, place) in enumerate(zip(images, lights.entries, exposures, places, strict=True))
    )
    return move_lights(frames, scale.region(*size), *size)


def _replace(new: Path, output: Path, scratch: Path) -> None:
    """Move the complete capture ``new`` to ``output`` by a rename; an existing ``output`` is first
    moved into ``scratch`` (removed with it), and moved back if the second rename fails."""
    if output.exists():
        old = scratch / "replaced"
        os.replace(output, old)
        try:
            os.replace(new, output)
        except OSError:
            os.replace(old, output)
            raise
    else:
        os.replace(new, output)
