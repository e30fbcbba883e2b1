"""Lights judged by what they predict: each frame left out of the Lambertian maps in turn and
predicted from the others, at its light as written or as calibrated.

A calibration that only explains the frames it was fitted on (a gain taking up a cast shadow, a
dome radius bending the shading to a relief) is no better at predicting a frame it did not see.
:func:`left_out_misfit` measures that: the frames are split into folds (frame ``k`` in fold
``k % folds``); for each fold, robust photometric stereo of a sample of pixels on the other folds'
frames (:mod:`torchspec.calibration.lights`'s ``_stereo``), then the fold's frames predicted at their nominal
intensity (gain 1: a frame's own gain is what cannot be known without it) under the lights'
positions or directions. The misfit of a frame is the median over its lit, valid samples of
``|I - prediction| / prediction`` (robust to highlights and cast shadows), and the capture's the
median over its frames.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ...model.near_lights import image_points
from ._solve import _Design, _gather, _lighting, _sample, _stereo

__all__ = ["left_out_misfit"]


def left_out_misfit(
    frames: Tensor,
    directions: Tensor,
    gains: Tensor,
    *,
    positions: Tensor | None = None,
    valid: Tensor | None = None,
    sample: int = 2048,
    folds: int = 5,
    shadow: float = 0.1,
    cut: float = 3.0,
) -> float:
    """The median relative misfit of each frame predicted from the others (module docstring).

    Args:
        frames: ``(K, C, H, W)`` linear values, the exposure divided out.
        directions: ``(K, 3)`` unit directions towards the lights (for near lights, at the centre).
        gains: ``(K, C)`` the lights' gains (ones: as written); a left-out frame is predicted at 1.
        positions: ``(K, 3)`` near lights' positions (image widths, :mod:`torchspec.model.near_lights`),
            ``None`` for distant lights.
        valid: ``(K, C, H, W)`` bool, the samples to use (default: the finite ones).
        sample: pixels used (a fixed random subset; all when fewer).
        folds: folds of the frames.
        shadow, cut: as :func:`torchspec.calibration.lights.calibrate_lights`'s.
    """
    k, c, h, w = frames.shape
    index = _sample(h * w, sample, frames.device, seed=1)
    values, ok = _gather(frames, valid, index, torch.float64)
    points = image_points(h, w, dtype=torch.float64, device=frames.device).reshape(-1, 3)[index]
    unit, vector = _lighting(
        points, directions.to(torch.float64), None if positions is None else positions.to(torch.float64)
    )
    fold = torch.arange(k, device=frames.device) % folds
    error = torch.full((k,), torch.nan, dtype=torch.float64, device=frames.device)
    for f in range(min(folds, k)):
        held = fold == f
        design = _Design.of(vector, torch.where(held[:, None], 1.0, gains.to(torch.float64)))
        b = _stereo(values, ok & ~held[None, :, None], unit, design, shadow=shadow, cut=cut, shift=False).b
        normal = b / b.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        lit = ok & (unit @ normal.transpose(1, 2) > shadow) & held[None, :, None]
        pred = design.predict(b)
        relative = torch.where(lit & (pred > 0), (values - pred).abs() / pred.clamp_min(1e-300), torch.nan)
        error = torch.where(held, relative.flatten(start_dim=2).transpose(0, 1).flatten(1).nanmedian(1).values, error)
    return float(error.nanmedian())
