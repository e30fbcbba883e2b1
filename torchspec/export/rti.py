"""The RTI export (:func:`export_rti`): an HSH ``.rti`` file that RTIViewer opens, fitted to the
SVBRDF's own renders over the hemisphere, with its fit described in ``rti.json``.

The file is the "universal RTI" layout that RTIBuilder writes and RTIViewer reads (RTIViewer's
``universalrti.cpp`` and ``hsh.cpp``, Visual Computing Lab ISTI-CNR and Cultural Heritage Imaging;
Relight's ``src/legacy_rti.cpp`` reads it the same way):

- text lines ``#HSH1.2``, ``3`` (the RTI type: HSH), ``W H 3`` (width, height, colour
  components), ``9 2 1`` (basis terms, basis type, bytes per element);
- ``9`` little-endian float32 scales, then ``9`` float32 biases;
- one byte per coefficient: rows from the top of the image to its bottom (RTIViewer reads them
  into its top-down image as they come, and turns a PTM's bottom-up rows over; Relight's reader
  and writer turn the rows of an ``.rti`` over against its bottom-up memory, not a PTM's), in each
  row the pixels left to right, for each pixel the 9 red coefficients, then the 9 green, then the 9 blue;
  coefficient ``k`` is ``byte / 255 * scale[k] + bias[k]``.

RTIViewer shows ``255 * sum_k c_k H_k(theta, phi)`` (clamped to 0..255) for the light of polar
angle ``theta`` and azimuth ``phi = atan2(l_y, l_x)`` in the image frame (``x`` right, ``y`` up),
with ``H`` the hemispherical harmonics of :func:`torchspec.model.residual_term.hsh_basis`: the fitted
values are display values (sRGB-encoded, 0..1), like the photographs an RTI fitter is given.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._version import __version__
from ..atomic import atomic_path, write_json
from ..errors import TorchspecError
from ..io import Capture, Maps, read_capture, read_svbrdf
from ..model.brdf import SVBRDF
from ..model.lights import Kernel, Lights
from ..model.rendering import render
from ..model.residual_term import MAP_NAME, TermDomain, hsh_basis
from ..outputs import check_output
from ..relight import capture_places, fitted_scales
from .arrays import ExportError, ExportWarning, checked_svbrdf

__all__ = [
    "FIT_LIGHTS",
    "FIT_THETA_MAX_DEG",
    "HSH_TERMS",
    "RtiFit",
    "RtiLighting",
    "export_rti",
    "fit_hsh",
    "fit_rti",
    "hemisphere_directions",
    "rti_lighting",
    "quantise",
    "read_rti",
    "rti_bytes",
    "render_display",
]

HSH_TERMS = 9
"""Coefficients per pixel and channel: HSH of order 3, what RTIBuilder writes."""
FIT_LIGHTS = 100
"""Point lights the coefficients are fitted to, spread evenly over the fitted cap."""
FIT_THETA_MAX_DEG = 75.0
"""The fitted cap of the hemisphere: lights up to 75 degrees from the zenith (15 degrees above the
horizon, the lowest light of a usual RTI dome)."""
_ROWS_PIXELS = 1 << 15


@dataclass(frozen=True)
class RtiFit:
    """An HSH fit of a relit image.

    Attributes:
        coefficients: ``(H, W, 3, 9)`` float64: per pixel, channel (R, G, B) and basis function.
        directions: ``(K, 3)`` the light directions fitted.
        rms: ``(H, W)`` the fit's RMS error over the fitted lights and channels, display units (0..1).
        irradiance: the point lights' irradiance of the renders.
    """

    coefficients: np.ndarray
    directions: np.ndarray
    rms: np.ndarray
    irradiance: float


def hemisphere_directions(
    count: int = FIT_LIGHTS, theta_max_deg: float = FIT_THETA_MAX_DEG, dtype=torch.float64, device=None
) -> Tensor:
    """``(count, 3)`` unit directions spread evenly (equal solid angle, a Fibonacci spiral) over the
    cap of polar angles ``0 .. theta_max_deg``; deterministic; of ``dtype`` on ``device``."""
    if count < HSH_TERMS:
        raise ExportError(f"an HSH fit needs at least {HSH_TERMS} lights; got {count}.")
    if not 0 < theta_max_deg < 90:
        raise ExportError(f"theta_max_deg must be in (0, 90) degrees; got {theta_max_deg}.")
    index = torch.arange(count, dtype=dtype, device=device) + 0.5
    z = 1 - index / count * (1 - math.cos(math.radians(theta_max_deg)))
    phi = index * math.pi * (3 - math.sqrt(5))
    r = (1 - z * z).clamp(min=0).sqrt()
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def render_display(svbrdf: SVBRDF, directions: Tensor, irradiance: float, domain: TermDomain | None = None) -> Tensor:
    """``(*, K, 3)`` display values of ``svbrdf`` (leading dims ``*``) under point lights from
    ``directions (K, 3)`` of irradiance ``irradiance``, seen from ``(0, 0, 1)``: the render clipped to
    ``[0, 1]`` and encoded by ``domain`` (default sRGB; a capture's camera response,
    :class:`~torchspec.model.residual_term.TermDomain`), grey maps as grey RGB; what a photograph of the
    relit maps shows."""
    domain = TermDomain() if domain is None else domain
    like = svbrdf.diffuse
    directions = directions.to(dtype=like.dtype, device=like.device)
    count = directions.shape[0]
    one = torch.ones(count, 1, dtype=like.dtype, device=like.device)
    lights = Lights(directions, Kernel("point"), one * irradiance, one[:, 0])
    view = torch.tensor([0.0, 0.0, 1.0], dtype=like.dtype, device=like.device)
    value = render(svbrdf, lights, view).clamp(0, 1)
    return domain.encode(value.expand(*value.shape[:-1], 3))


def fit_hsh(values: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
    """Least squares HSH coefficients of ``values (*, K, C)`` taken under ``directions (K, 3)``:
    ``(*, C, 9)`` coefficients and the ``(*, C)`` RMS residual over the K lights. One
    pseudo-inverse for every pixel (the design matrix depends on the lights only)."""
    basis = hsh_basis(directions.to(values.dtype), 3)  # (K, 9)
    solve = torch.linalg.pinv(basis)  # (9, K)
    coefficients = torch.einsum("jk,...kc->...cj", solve, values)
    residual = values - torch.einsum("kj,...cj->...kc", basis, coefficients)
    return coefficients, residual.pow(2).mean(-2).sqrt()


def quantise(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """8-bit codes of ``coefficients (..., 9)`` with one scale and bias per basis function over the
    whole image, as the ``.rti`` file holds them: ``(codes uint8, scale float32, bias float32)``,
    ``value = code / 255 * scale + bias``, off by at most ``scale / 510`` (plus float32 rounding)."""
    flat = coefficients.reshape(-1, coefficients.shape[-1])
    bias = flat.min(axis=0).astype(np.float32)
    top = flat.max(axis=0)
    scale = np.where(top > bias, top - bias.astype(np.float64), 1.0).astype(np.float32)
    codes = np.round((coefficients - bias.astype(np.float64)) / scale.astype(np.float64) * 255)
    return np.clip(codes, 0, 255).astype(np.uint8), scale, bias


def rti_bytes(codes: np.ndarray, scale: np.ndarray, bias: np.ndarray) -> bytes:
    """The ``.rti`` file of ``codes (H, W, 3, 9)`` (row 0 at the top of the image), ``scale`` and
    ``bias (9,)``: the header, the float32 scales and biases, then the rows top to bottom."""
    height, width, channels, terms = codes.shape
    header = f"#HSH1.2\n3\n{width} {height} {channels}\n{terms} 2 1\n".encode("ascii")
    floats = np.asarray(scale, "<f4").tobytes() + np.asarray(bias, "<f4").tobytes()
    return header + floats + np.ascontiguousarray(codes).tobytes()


def read_rti(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The coefficients of an HSH ``.rti`` (as :func:`export_rti` and RTIBuilder write it):
    ``(H, W, C, J)`` float64, row 0 at the top of the image, and the file's ``scale`` and ``bias (J,)``.

    Raises:
        ExportError: the file is not an HSH ``.rti`` of one-byte coefficients, or is cut short.
    """
    data = Path(path).read_bytes()
    lines, offset = [], 0
    while len(lines) < 3:
        end = data.find(b"\n", offset)
        if end < 0:
            raise ExportError(f"{path}: not an .rti file (its header ends early).")
        line = data[offset:end].decode("latin-1").strip()
        offset = end + 1
        if not line.startswith("#"):
            lines.append(line.split())
    try:
        (kind,), (width, height, colours), (terms, _, element) = ([int(v) for v in line] for line in lines)
    except ValueError as error:
        raise ExportError(f"{path}: not an .rti header ({lines}).") from error
    if kind != 3 or element != 1:
        raise ExportError(f"{path}: only HSH (type 3) .rti files of 1-byte coefficients are read; got type {kind}.")
    scale = np.frombuffer(data, "<f4", terms, offset).astype(np.float64)
    bias = np.frombuffer(data, "<f4", terms, offset + 4 * terms).astype(np.float64)
    body = np.frombuffer(data, np.uint8, offset=offset + 8 * terms)
    if body.size != width * height * colours * terms:
        raise ExportError(f"{path}: {body.size} coefficient bytes, {width * height * colours * terms} expected.")
    codes = body.reshape(height, width, colours, terms)
    return codes / 255.0 * scale + bias, scale, bias


def export_rti(
    maps: Maps | SVBRDF | str | Path,
    output: str | Path,
    *,
    irradiance: float | None = None,
    directions: Tensor | None = None,
    capture: Capture | str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Write ``image.rti``, an HSH relightable image that RTIViewer opens, and ``rti.json``.

    Every pixel's 9 HSH coefficients per channel are the least squares fit of its display values
    (:func:`render_display`: the point-light render, clipped to 1, encoded as the photographs the
    maps were fitted from are) under ``directions``, then quantised to 8 bits per coefficient with
    one scale and bias per basis function (:func:`quantise`). The maps' second lobe is rendered
    with the rest; a residual term (``residual_term.exr``) is not. The lights' irradiance and the
    encoding are those of the photographs (:func:`rti_lighting`): the .rti shows the object as
    bright as its photographs.

    Args:
        maps: see :func:`export`; grey (``Y``) maps give a grey RTI.
        output: the folder to write.
        irradiance: the lights' irradiance; ``None`` (default): the photographs' (:func:`rti_lighting`:
            the median exposure times irradiance, as calibrated, of the frames the maps were fitted
            from; ``pi`` for maps without their capture, which shows a white Lambertian surface
            facing the light as 1, 255).
        directions: ``(K, 3)`` unit light directions to fit, ``K >= 9``; default
            :func:`hemisphere_directions` (:data:`FIT_LIGHTS` lights up to :data:`FIT_THETA_MAX_DEG`).
        capture: the capture the maps were fitted from; default the one ``svbrdf.json`` names
            (``fit.capture``), when it can be read.

    Returns:
        The path of ``rti.json`` (written last), which records the fit's lights, irradiance (and
        where it comes from), encoding, RMS error (display units) and the quantisation.

    Raises:
        OutputError: ``output`` holds files and ``overwrite`` is not set, or cannot be written.
        ExportError: bad ``irradiance`` or ``directions``; maps not of leading dims ``(H, W)``; a
            capture of another size than the maps, or without the frames they were fitted from.
        CaptureError: ``capture`` is given and cannot be read.

    Warns:
        ExportWarning: the capture ``svbrdf.json`` names cannot be read: irradiance pi.
    """
    check_output(output, overwrite=overwrite)
    folder = Path(maps) if isinstance(maps, (str, Path)) else None
    maps = read_svbrdf(maps) if folder is not None else maps
    lighting = rti_lighting(maps, capture, irradiance, folder=folder)
    fit = fit_rti(maps, irradiance=lighting.irradiance, directions=directions, domain=lighting.domain)
    codes, scale, bias = quantise(fit.coefficients)
    folder = Path(output)
    manifest = folder / "rti.json"
    folder.mkdir(parents=True, exist_ok=True)
    manifest.unlink(missing_ok=True)
    with atomic_path(folder / "image.rti") as tmp:
        tmp.write_bytes(rti_bytes(codes, scale, bias))
    height, width = fit.rms.shape
    write_json(
        manifest,
        {
            "format": "torchspec.rti",
            "version": 1,
            "generator": f"torchspec {__version__} export",
            "file": "image.rti",
            "width": width,
            "height": height,
            "basis": "HSH order 3 (9 terms), RTIViewer's: value = 255 * sum_k c_k H_k(theta, phi)",
            "values": "display values: the point-light render times irradiance, clipped to [0, 1], encoded",
            "irradiance": fit.irradiance,
            "irradiance_from": lighting.source,
            "encoding": lighting.domain.to_json(),
            "view": [0.0, 0.0, 1.0],
            "fit_directions": fit.directions.tolist(),
            "fit_rms": {"mean": float(fit.rms.mean()), "max": float(fit.rms.max())},
            "scale": scale.tolist(),
            "bias": bias.tolist(),
            "decode": "coefficient k = byte / 255 * scale[k] + bias[k]",
        },
    )
    return manifest


@dataclass(frozen=True)
class RtiLighting:
    """How the .rti's display values are lit and encoded (:func:`rti_lighting`).

    Attributes:
        irradiance: the fitted point lights' irradiance.
        domain: the encoding of the display values: the photographs' (their estimated camera
            response), else sRGB.
        source: where the irradiance comes from, in words (``rti.json``'s ``irradiance_from``).
    """

    irradiance: float
    domain: TermDomain
    source: str


def rti_lighting(
    maps: Maps | SVBRDF,
    capture: Capture | str | Path | None = None,
    irradiance: float | None = None,
    *,
    folder: str | Path | None = None,
) -> RtiLighting:
    """The irradiance and encoding under which relit ``maps`` look as bright as the photographs
    they were fitted from.

    A photograph of frame ``k`` is ``exposure_k irradiance_k`` (times the gain the fit calibrated,
    ``svbrdf.json``'s ``fit.lights.gains``) times the maps' render under a unit light, encoded by
    the camera's response (an imported capture's ``source``; else the residual term's
    ``encoding``; else sRGB). One irradiance lights every direction of the .rti: the median of
    those products (over the frames fitted, ``fit.frames``, and the channels; an imported
    capture's is 1). ``irradiance``, given, replaces it (the encoding kept). The capture is
    ``capture``, else the one ``svbrdf.json`` names (``fit.capture``: as written, else beside the
    map folder ``folder``); without one (an :class:`~torchspec.SVBRDF`, or a capture that cannot be read,
    with an :class:`ExportWarning`) the irradiance is pi.

    Raises:
        ExportError: a capture of another size than the maps, or without the frames fitted.
        CaptureError: ``capture`` is given and cannot be read.
    """
    meta = maps.meta if isinstance(maps, Maps) else {}
    fit = meta.get("fit") if isinstance(meta.get("fit"), dict) else {}
    if capture is not None and not isinstance(capture, Capture):
        capture = read_capture(capture)
    elif capture is None and fit.get("capture"):
        capture = _named_capture(str(fit["capture"]), folder)
    domain = TermDomain.from_json((meta.get(MAP_NAME) or {}).get("encoding"), f"svbrdf.json {MAP_NAME}.encoding")
    if capture is not None and capture.extra.get("source"):
        domain = TermDomain.of_source(capture.extra.get("source"))
    if irradiance is not None:
        return RtiLighting(float(irradiance), domain, "given (--irradiance)")
    if capture is None:
        return RtiLighting(math.pi, domain, "pi, no capture: a white Lambertian surface facing the light shows 1")
    return _photographs_irradiance(maps, capture, fit, domain)


def _named_capture(name: str, folder: str | Path | None) -> Capture | None:
    """The capture ``svbrdf.json`` names: as written, else beside the map folder ``folder``;
    ``None`` with an :class:`ExportWarning` when none can be read."""
    folder = None if folder is None else Path(folder).resolve()
    folder = folder.parent if folder is not None and folder.suffix.lower() == ".json" else folder
    problems = []
    for place in [Path(name)] if folder is None else capture_places(name, folder):
        try:
            return read_capture(place)
        except TorchspecError as error:
            problems.append(str(error))
    warnings.warn(
        f"the capture the maps were fitted from (svbrdf.json fit.capture: {name}) cannot be read ({problems[0]}); "
        "the .rti is lit by irradiance pi, not as the photographs: give the capture (--capture) or --irradiance.",
        ExportWarning,
        stacklevel=3,
    )
    return None


def _photographs_irradiance(maps: Maps | SVBRDF, capture: Capture, fit: dict, domain: TermDomain) -> RtiLighting:
    """:func:`rti_lighting`'s irradiance from ``capture``'s frames (and the fit's gains)."""
    svbrdf = maps.svbrdf if isinstance(maps, Maps) else maps
    if (capture.height, capture.width) != tuple(svbrdf.shape):
        raise ExportError(
            f"{capture.manifest} is {capture.width}x{capture.height} but the maps are "
            f"{svbrdf.shape[1]}x{svbrdf.shape[0]}: export the maps with the capture they were fitted from."
        )
    count = len(capture.frames)
    frames = fit.get("frames") or list(range(count))
    if not all(isinstance(k, int) and 0 <= k < count for k in frames):
        raise ExportError(
            f"svbrdf.json fit.frames names frames {capture.manifest} does not have ({count} frames): export the "
            "maps with the capture they were fitted from."
        )
    products, gains = fitted_scales(capture.exposure().numpy()[frames], capture.irradiance().numpy()[frames],
                                    fit.get("lights") or {})  # fmt: skip
    words = f"the median exposure times irradiance of the {len(frames)} frames of {capture.root} fitted"
    if gains:
        words += ", times the gains the fit calibrated"
    return RtiLighting(float(np.median(products)), domain, words + ": the photographs' brightness")


def fit_rti(
    maps: Maps | SVBRDF | str | Path,
    *,
    irradiance: float = math.pi,
    directions: Tensor | None = None,
    domain: TermDomain | None = None,
) -> RtiFit:
    """The HSH fit of :func:`export_rti` before quantisation (:class:`RtiFit`), in chunks of rows,
    of the display values under lights of ``irradiance`` encoded by ``domain`` (default sRGB)."""
    svbrdf = checked_svbrdf(maps)
    if not (math.isfinite(irradiance) and irradiance > 0):
        raise ExportError(f"the irradiance must be a positive number; got {irradiance}.")
    device = svbrdf.diffuse.device
    if directions is None:
        directions = hemisphere_directions(device=device)
    else:
        directions = torch.as_tensor(directions, dtype=torch.float64, device=device)
    if directions.dim() != 2 or directions.shape[1] != 3 or directions.shape[0] < HSH_TERMS:
        raise ExportError(f"directions must be (K, 3) with K >= {HSH_TERMS}; got {tuple(directions.shape)}.")
    if not bool(torch.isclose(directions.norm(dim=-1), directions.new_ones(())).all()) or bool(
        (directions[:, 2] <= 0).any()
    ):
        raise ExportError("directions must be unit vectors above the horizon (z > 0).")
    height, width = svbrdf.shape
    rows = max(1, _ROWS_PIXELS // max(width, 1))
    coefficients, rms = [], []
    for top in range(0, height, rows):
        part = svbrdf[top : top + rows]
        values = render_display(part, directions, irradiance, domain).double()
        if not bool(torch.isfinite(values).all()):
            raise ExportError(
                f"the maps render to NaN or Inf values in rows {top}..{top + part.shape[0] - 1}: "
                "check them for NaN, Inf or negative values."
            )
        fitted, error = fit_hsh(values, directions.to(values.device))
        coefficients.append(fitted.cpu())
        rms.append(error.pow(2).mean(-1).sqrt().cpu())
    return RtiFit(
        coefficients=torch.cat(coefficients).numpy(),
        directions=directions.cpu().numpy(),
        rms=torch.cat(rms).numpy(),
        irradiance=float(irradiance),
    )
