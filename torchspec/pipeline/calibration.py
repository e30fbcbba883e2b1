"""The light-calibration policy of a fit: whether and what it estimates of its lights from the
photographs (:mod:`torchspec.calibration.lights`) before the tiles are fitted, and when it refuses an
estimate (:func:`calibrated`; its record becomes ``stats["lights"]``).

``FitConfig.calibrate`` (``--calibrate``):

- ``none``: the lights as written; nothing is estimated.
- ``gains``: a gain per frame and channel (multiplying the frames' irradiance, normalised to a
  geometric mean of 1 per channel, so that the capture's overall brightness stays in the diffuse
  map); the lights' directions or positions as written.
- ``positions``: gains and the near lights' positions.
- ``dome``: gains and, for lights written as directions, one dome radius
  (:func:`torchspec.calibration.lights.dome_radius`; the lights stay distant where no radius explains the
  photographs better).
- ``auto`` (the default): what the capture's manifest lists under ``unknown``, nothing where it
  lists nothing (:func:`calibrates`): ``irradiance`` gains, with a dome radius as ``dome`` estimates
  one for lights written as directions; ``position`` gains and near lights' positions.

An estimate is only as good as the Lambertian model it is fitted under: on a glossy object, a coin
or a relief in cast shadow, gains and positions take up what that model lacks instead of the
lamps' differences (``experiments/results/light_calibration.json``). So the photographs determine
the lights poorly where that model explains less than :data:`CALIBRATION_EXPLAINED` of the pixels
or leaves a median relative misfit per frame above :data:`CALIBRATION_RMS`. Asked for by name
(``gains``, ``positions``, ``dome``), such an estimate is kept with a :class:`FitWarning`; under
``auto`` it is refused with one, and the lights are taken as written (at the dome radius the
photographs show with the irradiance as written, where one explains them better than distant
lights). ``auto`` stops calibrating early where the misfit shows the estimate would be refused
(:data:`CALIBRATION_GIVE_UP_START`, :data:`CALIBRATION_GIVE_UP`), and keeps an estimate only where
it also predicts frames left out of the Lambertian maps better than the lights as written, by
:data:`CALIBRATION_LEFT_OUT` of the misfit (else refused with a :class:`FitWarning`: the lights as
written serve the fit as well).
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from pathlib import Path

import torch
from torch import Tensor

from ..model.lights import Lights
from .records import FitWarning, Setup

__all__ = [
    "CALIBRATION_EXPLAINED",
    "CALIBRATION_GIVE_UP",
    "CALIBRATION_GIVE_UP_START",
    "CALIBRATION_LEFT_OUT",
    "CALIBRATION_RMS",
    "calibrated",
    "calibrates",
]

CALIBRATION_EXPLAINED = 0.8
"""``FitConfig.calibrate = auto`` keeps calibrated lights only when the Lambertian model of
:mod:`torchspec.calibration.lights` explains at least this share of the pixels ..."""
CALIBRATION_RMS = 0.05
"""... with a median relative misfit per frame of at most this: on a coin or a relief in cast
shadow, gains and positions take up what the model lacks (``experiments/results/light_calibration.json``)."""
CALIBRATION_LEFT_OUT = 0.01
"""``auto`` also keeps calibrated lights only where they predict frames left out of the Lambertian
maps better than the lights as written, by this share of the misfit
(:func:`torchspec.calibration.lights.judge.left_out_misfit`; a left-out frame at its nominal intensity)."""
CALIBRATION_GIVE_UP = 1.5
"""``auto`` stops calibrating (:func:`torchspec.calibration.lights.calibrate_lights`'s ``give_up``) when the
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


def calibrates(calibrate: str, unknown) -> bool:
    """Whether ``FitConfig.calibrate`` (``calibrate``) estimates anything of the lights of a capture
    whose manifest lists ``unknown`` (:attr:`torchspec.io.Capture.unknown`): ``gains``,
    ``positions`` and ``dome`` always, ``auto`` where ``unknown`` lists something, ``none`` never."""
    return calibrate in ("gains", "positions", "dome") or (calibrate == "auto" and bool(unknown))


def calibrated(job: Setup, stack: Tensor, usable: Tensor) -> tuple[Setup, dict | None]:
    """``job`` with its lights calibrated from the photographs (:func:`torchspec.calibration.lights.calibrate_lights`)
    where ``FitConfig.calibrate`` asks for it, and the record of what was estimated (``None``: nothing).

    ``calibrate``: ``auto`` calibrates what the capture's manifest lists under ``unknown``
    (``irradiance``: a gain per frame and channel; ``position``: near lights' positions), ``gains``
    and ``positions`` force them (``positions`` with gains), ``dome`` estimates gains and one dome
    radius for lights written as directions (:func:`torchspec.calibration.lights.dome_radius`; distant where
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
    gains = calibrates(wanted, unknown)
    near = wanted == "positions" or (wanted == "auto" and "position" in unknown)
    dome = (wanted == "dome" or (wanted == "auto" and not near)) and job.positions is None
    if not gains:
        return job, None
    from ..calibration.lights import calibrate_lights  # the stage that estimates lights from photographs

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
    """:func:`torchspec.calibration.lights.judge.left_out_misfit` of the lights as written and as ``found``
    (its gains, and its positions where ``moved``: near lights or a dome radius)."""
    from ..calibration.lights.judge import left_out_misfit

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
    (:func:`torchspec.calibration.lights.dome_radius`'s choice under the gains given): the lights at that radius
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
