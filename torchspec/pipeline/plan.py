"""What every driver of a fit starts from: the settings, capture, frames, lights and view
(:func:`setup`, a :class:`Setup`), and the tiling (:func:`plan`): from the capture's size and the
settings only, so that every driver tiles a fit alike (the same maps, and either resumes the
other's checkpoint).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..io import Capture, read_capture
from ..io.scale import Scale, scaled
from ..layout import coverage_warning, fit_problem
from ..lights import Lights
from ..models import get_model
from ..photometric import peak_of, saturation_level
from ..residual_term import TermDomain
from .settings import AUTO, COMPILE_PIXELS, FitConfig, select_frames

__all__ = [
    "GPU_SHARE",
    "MIN_TILE",
    "RUNTIME_BYTES",
    "TERM_FOR_PHOTOGRAPHS",
    "TILES",
    "FitWarning",
    "Setup",
    "device_of",
    "frame_warnings",
    "plan",
    "setup",
    "tile_size",
]

TERM_FOR_PHOTOGRAPHS = 3
"""``FitConfig.residual_term = auto``'s order for a capture imported from photographs (its manifest's
``source``): on the RTI captures of ``../shared/data/rti`` the order-3 term relit left-out
photographs at or above HSH, where the physical model alone was below it
(``experiments/results/rti_relight.json``)."""
GPU_SHARE = 0.8
"""The share of a GPU's free memory (when the fit starts) that its tiles are sized to."""
RUNTIME_BYTES = 768 * 2**20
"""What a fit holds besides its stack and tiles: the torch runtime and fixed work arrays."""
TILES = 16
"""A fit sized by memory is cut into at least this many tiles when its image is large enough (the
progress bar moves per tile, and Ctrl-C keeps every finished tile)..."""
MIN_TILE = 1024
"""... of at least this many pixels each (the solver's batches stay efficient; each tile fits its
own sensor noise)."""


class FitWarning(UserWarning):
    """Something a fit ran through but its user should know: lights that miss where the peaks lie,
    many pixels stopped at the solver's iteration limit (also listed in ``stats["warnings"]``)."""


def frame_warnings(capture: Capture, picked: list[int]) -> list[str]:
    """What the frames ``picked`` of ``capture`` let a fit do only poorly (known before it starts):
    :func:`torchspec.layout.coverage_warning`."""
    if len(picked) < 3:
        return []
    l = capture.directions()[torch.tensor(picked)][:, :2]  # on the CPU: the capture's manifest, checked once
    found = coverage_warning(l, torch.tensor(capture.view, dtype=l.dtype, device=l.device))
    return [f"{capture.root}: {found}"] if found else []


def device_of(name: str | torch.device) -> torch.device:
    """The device of ``FitConfig.device`` (or ``--device``): ``auto`` is CUDA when present, else the
    CPU; ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        TorchspecError: a name torch does not know, or a CUDA device this machine lacks."""
    if str(name) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError) as error:
        raise TorchspecError(f"the device must be auto, cpu, cuda or cuda:N; got {name!r} ({error}).") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0 or (device.index or 0) >= count:
            raise TorchspecError(
                f"the device {name!r} is not on this machine: torch sees {count} CUDA device(s) "
                f"(torch {torch.__version__}, CUDA {torch.version.cuda or 'none: a CPU build'}). "
                "Use --device cpu or auto."
            )
    return device


def tile_size(
    config: FitConfig, frames: int, channels: int, itemsize: int, reserved: int, budget: float | None = None
) -> int:
    """Pixels per tile: ``config.tile``, or what fits in ``budget`` bytes (default ``memory_gib``)
    after ``reserved`` bytes (the stack and its masks) and :data:`RUNTIME_BYTES` (at least 256, at
    most 131072 within ``memory_gib``; a larger ``budget``, a GPU's, lifts that cap)."""
    if config.tile:
        return config.tile
    p = max(get_model(name).size(channels) for name in (config.ladder if config.model == AUTO else (config.model,)))
    # Per pixel: observations, weights, values, residuals and the Jacobian twice (the full columns and
    # the model's), J^T J, plus the photometric and specular stages' (N, K) work arrays; twice that
    # for transients (a conservative bound: the solver takes normal equations from Jacobian chunks).
    per_pixel = itemsize * frames * (channels * (2 * p + 8) + 16) + itemsize * 4 * p * p
    given = config.memory_gib * 2**30 if budget is None else budget
    available = given - reserved - RUNTIME_BYTES
    fits = available / (2 * per_pixel)
    return int(max(256, fits if budget is not None else min(1 << 17, fits)))


def plan(
    config: FitConfig, k: int, c: int, h: int, w: int, itemsize: int, device: torch.device | None = None
) -> tuple[FitConfig, int]:
    """The settings with ``compile`` decided and the pixels per tile of a fit of a ``(K, C, H, W)``
    stack of ``itemsize``-byte values on ``device`` (default the CPU): ``FitConfig.tile``, or what
    the memory allows (:func:`tile_size`). On the CPU the budget is ``memory_gib`` and the image is
    also cut into at least :data:`TILES` tiles (of at least :data:`MIN_TILE` pixels: progress,
    resumption, threads). On a GPU the budget is :data:`GPU_SHARE` of its free memory (the stack
    lives there too), and a tile may hold the whole image: a GPU is fed best by large batches."""
    if config.compile is None:
        config = replace(config, compile=h * w >= COMPILE_PIXELS)
    reserved = (k * c * itemsize + 3 * k) * h * w  # the stack, three bool masks
    gpu = device is not None and device.type == "cuda"
    budget = GPU_SHARE * torch.cuda.mem_get_info(device)[0] if gpu and not config.tile else None
    tile = tile_size(config, k, c, itemsize, reserved, budget)
    if not config.tile and not gpu:  # sized by memory: also cut into TILES tiles of at least MIN_TILE pixels
        tile = min(tile, max(MIN_TILE, -(-h * w // TILES)))
    return config, min(tile, h * w) if gpu else tile


@dataclass(frozen=True)
class Setup:
    """What every driver of a fit starts from.

    Attributes:
        config: the settings; capture: the capture (its manifest read); picked: the frames fitted.
        lights: the picked frames' lights (``K``), on the settings' device and dtype.
        view: ``(3,)`` the view direction, alike.
        positions: ``(K, 3)`` the picked frames' near-light positions (``Frame.position``; object
            units, :mod:`torchspec.near_lights`), alike; ``None`` for distant lights.
        gains: ``(K, C)`` the gains :func:`calibrated` found (in ``lights``' irradiance), else ``None``.
        domain: the encoding the residual term is fitted in: the capture's estimated camera response
            where its import estimated one (``source.transfer: response``), else sRGB
            (:class:`torchspec.residual_term.TermDomain`).
    """

    config: FitConfig
    capture: Capture
    picked: list[int]
    lights: Lights
    view: Tensor
    positions: Tensor | None = None
    gains: Tensor | None = None
    domain: TermDomain = field(default_factory=TermDomain)


def setup(capture: Capture | str | Path, config: FitConfig | None, frames: str | list[int] | None) -> Setup:
    """The :class:`Setup` of a fit of ``capture`` (or its folder) with ``config`` (the defaults
    if ``None``) on ``frames`` (a SPEC of :func:`~torchspec.pipeline.settings.select_frames`, or indices).

    Warns:
        FitWarning: :func:`frame_warnings`.

    Raises:
        TorchspecError: frames a fit cannot use (:func:`torchspec.layout.fit_problem`: fewer than 4,
            or too few along an axis for a lobe); CaptureError: an unreadable capture or light.
    """
    config = config or FitConfig()
    capture = capture if isinstance(capture, Capture) else read_capture(capture)
    if config.saturation is None and capture.saturation is not None:  # the level an imported capture records
        config = replace(config, saturation=capture.saturation)
    if config.residual_term == AUTO:  # photographs: the term carries what the physics misses, where it predicts
        config = replace(config, residual_term=TERM_FOR_PHOTOGRAPHS if capture.extra.get("source") else 0)
    picked = frames if isinstance(frames, list) else select_frames(frames, len(capture.frames))
    config, capture = _reduced(config, capture, picked)
    l = capture.directions()[torch.tensor(picked, dtype=torch.long)][:, :2]  # on the CPU: the manifest, checked once
    problem = fit_problem(l, lobe=config.model != "diffuse")
    if problem is not None:
        raise TorchspecError(f"{capture.root}: the frames cannot be fitted: {problem}")
    for message in frame_warnings(capture, picked):
        warnings.warn(message, FitWarning, stacklevel=3)
    dtype = getattr(torch, config.dtype)
    device = device_of(config.device)
    everything = capture.lights(dtype=dtype)
    index = torch.tensor(picked)  # on the CPU, as the capture's lights: picked there, then moved to the device
    lights = Lights(
        everything.directions[index], everything.kernel, everything.irradiance[index], everything.exposure[index]
    ).to(device=device)
    view = torch.tensor(capture.view, dtype=dtype, device=device)
    positions = capture.positions()
    if positions is not None:
        positions = positions[index].to(dtype=dtype, device=device)
    domain = TermDomain.of_source(capture.extra.get("source"))
    return Setup(
        config=config, capture=capture, picked=picked, lights=lights, view=view, positions=positions, domain=domain
    )


def _reduced(config: FitConfig, capture: Capture, picked: list[int]) -> tuple[FitConfig, Capture]:
    """``capture`` read at ``config``'s ``downsample`` and ``crop`` (:func:`torchspec.io.scale.scaled`),
    clipped boxes kept clipped at the settings' level: where neither the settings nor the capture
    give one, the level is found on the picked frames at full size first
    (:func:`torchspec.photometric.saturation_level`, as :func:`~torchspec.photometric.sample_masks`
    finds it; the frames are read twice) and becomes the settings' ``saturation``."""
    scale = Scale(config.downsample, config.crop)
    if scale.identity:
        return config, capture
    scale.region(capture.width, capture.height, f"the frames of {capture.manifest}")  # checked before any reading
    level = config.saturation
    if level is None:
        peaks = [peak_of(capture.read_frames([k], nonfinite="ignore")) for k in picked]
        found = float(saturation_level(peaks))
        level = found if math.isfinite(found) else None
        config = replace(config, saturation=level)
    return config, scaled(capture, scale, level)


CALIBRATION_EXPLAINED = 0.8
"""``FitConfig.calibrate = auto`` keeps calibrated lights only when the Lambertian model of
:mod:`torchspec.lightcal` explains at least this share of the pixels ..."""
CALIBRATION_RMS = 0.05
"""... with a median relative misfit per frame of at most this: on a coin or a relief in cast
shadow, gains and positions take up what the model lacks (``experiments/results/light_calibration.json``)."""
CALIBRATION_LEFT_OUT = 0.01
"""``auto`` also keeps calibrated lights only where they predict frames left out of the Lambertian
maps better than the lights as written, by this share of the misfit
(:func:`torchspec.lightcal.judge.left_out_misfit`; a left-out frame at its nominal intensity)."""
CALIBRATION_GIVE_UP = 1.5
"""``auto`` stops calibrating (:func:`torchspec.lightcal.calibrate_lights`'s ``give_up``) when the
sample's misfit after two steps exceeds :data:`CALIBRATION_RMS` by this factor: the lights would
be refused anyway, and the refinement cost most of a capture's calibration. On the six captures of
``../shared/data/rti`` at half size (``dome=True``, every step run), that misfit was 0.90-1.57
times the converged one that ``auto`` judges (SynthRTI m8: 3.5 % then 2.3 %; realrti-item3: 16.2 %
then 12.6 %; realrti-item7: 8.7 % then 9.7 %), so only a capture converging within 4.8-5 % could be
refused that the whole calibration would keep. At 2.0, item7 ran all ten steps to be refused:
calibrating it at full size took 35-50 s, 14.6 s with this bound."""


CALIBRATION_GIVE_UP_START = 2.0
"""... and before the first step, when the sample's misfit under the start's gains exceeds it by
this factor. On the same six captures the start's misfit was 0.89-1.70 times the converged one
(realrti-item3 21.3 % then 12.6 %, SynthRTI m8 3.7 % then 2.3 %); realrti-item3 and -item9 (44.7 %
then 39.2 %) stop there, saving the two steps' time; no capture converging below 5 % would by those
ratios."""


def calibrated(job: Setup, stack: Tensor, usable: Tensor) -> tuple[Setup, dict | None]:
    """``job`` with its lights calibrated from the photographs (:func:`torchspec.lightcal.calibrate_lights`)
    where ``FitConfig.calibrate`` asks for it, and the record of what was estimated (``None``: nothing).

    ``calibrate``: ``auto`` calibrates what the capture's manifest lists under ``unknown``
    (``irradiance``: a gain per frame and channel; ``position``: near lights' positions), ``gains``
    and ``positions`` force them (``positions`` with gains), ``dome`` estimates gains and one dome
    radius for lights written as directions (:func:`torchspec.lightcal.dome_radius`; distant where
    no radius explains the photographs better), ``none`` takes the lights as written.
    ``auto`` estimates a dome radius as ``dome`` does where it calibrates gains of lights written
    as directions, and keeps the estimate only where the photographs determine it
    (:data:`CALIBRATION_RMS`, :data:`CALIBRATION_EXPLAINED`; else a :class:`FitWarning` and the
    lights as written, at the dome radius if one was found: :func:`_dome_only`).
    Gains multiply the frames' irradiance (normalised to a geometric mean of 1 per channel: the
    capture's overall brightness stays in the diffuse map). ``stack (K, C, H, W)`` are the
    frames, ``usable (K, H, W)`` the samples to calibrate from (not saturated, finite).
    """
    wanted = job.config.calibrate
    unknown = job.capture.unknown
    gains = wanted in ("gains", "positions", "dome") or (wanted == "auto" and bool(unknown))
    near = wanted == "positions" or (wanted == "auto" and "position" in unknown)
    dome = (wanted == "dome" or (wanted == "auto" and not near)) and job.positions is None
    if not gains:
        return job, None
    from ..lightcal import calibrate_lights  # the stage that estimates lights from photographs

    lights = job.lights
    scale = lights.scale.to(stack)  # (K, C or 1)
    start = job.positions / job.positions.norm(dim=-1, keepdim=True) if job.positions is not None else None
    directions = lights.directions if start is None else start
    valid = usable[:, None].expand_as(stack) & stack.isfinite()
    give_up = (CALIBRATION_GIVE_UP_START * CALIBRATION_RMS, CALIBRATION_GIVE_UP * CALIBRATION_RMS)
    give_up = give_up if wanted == "auto" else None
    found = calibrate_lights(
        stack / scale[:, :, None, None], directions.to(stack), valid=valid, near=near, dome=dome, give_up=give_up
    )
    explained, misfit = float(found.explained[found.judged].double().mean()), float(found.rms.double().median())
    if explained < CALIBRATION_EXPLAINED or misfit > CALIBRATION_RMS:
        if wanted == "auto":
            radius = found.radius_as_written
            taken = (
                "taken as written"
                if radius is None
                else (
                    f"taken at the dome radius {radius:g} (image widths) the photographs show, with the irradiance as "
                    "written"
                )
            )
            message = _poorly_determined(job.capture.root, explained, misfit, wanted, taken)
            warnings.warn(message, FitWarning, stacklevel=3)
            refused = {
                "refused": message,
                "explained_share": explained,
                "judged_pixels": int(found.judged.sum()),
                "rms": found.rms.tolist(),
            }
            return (job, {"calibrated": [], **refused}) if radius is None else _dome_only(job, found, refused)
        warnings.warn(_poorly_determined(job.capture.root, explained, misfit, wanted), FitWarning, stacklevel=3)
    if wanted == "auto":  # kept only where it predicts frames left out of the maps better
        judged = _left_out(stack / scale[:, :, None, None], valid, directions, found, job.positions, near or dome)
        if judged["calibrated"] >= (1 - CALIBRATION_LEFT_OUT) * judged["as_written"]:
            message = (
                f"{job.capture.root}: the lights are taken as written, not calibrated from the photographs: the gains "
                f"and positions estimated explain the frames they were fitted on, but predict frames left out of the "
                f"maps no better (median relative misfit {100 * judged['calibrated']:.1f} % against "
                f"{100 * judged['as_written']:.1f} % with the lights as written). Nothing needs doing: the lights as "
                "written serve the fit as well."
            )
            warnings.warn(message, FitWarning, stacklevel=3)
            return job, {"calibrated": [], "refused": message, "left_out_misfit": judged}
    irradiance = lights.irradiance.to(stack) * found.gains
    calibrated_lights = Lights(found.directions.to(stack), lights.kernel, irradiance, lights.exposure.to(stack))
    positions = found.positions.to(stack) if (near or dome) and found.positions is not None else job.positions
    record = {
        "calibrated": ["irradiance", "position"] if near else ["irradiance"] + (["radius"] if found.radius else []),
        "radius": found.radius,
        "radius_misfit": found.radius_misfit,
        "gains": found.gains.tolist(),
        "gain_std": found.gain_std.tolist(),
        "positions": None if found.positions is None else found.positions.tolist(),
        "position_std": None if found.position_std is None else found.position_std.tolist(),
        "explained_share": explained,
        "judged_pixels": int(found.judged.sum()),
        "rms": found.rms.tolist(),
        "iterations": found.iterations,
        "left_out_misfit": judged if wanted == "auto" else None,
    }
    return replace(job, lights=calibrated_lights, positions=positions, gains=found.gains.to(stack)), record


def _left_out(frames: Tensor, valid: Tensor, directions: Tensor, found, positions, moved: bool) -> dict:
    """:func:`torchspec.lightcal.judge.left_out_misfit` of the lights as written and as ``found``
    (its gains, and its positions where ``moved``: near lights or a dome radius)."""
    from ..lightcal.judge import left_out_misfit

    ones = torch.ones_like(found.gains).to(frames)
    written = left_out_misfit(frames, directions, ones, positions=positions, valid=valid)
    new_positions = found.positions.to(frames) if moved and found.positions is not None else positions
    calibrated = left_out_misfit(
        frames, found.directions.to(frames), found.gains.to(frames), positions=new_positions, valid=valid
    )
    return {"as_written": written, "calibrated": calibrated}


def _dome_only(job: Setup, found, refused: dict) -> tuple[Setup, dict]:
    """``auto``'s lights where the gains are refused (``refused``: the warning and its figures) but one
    dome radius explains the photographs better than distant lights with the irradiance as written
    (:func:`torchspec.lightcal.dome_radius`'s choice under the gains given): the lights at that radius
    along their written directions, that irradiance."""
    radius = found.radius_as_written
    positions = radius * job.lights.directions
    record = {"calibrated": ["radius"], "radius": radius, "radius_misfit": found.radius_misfit_as_written, **refused}
    return replace(job, positions=positions), record


def _poorly_determined(
    root: Path, explained: float, misfit: float, wanted: str, taken: str = "taken as written"
) -> str:
    """The warning of lights the photographs determine poorly (below :data:`CALIBRATION_EXPLAINED`
    or above :data:`CALIBRATION_RMS`): the figures, what they mean and what the user can do.
    ``wanted``: ``FitConfig.calibrate`` (``auto``: the lights are ``taken`` otherwise; else they are
    calibrated as asked)."""
    figures = (
        f"under the lights estimated from them, a matte (Lambertian) surface explains {100 * explained:.0f} % of the "
        f"pixels with a median relative misfit of {100 * misfit:.1f} % per frame (calibrating needs at least "
        f"{100 * CALIBRATION_EXPLAINED:.0f} % and at most {100 * CALIBRATION_RMS:.0f} %): the object's gloss, "
        "shadows or relief are more than a matte surface, and estimated gains would take up what it lacks instead "
        "of the lamps' differences"
    )
    if wanted != "auto":
        return (
            f"{root}: the lights are calibrated from the photographs as asked (calibrate: {wanted}), but the "
            f"photographs determine them poorly: {figures}. Compare with a fit with --calibrate none (the lights as "
            "written)."
        )
    return (
        f"{root}: the lights are {taken}, not calibrated from the photographs: {figures}. Nothing needs doing if "
        "every frame was lit alike (the same lamp and setting at the same distance, as in most domes); if the "
        "frames' brightness differs from light to light, pass --calibrate gains to estimate a gain per frame anyway, "
        "and compare the two fits' residuals."
    )
