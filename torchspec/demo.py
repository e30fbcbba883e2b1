"""``torchspec demo``: what the package does so far, on an embedded default.

Simulates a stack of pixels whose specular peak, blurred by a Gaussian light kernel, is seen
through an 8 x 8 grid of light positions; locates every peak at once with :func:`fri.locate`;
and reports the accuracy against the truth and the Cramer-Rao bound, the speed and the share
of pixels the quality figure flags. The full pipeline (fit a painting, write SVBRDF maps)
replaces this as it lands.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch

from . import crb, fri
from ._atomic import save_figure, write_json

__all__ = ["run"]


def run(output: Path | None = None, *, pixels: int = 65536, snr_db: float = 20.0, seed: int = 0) -> dict:
    """Run the demo; with ``output``, write ``demo.json`` and ``demo.png`` there.

    Returns:
        The summary written to ``demo.json``.
    """
    generator = torch.Generator().manual_seed(seed)
    dtype = torch.float32
    grid = (8, 8)
    bands = (3, 3)
    width = torch.tensor(0.06, dtype=torch.float64)
    spectrum = fri.pulses.outer(*(fri.pulses.spectrum("gaussian", width, b) for b in bands))
    truth = 0.2 + 0.6 * torch.rand(pixels, 2, dtype=torch.float64, generator=generator)
    amplitude = 0.5 + torch.rand(pixels, dtype=torch.float64, generator=generator)
    clean = fri.pulses.sample_2d(spectrum, truth, shape=grid, amplitude=amplitude)
    sigma = clean.pow(2).mean((-2, -1)).div(10 ** (snr_db / 10)).sqrt()
    offset = torch.randn(pixels, 1, 1, dtype=torch.float64, generator=generator)  # a residual diffuse level
    noise = sigma[:, None, None] * torch.randn(clean.shape, dtype=torch.float64, generator=generator)
    samples = (clean + offset + noise).to(dtype)

    fri.locate(samples[:1024], period=(1.0, 1.0))  # warm-up, not timed
    start = time.perf_counter()
    result = fri.locate(samples, period=(1.0, 1.0))
    elapsed = time.perf_counter() - start

    error = torch.remainder(result.position.double() - truth + 0.5, 1.0) - 0.5
    bound = crb.location_2d(spectrum * amplitude[:, None, None], num_samples=grid, noise_sigma=sigma)
    mse = error.pow(2).sum(-1).mean().item()
    summary = {
        "pixels": pixels,
        "lights": grid[0] * grid[1],
        "snr_db": snr_db,
        "seconds": round(elapsed, 4),
        "pixels_per_second": round(pixels / elapsed),
        "rms_error": math.sqrt(mse),
        "mse_over_crb": mse / bound.diagonal(dim1=-2, dim2=-1).sum(-1).mean().item(),
        "outliers": (error.abs().amax(-1) > 0.1).double().mean().item(),
        "flagged": (result.quality < 0.5).double().mean().item(),
    }
    print(f"torchspec demo: {pixels} pixels, {grid[0]}x{grid[1]} light grid, Gaussian kernel, {snr_db:g} dB")
    print(f"  located in {elapsed:.3f} s ({summary['pixels_per_second']:,} pixels/s, float32, CPU)")
    print(f"  rms error {summary['rms_error']:.2e} of the grid period; MSE / CRB = {summary['mse_over_crb']:.3f}")
    print(f"  outliers (error > 0.1): {100 * summary['outliers']:.3f} %; flagged by quality < 0.5: "
          f"{100 * summary['flagged']:.3f} %")
    if output is not None:
        _write(Path(output), summary, truth, result.position.double(), error)
        print(f"  wrote {Path(output) / 'demo.json'} and {Path(output) / 'demo.png'}")
    return summary


def _write(output: Path, summary: dict, truth, position, error) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    write_json(output / "demo.json", summary)
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 4))
    show = slice(0, 4000)
    left.scatter(truth[show, 0], position[show, 0], s=2)
    left.set(xlabel="true peak position (axis 1)", ylabel="located", title="FRI location, 2D, 8x8 lights")
    right.hist(error.norm(dim=-1).clamp(min=1e-6).log10().numpy(), bins=60)
    right.set(xlabel="log10 |error|", ylabel="pixels", title=f"MSE / CRB = {summary['mse_over_crb']:.3f}")
    fig.tight_layout()
    save_figure(fig, output / "demo.png", dpi=100)
