"""Relighting real and RTI-format captures: torchspec against PTM, HSH and RBF, the fitters RTI users run.

The protocol of ``../shared/data/rti/README.md``: each capture's photographs are reduced by
``downsample`` (a box average of their 8-bit codes, rounded to 8 bits again: the photographs
scored), written as PNG files without a colour profile beside a copy of its light file, and
imported with ``torchspec import`` (:func:`torchspec.io.rti.import_rti`, with ``transfer``:
``null`` its default, the camera's response estimated from the photographs); every fifth light
(frame ``i % 5 == 2``) is left out, the rest fitted, and the left-out photographs predicted. A
prediction is encoded with the transfer the import decoded with (SynthRTI's ``Test/`` is imported
with its ``Dome/``'s). Scores on the 8-bit codes: PSNR over all pixels and channels (peak 1) and
the mean SSIM of the luminance
(``kornia.metrics.ssim``, 11 x 11 Gaussian window). On SynthRTI captures (a ``Dome/`` and a
``Test/`` folder) also: ``Dome/`` fitted whole and ``Test/`` predicted, and the median angle
between the fitted normals and ``Dome/normals.png`` (``RGB = (n + 1) / 2``) beside plain
least-squares photometric stereo on the same frames' luminance.

- PTM (6 terms: ``lu^2, lv^2, lu lv, lu, lv, 1``) and HSH (order 3, 9 terms) are fitted per pixel
  and channel by least squares on the codes (one ``torch.linalg.lstsq`` for all pixels).
- RBF, Relight's radial basis interpolation: Gaussians ``exp(-|l - l_j|^2 / (2 w^2))`` centred on
  the fitted lights' directions, ``w`` twice the mean distance from a fitted light to its nearest
  neighbour, weights by ridge regression (``ridge`` 0.1 on the diagonal) on the codes.
- torchspec: :func:`torchspec.fit` on the fitted frames with each ``models`` entry (``auto``, or a
  forced model), the maps rendered under the left-out lights by :func:`torchspec.relight.shaded_render`:
  ``torchspec MODEL`` the physical maps alone (``torchspec render --no-term``), ``+ term`` with the
  fit's residual term (what ``torchspec render`` renders; the default fit of an imported capture);
  the share of pixels given a lobe (``Fit.lobe``), the transfer and the lights are reported.
  ``shadows`` (``FitConfig.shadows``: ``off``, ``auto``, ``on``) adds rows ``torchspec MODEL shadows
  on`` (and ``+ term``): a fit that tried cast shadows (:mod:`torchspec.pipeline.shadows`) renders
  both times each light's visibility over its height where its judge kept them (``Fit.height``);
  each row records the judge's rounds (``shadows``) and the share of samples masked as shadows.
  ``synth_left_out: false`` scores SynthRTI captures on Dome -> Test only.
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
from dataclasses import asdict, dataclass
from pathlib import Path

import kornia
import torch
from _common import ROOT, parse_args

import torchspec
from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io.images import Transfer, read_photo
from torchspec.io.rti import find_light_file, import_rti, match_images, read_lights
from torchspec.model.lights import Lights
from torchspec.model.residual_term import hsh_basis  # order 3, 9 terms: the RTI fitters' HSH
from torchspec.relight import shaded_render, shadow_terms

SRGB = Transfer("srgb")
LUMA = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class Settings:
    data: str  # the folder of the captures, relative to the repository's root (or absolute)
    captures: tuple[str, ...]  # folders of `data`; a SynthRTI one holds Dome/ and Test/
    downsample: int = 1  # box-average factor of the frames (1: full size)
    models: tuple[str, ...] = ("auto",)  # torchspec fits: auto and/or forced models
    threads: int = 2  # torch threads
    compile: bool = False  # FitConfig.quadrature.compile
    left_out: int = 2  # frames i % 5 == left_out are predicted
    residual_term: int | str = "auto"  # FitConfig.term.order: rows with and without the term, of one fit
    calibrations: tuple[str, ...] = ("auto",)  # FitConfig.calibrate of the torchspec rows (each model, each)
    transfer: str | None = None  # import's --transfer (None: its default, auto for these untagged 8-bit files)
    ridge: float = 0.1  # the RBF baseline's ridge
    shadows: tuple[str, ...] = ("off",)  # FitConfig.shadows of the torchspec rows (each model, each)
    synth_left_out: bool = True  # SynthRTI captures: also the left-out protocol on Dome/ (else Dome -> Test only)


# --- data ---------------------------------------------------------------------------------------


def _reduce(frames: torch.Tensor, factor: int) -> torch.Tensor:
    """``(K, C, H, W)`` box-averaged by ``factor`` (cropped to a multiple of it)."""
    if factor == 1:
        return frames
    return torch.nn.functional.avg_pool2d(frames, factor)


def load_reduced(folder: Path, scratch: Path, factor: int, transfer: str | Transfer | None = None):
    """Reduce ``folder``'s photographs and import them (module docstring): ``(capture, linear
    (K, C, H, W) float64, codes (K, C, H, W) in [0, 1], the import's result)``."""
    from PIL import Image

    name = "-".join(folder.parts[-2:])
    light_file = find_light_file(folder)
    images, _, _ = match_images(read_lights(light_file))
    reduced = scratch / f"{name}-photographs"
    reduced.mkdir(parents=True)
    (reduced / light_file.name).write_bytes(light_file.read_bytes())
    codes = []
    for image in images:
        pixels = torch.from_numpy(read_photo(image).pixels).double().permute(2, 0, 1)[None]
        code = quantise(_reduce(pixels, factor))[0]
        codes.append(code)
        target = reduced / image.relative_to(light_file.parent)
        target.parent.mkdir(parents=True, exist_ok=True)
        array = (code.permute(1, 2, 0) * 255).round().to(torch.uint8).numpy()
        # PNG data under the light file's name for it (Pillow reads by content): lossless, no profile
        Image.fromarray(array.squeeze(-1) if array.shape[-1] == 1 else array).save(target, format="PNG")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the import's notes (norms, horizon) are not scores
        imported = import_rti(reduced, scratch / f"{name}-capture", transfer=transfer)
    capture = imported.capture
    return capture, capture.read_frames(dtype=torch.float64), torch.stack(codes), imported


def quantise(values: torch.Tensor) -> torch.Tensor:
    """Values in ``[0, 1]`` rounded to 8-bit codes (still in ``[0, 1]``)."""
    return (values.clamp(0, 1) * 255).round() / 255


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


def torchspec_predict(
    capture, fitted: list[int], lights: Lights, model: str, calibrate: str, settings: Settings, shadows: str = "off"
):
    """Fit ``capture`` on the ``fitted`` frames with ``model`` and ``calibrate``; render under
    ``lights`` as ``torchspec render`` does (under a dome the fit found, the lights at its radius
    along their directions, block by block: :func:`torchspec.relight.render_near`): ``(linear
    (K, C, H, W) of the physical maps, the same with the fit's residual term (``None`` without
    one), seconds, fit)``; a fit with cast shadows (``shadows``, ``FitConfig.shadows``) renders both
    times each light's visibility over its height plus its indirect light, as ``torchspec render`` does."""
    config = torchspec.FitConfig.from_dict(
        {
            "model": model,
            "calibrate": calibrate,
            "shadows": shadows,
            "quadrature": {"compile": settings.compile},
            "term": {"order": settings.residual_term},
        }
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = torchspec.fit(capture, config=config, frames=fitted)
    seconds = fit.stats["seconds"]["total"]
    view = torch.tensor(capture.view, dtype=torch.float64)
    radius = (fit.stats.get("lights") or {}).get("radius")
    svbrdf = fit.svbrdf.to(torch.float64)
    positions = None if radius is None else radius * lights.directions
    seen = bounce = None
    if fit.height is not None:  # the visibility over the fit's height, and the indirect light
        softness = math.radians(fit.stats["height"]["softness_deg"])
        share = None if fit.indirect is None else fit.indirect.to(torch.float64)
        seen, bounce = shadow_terms(svbrdf, fit.height.to(torch.float64), share, softness, lights, view, positions)
    values = shaded_render(svbrdf, lights, view, positions, seen=seen, bounce=bounce)  # (H, W, K, C)
    termed = None  # as torchspec render does: the maps rendered, shadowed, the term applied, the indirect light added
    if fit.term is not None:
        termed = shaded_render(svbrdf, lights, view, positions, seen=seen, bounce=bounce, term=fit.term)
    return values.permute(2, 3, 0, 1), None if termed is None else termed.permute(2, 3, 0, 1), seconds, fit


# --- scores -----------------------------------------------------------------------------------------


def scores(predicted_codes: torch.Tensor, codes: torch.Tensor, transfer: Transfer = SRGB) -> dict:
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
    ratio = brightness_ratios(predicted_codes, codes, transfer)
    worst = int(ratio.log().abs().argmax())
    return {
        "psnr_db": math.inf if mse == 0 else 10 * math.log10(1 / mse),
        "ssim": ssim,
        "worst_brightness_ratio": float(ratio[worst]),
        "worst_frame": worst,  # its index in the frames scored
    }


def brightness_ratios(predicted_codes: torch.Tensor, codes: torch.Tensor, transfer: Transfer = SRGB) -> torch.Tensor:
    """``(K,)`` each frame's mean brightness, predicted over photographed: the linear values (under
    ``transfer``) of the 8-bit ``predicted_codes`` (quantised here) and ``codes`` ``(K, C, H, W)``."""
    predicted = _linear(transfer, quantise(predicted_codes)).mean((1, 2, 3))
    return predicted / _linear(transfer, codes).mean((1, 2, 3)).clamp(min=1e-12)


def _linear(transfer: Transfer, codes: torch.Tensor) -> torch.Tensor:
    """``codes (K, C, H, W)`` decoded by ``transfer`` (channels last for it)."""
    return transfer.decode(codes.movedim(1, -1)).movedim(-1, 1)


def _encoded(transfer: Transfer, linear: torch.Tensor) -> torch.Tensor:
    """``linear (K, C, H, W)`` clamped to ``[0, 1]`` and encoded by ``transfer``."""
    return transfer.encode(linear.clamp(0, 1).movedim(1, -1)).movedim(-1, 1)


def rbf(train_d: torch.Tensor, train_codes: torch.Tensor, test_d: torch.Tensor, ridge: float):
    """Relight's Gaussian radial basis interpolation (module docstring) of ``train_codes (K, C, H, W)``
    over the directions ``train_d (K, 3)``, evaluated at ``test_d``; and the seconds of the fit."""
    clock = time.perf_counter()
    distance = torch.cdist(train_d, train_d)
    nearest = distance.masked_fill(torch.eye(len(train_d), dtype=torch.bool), math.inf).min(-1).values
    width = 2 * float(nearest.mean())
    gram = torch.exp(-(distance**2) / (2 * width**2))
    k = train_codes.shape[0]
    weights = torch.linalg.solve(gram + ridge * torch.eye(k, dtype=gram.dtype), train_codes.reshape(k, -1))
    seconds = time.perf_counter() - clock
    across = torch.exp(-(torch.cdist(test_d, train_d) ** 2) / (2 * width**2))
    return (across @ weights).reshape(-1, *train_codes.shape[1:]), seconds


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


def relight(capture, linear, codes, fitted, predicted, settings, transfer, target=None):
    """The rows of PTM, HSH, RBF and each torchspec model fitting ``fitted`` frames of ``capture``
    and predicting the ``predicted`` ones (of ``target = (capture, linear, codes)`` when given),
    torchspec's encoded with ``transfer``."""
    target_capture, _, target_codes = target or (capture, linear, codes)
    d = capture.directions()
    test_d = target_capture.directions()[predicted]
    truth = target_codes[predicted]
    rows, shown = [], {"photograph": truth}
    for name, basis in BASES.items():
        values, seconds = polynomial(basis, d[fitted], codes[fitted], test_d)
        shown[name] = quantise(values)
        rows.append({"method": name, "fit_seconds": seconds, **scores(values, truth, transfer)})
        rows[-1]["worst_frame"] = predicted[rows[-1]["worst_frame"]]  # the frame's index in the target
    values, seconds = rbf(d[fitted], codes[fitted], test_d, settings.ridge)
    shown["RBF"] = quantise(values)
    rows.append({"method": "RBF", "fit_seconds": seconds, **scores(values, truth, transfer)})
    rows[-1]["worst_frame"] = predicted[rows[-1]["worst_frame"]]
    fits = {}
    runs = [(m, c, s) for m in settings.models for c in settings.calibrations for s in settings.shadows]
    for model, calibrate, shadows in runs:
        values, termed, seconds, fit = torchspec_predict(
            capture, fitted, target_capture.lights(dtype=torch.float64)[predicted], model, calibrate, settings, shadows
        )
        label = model if calibrate == "auto" else f"{model} ({calibrate})"
        label = label if shadows == "off" else f"{label} shadows {shadows}"
        fits[label] = fit
        for name, prediction in ((f"torchspec {label}", values), (f"torchspec {label} + term", termed)):
            if prediction is None:
                continue
            shown[name] = quantise(_encoded(transfer, prediction))
            row = {"method": name, "fit_seconds": seconds, **scores(shown[name], truth, transfer)}
            row["worst_frame"] = predicted[row["worst_frame"]]
            row["lobe_share"] = float(fit.lobe.double().mean())
            row["term_share"] = None if fit.term is None else float(fit.term.chosen.double().mean())
            row["pixel_frames_per_second"] = capture.width * capture.height * len(fitted) / seconds
            row["dome_radius"] = (fit.stats.get("lights") or {}).get("radius")
            row["lights"] = _lights_record(fit.stats.get("lights"))
            row["shadows"] = fit.stats.get("shadows")  # tried: the rounds, their left-out RMS; used or not
            masked = fit.stats.get("masked_samples") or {}
            pixel_frames = max(capture.width * capture.height * len(fitted), 1)
            row["shadow_masked_share"] = masked.get("shadowed", 0) / pixel_frames
            rows.append(row)
    shown["elevation"] = test_d[:, 2]
    return rows, fits, shown


def _lights_record(record: dict | None) -> dict | None:
    """What the fit's light calibration kept (``fit.lights`` of ``svbrdf.json``), briefly."""
    if not record:
        return None
    gains = record.get("gains")
    spread = None
    if gains:
        flat = torch.tensor(gains, dtype=torch.float64).flatten()
        spread = [float(flat.min()), float(flat.max())]
    return {
        "calibrated": record.get("calibrated"),
        "refused": record.get("refused") is not None,
        "radius": record.get("radius"),
        "gain_range": spread,
    }


def run_capture(folder: Path, scratch: Path, settings: Settings, figure_rows: list) -> dict:
    """Every score of one capture (SynthRTI: the left-out protocol on Dome/, Dome -> Test, normals);
    its left-out frames' images appended to ``figure_rows`` (:func:`figure`)."""
    synth = (folder / "Dome").is_dir()
    source = folder / "Dome" if synth else folder
    capture, linear, codes, imported = load_reduced(source, scratch, settings.downsample, settings.transfer)
    transfer = imported.transfer
    count = len(capture.frames)
    predicted = [i for i in range(count) if i % 5 == settings.left_out]
    fitted = [i for i in range(count) if i % 5 != settings.left_out]
    rows, shown = [], {"elevation": capture.directions()[predicted][:, 2]}
    if settings.synth_left_out or not synth:
        rows, _, shown = relight(capture, linear, codes, fitted, predicted, settings, transfer)
    out = {
        "capture": folder.name,
        "size": [capture.width, capture.height],
        "frames": count,
        "left_out": predicted,
        "transfer": str(transfer),
        "response": None if getattr(imported, "response", None) is None else imported.response.to_json(),
        "rows": rows,
    }
    if rows:
        figure_rows.append((folder.name, shown))
    if synth:
        target = load_reduced(folder / "Test", scratch, settings.downsample, transfer)[:3]  # the Dome's curve
        every = list(range(count))
        tested = list(range(len(target[0].frames)))
        dome_rows, fits, _ = relight(capture, linear, codes, every, tested, settings, transfer, target)
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
        if not rows:
            continue
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
            out = {
                "settings": asdict(settings),
                "torch_threads": torch.get_num_threads(),
                "seconds": time.perf_counter() - started,
                "captures": results,
            }
            write_json(Path(args.output) / f"{Path(args.config).stem}.json", out)  # each capture's as it ends
    if shown:
        figure(shown, Path(args.output) / f"{Path(args.config).stem}.png")
    return out


if __name__ == "__main__":
    main()
