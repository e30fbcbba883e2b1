"""Accuracy of :func:`torchspec.render.render` against an independent brute-force integration.

The brute force (``tests/brute_force.py``) shares no code with the package: Ward from the format's
formula with explicit angles, kernels from their definitions, a fine midpoint rule in the
l-plane. Over random normals (tilt <= 30 deg), roughness 0.005-0.5 (anisotropic, rotated),
lights from the zenith to 75 deg and every kernel type, this reports the largest and the median
relative error of the reference and fast paths (and of the fast path at several orders).

    python experiments/render_accuracy.py [--config configs/render_accuracy.yaml] [--output experiments/results]
"""

from __future__ import annotations

import statistics
import sys
import time
from dataclasses import asdict, dataclass

import torch
from _common import ROOT, parse_args

from torchspec._atomic import write_json
from torchspec.brdf import SVBRDF
from torchspec.config import load_config
from torchspec.lights import Kernel, Lights
from torchspec.render import render

sys.path.insert(0, str(ROOT / "tests"))
from brute_force import random_case, reference_value  # noqa: E402

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


@dataclass(frozen=True)
class Settings:
    cases: int
    fast_orders: tuple[int, ...]


def _table():
    y, x = torch.meshgrid(torch.linspace(-1, 1, 24, dtype=F64), torch.linspace(-1, 1, 24, dtype=F64), indexing="ij")
    return torch.exp(-((x - 0.1) ** 2 / 0.18 + (y + 0.05) ** 2 / 0.12) * 2.0)


KERNELS = {
    "gaussian projected 0.08": (
        Kernel("gaussian", "projected", 0.08),
        dict(kind="gaussian-projected", sigma=0.08),
        0.08,
    ),
    "gaussian projected 0.02": (
        Kernel("gaussian", "projected", 0.02),
        dict(kind="gaussian-projected", sigma=0.02),
        0.02,
    ),
    "gaussian angular 0.05": (Kernel("gaussian", "angular", 0.05), dict(kind="gaussian-angular", sigma=0.05), 0.05),
    "super-Gaussian 0.035^6": (
        Kernel("supergaussian", "angular", 0.035, 6.0),
        dict(kind="supergaussian", sigma=0.035, power=6.0),
        0.035,
    ),
    "tabulated 24x24": (
        Kernel("tabulated", table=_table(), extent=0.15),
        dict(kind="tabulated", table=_table(), extent=0.15),
        0.15,
    ),
}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "render_accuracy.yaml", argv)
    settings = load_config(args.config, Settings)
    result = {"settings": asdict(settings), "kernels": {}}
    started = time.perf_counter()
    print(f"relative error of render against the brute force, {settings.cases} random cases per kernel")
    print(f"{'kernel':26s} {'path':14s} {'max':>9s} {'median':>9s}")
    for name, (kernel, kernel_args, width) in KERNELS.items():
        paths = {"reference": dict(path="reference")}
        if kernel.kind == "gaussian":
            paths["auto"] = dict(path="auto")
            for order in settings.fast_orders:
                paths[f"fast, order {order}"] = dict(path="fast", order=order)
        errors = {label: [] for label in paths}
        for seed in range(settings.cases):
            normal, alpha, rotation, centre = random_case(seed, width)
            maps = SVBRDF(
                normal[None],
                torch.tensor([[0.3]], dtype=F64),
                torch.tensor([[1.0]], dtype=F64),
                torch.tensor([alpha], dtype=F64),
                torch.tensor([rotation], dtype=F64),
            )
            lights = Lights(centre[None], kernel, torch.ones(1, 1, dtype=F64), torch.ones(1, dtype=F64))
            expected, _ = reference_value(kernel_args, width, normal, alpha, rotation, centre, 0.3, 1.0)
            for label, options in paths.items():
                value = render(maps, lights, VIEW, **options)[0, 0, 0].item()
                errors[label].append(abs(value - expected) / max(abs(expected), 1e-12))
        result["kernels"][name] = {
            label: {"max": max(e), "median": statistics.median(e)} for label, e in errors.items()
        }
        for label, stats in result["kernels"][name].items():
            print(f"{name:26s} {label:14s} {stats['max']:9.2e} {stats['median']:9.2e}", flush=True)
    result["seconds"] = time.perf_counter() - started
    write_json(args.output / "render_accuracy.json", result)
    print(f"wrote {args.output / 'render_accuracy.json'} in {result['seconds']:.0f} s")
    return result


if __name__ == "__main__":
    main()
