"""Exactness of FRI location without noise.

For every kernel of the config, number of samples (1D) or grid (2D, the same kernel on both
axes), dtype and method: the largest |error| over random locations of lowpass samples with a
negative DC level. Float64 should stay below 1e-10 of the period, float32 below 1e-5.

    python experiments/noise_free.py [--config experiments/configs/noise_free.yaml] [--output experiments/results]

Writes noise_free.json and noise_free.png (log10 of the worst error per kernel and size).
Most of its time goes to Cadzow on the 64 x 64 grids.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import parse_args

import torchspec as ts
from torchspec.atomic import save_figure, write_json
from torchspec.config import load_config
from torchspec.start.fri import pulses

F64 = torch.float64
DTYPES = {"float64": torch.float64, "float32": torch.float32}
BOUND = {"float64": 1e-10, "float32": 1e-5}


@dataclass(frozen=True)
class Kernel:
    kind: str
    width: float


@dataclass(frozen=True)
class Settings:
    kernels: tuple[Kernel, ...]
    samples: tuple[int, ...]
    grids: tuple[tuple[int, ...], ...]
    locations: int
    offset: float
    seed: int


def _worst(position: torch.Tensor, truth: torch.Tensor) -> float:
    return (torch.remainder(position.double() - truth + 0.5, 1.0) - 0.5).abs().max().item()


def run(settings: Settings) -> list[dict]:
    generator = torch.Generator().manual_seed(settings.seed)
    rows = []
    for kernel in settings.kernels:
        kind, width = kernel.kind, kernel.width
        width_t = torch.tensor(width, dtype=F64)
        cases = [("1D", (n,)) for n in settings.samples] + [("2D", tuple(g)) for g in settings.grids]
        for dims, shape in cases:
            bands = [(n - 1) // 2 for n in shape]
            count = settings.locations
            if dims == "1D":
                x = torch.rand(count, 1, dtype=F64, generator=generator)
                y = pulses.sample(pulses.spectrum(kind, width_t, bands[0]), x, num_samples=shape[0])
                truth, period = x[:, 0], 1.0
            else:
                x = torch.rand(count, 2, dtype=F64, generator=generator)
                spectrum = pulses.outer(*(pulses.spectrum(kind, width_t, b) for b in bands))
                y = pulses.sample_2d(spectrum, x, shape=shape)
                truth, period = x, (1.0, 1.0)
            y = y + settings.offset
            for dtype_name, dtype in DTYPES.items():
                errors = {
                    method: _worst(ts.start.fri.locate(y.to(dtype), period=period, method=method).position, truth)
                    for method in ts.start.fri.METHODS
                }
                rows.append({"kernel": kind, "width": width, "dims": dims, "shape": list(shape),
                             "dtype": dtype_name, "max_error": errors})
    return rows


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(14, 4.5))
    for ax, dtype in zip(axes, DTYPES, strict=True):
        sel = [r for r in rows if r["dtype"] == dtype]
        kernels = sorted({(r["kernel"], r["width"]) for r in sel}, key=lambda k: (k[0], k[1]))
        sizes = list(dict.fromkeys(f"{r['dims']} {'x'.join(map(str, r['shape']))}" for r in sel))
        grid = torch.full((len(kernels), len(sizes)), math.nan)
        for r in sel:
            i = kernels.index((r["kernel"], r["width"]))
            j = sizes.index(f"{r['dims']} {'x'.join(map(str, r['shape']))}")
            grid[i, j] = math.log10(max(max(r["max_error"].values()), 1e-17))
        image = ax.imshow(grid.numpy(), aspect="auto", cmap="viridis", vmin=-17, vmax=math.log10(BOUND[dtype]))
        ax.set_xticks(range(len(sizes)), sizes, rotation=70, fontsize=7)
        ax.set_yticks(range(len(kernels)), [f"{k} {w:g}" for k, w in kernels], fontsize=8)
        ax.set_title(f"{dtype}: log10 worst |error| over all methods (bound {BOUND[dtype]:g})")
        fig.colorbar(image, ax=ax)
    fig.tight_layout()
    save_figure(fig, path)


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(__doc__, "noise_free.yaml", argv)
    settings = load_config(args.config, Settings)
    rows = run(settings)
    print(f"worst |error| (periods) over {settings.locations} locations, every size, per kernel and dtype:")
    print(f"{'kernel':22s} {'dtype':8s} " + " ".join(f"{m:>9s}" for m in ts.start.fri.METHODS) + "  within bound")
    for kernel in settings.kernels:
        kind, width = kernel.kind, kernel.width
        for dtype in DTYPES:
            sel = [r for r in rows if r["kernel"] == kind and r["width"] == width and r["dtype"] == dtype]
            worst = {m: max(r["max_error"][m] for r in sel) for m in ts.start.fri.METHODS}
            ok = all(v <= BOUND[dtype] for v in worst.values())
            cells = " ".join(f"{worst[m]:9.1e}" for m in ts.start.fri.METHODS)
            print(f"{kind + ' ' + str(width):22s} {dtype:8s} " + cells
                  + f"  {'yes' if ok else 'NO'}")
    write_json(args.output / "noise_free.json", {"settings": asdict(settings), "rows": rows})
    _plot(rows, args.output / "noise_free.png")
    print(f"wrote {args.output / 'noise_free.json'} and {args.output / 'noise_free.png'}")
    return rows


if __name__ == "__main__":
    main()
