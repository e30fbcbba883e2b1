"""Camera responses judged by the physical model: which curve lets ``torchspec fit`` predict
photographs it was not fitted to.

:func:`torchspec.calibration.response.estimate_response` chooses a curve with a Lambertian model; where the
photographs hold what that model lacks (a glossy lobe on every pixel, a sheen, cast shadows), a
curve can take it up, and on some captures it bends the curve towards what the Lambertian model
misses. :func:`judge_curves` settles between candidate curves (the estimate from every sample,
the estimate without the samples near a highlight, sRGB) with the fit itself: the centre of the
image (``size`` x ``size`` pixels) decoded by each, fitted (``auto``, the lights as written, no
residual term) on every frame but each fifth (``i % 5 == 2``), the left-out frames rendered,
encoded by the same curve, rounded to the photographs' 8 bits and compared with them. The curve
whose prediction is closest (PSNR over the crop's codes) is kept.
"""

from __future__ import annotations

import math
import tempfile
import warnings
from pathlib import Path

import torch
from torch import Tensor

from ..io.capture import Capture, Frame, LightSpec, write_capture
from ..io.images import Transfer

__all__ = ["JUDGE_SIZE", "judge_curves"]

JUDGE_SIZE = 48
"""The side of the image's central crop the candidate curves are judged on (pixels)."""


def _crop(codes: Tensor, size: int) -> Tensor:
    h, w = codes.shape[-2:]
    top, left = max(0, (h - size) // 2), max(0, (w - size) // 2)
    return codes[..., top : top + size, left : left + size]


def judge_curves(
    codes: Tensor, directions: Tensor, candidates: dict[str, Transfer], *, size: int = JUDGE_SIZE, left_out: int = 2
) -> dict[str, float]:
    """Each candidate transfer's PSNR (dB, codes in ``[0, 1]``, peak 1) of the left-out frames of
    ``codes (K, C, H, W)`` (encoded values) under distant lights ``directions (K, 3)``, predicted
    by the default fit of the other frames decoded by it (module docstring). Needs ``K >= 10``."""
    from ..model.rendering import render_image
    from ..pipeline import FitConfig, QuadratureConfig, TermConfig, fit  # the stage that fits: imported where it judges

    crop = _crop(codes, size).to(torch.float64)
    k, c, h, w = crop.shape
    fitted = [i for i in range(k) if i % 5 != left_out]
    predicted = [i for i in range(k) if i % 5 == left_out]
    view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=crop.device)
    frames = tuple(
        Frame(
            file=f"frames/{i:04d}.exr", direction=tuple(float(x) for x in directions[i]), irradiance=1.0, exposure=1.0
        )
        for i in range(k)
    )
    scores = {}
    plain = FitConfig(
        calibrate="none", shadows="off", term=TermConfig(order=0), quadrature=QuadratureConfig(compile=False)
    )
    with tempfile.TemporaryDirectory(prefix="torchspec-judge-") as scratch:
        for name, transfer in candidates.items():
            linear = transfer.decode(crop.movedim(1, -1)).movedim(-1, 1)
            root = Path(scratch) / f"c{len(scores)}"
            capture = Capture(
                root=root,
                width=w,
                height=h,
                channels=("Y",) if c == 1 else ("R", "G", "B"),
                view=(0.0, 0.0, 1.0),
                light=LightSpec(kernel="point"),
                frames=frames,
                extra={"source": {"saturation": 1.0}},
            )
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                capture = write_capture(root, capture, linear.float())
                result = fit(capture, config=plain, frames=fitted)
            lights = capture.lights(dtype=torch.float64)[predicted].to(device=crop.device)
            maps = result.svbrdf.to(dtype=torch.float64, device=crop.device)  # where the codes are
            values = render_image(maps, lights, view).permute(2, 3, 0, 1)  # (K', C, H, W)
            encoded = transfer.encode(values.clamp(0, 1).movedim(1, -1)).movedim(-1, 1)
            mse = float(((encoded * 255).round() / 255 - crop[predicted]).pow(2).nanmean())
            scores[name] = math.inf if mse == 0 else 10 * math.log10(1 / mse)
    return scores
