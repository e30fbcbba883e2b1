"""Does fri.locate say when its samples alias? Noise-free (and noisy) point samples of periodic
Gaussians of width ``sigma`` at ``N`` samples per period; per setting, the RMS error of the
position (periods), the median predicted ``std``, the ratio of the two, and the share of quality
above 0.5. Prints a table and writes ``experiments/results/fri_aliasing.json``.

    PYTHONPATH=$PWD python experiments/fri_aliasing.py
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

import torchspec as ts
from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.start.fri import pulses

HERE = Path(__file__).parent


@dataclass(frozen=True)
class Settings:
    sigmas: tuple[float, ...] = (0.05, 0.08, 0.1)
    samples: tuple[int, ...] = (9, 16)
    locations: int = 2000
    noise: tuple[float, ...] = (0.0, 0.01)
    seed: int = 0


def measure(settings: Settings) -> list[dict]:
    dtype = torch.float64
    generator = torch.Generator().manual_seed(settings.seed)
    rows = []
    for sigma in settings.sigmas:
        spectrum = pulses.spectrum("gaussian", torch.tensor(sigma, dtype=dtype), 60)
        for n in settings.samples:
            for noise in settings.noise:
                x = torch.rand(settings.locations, 1, dtype=dtype, generator=generator)
                y = pulses.sample(spectrum, x, num_samples=n)
                y = y + noise * y.abs().max() * torch.randn(y.shape, dtype=dtype, generator=generator)
                found = ts.start.fri.locate(y, period=1.0)
                error = torch.remainder(found.position - x[:, 0] + 0.5, 1.0) - 0.5
                rms = float(error.pow(2).mean().sqrt())
                std = float(found.std.median())
                rows.append(
                    {
                        "sigma": sigma,
                        "samples": n,
                        "noise": noise,
                        "rms_error": rms,
                        "median_std": std,
                        "rms_over_std": rms / std if std > 0 else float("inf"),
                        "within_2_std": float((error.abs() <= 2 * found.std).double().mean()),
                        "quality_above_half": float((found.quality > 0.5).double().mean()),
                        "median_quality": float(found.quality.median()),
                    }
                )
    return rows


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=HERE / "configs" / "fri_aliasing.yaml")
    parser.add_argument("--output", type=Path, default=HERE / "results")
    args = parser.parse_args(argv)
    settings = load_config(args.config, Settings)
    rows = measure(settings)
    print(
        f"{'sigma':>6s} {'N':>3s} {'noise':>6s} {'rms err':>9s} {'med std':>9s} {'rms/std':>8s} {'<=2std':>7s} "
        f"{'q>0.5':>6s} {'med q':>6s}"
    )
    for row in rows:
        print(
            f"{row['sigma']:6.3f} {row['samples']:3d} {row['noise']:6.3f} {row['rms_error']:9.2e} "
            f"{row['median_std']:9.2e} {row['rms_over_std']:8.2f} {row['within_2_std']:7.3f} "
            f"{row['quality_above_half']:6.3f} {row['median_quality']:6.3f}"
        )
    write_json(args.output / "fri_aliasing.json", {"settings": asdict(settings), "rows": rows})
    return rows


if __name__ == "__main__":
    main()
