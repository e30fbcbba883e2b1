"""Relighting transfer: fit a capture under one light and predict another capture of the same object
under other lights, per choice of model.

Each pair is a capture fitted (an extended light) and a capture predicted (point lights, none of
them among the fitted frames): ``painting-dev`` -> ``painting-dev-relight`` of ``../shared/data``
(skipped when absent), and simulated pairs (:mod:`_scenes`: a procedural painting rendered with a
Ward or a Beckmann lobe, the second like the development captures' path tracer). Rows: ``auto``,
each model forced, the fits of ``runs`` (e.g. ``auto`` with its ladder ending at ``ward-aniso``), and
the true maps rendered with the fit's Ward lobe (``truth``: the ceiling a perfect Ward fit reaches)
and, where the captures were rendered with another lobe, with that lobe (``truth-<lobe>``).

Per row: the PSNR of the prediction of every frame of the other capture (peak: that capture's
maximum, as ``torchspec render`` and the data's README define it; ``inf`` for an exact
prediction), its relative RMS error (``|pred - obs| / |obs|`` over all samples), the worst frame's
PSNR, the fit's wall time and CPU time (this process's, every thread: steadier than the wall
time on a loaded machine), each the fastest of the pair's ``repeats`` for the rows in ``timed``; one
untimed fit of a tiny painting first pays the process's one-off costs), the share of pixels
per chosen model, and the brightness at the mirror direction (a point light at the true normal's
mirror of the view, the mean over the channels and over the pixels ``auto`` gave ``ward-dual``) of
the fit against the truth rendered with the captures' own lobe.

    python experiments/relight_transfer.py [--config experiments/configs/relight_transfer.yaml]
        [--output experiments/results] [--pairs NAME ...] [--rows LABEL ...]
"""

from __future__ import annotations

import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from _common import ROOT, parse_args
from _scenes import Lighting, Scene, warm_up, write_scene

from torchspec.atomic import write_json
from torchspec.config import from_mapping, load_config
from torchspec.io import read_svbrdf
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import reflect
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render
from torchspec.pipeline import MODEL_CODES, FitConfig, fit, write_fit
from torchspec.relight import render_capture
from torchspec.report import REGIONS

F64 = torch.float64


@dataclass(frozen=True)
class Simulated:
    scene: Scene
    fitted: Lighting  # the capture fitted
    predicted: Lighting  # the capture predicted


@dataclass(frozen=True)
class Pair:
    name: str
    fitted: str = ""  # a capture under Settings.data (with simulated: unused)
    predicted: str = ""
    truth_lobe: str = "ward"  # the lobe the shared captures were rendered with (simulated: the scene's)
    simulated: Simulated | None = None
    repeats: int = 1  # fits of the rows in Settings.timed, the fastest reported


@dataclass(frozen=True)
class Settings:
    data: str  # the shared captures' folder, relative to the repository root (or absolute)
    pairs: tuple[Pair, ...]
    models: tuple[str, ...]  # "auto" and the forced ones
    runs: dict[str, dict] = field(default_factory=dict)  # more fits: label -> FitConfig settings
    timed: tuple[str, ...] = ()  # rows fitted Pair.repeats times
    warm_up: bool = True  # fit a tiny painting first, untimed


def mirror_brightness(svbrdf: SVBRDF, normal: torch.Tensor, lobe: str = "ward", block: int = 256) -> torch.Tensor:
    """``(n,)`` the value of flat maps ``svbrdf (n,)`` under a unit point light at the mirror
    direction of the view ``(0, 0, 1)`` about ``normal (n, 3)``, the mean over the channels
    (each block of pixels rendered under the block's lights at once; the diagonal kept)."""
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    out = []
    for start in range(0, svbrdf.normal.shape[0], block):
        part = svbrdf[start : start + block].to(F64)
        m = part.normal.shape[0]
        directions = reflect(view.expand(m, 3), normal[start : start + block].to(F64))
        lights = Lights(directions, Kernel("point"), torch.ones(m, 1, dtype=F64), torch.ones(m, dtype=F64))
        values = render(part, lights, view, lobe=lobe)  # (m, m, C)
        out.append(values.diagonal(0, 0, 1).mean(0))
    return torch.cat(out) if out else torch.zeros(0, dtype=F64)


def _folders(settings: Settings, pair: Pair, tmp: Path) -> tuple[Path, Path, str] | None:
    """The fitted and predicted captures' folders and the lobe they were rendered with; ``None``
    where a shared capture is absent."""
    if pair.simulated is not None:
        sim = pair.simulated
        fitted = write_scene(tmp / pair.name / "fitted", sim.scene, sim.fitted)
        predicted = write_scene(tmp / pair.name / "predicted", sim.scene, sim.predicted)
        return fitted, predicted, sim.scene.lobe
    data = (ROOT / settings.data).resolve()
    fitted, predicted = data / pair.fitted, data / pair.predicted
    if not (fitted / "capture.json").exists() or not (predicted / "capture.json").exists():
        print(f"{pair.name}: skipped, {fitted} or {predicted} is absent")
        return None
    return fitted, predicted, pair.truth_lobe


def _fit_row(label, config, repeats, fitted, predicted, regions, out):
    seconds, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fit(fitted, config=config)
        seconds.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    write_fit(out / label, result)
    report = render_capture(out / label, predicted, None, dtype=F64)
    codes = result.model.flatten()
    names = Counter(MODEL_CODES[int(c)] for c in codes)
    row = {
        "row": label,
        "psnr_db": report["psnr_db"],
        "relative_rms": report["relative_rms"],
        "worst_frame_psnr_db": min(report["per_frame_psnr_db"]),
        "fit_seconds": min(seconds),
        "fit_seconds_all": seconds,
        "fit_cpu_seconds": min(cpu),
        "fit_cpu_seconds_all": cpu,
        "model_share": {name: count / codes.numel() for name, count in sorted(names.items())},
        "quality_share_0.5": float((result.quality >= 0.5).double().mean()),
    }
    if regions is not None:
        row["models_per_region"] = {
            region: dict(Counter(MODEL_CODES[int(c)] for c in codes[regions == r]))
            for r, region in enumerate(REGIONS)
            if bool((regions == r).any())
        }
    return row, result


def _pair(settings: Settings, pair: Pair, tmp: Path, rows_only: list[str] | None = None) -> dict | None:
    found = _folders(settings, pair, tmp)
    if found is None:
        return None
    fitted, predicted, lobe = found
    truth = read_svbrdf(fitted / "truth")
    regions = truth.extra["regions"].round().long().flatten() if "regions" in truth.extra else None
    runs = [(name, FitConfig(model=name)) for name in settings.models]
    runs += [(label, from_mapping(values, FitConfig, f"runs.{label}")) for label, values in settings.runs.items()]
    runs = [(label, config) for label, config in runs if rows_only is None or label in rows_only]
    rows, fits = [], {}
    for label, config in runs:
        repeats = pair.repeats if label in settings.timed else 1
        row, fits[label] = _fit_row(label, config, repeats, fitted, predicted, regions, tmp / pair.name)
        rows.append(row)
        print(f"  {pair.name} {label}: {row['psnr_db']:.2f} dB in {row['fit_seconds']:.1f} s", flush=True)
    for name in ["ward"] + ([lobe] if lobe != "ward" else []):
        report = render_capture(fitted / "truth", predicted, None, dtype=F64, lobe=name)
        label = "truth" if name == "ward" else f"truth-{name}"
        rows.append(
            {
                "row": label,
                "psnr_db": report["psnr_db"],
                "relative_rms": report["relative_rms"],
                "worst_frame_psnr_db": min(report["per_frame_psnr_db"]),
            }
        )
    out = {"pair": pair.name, "fitted": str(fitted), "predicted": str(predicted), "lobe": lobe, "rows": rows}
    if "auto" in fits:
        out["mirror"] = _mirror(fits, truth.svbrdf.flatten(), lobe)
    return out


def _mirror(fits: dict, truth: SVBRDF, lobe: str) -> dict:
    """Brightness at the mirror direction on the pixels ``auto`` gave ``ward-dual``: each fit's
    (mean over those pixels) against the truth's rendered with the captures' lobe."""
    pick = fits["auto"].model.flatten() == MODEL_CODES.index("ward-dual")
    normal = truth.normal[pick]
    out = {"pixels": int(pick.sum()), "truth": float(mirror_brightness(truth[pick], normal, lobe).mean())}
    for label, result in fits.items():
        out[label] = float(mirror_brightness(result.svbrdf.flatten()[pick], normal).mean())
    return out


def _print(result: dict) -> None:
    print(
        f"\n{result['pair']}: fitted {result['fitted']}, predicted {result['predicted']} (rendered: {result['lobe']})"
    )
    print(
        f"{'row':16s} {'PSNR dB':>8s} {'rel RMS %':>9s} {'worst dB':>8s} {'fit s':>6s} {'CPU s':>6s}  "
        "models (share of pixels)"
    )
    for row in result["rows"]:
        fitted = "fit_seconds" in row
        seconds = f"{row['fit_seconds']:6.1f} {row['fit_cpu_seconds']:6.1f}" if fitted else f"{'-':>6s} {'-':>6s}"
        share = ", ".join(f"{k} {100 * v:.1f}%" for k, v in row.get("model_share", {}).items())
        print(
            f"{row['row']:16s} {row['psnr_db']:8.2f} {100 * row['relative_rms']:9.2f} "
            f"{row['worst_frame_psnr_db']:8.2f} {seconds}  {share}"
        )
    mirror = result.get("mirror")
    if mirror and mirror["pixels"]:
        fits = ", ".join(f"{k} {v:.3g}" for k, v in mirror.items() if k not in ("pixels", "truth"))
        print(f"mirror brightness on auto's {mirror['pixels']} ward-dual pixels: truth {mirror['truth']:.3g}; {fits}")


def _only(parser) -> None:
    parser.add_argument(
        "--pairs",
        nargs="+",
        metavar="NAME",
        help="run these pairs of the config only (the JSON's name then lists them)",
    )
    parser.add_argument(
        "--rows", nargs="+", metavar="LABEL", help="fit these rows only (models or runs; the JSON's name lists them)"
    )


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "relight_transfer.yaml", argv, options=_only)
    settings = load_config(args.config, Settings)
    pairs = settings.pairs
    name = Path(args.config).stem
    if args.pairs:
        unknown = sorted(set(args.pairs) - {p.name for p in pairs})
        if unknown:
            raise SystemExit(f"--pairs: {unknown} not in {args.config} (its pairs: {[p.name for p in pairs]})")
        pairs = tuple(p for p in pairs if p.name in args.pairs)
        name += "_" + "+".join(p.name for p in pairs)
    if args.rows:
        unknown = sorted(set(args.rows) - {*settings.models, *settings.runs})
        if unknown:
            raise SystemExit(f"--rows: {unknown} are neither models nor runs of {args.config}")
        name += "_" + "+".join(args.rows)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        if settings.warm_up:
            warm_up(Path(tmp) / "warm-up")
        for pair in pairs:
            result = _pair(settings, pair, Path(tmp), args.rows)
            if result is not None:
                results.append(result)
    for result in results:
        _print(result)
    out = {"settings": asdict(settings), "peak": "the predicted capture's maximum", "pairs": results}
    write_json(args.output / f"{name}.json", out)
    print(f"wrote {args.output / (name + '.json')}")
    return out


if __name__ == "__main__":
    main()
