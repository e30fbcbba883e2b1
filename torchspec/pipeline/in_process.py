"""The in-process driver: :func:`fit`, every tile of a capture in this process, one after another
(memory is bounded by the frame stack and one tile).
"""

from __future__ import annotations

import time
from pathlib import Path

from torch import Tensor

from ..io import Capture
from ..progress import bar as progress_bar
from ..start.photometric import sample_masks
from .assembly import assemble, run_stats
from .calibration import calibrated
from .checkpoint import FitInterrupted, job_record, open_checkpoint, refuse_unfinished
from .plan import plan, setup
from .records import StackRun
from .result import Fit
from .settings import FitConfig
from .shadows import fit_with_shadows, shadows_tried
from .start import light_context
from .tile import FitInputs, TileInputs, fit_tile
from .tiling import tiling_of

__all__ = ["fit", "fit_stack"]


def fit(
    capture: Capture | str | Path,
    *,
    config: FitConfig | None = None,
    frames: str | list[int] | None = None,
    progress: bool = False,
    checkpoint: str | Path | None = None,
    resume: bool = False,
) -> Fit:
    """Fit SVBRDF maps to a capture.

    Args:
        capture: a :class:`~torchspec.io.Capture` or its folder.
        config: :class:`~torchspec.pipeline.settings.FitConfig` (the defaults otherwise).
        frames: the frames to fit: a SPEC of :func:`~torchspec.pipeline.settings.select_frames` or
            a list of indices.
        progress: show a tqdm bar over the pixels.
        checkpoint: a folder where each finished tile is saved (atomically), so that an
            interrupted fit can be continued; a ``KeyboardInterrupt`` then becomes
            :class:`~torchspec.pipeline.checkpoint.FitInterrupted`. The caller removes the folder
            once the maps are written.
        resume: continue the fit whose tiles ``checkpoint`` holds (the same capture, frames,
            settings and tiling, else ``TorchspecError``): the maps are identical to an
            uninterrupted fit's. Without it, a checkpoint of an unfinished fit is an error (never
            silently dropped), raised before any work.

    Returns:
        :class:`~torchspec.pipeline.result.Fit`.

    Raises:
        CaptureError: an unreadable capture or frame, or a light whose shape is unknown. (NaN
            or Inf pixels are not an error: they are masked, with a warning naming the frame, and
            counted in ``stats["masked_samples"]``.)
        ConfigError: a bad SPEC or setting; TorchspecError: fewer than 4 frames.
        ValueError: a checkpoint of another job, or an unfinished one without ``resume``.

    Example:
        >>> result = fit("painting-dev", frames="::2")  # doctest: +SKIP
        >>> write_fit("maps", result)  # doctest: +SKIP
    """
    folder = Path(checkpoint) if checkpoint is not None else None
    refuse_unfinished(folder, resume)  # before any work: reading and calibrating take seconds
    clock = time.perf_counter()
    job = setup(capture, config, frames)
    capture, view = job.capture, job.view
    # NaN or Inf pixels (a failed HDR merge) are masked like saturated ones, with a warning per frame.
    stack = capture.read_frames(job.picked, dtype=view.dtype, device=view.device, nonfinite="keep")  # (K, C, H, W)
    read_seconds = time.perf_counter() - clock

    clock = time.perf_counter()
    config = job.config
    masks = sample_masks(stack, saturation=config.masks.saturation, grow=config.masks.grow, shadow=config.masks.shadow)
    job, calibration = calibrated(job, stack, masks.usable)
    mask_seconds = time.perf_counter() - clock

    run = StackRun(job=job, stack=stack, masks=masks, calibration=calibration,
                   seconds={"read": read_seconds, "masks": mask_seconds}, started=clock - read_seconds)  # fmt: skip
    imported = bool(capture.extra.get("source"))
    if shadows_tried(config, masks, imported=imported):  # cast shadows from a height field (pipeline.shadows)
        return fit_with_shadows(run, fit_stack, folder=folder, resume=resume, progress=progress)
    return fit_stack(run, folder=folder, resume=resume, progress=progress)


def fit_stack(
    run: StackRun,
    *,
    visibility: Tensor | None = None,
    folder: Path | None = None,
    resume: bool = False,
    progress: bool = False,
) -> Fit:
    """Every tile of ``run``'s frames in this process (:func:`fit`'s work once the frames are read
    and masked), with the lights' fixed ``visibility (K, H, W)`` where given
    (:func:`~torchspec.pipeline.tile.fit_tile`; ``None``: no cast shadow, today's fit)."""
    job, stack, masks = run.job, run.stack, run.masks
    view, capture, config = job.view, job.capture, job.config
    lights, ctx = job.lights, light_context(job.lights)
    k, c, h, w = stack.shape
    pixels = h * w
    config, tile = plan(config, k, c, h, w, stack.element_size(), stack.device)
    tiling = tiling_of(h, w, tile, job.positions)
    flat = tiling.pixels(stack.flatten(2))  # (K, C, H W) in the fit's order (a view for row-major tiles)
    flat_masks = masks.flat().map(tiling.pixels)  # each (K, H W) in the fit's order
    seen = None if visibility is None else tiling.pixels(visibility.flatten(1))  # (K, H W)
    shared = FitInputs(view=view, channels=capture.channels, config=config, folder=folder, gains=job.gains,
                       domain=job.domain)  # fmt: skip
    done = {}
    if folder is not None:
        done = open_checkpoint(folder, job_record(capture, job.picked, config, tile, pixels), resume)
    parts = []
    with progress_bar(pixels, desc="fit", unit="px", enabled=progress) as bar:
        try:
            for first, stop in tiling.ranges:
                if first in done:  # resumed: the tile as it was computed (its times are that run's)
                    out = done[first].to(view.device)
                else:
                    tile_lights, tile_ctx = tiling.lights(lights, ctx, first, stop)
                    values, tile_masks = flat[:, :, first:stop], flat_masks.of_pixels(slice(first, stop))
                    inputs = TileInputs(first=first, values=values, masks=tile_masks, lights=tile_lights, ctx=tile_ctx,
                                        visibility=None if seen is None else seen[:, first:stop])  # fmt: skip
                    out = fit_tile(inputs, shared)
                parts.append(out)
                bar.update(stop - first)
        except KeyboardInterrupt as interrupt:
            if folder is None:
                raise
            raise FitInterrupted(len(parts), len(tiling.ranges), folder) from interrupt
    stats = run_stats(
        capture=capture,
        picked=job.picked,
        config=config,
        device=view.device,
        pixels=pixels,
        tile=tile,
        resumed=len(done),
        seconds=dict(run.seconds),
        masked=masks.counts(),
        lights=run.calibration,
    )
    return assemble(
        tiling.restore(parts), height=h, width=w, channels=capture.channels, stats=stats, started=run.started
    )
