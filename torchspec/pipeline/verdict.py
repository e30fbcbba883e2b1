"""A fit's verdict in words: the warnings a user can act on (:func:`trust_warnings`, listed in
``svbrdf.json``'s ``fit.warnings``) and the summary ``torchspec fit`` ends with
(:func:`summary_lines`), both from the fit's statistics alone (``Fit.stats``, the ``fit`` block of
``svbrdf.json``), so that a fit read back from its folder says the same.
"""

from __future__ import annotations

import shlex
from pathlib import Path

from .flags import UNTRUSTED

__all__ = [
    "UNTRUSTED_SHARE",
    "LOW_QUALITY",
    "LOW_QUALITY_SHARE",
    "REASONS",
    "scale_words",
    "trust_warnings",
    "summary_lines",
]

UNTRUSTED_SHARE = 0.05
"""The share of a fit's pixels untrusted (quality 0) above which the fit warns, per flag."""

LOW_QUALITY = 0.5
"""A pixel whose quality is below this is counted as low quality (``stats["low_quality"]``)."""

LOW_QUALITY_SHARE = 0.25
"""The share of low-quality pixels above which the fit warns."""

REASONS = {
    "poor_fit": (
        "no model explains their photographs (a relative misfit above trust_rms, 5 % by default)",
        "a relief's cast shadows, frames of unequal brightness or a tone curve the import did not find are the "
        "usual causes: check the capture with torchspec info; torchspec render relights such pixels with the "
        "fit's residual term, but their maps stay untrusted",
    ),
    "implausible": (
        "their maps render more than flag_overshoot (10 by default) times the brightest value their photographs "
        "recorded: a lobe grown without bound where its samples were clipped or masked",
        "photographs with a shorter exposure (no clipped highlights), or more lights near the highlights, "
        "determine such lobes",
    ),
    "peak_misfit": (
        "the photographs about their specular peak are not explained",
        "two overlapping lobes or a lobe the lights sample too coarsely: more lights near the highlights help",
    ),
    "astray": (
        "their fitted specular peak lies far from their brightest photograph",
        "more lights near the highlights help",
    ),
    "undetermined": (
        "their photographs leave the normal undetermined",
        "too few frames are usable there (clipped, dark or masked): check the capture with torchspec info",
    ),
    "few_samples": (
        "fewer than 3 of their frames are usable (clipped, dark or masked)",
        "check the capture with torchspec info; a shorter exposure keeps highlights unclipped",
    ),
    "diverged": ("the solver diverged", "please report it with the capture"),
}
"""Per flag of :data:`torchspec.pipeline.flags.UNTRUSTED`: what it means of the pixels and what the user can do."""


def _share(count: int, pixels: int) -> str:
    return f"{count} of {pixels} pixels ({100 * count / max(pixels, 1):.1f} %)"


def trust_warnings(stats: dict) -> list[str]:
    """The warnings of a fit whose pixels are untrusted in a share above :data:`UNTRUSTED_SHARE`
    (one per flag of :data:`torchspec.pipeline.flags.UNTRUSTED`, saying what it means and what to do) or of
    low quality in a share above :data:`LOW_QUALITY_SHARE`, from ``stats`` (``Fit.stats``)."""
    pixels, flags = stats["pixels"], stats.get("flags", {})
    found = []
    for name in UNTRUSTED:
        count = flags.get(name, 0)
        if pixels and count > UNTRUSTED_SHARE * pixels:
            meaning, action = REASONS[name]
            found.append(
                f"{_share(count, pixels)} are untrusted ({name}): {meaning}. Their quality is 0 and flags.exr marks "
                f"them; {action}."
            )
    low = stats.get("low_quality")
    if low is not None and pixels and low > LOW_QUALITY_SHARE * pixels:
        found.append(
            f"{_share(low, pixels)} have a quality below {LOW_QUALITY} (quality.exr; previews/quality.png shows "
            "where): use their maps with care."
        )
    refused = (stats.get("lights") or {}).get("refused")
    if refused:
        found.append(refused)
    return found


def scale_words(record: dict | None) -> str:
    """`` (of 4000x3000 at --downsample 4, the region X,Y,W,H)``: a scale record
    (:meth:`torchspec.io.scale.Scale.record`) in words, or nothing for none."""
    if not record:
        return ""
    x, y, w, h = record["crop"]
    width, height = record["full_size"]
    crop = "" if (x, y, w, h) == (0, 0, width, height) else f", the region {x},{y},{w},{h}"
    return f" (of {width}x{height} at --downsample {record['downsample']}{crop})"


def _count(name: str, count: int, pixels: int) -> str:
    """``name`` and its share of ``pixels`` (its count at 0.1 % and below)."""
    if count > 0.001 * pixels:
        return f"{name} {100 * count / max(pixels, 1):.1f} %"
    return f"{name} {count} pixel{'s' if count > 1 else ''}"


def summary_lines(stats: dict, output: str, *, capture: str | None = None, previews: list | None = None) -> list[str]:
    """The lines ``torchspec fit`` ends with, from ``stats`` (``Fit.stats``) of the maps written to
    ``output``: size and speed, the models chosen, how many pixels to trust, every warning of
    ``stats["warnings"]``, the ``previews`` written (paths) and what to run next (``capture``: the
    capture's folder as typed)."""
    pixels = stats["pixels"]
    seconds, rate = stats["seconds"]["total"], stats["pixels_per_second"]
    lines = [
        f"wrote {output}: {pixels} pixels{scale_words(stats.get('scale'))} from {len(stats['frames'])} frames in "
        f"{seconds:.1f} s ({rate:.0f} pixels/s)",
    ]
    models = ", ".join(_count(name, count, pixels) for name, count in stats["models"].items() if count)
    lines.append(f"  models: {models}")
    untrusted = stats.get("untrusted", 0)
    low = stats.get("low_quality")
    quality = "" if low is None else f"; {100 * low / max(pixels, 1):.1f} % with quality below {LOW_QUALITY}"
    lines.append(f"  trust: {100 * untrusted / max(pixels, 1):.1f} % of pixels untrusted (quality 0){quality}")
    warnings = stats.get("warnings", [])
    lines += [f"  warning: {message}" for message in warnings] or ["  warnings: none"]
    if previews:
        names = ", ".join(Path(path).stem for path in previews)
        lines.append(f"  previews: {Path(previews[0]).parent}/ ({names})")
    if capture is not None:
        view = f"torchspec view {shlex.quote(output)} --capture {shlex.quote(capture)}"
        lines.append(f"  next: {view}   (relight in the browser)")
    return lines
