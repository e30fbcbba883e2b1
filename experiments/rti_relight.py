"""Relighting real and RTI-format captures: torchspec against PTM and HSH, the fitters RTI users run.

The protocol of ``../shared/data/rti/README.md``: each capture is imported with ``torchspec import``
(:func:`torchspec.io.rti.import_rti`), reduced by ``downsample`` (a box average of the linear
values; the photographs scored are the reduced ones, encoded as 8-bit sRGB again), every fifth light
(frame ``i % 5 == 2``) is left out, the rest fitted, and the left-out photographs predicted. Scores
on 8-bit sRGB: PSNR over all pixels and channels (peak 1) and the mean SSIM of the luminance
(``kornia.metrics.ssim``, 11 x 11 Gaussian window). On SynthRTI captures (a ``Dome/`` and a
``Test/`` folder) also: ``Dome/`` fitted whole and ``Test/`` predicted, and the median angle
between the fitted normals and ``Dome/normals.png`` (``RGB = (n + 1) / 2``) beside plain
least-squares photometric stereo on the same frames' luminance.

- PTM (6 terms: ``lu^2, lv^2, lu lv, lu, lv, 1``) and HSH (order 3, 9 terms) are fitted per pixel
  and channel by least squares on the sRGB values (one ``torch.linalg.lstsq`` for all pixels).
- torchspec: :func:`torchspec.fit` on the fitted frames with each ``models`` entry (``auto``, or a
  forced model), the maps rendered under the left-out lights by :func:`torchspec.rendering.render_image`; the
  share of pixels given a lobe (``Fit.lobe``) is reported.
- per method: the worst left-out frame's mean brightness ratio (predicted over photographed, in
  linear values; the frame furthest from 1).

The figure (``rti_relight.png``): per capture, the most grazing and the highest left-out light,
the photograph beside HSH and each torchspec prediction.

    python experiments/rti_relight.py [--config experiments/configs/rti_relight.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import kornia
import torch
from _common import ROOT, parse_args

import torchspec
from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import write_capture
from torchspec.io.images import Transfer, read_photo
from torchspec.io.rti import import_rti
from torchspec.lights import Lights
from torchspec.relight import render_near
from torchspec.rendering import render_image
from torchspec.residual_term import hsh_basis  # order 3, 9 terms: the RTI fitters' HSH

SRGB = Transfer("srgb")
LUMA = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class Settings:
    data: str  # the folder of the captures, relative to the repository's root (or absolute)
    captures: tuple[str, ...]  # folders of `data`; a SynthRTI one holds Dome/ and Test/
    downsample: int = 1  # box-average factor of the frames (1: full size)
    models: tuple[str, ...] = ("auto",)  # torchspec fits: auto and/or forced models
    threads: int = 2  # torch threads
    compile: bool = False  # FitConfig.compile
    left_out: int = 2  # frames i % 5 == left_out are predicted
    residual_term: int = 3  # FitConfig.residual_term: rows with and without the term, of one fit
    calibrations: tuple[str, ...] = ("auto",)  # FitConfig.calibrate of the torchspec rows (each model, each)


# --- data ---------------------------------------------------------------------------------------


def _reduce(frames: torch.Tensor, factor: int) -> torch.Tensor:
    """``(K, C, H, W)`` box-averaged by ``factor`` (cropped to a multiple of it)."""
    if factor == 1:
        return frames
    return torch.nn.functional.avg_pool2d(frames, factor)


def load_reduced(folder: Path, scratch: Path, factor: int):
    """Import ``folder`` and reduce it: ``(capture, linear (K, C, H, W) float64, codes (K, C, H, W))``
    where ``codes`` are the reduced photographs as 8-bit sRGB in ``[0, 1]``."""
    name = "-".join(folder.parts[-2:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the import's notes (norms, horizon) are not scores
        imported = import_rti(folder, scratch / f"{name}-import")
    full = imported.capture
    linear = _reduce(full.read_frames(dtype=torch.float64), factor)
    codes = quantise(SRGB.encode(linear))
    linear = SRGB.decode(codes)  # the photograph as it is scored: reduced, 8-bit again
    k, c, h, w = linear.shape
    capture = replace(full, root=scratch / name, width=w, height=h)
    capture = write_capture(scratch / name, capture, linear.float())
    return capture, linear, codes


def quantise(values: torch.Tensor) -> torch.Tensor:
    """Values in ``[0, 1]`` rounded to 8-bit codes (still in ``[0, 1]``)."""
    return (values.clamp(0, 1) * 255).round() / 255


def _lights(capture, indices: list[int]) -> Lights:
    every = capture.lights(dtype=torch.float64)
    index = torch.tensor(indices)
    return Lights(every.directions[index], every.kernel, every.irradiance[index], every.exposure[index])


# --- the baselines: PTM and HSH on sRGB values ----------------------------------------------------


def ptm_basis(d: torch.Tensor) -> torch.Tensor:
    """``(K, 6)`` the PTM terms of unit directions ``d (K, 3)``."""
    u, v = d[:, 0], d[:, 1]
    return torch.stack([u * u, v * v, u * v, u, v, torch.ones_like(u)], -1)


BASES = {"PTM": ptm_basis, "HSH": hsh_basis}


def polynomial(basis, train_d, train_codes, test_d):
    """Least squares per pixel and channel of ``train_codes (K, C, H, W)`` on ``basis``; the
    prediction under ``test_d``, sRGB in ``[0, 1]``, and the seconds of the fit."""
    clock = time.perf_counter()
    k = train_codes.shape[0]
    a = basis(train_d)
    coefficients = torch.linalg.lstsq(a, train_codes.reshape(k, -1)).solution  # (P, C H W)
    seconds = time.perf_counter() - clock
    predicted = (basis(test_d) @ coefficients).reshape(-1, *train_codes.shape[1:])
    return predicted, seconds


# --- torchspec ------------------------------------------------------------------------------------


def torchspec_predict(capture, fitted: list[int], lights: Lights, model: str, calibrate: str, settings: Settings):
    """Fit ``capture`` on the ``fitted`` frames with ``model`` and ``calibrate``; render under
    ``lights`` as ``torchspec render`` does (under a dome the fit found, the lights at its radius
    along their directions, block by block: :func:`torchspec.relight.render_near`): ``(linear
    (K, C, H, W) of the physical maps, the same with the fit's residual term (``None`` without
    one), seconds, fit)``."""
    config = torchspec.FitConfig(
        model=model, compile=settings.compile, residual_term=settings.residual_term, calibrate=calibrate
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = torchspec.fit(capture, config=config, frames=fitted)
    seconds = fit.stats["seconds"]["total"]
    view = torch.tensor(capture.view, dtype=torch.float64)
    radius = (fit.stats.get("lights") or {}).get("radius")
    svbrdf = fit.svbrdf.to(torch.float64)
    if radius is not None:
        positions = radius * lights.directions
        values = render_near(svbrdf, lights, positions, view)
        termed = None if fit.term is None else render_near(svbrdf, lights, positions, view, term=fit.term)
        return values.permute(2, 3, 0, 1), None if termed is None else termed.permute(2, 3, 0, 1), seconds, fit
    values = render_image(svbrdf, lights, view)  # (H, W, K, C)
    termed = None
    if fit.term is not None:  # as torchspec render does: the maps rendered, then the term applied
        termed = fit.term.apply(values, lights).permute(2, 3, 0, 1)
    return values.permute(2, 3, 0, 1), termed, seconds, fit


# --- scores -----------------------------------------------------------------------------------------


def scores(predicted_codes: torch.Tensor, codes: torch.Tensor) -> dict:
    """PSNR (peak 1) and mean luminance SSIM of 8-bit sRGB ``(K, C, H, W)``, and the worst frame's
    mean brightness ratio (linear)."""
    predicted_codes = quantise(predicted_codes)
    mse = float((predicted_codes - codes).pow(2).mean())
    luma = torch.tensor(LUMA, dtype=codes.dtype)[None, :, None, None]
    if codes.shape[1] == 1:
        luma = torch.ones_like(luma[:, :1])
    y_p, y_o = (predicted_codes * luma).sum(1, keepdim=True), (codes * luma).sum(1, keepdim=True)
    window = min(11, codes.shape[-1] - (codes.shape[-1] + 1) % 2, codes.shape[-2] - (codes.shape[-2] + 1) % 2)
    ssim = float(kornia.metrics.ssim(y_p.float(), y_o.float(), window, max_val=1.0).mean())
    ratio = brightness_ratios(predicted_codes, codes)
    worst = int(ratio.log().abs().argmax())
    return {
        "psnr_db": math.inf if mse == 0 else 10 * math.log10(1 / mse),
        "ssim": ssim,
        "worst_brightness_ratio": float(ratio[worst]),
        "worst_frame": worst,  # its index in the frames scored
    }


def brightness_ratios(predicted_codes: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """``(K,)`` each frame's mean brightness, predicted over photographed: the linear values of the
    8-bit sRGB ``predicted_codes`` (quantised here) and ``codes`` ``(K, C, H, W)``."""
    predicted = SRGB.decode(quantise(predicted_codes)).mean((1, 2, 3))
    return predicted / SRGB.decode(codes).mean((1, 2, 3)).clamp(min=1e-12)


def normal_errors(fitted_normal: torch.Tensor, truth_png: Path, linear, directions, factor) -> dict:
    """Median angle (degrees) of torchspec's normals ``(H, W, 3)`` and of least-squares photometric
    stereo on the luminance of ``linear (K, C, H, W)`` under ``directions (K, 3)``, against
    ``truth_png`` (``RGB = (n + 1) / 2``), reduced alike."""
    truth = torch.from_numpy(read_photo(truth_png).pixels).double().permute(2, 0, 1)[None] * 2 - 1
    truth = _reduce(truth, factor)[0].permute(1, 2, 0)
    truth = truth / truth.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    luma = torch.tensor(LUMA, dtype=linear.dtype)[None, :, None, None]
    y = (linear * luma).sum(1) if linear.shape[1] == 3 else linear[:, 0]  # (K, H, W)
    g = torch.linalg.lstsq(directions, y.reshape(y.shape[0], -1)).solution.T.reshape(*y.shape[1:], 3)
    ls = g / g.norm(dim=-1, keepdim=True).clamp(min=1e-12)

    def median_deg(n):
        cos = (n.double() * truth).sum(-1).clamp(-1, 1)
        return float(torch.rad2deg(torch.acos(cos)).median())

    return {"torchspec_deg": median_deg(fitted_normal), "least_squares_ps_deg": median_deg(ls)}


# --- one capture ------------------------------------------------------------------------------------


def relight(capture, linear, codes, fitted, predicted, settings, target=None):
    """The rows of PTM, HSH and each torchspec model fitting ``fitted`` frames of ``capture`` and
    predicting the ``predicted`` ones (of ``target = (capture, linear, codes)`` when given)."""
    target_capture, _, target_codes = target or (capture, linear, codes)
    d = capture.directions()
    test_d = target_capture.directions()[predicted]
    truth = target_codes[predicted]
    rows, shown = [], {"photograph": truth}
    for name, basis in BASES.items():
        values, seconds = polynomial(basis, d[fitted], codes[fitted], test_d)
        shown[name] = quantise(values)
        rows.append({"method": name, "fit_seconds": seconds, **scores(values, truth)})
        rows[-1]["worst_frame"] = predicted[rows[-1]["worst_frame"]]  # the frame's index in the target
    fits = {}
    for model, calibrate in [(m, c) for m in settings.models for c in settings.calibrations]:
        values, termed, seconds, fit = torchspec_predict(
            capture, fitted, _lights(target_capture, predicted), model, calibrate, settings
        )
        label = model if calibrate == "auto" else f"{model} ({calibrate})"
        fits[label] = fit
        for name, prediction in ((f"torchspec {label}", values), (f"torchspec {label} + term", termed)):
            if prediction is None:
                continue
            shown[name] = quantise(SRGB.encode(prediction.clamp(0, 1)))
            row = {"method": name, "fit_seconds": seconds, **scores(shown[name], truth)}
            row["worst_frame"] = predicted[row["worst_frame"]]
            row["lobe_share"] = float(fit.lobe.double().mean())
            row["term_share"] = None if fit.term is None else float(fit.term.chosen.double().mean())
            row["pixel_frames_per_second"] = capture.width * capture.height * len(fitted) / seconds
            row["dome_radius"] = (fit.stats.get("lights") or {}).get("radius")
            rows.append(row)
    shown["elevation"] = test_d[:, 2]
    return rows, fits, shown


def run_capture(folder: Path, scratch: Path, settings: Settings, figure_rows: list) -> dict:
    """Every score of one capture (SynthRTI: the left-out protocol on Dome/, Dome -> Test, normals);
    its left-out frames' images appended to ``figure_rows`` (:func:`figure`)."""
    synth = (folder / "Dome").is_dir()
    capture, linear, codes = load_reduced(folder / "Dome" if synth else folder, scratch, settings.downsample)
    count = len(capture.frames)
    predicted = [i for i in range(count) if i % 5 == settings.left_out]
    fitted = [i for i in range(count) if i % 5 != settings.left_out]
    rows, _, shown = relight(capture, linear, codes, fitted, predicted, settings)
    out = {
        "capture": folder.name,
        "size": [capture.width, capture.height],
        "frames": count,
        "left_out": predicted,
        "rows": rows,
    }
    figure_rows.append((folder.name, shown))
    if synth:
        target = load_reduced(folder / "Test", scratch, settings.downsample)
        every = list(range(count))
        tested = list(range(len(target[0].frames)))
        dome_rows, fits, _ = relight(capture, linear, codes, every, tested, settings, target)
        out["dome_to_test"] = dome_rows
        truth = folder / "Dome" / "normals.png"
        for label, fit in fits.items():  # the first model's first: "torchspec_deg"
            errors = normal_errors(fit.svbrdf.normal, truth, linear, capture.directions(), settings.downsample)
            if "normals" not in out:
                out["normals"] = errors
            else:
                out["normals"][f"torchspec {label}_deg"] = errors["torchspec_deg"]
    return out


def _print(result: dict) -> None:
    print(f"\n{result['capture']} ({result['size'][0]}x{result['size'][1]}, {result['frames']} frames)")
    blocks = [("left out i % 5 == 2", result["rows"])]
    if "dome_to_test" in result:
        blocks.append(("Dome -> Test", result["dome_to_test"]))
    for title, rows in blocks:
        print(f"  {title}:")
        print(f"    {'method':22s} {'PSNR dB':>8s} {'SSIM':>6s} {'fit s':>7s} {'lobes':>6s} {'worst ratio':>11s}")
        for row in rows:
            lobes = f"{100 * row['lobe_share']:5.1f}%" if "lobe_share" in row else ""
            print(
                f"    {row['method']:22s} {row['psnr_db']:8.2f} {row['ssim']:6.3f} {row['fit_seconds']:7.2f} "
                f"{lobes:>6s} {row['worst_brightness_ratio']:11.3f}"
            )
    if "normals" in result:
        n = result["normals"]
        extra = "".join(f", {key[:-4]} {value:.2f} deg" for key, value in n.items() if key.startswith("torchspec "))
        print(
            f"  normals: torchspec {n['torchspec_deg']:.2f} deg{extra}, least-squares PS "
            f"{n['least_squares_ps_deg']:.2f} deg"
        )


def figure(shown: list, path: Path) -> None:
    """Per capture, its most grazing and its highest left-out light: the photograph, HSH and each
    torchspec prediction (8-bit sRGB), one row each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = [name for name in shown[0][1] if name not in ("elevation", "PTM")]
    fig, axes = plt.subplots(2 * len(shown), len(methods), figsize=(2.2 * len(methods), 2.3 * 2 * len(shown)))
    axes = axes.reshape(2 * len(shown), len(methods))
    for row, (name, images) in enumerate(shown):
        elevation = torch.rad2deg(torch.asin(images["elevation"].clamp(-1, 1)))
        for half, frame in enumerate((int(elevation.argmin()), int(elevation.argmax()))):
            for col, method in enumerate(methods):
                ax = axes[2 * row + half, col]
                ax.imshow(images[method][frame].permute(1, 2, 0).squeeze(-1).clamp(0, 1).numpy(), cmap="gray")
                ax.set_xticks([])
                ax.set_yticks([])
                if col == 0:
                    ax.set_ylabel(f"{name}\n{float(elevation[frame]):.0f} deg", fontsize=7)
                if row == 0 and half == 0:
                    ax.set_title(method, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "rti_relight.yaml", argv)
    settings = load_config(args.config, Settings)
    torch.set_num_threads(settings.threads)
    data = Path(settings.data) if Path(settings.data).is_absolute() else ROOT / settings.data
    results, shown = [], []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        for name in settings.captures:
            results.append(run_capture(data / name, Path(scratch), settings, shown))
            _print(results[-1])
    figure(shown, Path(args.output) / f"{Path(args.config).stem}.png")
    out = {
        "settings": asdict(settings),
        "torch_threads": torch.get_num_threads(),
        "seconds": time.perf_counter() - started,
        "captures": results,
    }
    write_json(Path(args.output) / f"{Path(args.config).stem}.json", out)
    return out


if __name__ == "__main__":
    main()
