"""``torchspec info CAPTURE``: what a capture holds and whether it can be fitted, without fitting.

:func:`inspect_capture` validates a capture as :func:`~torchspec.io.read_capture` and
:meth:`~torchspec.io.Capture.read_frames` do, reading the frames one at a time (memory bounded by
one frame), and counts what a fit would have to mask: saturated samples (the clipped plateau that
:func:`torchspec.start.photometric.sample_masks` detects), NaN or Inf pixels and negative pixels. It
never raises for a bad capture: the report's verdict is then ``"unusable"``, with the reason.
:func:`format_report` renders a report for a terminal.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .calibration.brightness import (
    DARKER,
    MIN_ELEVATION_DEG,
    MIN_SHARE,
    NEIGHBOURS,
    brightness_ratios,
    departures,
    sample_grid,
)
from .calibration.response import describe_response
from .errors import TorchspecError
from .io import Capture, LightSpec, read_capture
from .model.layout import MIN_FRAMES, MIN_PEAK_SAMPLES, coverage_warning, fit_problem, layout_of
from .progress import bar as progress_bar
from .start.photometric import peak_of, sample_masks, saturation_level

__all__ = ["OK", "WARNINGS", "UNUSABLE", "inspect_capture", "format_report"]

OK = "ok"
WARNINGS = "usable with warnings"
"""Problems a fit masks or fixes at a cost: NaN, Inf or negative pixels, saturated samples that
leave a pixel short of frames, renormalised directions, unknown keys. Saturated samples that every
pixel can spare (clipped highlights, masked by the fit) are ``notes`` and leave the verdict :data:`OK`."""
UNUSABLE = "unusable"

_LISTED = 10
"""Frames at fault that :func:`format_report` lists one by one."""
PIXEL_COUNTS = ("clipped", "saturated", "nonfinite", "negative")
"""What the report counts, per frame and summed over the frames (a pixel counts once per frame):
``clipped``, pixels with a channel at or above the clipping level (what ``torchspec import``
reports as clipped pixels, :attr:`torchspec.io.rti.Imported.saturated`); ``saturated``, the clipped
pixels grown by a pixel, which the fit masks (:func:`torchspec.start.photometric.sample_masks`);
``nonfinite``, pixels with NaN or Inf in a channel; ``negative``, pixels with a negative channel."""


def inspect_capture(path: str | Path, *, saturation: float | None = None, progress: bool = False) -> dict[str, Any]:
    """Validate a capture and summarise it.

    Args:
        path: the capture directory, or its ``capture.json``.
        saturation: the sensor's clipping level, as ``FitConfig.masks.saturation``;
            ``None``: the level the capture records (:attr:`torchspec.io.Capture.saturation`), else
            a clipped plateau detected over all the frames, as the fit does.
        progress: show a tqdm bar over the frames.

    Returns:
        A JSON-ready dict. Always: ``capture`` (the path), ``verdict`` (:data:`OK`,
        :data:`WARNINGS` or :data:`UNUSABLE`), ``reason`` (why it is unusable, else ``None``) and
        ``warnings`` (messages). When the manifest is valid, also: ``width``, ``height``,
        ``channels``, ``frames`` (``K``), ``view``, ``light`` (the manifest's keys), ``kernel``
        (a description), ``layout`` (``kind`` ``"grid"``, ``"line"`` or ``"scattered"``, as
        :func:`torchspec.model.layout.layout_of` sees the frames' ``l``, with ``spacing``, ``radius``
        (the largest ``|l|``) and the grid's ``rows`` and ``columns``; ``None`` for fewer than 3
        frames), ``exposure`` and ``irradiance`` (``[min, max]``), ``values`` (``[min, max]`` of
        the finite pixel values), ``saturation`` (the clipping level, ``None`` when nothing
        clips), ``counts`` (the pixels of :data:`PIXEL_COUNTS` summed over the frames),
        ``per_frame`` (one dict per frame: ``index``, ``file``, those four counts, ``min``,
        ``max`` and ``error``, the message of an unreadable frame), ``frames_at_fault``, ``kept``
        (what masking saturated samples leaves each pixel: ``fewest`` frames, ``need`` and
        ``short`` pixels, see :func:`_kept`; ``None`` when nothing clips) and ``notes`` (facts
        that do not lower the verdict, e.g. saturated samples every pixel can spare), ``decoded``
        (an imported capture's transfer in words: ``source.transfer``, and the estimated camera
        response with its uncertainty, ``source.response``; ``None`` for a capture not imported).

    Example:
        >>> report = inspect_capture("../shared/data/painting-dev")  # doctest: +SKIP
        >>> report["verdict"], report["layout"]["kind"], report["frames"]  # doctest: +SKIP
        ('ok', 'grid', 88)
    """
    report: dict[str, Any] = {"capture": str(path), "verdict": UNUSABLE, "reason": None, "warnings": [], "notes": []}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            capture = read_capture(path)
        except TorchspecError as error:
            report["reason"] = str(error)
    report["warnings"] = [str(warning.message) for warning in caught]
    if report["reason"] is not None:
        return report

    reasons: list[str] = []
    count = len(capture.frames)
    irradiance, exposure = capture.irradiance(), capture.exposure()
    report.update(
        width=capture.width,
        height=capture.height,
        channels=list(capture.channels),
        frames=count,
        view=list(capture.view),
        light={name: value for name, value in vars(capture.light).items() if value is not None},
        kernel=_describe(capture.light),
        layout=_layout(capture.directions(), capture.extra) if count >= 3 else None,
        exposure=[float(exposure.min()), float(exposure.max())],
        irradiance=[float(irradiance.min()), float(irradiance.max())],
        decoded=_decoded(capture.extra.get("source")),
    )
    if capture.light.kernel == "tabulated":
        try:
            table = capture.read_kernel()
            report["kernel"] += f", a {table.shape[1]}x{table.shape[0]} image"
        except TorchspecError as error:
            reasons.append(str(error))
    elif capture.light.kernel == "unknown":
        report["warnings"].append(
            f"{capture.manifest}: light.kernel is 'unknown': only the specular location can be recovered; "
            "torchspec fit needs the light's shape (calibrate the light first)."
        )
    reasons += _layout_notes(capture, report["warnings"])

    if saturation is None:  # the level an imported capture records, as the fit uses it
        saturation = capture.saturation
    samples: list[Tensor] = []
    rows, level, saturated_frames = _scan(capture, saturation, progress, samples)
    report["values"] = _range([row["min"] for row in rows], [row["max"] for row in rows])
    report["saturation"] = level if math.isfinite(level) else None
    report["counts"] = {name: sum(row[name] for row in rows) for name in PIXEL_COUNTS}
    report["per_frame"] = rows
    report["frames_at_fault"] = [
        row["index"] for row in rows if row["error"] or row["saturated"] or row["nonfinite"] or row["negative"]
    ]
    report["kept"] = _kept(saturated_frames, count)
    report["warnings"] += _pixel_warnings(rows, level, capture, report["kept"], report["notes"])
    report["brightness"], found = _brightness(rows, torch.stack(samples) if samples else None, capture)
    report["warnings"] += found
    unreadable = [row for row in rows if row["error"]]
    if unreadable:
        reasons.append(
            f"{len(unreadable)} of {count} frame(s) cannot be read (frames {_indices(unreadable)}); "
            f"the first: {unreadable[0]['error']}"
        )
    report["reason"] = "\n".join(reasons) if reasons else None
    report["verdict"] = UNUSABLE if reasons else WARNINGS if report["warnings"] else OK
    return report


def _decoded(source: Any) -> str | None:
    """An imported capture's transfer in words (``source.transfer``, ``source.response``)."""
    if not isinstance(source, dict) or not source.get("transfer"):
        return None
    response = source.get("response")
    if source["transfer"] == "response" and isinstance(response, dict):
        return f"{describe_response(response)}, from {source.get('encoding', 'integer')} photographs"
    words = f"{source['transfer']} ({source.get('encoding', 'integer')} photographs)"
    if isinstance(response, dict) and response.get("judged_psnr_db"):
        judged = ", ".join(f"{name} {value:.1f} dB" for name, value in response["judged_psnr_db"].items())
        words += f"; it predicted left-out photographs better than the curves estimated from them ({judged})"
    if source.get("icc_profiles"):
        words += "; frames with an ICC profile decoded by it"
    return words


def _layout_notes(capture: Capture, notes: list[str]) -> list[str]:
    """Why no fit can use the frames (the reasons the capture is unusable), and, in ``notes``, what
    the default fit (with lobes) refuses or does poorly (:func:`torchspec.model.layout.fit_problem`,
    :func:`torchspec.model.layout.coverage_warning`)."""
    l = capture.directions()[:, :2]
    problem = fit_problem(l, lobe=False)
    if problem is not None:
        return [f"{capture.manifest}: {problem}"]
    problem = fit_problem(l)
    if problem is not None:
        notes.append(f"{capture.manifest}: torchspec fit (with lobes, its default) refuses these frames: {problem}")
    cover = coverage_warning(l, torch.tensor(capture.view, dtype=l.dtype, device=l.device))
    if cover is not None:
        notes.append(f"{capture.manifest}: {cover}")
    return []


def _scan(
    capture: Capture, saturation: float | None, progress: bool, samples: list[Tensor]
) -> tuple[list[dict[str, Any]], float, Tensor | None]:
    """Read the frames one by one: a row of counts per frame, the clipping level (``inf`` when
    nothing clips) and, per pixel, how many frames are saturated there (``None`` when none is).
    Each frame's pixels on :func:`torchspec.calibration.brightness.sample_grid` go to ``samples``: over its
    exposure times irradiance, the channels' mean, NaN where saturated, NaN or Inf (or unread)."""
    rows, peaks, tops, masks = [], [], [], []
    grid = sample_grid(capture.height, capture.width)
    scale = capture.exposure()[:, None] * capture.irradiance()  # (K, C)
    size = len(range(capture.height)[grid[0]]) * len(range(capture.width)[grid[1]])
    unread = torch.full((size,), math.nan, dtype=torch.float64)  # CPU on purpose: with the samples, moved there
    # Per-pixel counts of saturated frames, one map per candidate level (a frame's own top) until
    # the stack's level is known; a sensor has one or two distinct tops, so few maps are kept.
    counts: dict[float, Tensor] = {}
    with progress_bar(len(capture.frames), unit="frame", desc="info", enabled=progress) as bar:
        for k, frame in enumerate(capture.frames):
            row = {"index": k, "file": frame.file, "clipped": 0, "saturated": 0, "nonfinite": 0, "negative": 0}
            row.update(min=None, max=None, error=None)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # NaN, Inf and negative values are counted here
                    image = capture.read_frames([k], nonfinite="keep")  # (1, C, H, W)
            except TorchspecError as error:
                row["error"] = str(error)
                rows.append(row)
                samples.append(unread)
                bar.update()
                continue
            finite = torch.isfinite(image)
            row["nonfinite"] = int((~finite).any(1).sum())
            row["negative"] = int(((image < 0) & finite).any(1).sum())
            if finite.any():
                row["min"], row["max"] = float(image[finite].min()), float(image[finite].max())
            # The fit detects one level for the whole stack; a frame clips at it only when its own
            # top is that level, so each frame's count at its own top is kept until the level is known.
            top, repeats = peak_of(image)
            peaks.append((top, repeats))
            tops.append((row, float(top)))
            clip = top if saturation is None else saturation
            mask = sample_masks(image, saturation=clip, shadow=0.0).saturated[0]
            row["saturated"] = int(mask.sum())
            row["clipped"] = int(sample_masks(image, saturation=clip, shadow=0.0, grow=0).saturated[0].sum())
            value = image[0][:, grid[0], grid[1]].double() / scale[k].to(image.device)[:, None, None]
            samples.append(value.mean(0).reshape(-1).cpu())
            masks.append((k, float(clip), mask[grid].reshape(-1).cpu()))
            if row["saturated"]:
                key = float(clip)
                # on the CPU: per-pixel counts for the report, kept off the accelerator (mask.cpu())
                counts[key] = counts.get(key, torch.zeros(mask.shape, dtype=torch.int32)) + mask.cpu()
            rows.append(row)
            bar.update()
    level = float(saturation) if saturation is not None else float(saturation_level(peaks)) if peaks else math.inf
    for k, clip, mask in masks:  # the samples at the stack's level (a frame's own top is not one)
        samples[k] = samples[k].masked_fill(mask, math.nan) if clip == level else samples[k]
    if saturation is not None:
        return rows, level, counts.get(level)
    for row, top in tops:
        if top != level:
            row["saturated"] = row["clipped"] = 0
    return rows, level, counts.get(level)


def _brightness(
    rows: list[dict[str, Any]], samples: Tensor | None, capture: Capture
) -> tuple[dict[str, Any] | None, list[str]]:
    """Each frame's brightness against its neighbours in light direction
    (:func:`torchspec.calibration.brightness.brightness_ratios`) into its row (``brightness``: ``ratio``,
    ``quartiles`` of its pixels' ratios, ``neighbours`` and their ``spread``; ``None`` when not
    judged), the summary
    (``judged`` frames, ``range`` of their ratios, ``flagged`` frames; ``None`` without frames) and
    one warning per frame that departs (:func:`torchspec.calibration.brightness.departures`)."""
    if samples is None:
        return None, []
    ratios = brightness_ratios(samples, capture.directions())
    for k, row in enumerate(rows):
        ratio, low, high, spread = (float(ratios[name][k]) for name in ("ratio", "low", "high", "spread"))
        row["brightness"] = None
        if math.isfinite(ratio):
            neighbours = ratios["neighbours"][k].tolist()
            row["brightness"] = {"ratio": ratio, "quartiles": [low, high], "neighbours": neighbours, "spread": spread}
    judged = [row["brightness"]["ratio"] for row in rows if row["brightness"]]
    flagged = departures(ratios)
    summary = {"judged": len(judged), "range": [min(judged), max(judged)] if judged else None, "flagged": flagged}
    if not judged:
        summary["reason"] = (
            f"no frame has {MIN_SHARE:.0%} of its pixels to compare (lit under its neighbours' lights, not saturated)"
            if bool(ratios["judged"].any())
            else f"fewer than {NEIGHBOURS + 1} frames {MIN_ELEVATION_DEG:g} deg or more above the horizon"
        )
    warned = []
    for k in flagged:
        row, found = rows[k], rows[k]["brightness"]
        ratio, (low, high) = found["ratio"], found["quartiles"]
        dark = ratio < DARKER
        how = f"{100 * (1 - ratio):.0f} % darker than" if dark else f"{ratio:.2f} times as bright as"
        warned.append(
            f"frames[{k}] {row['file']} is {how} its neighbours in light direction (frames "
            f"{', '.join(map(str, found['neighbours']))}): {ratio:.2f} times their brightness, the median over "
            f"its pixels with the cosine falloff taken out (half of its pixels within {low:.2f} .. {high:.2f}); "
            f"a flash or lamp that fired {'weakly' if dark else 'strongly'}, or an exposure other than the one "
            "recorded? The fit takes the frame as lit as written: check its photograph, or leave it out "
            "(torchspec fit --frames)."
        )
    return summary, warned


def _kept(saturated: Tensor | None, frames: int) -> dict[str, int] | None:
    """What masking the saturated samples leaves the fit, per pixel: ``fewest`` frames kept at a
    pixel, ``need`` (what every pixel should keep) and ``short`` (pixels that keep fewer).

    A pixel is short when masking leaves it fewer than half its frames, or fewer than a fit needs
    (:data:`~torchspec.model.layout.MIN_FRAMES`; :data:`~torchspec.model.layout.MIN_PEAK_SAMPLES` squared for a
    lobe) where all the frames had enough."""
    if saturated is None:
        return None
    need = math.ceil(frames / 2)
    for minimum in (MIN_FRAMES, MIN_PEAK_SAMPLES**2):
        if frames >= minimum:
            need = max(need, minimum)
    kept = frames - saturated
    return {"fewest": int(kept.min()), "need": need, "short": int((kept < need).sum())}


def _pixel_warnings(
    rows: list[dict[str, Any]], level: float, capture: Capture, kept: dict[str, int] | None, notes: list[str]
) -> list[str]:
    """One message per kind of bad pixel, naming the frames. Saturated samples are a warning only
    where masking them leaves some pixel short of frames (:func:`_kept`); otherwise the fit loses
    nothing it needs and they go to ``notes``."""
    warned = []
    pixels = capture.width * capture.height
    saturated = [row for row in rows if row["saturated"]]
    if saturated and kept is not None:
        total = sum(row["saturated"] for row in saturated)
        clipped = sum(row["clipped"] for row in saturated)
        message = (
            f"{total} saturated pixel(s) (clipped at {level:.6g}, grown by a pixel: the {clipped} clipped pixels and "
            f"their neighbours) in {len(saturated)} frame(s) (frames {_indices(saturated)}, of {pixels} pixels each): "
            "the fit masks them"
        )
        if kept["short"]:
            warned.append(
                f"{message}, which leaves {kept['short']} pixel(s) fewer than {kept['need']} of the "
                f"{len(rows)} frames (the fewest: {kept['fewest']}); their maps rest on the frames left."
            )
        else:
            notes.append(f"{message}; every pixel keeps at least {kept['fewest']} of the {len(rows)} frames.")
    nonfinite = [row for row in rows if row["nonfinite"]]
    if nonfinite:
        total = sum(row["nonfinite"] for row in nonfinite)
        warned.append(
            f"{total} pixel(s) with NaN or Inf in {len(nonfinite)} frame(s) (frames {_indices(nonfinite)}): the fit "
            "masks them."
        )
    negative = [row for row in rows if row["negative"]]
    if negative:
        total = sum(row["negative"] for row in negative)
        lowest = min(row["min"] for row in negative)
        warned.append(
            f"{total} pixel(s) with a negative value in {len(negative)} frame(s) (frames {_indices(negative)}, the "
            f"most negative {lowest:.3g}): the fit reads them as they are (sensor noise "
            "about a black level of 0); a black-level offset is not subtracted."
        )
    return warned


def _layout(directions: torch.Tensor, extra: dict | None = None) -> dict[str, Any]:
    """The light layout as the fit sees it: :func:`torchspec.model.layout.layout_of` of the frames' ``l``;
    for a grid, its ``positions`` (rows x columns, of which the frames fill those within the
    disk) and, when the manifest's ``generator`` records the planned grid (``torchspec acquire``,
    ``torchspec simulate``), that ``planned`` grid: its outer rows and columns may lie wholly
    beyond the radius."""
    l = directions[:, :2].to(torch.float32)  # the fit's default dtype, so the same grid test
    layout = layout_of(l)
    out: dict[str, Any] = {"kind": "grid" if layout.grid is not None else "line" if layout.dims == 1 else "scattered"}
    if layout.grid is not None:
        out.update(rows=layout.grid.rows, columns=layout.grid.columns, positions=layout.grid.rows * layout.grid.columns)
        planned = _planned_grid((extra or {}).get("generator"))
        if planned is not None:
            out["planned"] = planned
    if layout.dims == 1:
        out["axis"] = [float(v) for v in layout.axis]
    out.update(spacing=float(layout.spacing), radius=float(l.norm(dim=-1).max()))
    return out


def _planned_grid(generator: Any) -> dict[str, Any] | None:
    """``{"columns", "rows", "radius"}`` of the grid a generator record planned, or ``None``:
    ``torchspec acquire`` records ``layout: "grid:NXxNY"`` and ``radius``; ``torchspec simulate``
    its config's ``layout`` (``kind: grid``, ``nx``, ``ny``, ``radius``)."""
    if not isinstance(generator, dict):
        return None
    spec = generator.get("layout")
    if isinstance(spec, str):
        match = re.fullmatch(r"grid:(\d+)x(\d+)", spec)
        radius = generator.get("radius")
        if match and isinstance(radius, (int, float)):
            return {"columns": int(match[1]), "rows": int(match[2]), "radius": float(radius)}
        return None
    config = generator.get("torchspec")
    spec = config.get("layout") if isinstance(config, dict) else None
    if isinstance(spec, dict) and spec.get("kind") == "grid":
        values = [spec.get(key) for key in ("nx", "ny", "radius")]
        if all(isinstance(v, (int, float)) for v in values):
            return {"columns": int(values[0]), "rows": int(values[1]), "radius": float(values[2])}
    return None


def _grid_words(layout: dict[str, Any], frames: int) -> str:
    """The grid in words: ``grid 10 x 10 (88 of its 100 positions, ...)`` and, when the planned grid
    was larger, which of its rows and columns fell outside the radius."""
    words = f"grid {layout['rows']} x {layout['columns']}"
    if frames < layout.get("positions", frames):
        words += f" ({frames} of its {layout['positions']} positions: those beyond the radius are left out)"
    return words


def _planned_words(layout: dict[str, Any] | None) -> str | None:
    """The planned grid when it is not the grid the frames form: its outer rows or columns lie
    wholly beyond the radius (``grid:12x12 --radius 0.8`` lights a 10 x 10 grid)."""
    planned = (layout or {}).get("planned")
    if not planned or (planned["rows"], planned["columns"]) == (layout["rows"], layout["columns"]):
        return None
    lost = []
    if planned["rows"] > layout["rows"]:
        lost.append(f"{planned['rows'] - layout['rows']} of its {planned['rows']} rows")
    if planned["columns"] > layout["columns"]:
        lost.append(f"{planned['columns'] - layout['columns']} of its {planned['columns']} columns")
    return (
        f"a {planned['columns']} x {planned['rows']} grid within |l| <= {planned['radius']:g}; "
        f"{' and '.join(lost) or 'some positions'} (the outermost) lie wholly beyond that radius and hold no light, "
        f"so the frames form a {layout['columns']} x {layout['rows']} grid"
    )


def _describe(light: LightSpec) -> str:
    """The light kernel in words."""
    if light.kernel == "gaussian":
        unit = "radians" if light.domain == "angular" else "l units"
        return f"gaussian, {light.domain} domain, sigma {light.sigma:g} {unit}"
    if light.kernel == "tabulated":
        return f"tabulated, {light.file}, extent {light.extent:g} l units"
    if light.kernel == "unknown":
        return "unknown, symmetric"
    return light.kernel


def _range(lows: list[float | None], highs: list[float | None]) -> list[float] | None:
    lows, highs = [v for v in lows if v is not None], [v for v in highs if v is not None]
    return [min(lows), max(highs)] if lows else None


def _indices(rows: list[dict[str, Any]]) -> str:
    """``"0, 4, 7"``, or the first few and how many more."""
    shown = ", ".join(str(row["index"]) for row in rows[:_LISTED])
    return shown + (f" and {len(rows) - _LISTED} more" if len(rows) > _LISTED else "")


def format_report(report: dict[str, Any]) -> str:
    """A report of :func:`inspect_capture` as lines of text for a terminal.

    Example:
        >>> print(format_report(inspect_capture("no-such-capture")))  # doctest: +ELLIPSIS
        capture   no-such-capture
        verdict   unusable
        reason    the capture folder no-such-capture does not exist. ...
    """
    lines = [f"capture   {report['capture']}", f"verdict   {report['verdict']}"]
    if report["reason"]:
        lines += _block("reason", report["reason"].splitlines())
    if "width" in report:
        layout = report["layout"]
        if layout is None:
            where = "too few for a layout"
        else:
            where = "layout " + (_grid_words(layout, report["frames"]) if layout["kind"] == "grid" else layout["kind"])
            where += f", spacing {layout['spacing']:.3g}, |l| <= {layout['radius']:.3g}"
        values = report["values"]
        counts = report["counts"]
        lines += [
            f"size      {report['width']} x {report['height']} (W x H), channels {', '.join(report['channels'])}",
            f"frames    {report['frames']}, {where}",
            *([f"planned   {_planned_words(layout)}"] if _planned_words(layout) else []),
            f"light     {report['kernel']}; view {_vector(report['view'])}",
            *([f"decoded   {report['decoded']}"] if report.get("decoded") else []),
            f"exposure  {_span(report['exposure'])}; irradiance {_span(report['irradiance'])}",
            f"values    {_span(values) if values else 'none finite'}"
            + (f"; clipped at {report['saturation']:.6g}" if report["saturation"] is not None else "; none clipped"),
            *_block(
                "pixels",
                [
                    f"{counts['clipped']} clipped pixels (a channel at the clipping level: torchspec import's count), "
                    f"{counts['saturated']} saturated (the clipped grown by a pixel: what the fit masks),",
                    f"{counts['nonfinite']} NaN or Inf, {counts['negative']} negative; counted in each frame "
                    f"({report['width'] * report['height']} pixels) and summed over the {report['frames']} frames",
                ],
            ),
        ]
        lines += _brightness_line(report.get("brightness"), report["frames"])
        faults = [row for row in report["per_frame"] if row["index"] in set(report["frames_at_fault"])]
        if faults:
            described = [_fault(row) for row in faults[:_LISTED]]
            if len(faults) > _LISTED:
                described.append(f"... and {len(faults) - _LISTED} more (--json lists every frame)")
            lines += _block(f"{len(faults)} frame(s) the fit cannot use whole", described, header=True)
    if report["warnings"]:
        lines += _block("warnings", report["warnings"], header=True)
    if report.get("notes"):
        lines += _block("notes", report["notes"], header=True)
    return "\n".join(lines)


def _brightness_line(summary: dict[str, Any] | None, frames: int) -> list[str]:
    """The ``brightness`` line of :func:`format_report`: how many frames were judged against their
    neighbours in light direction, the range of their ratios and the frames flagged."""
    if summary is None:
        return []
    if not summary["judged"]:
        return [f"bright    frames not compared with their neighbours in light direction: {summary['reason']}"]
    low, high = summary["range"]
    flagged = f"; departing: frames {', '.join(map(str, summary['flagged']))}" if summary["flagged"] else ""
    return [
        f"bright    {summary['judged']} of {frames} frames against their neighbours in light direction: "
        f"{low:.2f} .. {high:.2f} times as bright{flagged}"
    ]


def _fault(row: dict[str, Any]) -> str:
    if row["error"]:
        return f"frames[{row['index']}] {row['file']}: {row['error']}"
    found = [
        f"{row[name]} {label}"
        for name, label in (
            ("clipped", "clipped"),
            ("saturated", "saturated (grown by a pixel)"),
            ("nonfinite", "NaN or Inf"),
            ("negative", "negative"),
        )
        if row[name]
    ]
    return f"frames[{row['index']}] {row['file']}: {', '.join(found)}"


def _block(title: str, items: list[str], *, header: bool = False) -> list[str]:
    if header:
        return [f"{title}:"] + [f"  - {item}" for item in items]
    return [f"{title:<9} {items[0]}"] + [f"          {item}" for item in items[1:]]


def _span(values: list[float]) -> str:
    low, high = values
    return f"{low:.4g}" if low == high else f"{low:.4g} .. {high:.4g}"


def _vector(values: list[float]) -> str:
    return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"
