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
3. the same frames are fitted with that visibility fixed (from the second round on, less the
   indirect light of the previous round's maps: :mod:`torchspec.model.indirect`), the indirect share
   of the new maps fitted (:func:`indirect_of`), and the left-out frames predicted times their
   visibility (each penumbra width of :data:`SOFTNESSES_DEG` over the height scaled by each of
   :data:`DEPTHS`, all from one horizon: :func:`torchspec.model.visibility.frame_visibilities`;
   the best pair kept) plus their indirect
   light (kept where it predicts better than none); where that predicts better than the best so
   far by more than the noise would make it (:func:`torchspec.statistics.predicts_better` with
   ``FitConfig.ladder.predict_z``, the whole image as one pixel, every left-out sample in the
   statistic, the shadowed ones too; predictions clipped to the brightest value recorded), the height
   is integrated again from the new normals (and refitted at the depth chosen) and the next round
   begins (at most :data:`ROUNDS`);
4. all frames are fitted, with the visibility of the best height and less the best round's
   indirect light if any round predicted better (its height, at its depth, is the fit's ``height``,
   written as ``height.exr``; the final maps' indirect share is ``indirect``, ``indirect.exr``), else
   without: today's fit.

``auto`` tries this on captures imported from photographs (``source`` in ``capture.json``) and
where the photographs hold shadows: at least :data:`SHADOW_SHARE` of the usable samples masked as
shadows (:func:`shadows_tried`; a simulated flat painting has none and keeps today's fit and
speed); and stops before the first refit where the first height hides fewer than
:data:`SHADOWED_SHARE` of the samples (the cost is then one fit of four fifths of the frames).
``on`` skips both gates (the judge still decides). Cost where refitted: two to ``ROUNDS + 1`` fits
of four fifths of the frames, then the fit.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..model.brdf import SVBRDF
from ..model.height import height_from_normals
from ..model.indirect import bound, flat_maps, indirect_share
from ..model.registry import render_chosen
from ..model.rendering import TILE_PIXELS
from ..model.visibility import SOFTNESS, frame_visibilities, frame_visibility, sky_view
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
    "SOFTNESSES_DEG",
    "DEPTHS",
    "fit_with_shadows",
    "flat_frames",
    "height_of",
    "indirect_of",
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
SOFTNESSES_DEG = (1.0, 2.0)
"""The penumbra widths (degrees of elevation, :func:`torchspec.model.visibility.visibility`'s
``softness``) each round tries on the left-out frames: a shadow's edge is soft by the light's size
and the height's own error. Not wider: the sigmoid's 10-90 % ramp is 4.4 softnesses, so at 4
degrees a light 8 degrees above a flat horizon is dimmed by an eighth (a flat painting under
grazing lights then loses lit samples to the fit's ``VISIBLE`` cut)."""
DEPTHS = (1.0, 1.25, 1.5, 2.0)
"""The scales of the integrated height (the relief's depth) each round tries on the left-out frames
with each penumbra: a pixel that averages a steep wall has a normal flatter than its mean slope
(the mean of unit normals, renormalised), so the height integrated from the normals of a
reduced or sharp relief underestimates its steps and its shadows fall short. With the true
normals of SynthRTI's object3 reduced 4 x 4, Lambert times the visibility plus the indirect light
predicts the Test lights best at a depth of 1.25, and worse at 1 and 2 than at 1.5
(``python experiments/shadow_depth.py``)."""
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
    usable = masks.usable
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


def visibility_of(height: Tensor, run: StackRun, softness: float = SOFTNESS) -> Tensor:
    """``(K, H, W)`` the visibility of ``run``'s frames over ``height (H, W)`` (pixels), in the
    frames' dtype, with the penumbra ``softness`` (radians;
    :func:`torchspec.model.visibility.frame_visibility`)."""
    seen = frame_visibility(height, run.job.lights, run.job.positions, softness=softness)
    return seen.permute(2, 0, 1).to(run.stack)


def predict_frames(fit: Fit, run: StackRun, seen: Tensor | None = None) -> Tensor:
    """``(K, C, H, W)`` ``fit``'s physical maps rendered under ``run``'s frames as the fit lights
    its pixels (near lights: as seen from each block's centre), each pixel with its model's lobe
    (:func:`torchspec.model.registry.render_chosen`), times ``seen (K, H, W)`` when given."""
    direct = _render(fit.svbrdf, fit.model, run)
    return direct if seen is None else direct * seen[:, None]


def flat_frames(fit: Fit, run: StackRun) -> Tensor:
    """``(K, C, H, W)`` the flat diffuse ``D`` of ``fit``'s maps under ``run``'s frames
    (:func:`torchspec.model.indirect.flat_maps`), lit as :func:`predict_frames` lights them."""
    return _render(flat_maps(fit.svbrdf), None, run)


def indirect_of(fit: Fit, run: StackRun, seen: Tensor, sky: Tensor) -> Tensor:
    """``(H, W)`` the indirect share of ``fit``'s maps on ``run``'s frames under their visibility
    ``seen (K, H, W)`` (:func:`torchspec.model.indirect.indirect_share` of the usable samples:
    finite, not saturated, the shadowed ones too: they hold most of it), at most
    :func:`torchspec.model.indirect.bound` of the pixels' ``sky (H, W)``
    (:func:`torchspec.model.visibility.sky_view`)."""
    usable = run.masks.usable
    y = torch.where(usable[:, None], run.stack, torch.zeros_like(run.stack))
    residual = y - predict_frames(fit, run, seen)
    return indirect_share(residual, flat_frames(fit, run), usable, bound(sky.to(y)))


def _without(run: StackRun, fit: Fit, share: Tensor) -> StackRun:
    """``run`` with the indirect light of ``fit``'s maps and ``share (H, W)`` taken from its frames:
    what the maps times the visibility are to explain."""
    return replace(run, stack=run.stack - share.to(run.stack) * flat_frames(fit, run))


def _render(svbrdf: SVBRDF, model: Tensor | None, run: StackRun) -> Tensor:
    """``(K, C, H, W)`` maps ``svbrdf (H, W)`` (each pixel's model code ``model``, ``None``: Ward's
    lobe) under ``run``'s frames, tile by tile as the fit lights them."""
    job = run.job
    k, c, h, w = run.stack.shape
    svbrdf = svbrdf.to(run.stack.dtype).flatten()
    code = None if model is None else model.reshape(-1).to(run.stack.device)
    lights, ctx = job.lights, light_context(job.lights)
    tiling = tiling_of(h, w, TILE_PIXELS, job.positions)
    out = run.stack.new_empty((h * w, k, c))
    order = torch.arange(h * w, device=run.stack.device) if tiling.order is None else tiling.order
    for first, stop in tiling.ranges:
        index = order[first:stop].to(run.stack.device)
        tile_lights, _ = tiling.lights(lights, ctx, first, stop)
        out[index] = render_chosen(svbrdf[index], None if code is None else code[index], tile_lights, job.view)
    return out.permute(1, 2, 0).reshape(k, c, h, w)


def _errors(predicted: Tensor, run: StackRun, noise: tuple[float, float], floor: float, ceiling: Tensor) -> Tensor:
    """``(K, C, H, W)`` the left-out samples' residuals in noise units (every finite, unsaturated
    sample: shadowed ones too; 0 at the others), the sensor's ``sqrt(a y + b)`` floored at
    ``floor`` times the pixel's mean value. The predictions are clipped to ``[0, ceiling]``
    (:func:`_ceiling`): a camera records nothing brighter, and one failed pixel (a lobe whose peak
    no fitted sample saw, flagged untrusted) must not outweigh the image."""
    y = run.stack
    predicted = predicted.clamp(min=0).minimum(ceiling)
    usable = run.masks.usable[:, None].expand_as(y)
    clean = torch.where(usable, y, torch.zeros_like(y))
    level = clean.sum((0, 1)) / usable.sum((0, 1)).clamp(min=1)  # (H, W)
    sigma = (noise[0] * clean.clamp(min=0) + noise[1]).clamp(min=0).sqrt()
    sigma = torch.maximum(sigma, floor * level).clamp(min=torch.finfo(y.dtype).tiny)
    return torch.where(usable, (predicted - clean) / sigma, torch.zeros_like(y))


def _image(errors: Tensor) -> Tensor:
    """``(1, 1, K C H W, 1)``: :func:`_errors` as one pixel of :func:`torchspec.statistics.predicts_better`."""
    return errors.reshape(1, 1, -1, 1)


def _rms(errors: Tensor, run: StackRun) -> float:
    """The RMS of :func:`_errors` over the usable samples (one host sync)."""
    usable = run.masks.usable
    return float((errors.square().sum() / (usable.sum() * errors.shape[1]).clamp(min=1)).sqrt())


def _ceiling(run: StackRun) -> Tensor:
    """The brightest usable (finite, unsaturated) value ``run``'s frames recorded (0-dim tensor)."""
    usable = run.masks.usable[:, None].expand_as(run.stack)
    return torch.where(usable, run.stack, torch.zeros_like(run.stack)).amax()


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
    predict better), ``indirect`` the indirect share (``None`` where none predicted better),
    ``stats["height"]["softness_deg"]`` the penumbra chosen, and ``stats["shadows"]`` records the
    rounds: each one's left-out RMS residual in noise units, the share of samples it hid, its
    softness and indirect share, and whether it predicted better."""
    clock = time.perf_counter()
    config = run.job.config
    k = run.stack.shape[0]
    test = [i for i in range(k) if i % LEFT_OUT == 2]
    train = [i for i in range(k) if i % LEFT_OUT != 2]
    record = {"tried": True, "used": False, "left_out": [run.job.picked[i] for i in test], "rounds": []}
    best_height = best_share = best_maps = best_kept = best_softness = best_depth = best_sky = None
    kept = False
    if len(train) >= 4 and test:
        fitted, judged = run.frames(train), run.frames(test)
        plain = fit_stack(fitted)
        noise, floor, ceiling = _noise(plain), config.start.noise_floor, _ceiling(fitted)
        best = _errors(predict_frames(plain, judged), judged, noise, floor, ceiling)
        record["plain_rms"] = _rms(best, judged)
        height, maps, softness, depth = height_of(plain), plain, SOFTNESS, 1.0
        for round_ in range(ROUNDS):
            shown = depth  # the depth the previous round chose (DEPTHS): this round's visibility and sky
            scaled = height * shown
            seen = visibility_of(scaled.to(run.stack.device), fitted, softness)
            hidden = float((seen < 0.5).double().mean())
            if round_ == 0 and config.shadows == "auto" and hidden < SHADOWED_SHARE:
                record["rounds"].append({"hidden_share": hidden, "refitted": False})
                break
            sky = sky_view(scaled.to(run.stack.device))
            # the first refit has no indirect light (maps fitted without shadows darken their shadows' pixels),
            # later ones the previous round's where it was kept
            mine = _without(fitted, maps, indirect_of(maps, fitted, seen, sky)) if kept else fitted
            candidate = fit_stack(mine, visibility=seen)
            share = indirect_of(candidate, fitted, seen, sky)
            judge = _Judge(judged, noise, floor, ceiling, config.ladder.predict_z)
            verdict = judge.round(candidate, height, share)
            errors, kept, softness, depth = verdict.errors, verdict.kept, verdict.softness, verdict.depth
            share = share * float(kept)
            better = bool(predicts_better(_image(errors), _image(best), config.ladder.predict_z)[0])
            record["rounds"].append(
                {"hidden_share": hidden, "refitted": True, "rms": _rms(errors, judged), "better": better,
                 "softness_deg": math.degrees(softness), "depth": depth, "indirect": _summary(share),
                 "indirect_pixels": float(kept)}
            )  # fmt: skip
            if not better:
                break
            best, best_share, best_maps, best_kept = errors, share, candidate, kept
            best_sky = sky if depth == shown else None  # this round's sky, where the depth stayed
            best_height = height * depth
            best_softness, best_depth = softness, depth
            height, maps = height_of(candidate), candidate
    judging = time.perf_counter() - clock
    if best_height is None:
        final = fit_stack(run, folder=folder, resume=resume, progress=progress)
        share = None
    else:
        seen = visibility_of(best_height.to(run.stack.device), run, best_softness)
        whole = _without(run, best_maps, best_share) if best_kept else run
        final = fit_stack(whole, visibility=seen, folder=folder, resume=resume, progress=progress)
        if best_kept:
            sky = best_sky if best_sky is not None else sky_view(best_height.to(run.stack.device))
            share = indirect_of(final, run, seen, sky)
        else:
            share = torch.zeros_like(best_share)
    record["used"] = best_height is not None
    record["seconds"] = judging
    if share is not None:
        record["indirect"] = _summary(share)
    stats = dict(final.stats)
    stats["shadows"] = record
    stats["seconds"] = {**stats["seconds"], "shadows": judging}
    if best_height is not None:
        stats["height"] = {"unit": "pixel", "pitch": 1.0, "softness_deg": math.degrees(best_softness),
                           "depth": best_depth}  # fmt: skip
    height = None if best_height is None else best_height.to(final.svbrdf.normal)
    indirect = None if share is None or not best_kept else share.to(final.svbrdf.normal)
    return replace(final, stats=stats, height=height, indirect=indirect)


@dataclass(frozen=True)
class _Judge:
    """The left-out frames ``run`` and how their residuals are weighed (:func:`_errors`)."""

    run: StackRun
    noise: tuple[float, float]
    floor: float
    ceiling: Tensor
    z: float

    def round(self, fit: Fit, height: Tensor, share: Tensor) -> _Verdict:
        """A round's candidate ``fit`` with its ``height`` and indirect ``share`` on the left-out
        frames: each depth of :data:`DEPTHS` (the height scaled) with each softness of
        :data:`SOFTNESSES_DEG`, and the indirect light where it predicts the left-out samples
        better than none (the image as one pixel, as a model is chosen: a pixel's few left-out
        samples rarely show one parameter's gain); the :class:`_Verdict` of the pair that
        predicts best."""
        direct = predict_frames(fit, self.run)
        bounce = share * flat_frames(fit, self.run)
        job, chosen = self.run.job, None
        softnesses = tuple(math.radians(degrees) for degrees in SOFTNESSES_DEG)
        # one horizon for every pair (frame_visibilities): 8 frame_visibility calls took 5 times as long
        pairs = frame_visibilities(height.to(direct.device), job.lights, job.positions, DEPTHS, softnesses)
        for depth, softness, seen in pairs:
            shaded = direct * seen.permute(2, 0, 1).to(direct)[:, None]
            without = _errors(shaded, self.run, self.noise, self.floor, self.ceiling)
            bounced = _errors(shaded + bounce, self.run, self.noise, self.floor, self.ceiling)
            kept = bool(predicts_better(_image(bounced), _image(without), self.z)[0])
            errors = bounced if kept else without
            total = errors.square().sum()
            if chosen is None or bool(total < chosen[0]):
                chosen = (total, _Verdict(errors, kept, softness, depth))
        return chosen[1]


@dataclass(frozen=True)
class _Verdict:
    """What :meth:`_Judge.round` chose: the left-out ``errors`` (:func:`_errors`), whether the
    indirect light is ``kept``, the penumbra's ``softness`` (radians) and the height's ``depth``."""

    errors: Tensor
    kept: bool
    softness: float
    depth: float


def _summary(share: Tensor) -> dict:
    """The indirect share's median and 99th percentile (one host sync)."""
    q = torch.quantile(share.double().flatten(), torch.tensor([0.5, 0.99], dtype=torch.float64, device=share.device))
    return {"median": float(q[0]), "p99": float(q[1])}
