"""Is a left-out photograph's brightness in the other photographs? The brightness target of issue 21.

The protocol of ``experiments/rti_relight.py`` (each capture imported and reduced by ``downsample``,
frame ``i % 5 == left_out`` left out, the rest fitted), with the fitters RTI users run, PTM and HSH
(:data:`rti_relight.BASES`), fitted on the 8-bit sRGB values. Per left-out frame: its mean
brightness ratio, predicted over photographed (linear values), as ``rti_relight`` scores it.

Then a correction that uses the fitted frames only: each fitted frame's own ratio when it is left
out of them (nested leave-one-out, the same fitter), and for each left-out frame the weighted
geometric mean of those ratios over the ``m`` fitted lights nearest it (weights one over the angle).
If a frame's brightness error were a smooth function of the light's direction (a dome whose lights
dim towards one side, a falloff), its neighbours' errors would predict it and the correction would
remove it; where each light has its own intensity (or a grazing light its own shadows), nothing in
the other photographs does.

    python experiments/left_out_brightness.py [--config CONFIG] [--output experiments/results]
"""

from __future__ import annotations

import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from _common import ROOT, parse_args
from rti_relight import BASES, brightness_ratios, load_reduced, polynomial

from torchspec.atomic import write_json
from torchspec.config import load_config

LIMIT = 0.1
"""The issue's bound: no left-out frame's mean brightness off by more than this fraction."""


@dataclass(frozen=True)
class Settings:
    data: str  # the folder of the captures, relative to the repository's root (or absolute)
    captures: tuple[str, ...]  # folders of `data` (a SynthRTI one: its Dome/)
    downsample: int = 4  # box-average factor of the frames (1: full size)
    left_out: int = 2  # frames i % 5 == left_out are predicted
    neighbours: tuple[int, ...] = (1, 2, 3, 4, 6)  # m of the correction
    threads: int = 2  # torch threads


def left_out_ratios(basis, directions: torch.Tensor, codes: torch.Tensor, fitted: list[int], predicted: list[int]):
    """``(len(predicted),)`` brightness ratios, predicted over photographed, of ``basis`` fitted on
    the ``fitted`` frames of ``codes (K, C, H, W)`` under ``directions (K, 3)``."""
    values, _ = polynomial(basis, directions[fitted], codes[fitted], directions[predicted])
    return brightness_ratios(values, codes[predicted])


def neighbour_correction(
    directions: torch.Tensor, fitted: list[int], own: torch.Tensor, predicted: list[int], count: int
) -> torch.Tensor:
    """``(len(predicted),)`` each predicted frame's expected ratio from the fitted frames' ``own
    (len(fitted),)`` leave-one-out ratios: their geometric mean over the ``count`` fitted lights
    nearest it, weighted by one over the angle (at least 1e-3 rad)."""
    angle = torch.acos((directions[predicted] @ directions[fitted].T).clamp(-1.0, 1.0))  # (P, F)
    near = angle.argsort(-1)[:, :count]
    weight = 1.0 / angle.gather(-1, near).clamp_min(1e-3)
    log = own.log()[near]
    return ((weight * log).sum(-1) / weight.sum(-1)).exp()


def run_capture(folder: Path, scratch: Path, settings: Settings) -> dict:
    """Every left-out frame's ratio of each basis, with and without each correction, and the summary."""
    synth = (folder / "Dome").is_dir()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the import's notes are not scores
        capture, _, codes, _ = load_reduced(folder / "Dome" if synth else folder, scratch, settings.downsample, "srgb")
    directions = capture.directions().double()
    count = len(capture.frames)
    predicted = [i for i in range(count) if i % 5 == settings.left_out]
    fitted = [i for i in range(count) if i % 5 != settings.left_out]
    elevation = torch.rad2deg(torch.asin(directions[predicted, 2].clamp(-1, 1)))
    out = {"capture": folder.name, "frames": count, "left_out": predicted, "elevation_deg": elevation.tolist()}
    for name, basis in BASES.items():
        ratios = left_out_ratios(basis, directions, codes, fitted, predicted)
        own = torch.cat([left_out_ratios(basis, directions, codes, [f for f in fitted if f != j], [j]) for j in fitted])
        rows = {"as fitted": ratios}
        for m in settings.neighbours:
            rows[f"corrected, {m} nearest"] = ratios / neighbour_correction(directions, fitted, own, predicted, m)
        out[name] = {label: _summary(r) for label, r in rows.items()}
    return out


def _summary(ratios: torch.Tensor) -> dict:
    worst = int(ratios.log().abs().argmax())
    return {
        "ratios": ratios.tolist(),
        "worst_ratio": float(ratios[worst]),
        "off": int(((ratios - 1).abs() > LIMIT).sum()),
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "left_out_brightness.yaml", argv)
    settings = load_config(args.config, Settings)
    torch.set_num_threads(settings.threads)
    data = Path(settings.data)
    data = data if data.is_absolute() else ROOT / data
    missing = [name for name in settings.captures if not (data / name).is_dir()]
    if missing:
        raise SystemExit(f"{args.config}: no capture folder {', '.join(missing)} in {data}")
    result = {"limit": LIMIT, "captures": []}
    with tempfile.TemporaryDirectory() as scratch:
        for name in settings.captures:
            found = run_capture(data / name, Path(scratch), settings)
            result["captures"].append(found)
            _print(found)
    args.output.mkdir(parents=True, exist_ok=True)
    write_json(args.output / f"{args.config.stem}.json", result)
    return result


def _print(found: dict) -> None:
    print(f"\n{found['capture']}: {len(found['left_out'])} of {found['frames']} frames left out")
    print(f"  {'fitter':5s} {'prediction':22s} {'worst ratio':>11s} {'off > 10 %':>10s}")
    for name in BASES:
        for label, row in found[name].items():
            print(f"  {name:5s} {label:22s} {row['worst_ratio']:11.3f} {row['off']:10d}")


if __name__ == "__main__":
    main()
