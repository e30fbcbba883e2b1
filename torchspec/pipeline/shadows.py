"""Cast shadows in the fit (``FitConfig.shadows``): a height field integrated from the fitted
normals, each light's visibility over it, and the maps refitted with that visibility fixed.

A relief (a coin, impasto, a carving) shadows itself under grazing lights. Without a visibility a
shadowed sample is either masked (too dark: :func:`torchspec.start.photometric.sample_masks`) or explained
by wrong maps, and a left-out grazing light cannot be predicted. With a fixed visibility
``V (K, H, W)`` in ``(0, 1]`` the per-pixel fit is today's on ``y / V`` with each sample's weight
times ``V`` (:class:`~torchspec.pipeline.samples.TileSamples`, :func:`~torchspec.pipeline.tile.seen_through`):
the residual ``w (V r - y)`` is ``(w V) (r - y / V)``, so the models and the renderer are unchanged.

The alternation (:func:`fit_with_shadows`), judged by left-out frames as the models are:

1. every fifth of the fit's frames (``i % 5 == 2``, :data:`LEFT_OUT`) is left out; the rest are
   fitted without shadows, and the left-out frames predicted (the physical maps, rendered as the
   fit lights its pixels, :func:`predict_frames`);
2. the height is integrated from the normals (:func:`torchspec.model.height.height_from_normals`, each
   normal weighted by ``1 / std_normal^2``: :func:`height_of`), the visibility of every frame
   computed over it (:func:`visibility_of`: :func:`torchspec.model.visibility.kernel_visibility` for
   distant lights, a direction per pixel for near ones);
3. the same frames are fitted with that visibility fixed and the left-out frames predicted times
   their visibility; where that predicts better than the best so far by more than the noise would
   make it (:func:`torchspec.statistics.predicts_better` with ``FitConfig.ladder.predict_z``, the whole
   image as one pixel, every left-out sample in the statistic, the shadowed ones too), the height
   is integrated again from the new normals and the next round begins (at most :data:`ROUNDS`);
4. all frames are fitted, with the visibility of the best height if any round predicted better
   (its height is the fit's ``height``, written as ``height.exr``), else without: today's fit.

``auto`` tries this on captures imported from photographs (``source`` in ``capture.json``) and
where the photographs hold shadows: at least :data:`SHADOW_SHARE` of the usable samples masked as
shadows (:func:`shadows_tried`; a simulated flat painting has none and keeps today's fit and
speed); and stops before the first refit where the first height hides fewer than
:data:`SHADOWED_SHARE` of the samples (the cost is then one fit of four fifths of the frames).
``on`` skips both gates (the judge still decides). Cost where refitted: two to ``ROUNDS + 1`` fits
of four fifths of the frames, then the fit.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from ..model.height import height_from_normals
from ..model.registry import render_chosen
from ..model.rendering import TILE_PIXELS
from ..model.visibility import frame_visibility
from ..statistics import predicts_better
from .records import StackRun
from .result import Fit
from .settings import FitConfig
from .start import light_context
from .tiling import tiling_of

__all__ = [
    "LEFT_OUT",
    "MIN_FRAMES",
    "ROUNDS",
    "SHADOWED_SHARE",
    "SHADOW_SHARE",
    "fit_with_shadows",
    "height_of",
    "predict_frames",
    "shadow_share",
    "shadows_tried",
    "visibility_of",
]

SHADOW_SHARE = 0.005
"""``auto`` tries shadows where at least this share of the usable samples (finite, not saturated)
is masked as a shadow (below ``FitConfig.masks.shadow`` of its pixel's median)."""
SHADOWED_SHARE = 0.002
"""``auto`` refits with a visibility only where the first height hides (``V < 0.5``) at least this
share of the samples."""
ROUNDS = 2
"""The most refits with a visibility (each from the previous round's height)."""
MIN_FRAMES = 20
"""``auto`` tries shadows only on at least this many frames (a fit of four fifths of fewer frames
may not resolve a lobe, and few lights show little of a relief's shadows)."""
LEFT_OUT = 5
"""Every ``LEFT_OUT``-th frame (``i % LEFT_OUT == 2``) judges the shadows."""


def shadow_share(masks) -> float:
    """The share of the usable samples (finite, not saturated) that ``masks``
    (:class:`torchspec.start.photometric.Masks`) mark as shadows (one host sync)."""
    usable = ~(masks.nonfinite | masks.saturated)
    return float((masks.shadowed & usable).sum()) / max(int(usable.sum()), 1)


def shadows_tried(config: FitConfig, masks, imported: bool = False) -> bool:
    """Whether the fit tries cast shadows: ``FitConfig.shadows`` ``on``, or ``auto`` on a capture
    ``imported`` from photographs (an RTI capture: reliefs, coins; their shadows are rarely dark
    enough to be masked) or where :func:`shadow_share` of ``masks``
    (:class:`torchspec.start.photometric.Masks`) reaches :data:`SHADOW_SHARE` (one host sync); on at
    least :data:`MIN_FRAMES` frames."""
    if config.shadows == "off":
        return False
    if config.shadows == "on":
        return True
    return masks.shadowed.shape[0] >= MIN_FRAMES and (imported or shadow_share(masks) >= SHADOW_SHARE)


def height_of(fit: Fit) -> Tensor:
    """``(H, W)`` the height (pixels, float64) of ``fit``'s normals, each weighted by ``1 /
    std_normal^2`` (an undetermined normal: 0; the weights capped at 100 times their median, so a
    few over-confident pixels do not pin the surface)."""
    normal = fit.svbrdf.normal.double()
    std = fit.std["normal"].double()
    weight = torch.where(std.isfinite() & (std > 0), 1.0 / std.square().clamp(min=1e-30), torch.zeros_like(std))
    positive = weight[weight > 0]
    if positive.numel() == 0:
        return height_from_normals(normal)
    weight = weight.clamp(max=100.0 * float(positive.median()))
    return height_from_normals(normal, weight, tol=1e-4)  # the heights to 1e-4 of their scale: enough for shadows


def visibility_of(height: Tensor, run: StackRun) -> Tensor:
    """``(K, H, W)`` the visibility of ``run``'s frames over ``height (H, W)`` (pixels), in the
    frames' dtype (:func:`torchspec.model.visibility.frame_visibility`)."""
    seen = frame_visibility(height, run.job.lights, run.job.positions)
    return seen.permute(2, 0, 1).to(run.stack)


def predict_frames(fit: Fit, run: StackRun, seen: Tensor | None = None) -> Tensor:
    """``(K, C, H, W)`` ``fit``'s physical maps rendered under ``run``'s frames as the fit lights
    its pixels (near lights: as seen from each block's centre), each pixel with its model's lobe
    (:func:`torchspec.model.registry.render_chosen`), times ``seen (K, H, W)`` when given."""
    job = run.job
    k, c, h, w = run.stack.shape
    svbrdf = fit.svbrdf.to(run.stack.dtype).flatten()
    code = fit.model.reshape(-1).to(run.stack.device)
    lights, ctx = job.lights, light_context(job.lights)
    tiling = tiling_of(h, w, TILE_PIXELS, job.positions)
    out = run.stack.new_empty((h * w, k, c))
    order = torch.arange(h * w, device=run.stack.device) if tiling.order is None else tiling.order
    for first, stop in tiling.ranges:
        index = order[first:stop].to(run.stack.device)
        tile_lights, _ = tiling.lights(lights, ctx, first, stop)
        out[index] = render_chosen(svbrdf[index], code[index], tile_lights, job.view)
    out = out.permute(1, 2, 0).reshape(k, c, h, w)
    return out if seen is None else out * seen[:, None]


def _errors(predicted: Tensor, run: StackRun, noise: tuple[float, float], floor: float) -> Tensor:
    """``(1, 1, N, 1)`` the left-out samples' residuals in noise units (every finite, unsaturated
    sample: shadowed ones too), the sensor's ``sqrt(a y + b)`` floored at ``floor`` times the
    pixel's mean value; the whole image as one pixel of :func:`torchspec.statistics.predicts_better`."""
    y = run.stack
    usable = ~(run.masks.nonfinite | run.masks.saturated)[:, None].expand_as(y)
    clean = torch.where(usable, y, torch.zeros_like(y))
    level = clean.sum((0, 1)) / usable.sum((0, 1)).clamp(min=1)  # (H, W)
    sigma = (noise[0] * clean.clamp(min=0) + noise[1]).clamp(min=0).sqrt()
    sigma = torch.maximum(sigma, floor * level).clamp(min=torch.finfo(y.dtype).tiny)
    return ((predicted - clean) / sigma)[usable].reshape(1, 1, -1, 1)


def _noise(fit: Fit) -> tuple[float, float]:
    """The sensor's noise ``(a, b)`` of ``fit``, its tiles' mean."""
    found = fit.stats.get("sensor_noise") or {}
    a, b = found.get("a") or [0.0], found.get("b") or [0.0]
    return sum(a) / len(a), sum(b) / len(b)


def fit_with_shadows(
    run: StackRun,
    fit_stack: Callable[..., Fit],
    *,
    folder=None,
    resume: bool = False,
    progress: bool = False,
) -> Fit:
    """The alternation of the module's docstring on ``run``'s frames; ``fit_stack(run, visibility=,
    folder=, resume=, progress=)`` fits the tiles once (:func:`torchspec.pipeline.in_process.fit_stack`).
    The result's ``height`` is the height its visibility came from (``None`` where shadows did not
    predict better) and ``stats["shadows"]`` records the rounds: each one's left-out RMS residual in
    noise units, the share of samples it hid, and whether it predicted better."""
    clock = time.perf_counter()
    config = run.job.config
    k = run.stack.shape[0]
    test = [i for i in range(k) if i % LEFT_OUT == 2]
    train = [i for i in range(k) if i % LEFT_OUT != 2]
    record = {"tried": True, "used": False, "left_out": [run.job.picked[i] for i in test], "rounds": []}
    best_height = None
    if len(train) >= 4 and test:
        fitted, judged = run.frames(train), run.frames(test)
        plain = fit_stack(fitted)
        noise, floor = _noise(plain), config.start.noise_floor
        best = _errors(predict_frames(plain, judged), judged, noise, floor)
        record["plain_rms"] = float(best.square().mean().sqrt())
        height = height_of(plain)
        for round_ in range(ROUNDS):
            seen = visibility_of(height.to(run.stack.device), fitted)
            hidden = float((seen < 0.5).double().mean())
            if round_ == 0 and config.shadows == "auto" and hidden < SHADOWED_SHARE:
                record["rounds"].append({"hidden_share": hidden, "refitted": False})
                break
            candidate = fit_stack(fitted, visibility=seen)
            errors = _errors(
                predict_frames(candidate, judged, visibility_of(height.to(run.stack.device), judged)),
                judged,
                noise,
                floor,
            )
            better = bool(predicts_better(errors, best, config.ladder.predict_z)[0])
            rms = float(errors.square().mean().sqrt())
            record["rounds"].append({"hidden_share": hidden, "refitted": True, "rms": rms, "better": better})
            if not better:
                break
            best, best_height = errors, height
            height = height_of(candidate)
    judging = time.perf_counter() - clock
    seen = None if best_height is None else visibility_of(best_height.to(run.stack.device), run)
    final = fit_stack(run, visibility=seen, folder=folder, resume=resume, progress=progress)
    record["used"] = best_height is not None
    record["seconds"] = judging
    stats = dict(final.stats)
    stats["shadows"] = record
    stats["seconds"] = {**stats["seconds"], "shadows": judging}
    if best_height is not None:
        stats["height"] = {"unit": "pixel", "pitch": 1.0}
    height = None if best_height is None else best_height.to(final.svbrdf.normal)
    return replace(final, stats=stats, height=height)
