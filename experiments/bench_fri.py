"""Benchmark of FRI location: speed, peak memory and accuracy against the Cramer-Rao bound, for
every method of :func:`torchspec.start.fri.locate` and for the baselines a user would otherwise pick:

- ``argmax + parabola``: the brightest sample refined by a parabola through it and its two
  neighbours (vectorised NumPy), the usual way to read a peak off point samples;
- ``scipy least_squares``: a per-pixel fit of the exact model (lowpass Gaussian pulse: location,
  amplitude, width, offset) with ``scipy.optimize.least_squares``, started from the parabola.

Its rows are points of the speed-vs-accuracy chart (``speed_accuracy.py``). Each row runs in a fresh
process, so its peak memory (the rise of ``ru_maxrss`` during the call) is its own.

    python experiments/bench_fri.py [--config experiments/configs/bench_fri.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import multiprocessing
import resource
import statistics
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

F64 = torch.float64


@dataclass(frozen=True)
class Settings:
    samples: int
    kernel_sigma: float
    snr_db: float
    locations: int
    slow_locations: int
    scipy_locations: int
    repeats: int
    seed: int
    rows: tuple[tuple[str, ...], ...]


def _data(settings: Settings, count: int, dtype: torch.dtype):
    """Noisy samples ``(count, N)`` in ``dtype``, the truth and the bound, made in chunks straight
    into their final tensor, so that making them does not set a high-water mark above the call."""
    from torchspec.model import crb
    from torchspec.start.fri import pulses

    generator = torch.Generator().manual_seed(settings.seed)
    bands = (settings.samples - 1) // 2
    spectrum = pulses.spectrum("gaussian", torch.tensor(settings.kernel_sigma, dtype=F64), bands)
    x = torch.rand(count, 1, dtype=F64, generator=generator)
    y = torch.empty(count, settings.samples, dtype=dtype)
    sigma = torch.empty(count, dtype=F64)
    for rows in torch.arange(count).split(1 << 14):
        clean = pulses.sample(spectrum, x[rows], num_samples=settings.samples)
        sigma[rows] = clean.pow(2).mean(-1).div(10 ** (settings.snr_db / 10)).sqrt()
        noise = torch.randn(clean.shape, dtype=F64, generator=generator)
        y[rows] = (clean + sigma[rows, None] * noise).to(dtype)
    bound = crb.location_1d(spectrum, num_samples=settings.samples, noise_sigma=sigma)
    return y, x[:, 0], bound


def _accuracy(position: torch.Tensor, x: torch.Tensor, bound: torch.Tensor) -> dict:
    error = torch.remainder(position.double() - x + 0.5, 1.0) - 0.5
    ratio = error.pow(2) / bound.mean()
    return {
        "mse_over_crb": ratio.mean().item(),
        "stderr": (ratio.std() / math.sqrt(ratio.numel())).item(),
        "outliers": (error.abs() > 0.1).double().mean().item(),
    }


def _parabola(y: np.ndarray) -> np.ndarray:
    n = y.shape[-1]
    k = y.argmax(-1)
    rows = np.arange(y.shape[0])
    left, mid, right = y[rows, (k - 1) % n], y[rows, k], y[rows, (k + 1) % n]
    curv = left - 2 * mid + right
    offset = np.where(curv < 0, 0.5 * (left - right) / np.where(curv < 0, curv, -1.0), 0.0)
    return ((k + np.clip(offset, -0.5, 0.5)) / n) % 1.0


def _least_squares(y: np.ndarray, start: np.ndarray, bands: int) -> np.ndarray:
    from scipy.optimize import least_squares

    n = y.shape[-1]
    t = np.arange(n) / n
    m = np.arange(1, bands + 1)

    def model(p):
        x, amp, width, offset = p
        a = np.exp(-2 * math.pi**2 * width**2 * m**2)
        return offset + amp * (1 + 2 * (a * np.cos(2 * math.pi * m * (t[:, None] - x))).sum(-1))

    out = np.empty(y.shape[0])
    for row in range(y.shape[0]):
        target = y[row]
        guess = [start[row], target.max() - target.mean(), 0.05, 0.0]
        bounds = ([-1, 0, 1e-3, -np.inf], [2, np.inf, 0.5, np.inf])
        fit = least_squares(lambda p, target=target: model(p) - target, guess, bounds=bounds)
        out[row] = fit.x[0] % 1.0
    return out


def _row(settings: Settings, name: str, dtype: str) -> dict:
    """One benchmark row, run in its own process."""
    import torchspec as ts

    torch.manual_seed(settings.seed)
    if name in ("argmax + parabola", "scipy least_squares"):
        count = settings.scipy_locations if name.startswith("scipy") else settings.locations
    else:
        count = settings.slow_locations if name in ("esprit", "cadzow") else settings.locations
    y, x, bound = _data(settings, count, getattr(torch, dtype))
    bands = (settings.samples - 1) // 2
    if name == "argmax + parabola":

        def call():
            return torch.from_numpy(_parabola(y.numpy()))
    elif name == "scipy least_squares":
        start = _parabola(y.numpy())

        def call():
            return torch.from_numpy(_least_squares(y.numpy(), start, bands))
    else:
        # "pooled": coherent with the kernel pooled over the batch (two passes).
        options = {"kernel": "pooled"} if name == "pooled" else {"method": name}
        ts.start.fri.locate(y[:1024], period=1.0, **options)

        def call():
            return ts.start.fri.locate(y, period=1.0, **options).position

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    runs = []
    for _ in range(1 if name.startswith("scipy") else settings.repeats):
        start_time = time.perf_counter()
        position = call()
        runs.append(time.perf_counter() - start_time)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    seconds = statistics.median(runs)
    return {
        "method": name,
        "dtype": dtype,
        "measured_on": count,
        "seconds_per_million": seconds * 1e6 / count,
        "locations_per_second": count / seconds,
        "peak_memory_mb": (peak - before) / 1024,  # ru_maxrss is in KiB on Linux
        **_accuracy(position, x, bound),
    }


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchspec.atomic import save_figure

    fig, ax = plt.subplots(figsize=(7, 5))
    for k, row in enumerate(rows):
        point = (row["seconds_per_million"] * 1e-6, row["mse_over_crb"])
        ax.loglog(*point, "o")
        # Stagger the labels: the fast rows sit close together near the bound.
        ax.annotate(
            f"{row['method']} ({row['dtype']})",
            point,
            fontsize=8,
            xytext=(6, 14 * (k % 3) - 10),
            textcoords="offset points",
            arrowprops={"arrowstyle": "-", "lw": 0.5},
        )
    ax.axhline(1.0, color="k", lw=1, label="Cramer-Rao bound")
    ax.set(
        xlabel="seconds per location (2 CPU threads)",
        ylabel="MSE / CRB",
        title="FRI location: speed against accuracy (N = 16, 20 dB)",
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> list[dict]:
    from _common import parse_args

    from torchspec.atomic import write_json
    from torchspec.config import load_config

    args = parse_args(__doc__, "bench_fri.yaml", argv)
    settings = load_config(args.config, Settings)
    jobs = [tuple(r) for r in settings.rows] + [("argmax + parabola", "float64"), ("scipy least_squares", "float64")]
    context = multiprocessing.get_context("spawn")
    rows = []
    print(
        f"N = {settings.samples}, Gaussian kernel sigma = {settings.kernel_sigma}, {settings.snr_db:g} dB, "
        f"{torch.get_num_threads()} torch threads"
    )
    header = ("method", "dtype", "M loc/s", "s / 10^6", "peak MB", "MSE/CRB", "outliers")
    print("{:22s} {:8s} {:>8s} {:>9s} {:>8s} {:>15s} {:>9s}".format(*header))
    for name, dtype in jobs:
        with context.Pool(1) as pool:
            row = pool.apply(_row, (settings, name, dtype))
        rows.append(row)
        print(
            f"{row['method']:22s} {row['dtype']:8s} {row['locations_per_second'] / 1e6:8.3f} "
            f"{row['seconds_per_million']:9.3f} {row['peak_memory_mb']:8.0f} "
            f"{row['mse_over_crb']:8.3f}+-{row['stderr']:.3f} {100 * row['outliers']:8.3f}%",
            flush=True,
        )
    write_json(args.output / "bench_fri.json", {"settings": asdict(settings), "torch": torch.__version__, "rows": rows})
    _plot(rows, args.output / "bench_fri.png")
    print(f"wrote {args.output / 'bench_fri.json'} and {args.output / 'bench_fri.png'}")
    return rows


if __name__ == "__main__":
    main()
