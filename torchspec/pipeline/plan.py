"""What every driver of a fit starts from: the settings, capture, frames, lights and view
(:func:`setup`, a :class:`Setup`), and the tiling (:func:`plan`): from the capture's size and the
settings only, so that every driver tiles a fit alike (the same maps, and either resumes the
other's checkpoint); the device (:func:`device_of`) and the pixels per tile (:func:`tile_size`).

Whether and what a fit calibrates of its lights from the photographs is the policy of
:mod:`~torchspec.pipeline.calibration`; its names (:func:`calibrated`, the ``CALIBRATION_*``
constants) are re-exported here for one release, and :class:`Setup` and :class:`FitWarning` (which
it shares) live in :mod:`~torchspec.pipeline.records`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import replace
from pathlib import Path

import torch

from ..errors import TorchspecError
from ..io import Capture, read_capture
from ..io.scale import Scale, scaled
from ..model.layout import coverage_warning, fit_problem
from ..model.lights import Lights
from ..model.registry import get_model
from ..model.residual_term import TermDomain
from ..start.photometric import peak_of, saturation_level
from .calibration import (
    CALIBRATION_EXPLAINED,
    CALIBRATION_GIVE_UP,
    CALIBRATION_GIVE_UP_START,
    CALIBRATION_LEFT_OUT,
    CALIBRATION_RMS,
    calibrated,
)
from .records import FitWarning, Setup
from .settings import AUTO, COMPILE_PIXELS, FitConfig, select_frames

__all__ = [
    "CALIBRATION_EXPLAINED",
    "CALIBRATION_GIVE_UP",
    "CALIBRATION_GIVE_UP_START",
    "CALIBRATION_LEFT_OUT",
    "CALIBRATION_RMS",
    "GPU_SHARE",
    "MIN_TILE",
    "RUNTIME_BYTES",
    "TERM_FOR_PHOTOGRAPHS",
    "TILES",
    "FitWarning",
    "Setup",
    "calibrated",
    "device_of",
    "frame_warnings",
    "plan",
    "setup",
    "tile_size",
]

TERM_FOR_PHOTOGRAPHS = 3
"""``FitConfig.term.order = auto``'s order for a capture imported from photographs (its manifest's
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


def frame_warnings(capture: Capture, picked: list[int]) -> list[str]:
    """What the frames ``picked`` of ``capture`` let a fit do only poorly (known before it starts):
    :func:`torchspec.model.layout.coverage_warning`."""
    if len(picked) < 3:
        return []
    l = capture.directions()[torch.tensor(picked)][:, :2]  # on the CPU: the capture's manifest, checked once
    found = coverage_warning(l, torch.tensor(capture.view, dtype=l.dtype, device=l.device))
    return [f"{capture.root}: {found}"] if found else []


def device_of(name: str | torch.device) -> torch.device:
    """The device of ``FitConfig.compute.device`` (or ``--device``): ``auto`` is CUDA when present, else the
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
    """Pixels per tile: ``config.compute.tile``, or what fits in ``budget`` bytes (default ``memory_gib``)
    after ``reserved`` bytes (the stack and its masks) and :data:`RUNTIME_BYTES` (at least 256, at
    most 131072 within ``memory_gib``; a larger ``budget``, a GPU's, lifts that cap)."""
    if config.compute.tile:
        return config.compute.tile
    p = max(get_model(name).size(channels) for name in (config.ladder_climbed or (config.model,)))  # diffuse: its own
    # Per pixel: observations, weights, values, residuals and the Jacobian twice (the full columns and
    # the model's), J^T J, plus the photometric and specular stages' (N, K) work arrays; twice that
    # for transients (a conservative bound: the solver takes normal equations from Jacobian chunks).
    per_pixel = itemsize * frames * (channels * (2 * p + 8) + 16) + itemsize * 4 * p * p
    given = config.compute.memory_gib * 2**30 if budget is None else budget
    available = given - reserved - RUNTIME_BYTES
    fits = available / (2 * per_pixel)
    return int(max(256, fits if budget is not None else min(1 << 17, fits)))


def plan(
    config: FitConfig, k: int, c: int, h: int, w: int, itemsize: int, device: torch.device | None = None
) -> tuple[FitConfig, int]:
    """The settings with ``compile`` decided and the pixels per tile of a fit of a ``(K, C, H, W)``
    stack of ``itemsize``-byte values on ``device`` (default the CPU): ``FitConfig.compute.tile``, or what
    the memory allows (:func:`tile_size`). On the CPU the budget is ``memory_gib`` and the image is
    also cut into at least :data:`TILES` tiles (of at least :data:`MIN_TILE` pixels: progress,
    resumption, threads). On a GPU the budget is :data:`GPU_SHARE` of its free memory (the stack
    lives there too), and a tile may hold the whole image: a GPU is fed best by large batches."""
    if config.quadrature.compile is None:
        config = replace(config, quadrature=replace(config.quadrature, compile=h * w >= COMPILE_PIXELS))
    reserved = (k * c * itemsize + 3 * k) * h * w  # the stack, three bool masks
    gpu = device is not None and device.type == "cuda"
    budget = GPU_SHARE * torch.cuda.mem_get_info(device)[0] if gpu and not config.compute.tile else None
    tile = tile_size(config, k, c, itemsize, reserved, budget)
    if not config.compute.tile and not gpu:  # sized by memory: also cut into TILES tiles of at least MIN_TILE pixels
        tile = min(tile, max(MIN_TILE, -(-h * w // TILES)))
    return config, min(tile, h * w) if gpu else tile


def setup(capture: Capture | str | Path, config: FitConfig | None, frames: str | list[int] | None) -> Setup:
    """The :class:`Setup` of a fit of ``capture`` (or its folder) with ``config`` (the defaults
    if ``None``) on ``frames`` (a SPEC of :func:`~torchspec.pipeline.settings.select_frames`, or indices).

    Warns:
        FitWarning: :func:`frame_warnings`.

    Raises:
        TorchspecError: frames a fit cannot use (:func:`torchspec.model.layout.fit_problem`: fewer than 4,
            or too few along an axis for a lobe); CaptureError: an unreadable capture or light.
    """
    config = config or FitConfig()
    capture = capture if isinstance(capture, Capture) else read_capture(capture)
    if config.masks.saturation is None and capture.saturation is not None:  # the level an imported capture records
        config = replace(config, masks=replace(config.masks, saturation=capture.saturation))
    if config.term.order == AUTO:  # photographs: the term carries what the physics misses, where it predicts
        order = TERM_FOR_PHOTOGRAPHS if capture.extra.get("source") else 0
        config = replace(config, term=replace(config.term, order=order))
    picked = frames if isinstance(frames, list) else select_frames(frames, len(capture.frames))
    config, capture = _reduced(config, capture, picked)
    l = capture.directions()[torch.tensor(picked, dtype=torch.long)][:, :2]  # on the CPU: the manifest, checked once
    problem = fit_problem(l, lobe=config.lobes)
    if problem is not None:
        raise TorchspecError(f"{capture.root}: the frames cannot be fitted: {problem}")
    for message in frame_warnings(capture, picked):
        warnings.warn(message, FitWarning, stacklevel=3)
    dtype = getattr(torch, config.compute.dtype)
    device = device_of(config.compute.device)
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
    (:func:`torchspec.start.photometric.saturation_level`, as :func:`~torchspec.start.photometric.sample_masks`
    finds it; the frames are read twice) and becomes the settings' ``saturation``."""
    scale = Scale(config.masks.downsample, config.masks.crop)
    if scale.identity:
        return config, capture
    scale.region(capture.width, capture.height, f"the frames of {capture.manifest}")  # checked before any reading
    level = config.masks.saturation
    if level is None:
        peaks = [peak_of(capture.read_frames([k], nonfinite="ignore")) for k in picked]
        found = float(saturation_level(peaks))
        level = found if math.isfinite(found) else None
        config = replace(config, masks=replace(config.masks, saturation=level))
    return config, scaled(capture, scale, level)
