"""Fig. 2 of the paper: FRI location error against SNR, every method beside the Cramer-Rao bound.

Reproduces "Accurate recovery of a specularity from a few samples of the reflectance function"
(ICASSP 2016), Sec. 4, Fig. 2: a Gaussian pulse (tau = 1), N = 2M + 1 lowpass samples with
M = 2 and 8, white noise at SNR -10..50 dB (SNR = mean square of the samples over the noise
variance), 10,000 repetitions per point in one batched call per method. The caption's
sigma = 0.05 and the text's variance 0.05 are both run. Method ``pooled`` is ``coherent`` with
the kernel's spectrum pooled over the point's repetitions (``locate(..., kernel="pooled")``),
which share it. Adds the 2D case (separable Gaussian, 8 x 8 grid) with the paper's single-row
estimator, and the time per 10^6 locations.

    python experiments/fig2_crb.py [--config experiments/configs/fig2.yaml] [--output experiments/results]

Writes <config stem>.json and .png (fig2.json, fig2.png); prints MSE / CRB (with its standard
error in the JSON) and the outlier rate per point.
"""

from __future__ import annotations

import math
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import parse_args

import torchspec as ts
from torchspec.atomic import save_figure, write_json
from torchspec.config import load_config
from torchspec.start.fri import pulses

F64 = torch.float64


@dataclass(frozen=True)
class Kernel:
    label: str
    sigma: float


@dataclass(frozen=True)
class TwoD:
    grid: tuple[int, ...]
    snr_db: tuple[float, ...]


@dataclass(frozen=True)
class Timing:
    samples: int
    locations: int
    slow_locations: int
    repeats: int


@dataclass(frozen=True)
class Settings:
    period: float
    kernels: tuple[Kernel, ...]
    bands: tuple[int, ...]
    snr_db: tuple[float, ...]
    repetitions: int
    methods: tuple[str, ...]
    outlier: float
    seed: int
    two_d: TwoD
    timing: Timing


POOLED = "pooled"
"""The method name of ``coherent`` with the kernel pooled over the batch (``kernel="pooled"``):
every repetition of a point shares the kernel, as the pixels of a tile do."""


def _locate(y: torch.Tensor, period, method: str) -> torch.Tensor:
    if method == POOLED:
        return ts.start.fri.locate(y, period=period, kernel="pooled").position
    return ts.start.fri.locate(y, period=period, method=method).position


def _noisy(clean: torch.Tensor, snr_db: float, generator) -> tuple[torch.Tensor, torch.Tensor]:
    dims = tuple(range(1, clean.dim()))
    sigma = clean.pow(2).mean(dims).div(10 ** (snr_db / 10)).sqrt()
    noise = torch.randn(clean.shape, dtype=clean.dtype, generator=generator)
    return clean + sigma.view(-1, *[1] * len(dims)) * noise, sigma


def _score(sq_error: torch.Tensor, bound: torch.Tensor, outlier: torch.Tensor) -> dict:
    """MSE over the (mean) bound, with the standard error of that ratio, and the outlier rate."""
    ratio = sq_error / bound.mean()
    return {
        "mse": sq_error.mean().item(),
        "mse_over_crb": ratio.mean().item(),
        "stderr": (ratio.std() / math.sqrt(ratio.numel())).item(),
        "outliers": outlier.double().mean().item(),
    }


def run_1d(settings: Settings, generator) -> list[dict]:
    tau = settings.period
    curves = []
    for kernel in settings.kernels:
        for bands in settings.bands:
            n = 2 * bands + 1
            spectrum = pulses.spectrum("gaussian", torch.tensor(kernel.sigma, dtype=F64), bands, period=tau)
            points = []
            for snr in settings.snr_db:
                x = tau * torch.rand(settings.repetitions, 1, dtype=F64, generator=generator)
                y, sigma = _noisy(pulses.sample(spectrum, x, num_samples=n, period=tau), snr, generator)
                bound = ts.model.crb.location_1d(spectrum, num_samples=n, noise_sigma=sigma, period=tau)
                point = {"snr_db": snr, "crb": bound.mean().item(), "methods": {}}
                for method in settings.methods:
                    position = _locate(y, tau, method)
                    error = torch.remainder(position - x[:, 0] + tau / 2, tau) - tau / 2
                    point["methods"][method] = _score(error**2, bound, error.abs() > settings.outlier * tau)
                points.append(point)
            curves.append({"kernel": kernel.label, "sigma": kernel.sigma, "M": bands, "N": n, "points": points})
    return curves


def run_2d(settings: Settings, generator) -> list[dict]:
    tau = settings.period
    shape = tuple(settings.two_d.grid)
    bands = tuple((n - 1) // 2 for n in shape)
    curves = []
    for kernel in settings.kernels:
        width = torch.tensor(kernel.sigma, dtype=F64)
        spectrum = pulses.outer(*(pulses.spectrum("gaussian", width, b, period=tau) for b in bands))
        points = []
        for snr in settings.two_d.snr_db:
            x = tau * torch.rand(settings.repetitions, 2, dtype=F64, generator=generator)
            y, sigma = _noisy(pulses.sample_2d(spectrum, x, shape=shape, period=(tau, tau)), snr, generator)
            cov = ts.model.crb.location_2d(spectrum, num_samples=shape, noise_sigma=sigma, period=(tau, tau))
            bound = cov.diagonal(dim1=-2, dim2=-1).sum(-1)
            point = {"snr_db": snr, "crb": bound.mean().item(), "methods": {}}
            estimates = {m: _locate(y, (tau, tau), m) for m in settings.methods}
            # The paper's estimator: equation (5) on the row through the origin of the spectrum,
            # i.e. on the marginal sums of the samples, one axis at a time.
            estimates["ls (row 0 only, the paper)"] = torch.stack(
                [
                    ts.start.fri.locate(y.sum(-1), period=tau, method="ls").position,
                    ts.start.fri.locate(y.sum(-2), period=tau, method="ls").position,
                ],
                -1,
            )
            for method, position in estimates.items():
                error = torch.remainder(position - x + tau / 2, tau) - tau / 2
                outlier = error.abs().amax(-1) > settings.outlier * tau
                point["methods"][method] = _score(error.pow(2).sum(-1), bound, outlier)
            points.append(point)
        curves.append({"kernel": kernel.label, "sigma": kernel.sigma, "grid": list(shape), "points": points})
    return curves


def run_timing(settings: Settings, generator) -> dict:
    """Seconds per 10^6 one-dimensional locations, N samples, float32 (the working dtype)."""
    timing = settings.timing
    bands = (timing.samples - 1) // 2
    spectrum = pulses.spectrum("gaussian", torch.tensor(0.05, dtype=F64), bands)
    x = torch.rand(timing.locations, 1, dtype=F64, generator=generator)
    y, _ = _noisy(pulses.sample(spectrum, x, num_samples=timing.samples), 20.0, generator)
    y = y.float()
    out = {"samples": timing.samples, "dtype": "float32", "threads": torch.get_num_threads(), "methods": {}}
    for method in settings.methods:
        count = timing.slow_locations if method in ("esprit", "cadzow") else timing.locations
        batch = y[:count]
        _locate(batch[:1024], 1.0, method)
        runs = []
        for _ in range(timing.repeats):
            start = time.perf_counter()
            _locate(batch, 1.0, method)
            runs.append(time.perf_counter() - start)
        seconds = statistics.median(runs) * 1e6 / count
        out["methods"][method] = {"seconds_per_million": seconds, "measured_on": count}
    return out


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves_1d, curves_2d = result["one_d"], result["two_d"]
    fig, axes = plt.subplots(2, 3, figsize=(16, 9))
    markers = {
        "coherent": "o",
        POOLED: "P",
        "ml": "s",
        "ls": "^",
        "esprit": "v",
        "cadzow": "D",
        "ls (row 0 only, the paper)": "x",
    }
    # A config with fewer curves leaves panels empty: zip stops at the shorter on purpose.
    panels = list(zip(axes[:, :2].T.reshape(-1), curves_1d, strict=False))
    panels += list(zip(axes[:, 2], curves_2d, strict=False))
    for ax, curve in panels:
        snr = [p["snr_db"] for p in curve["points"]]
        ax.semilogy(snr, [math.sqrt(p["crb"]) for p in curve["points"]], "k-", lw=2, label="CRB")
        for method in curve["points"][0]["methods"]:
            rmse = [math.sqrt(p["methods"][method]["mse"]) for p in curve["points"]]
            ax.semilogy(snr, rmse, marker=markers.get(method, "."), ls="none", ms=4, label=method)
        if "M" in curve:
            where = f"M = {curve['M']} (N = {curve['N']})"
        else:
            where = f"2D, {curve['grid'][0]}x{curve['grid'][1]} grid"
        ax.set(title=f"{curve['kernel']}, {where}", xlabel="SNR (dB)", ylabel="RMS location error (periods)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    axes[0, 2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


def _print(result: dict) -> None:
    for curve in result["one_d"] + result["two_d"]:
        where = f"M={curve['M']} N={curve['N']}" if "M" in curve else f"2D {curve['grid']}"
        methods = list(curve["points"][0]["methods"])
        print(f"\n{curve['kernel']}, {where}: MSE / CRB (outlier %)")
        print(f"{'SNR':>5} {'CRB std':>9} " + " ".join(f"{m[:16]:>18}" for m in methods))
        for p in curve["points"]:
            cells = " ".join(
                f"{p['methods'][m]['mse_over_crb']:7.3f} ({100 * p['methods'][m]['outliers']:5.2f}%)".rjust(18)
                for m in methods
            )
            print(f"{p['snr_db']:5.0f} {math.sqrt(p['crb']):9.2e} {cells}")
    timing = result["timing"]
    print(f"\nseconds per 10^6 locations, N = {timing['samples']}, {timing['dtype']}, {timing['threads']} threads:")
    for method, t in timing["methods"].items():
        rate = 1 / t["seconds_per_million"]
        print(f"  {method:9s} {t['seconds_per_million']:8.3f} s  ({rate:.2f} M/s; measured on {t['measured_on']:,})")


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "fig2.yaml", argv)
    settings = load_config(args.config, Settings)
    generator = torch.Generator().manual_seed(settings.seed)
    started = time.perf_counter()
    result = {
        "settings": asdict(settings),
        "torch": torch.__version__,
        "one_d": run_1d(settings, generator),
        "two_d": run_2d(settings, generator),
        "timing": run_timing(settings, generator),
    }
    result["seconds"] = time.perf_counter() - started
    _print(result)
    stem = args.output / args.config.stem
    write_json(stem.with_suffix(".json"), result)
    _plot(result, stem.with_suffix(".png"))
    print(f"\nwrote {stem.with_suffix('.json')} and {stem.with_suffix('.png')} in {result['seconds']:.0f} s")
    return result


if __name__ == "__main__":
    main()
