"""Accuracy of :func:`torchspec.model.rendering.render` against an independent brute-force integration.

The brute force (``tests/brute_force.py``) shares no code with the package: Ward from the format's
formula with explicit angles, kernels from their definitions, a fine midpoint rule in the
l-plane. Over random normals (tilt <= 30 deg), roughness 0.005-0.5 (anisotropic, rotated),
lights from the zenith to 75 deg and every kernel type, this reports the largest and the median
relative error of the reference and fast paths (and of the fast path at several orders): of the
value (k_d = 0.3, k_s = 1) in every case, and of the specular part alone in the cases where the
light lies near the mirror direction (the lobe lit up; elsewhere it is nil).

A batched study follows, as a fit sees it: many random pixels (alpha up to 10:1) under many frames
at once, the fast and auto paths against the reference, the error relative to each pixel's
brightest frame; then the pairs where auto and reference disagree most, and some random lit pairs,
are integrated by the brute force to check the reference itself.

    python experiments/render_accuracy.py [--config experiments/configs/render_accuracy.yaml]
        [--output experiments/results]
"""

from __future__ import annotations

import math
import statistics
import sys
import time
from dataclasses import asdict, dataclass

import torch
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.model.brdf import SVBRDF
from torchspec.model.lights import Kernel, Lights
from torchspec.model.quadrature import Quadrature
from torchspec.model.rendering import render

sys.path.insert(0, str(ROOT / "tests"))
from brute_force import pixel_tensors, random_case, reference_value  # noqa: E402
from kernel_cases import KERNELS  # noqa: E402

F64 = torch.float64
VIEW = torch.tensor([0.0, 0.0, 1.0], dtype=F64)


@dataclass(frozen=True)
class Settings:
    cases: int
    fast_orders: tuple[int, ...]
    batch_pixels: int
    batch_frames: int
    spot_checks: int


def _batch(count: int, frames: int, seed: int):
    """``count`` random pixels (tilt <= 30 deg, alpha_x log-uniform in 0.005-0.5, anisotropy up to
    10:1, rotated; k_d = 0, k_s = 1) and ``frames`` light directions uniform in the l-plane disk
    out to 75 deg."""
    g = torch.Generator().manual_seed(seed)

    def uniform(n, a, b):
        return a + (b - a) * torch.rand(n, generator=g, dtype=F64)

    tilt, azimuth = uniform(count, 0.0, math.radians(30)), uniform(count, 0.0, 2 * math.pi)
    normal = torch.stack([tilt.sin() * azimuth.cos(), tilt.sin() * azimuth.sin(), tilt.cos()], -1)
    alpha_x = torch.exp(uniform(count, math.log(0.005), math.log(0.5)))
    ratio = torch.exp(uniform(count, 0.0, math.log(10.0)))
    roughness = torch.stack([alpha_x, (alpha_x / ratio).clamp(min=0.005)], -1)
    one = torch.ones(count, 1, dtype=F64)
    maps = SVBRDF(normal, 0.0 * one, one, roughness, uniform(count, 0.0, math.pi))
    radius = math.sin(math.radians(75)) * torch.sqrt(uniform(frames, 0.0, 1.0))
    phi = uniform(frames, 0.0, 2 * math.pi)
    plane = torch.stack([radius * phi.cos(), radius * phi.sin()], -1)
    return maps, torch.cat([plane, torch.sqrt(1.0 - (plane * plane).sum(-1, keepdim=True))], -1)


def _batch_study(settings: Settings) -> dict:
    print(
        f"\nbatched: {settings.batch_pixels} pixels x {settings.batch_frames} frames, error relative to each "
        f"pixel's brightest frame; reference and auto against the brute force on {settings.spot_checks} pairs"
    )
    print(f"{'kernel':26s} {'path':14s} {'max':>9s} {'p99.9':>9s} {'median':>9s} {'brute max':>9s}")
    kernels = {name: entry for name, entry in KERNELS.items() if entry[0].kind == "gaussian"}
    kernels["gaussian projected 0.2"] = (
        Kernel("gaussian", "projected", 0.2),
        dict(kind="gaussian-projected", sigma=0.2),
        0.2,
    )
    out = {}
    for index, (name, (kernel, kernel_args, width)) in enumerate(kernels.items()):
        maps, centre = _batch(settings.batch_pixels, settings.batch_frames, seed=index)
        frames = centre.shape[0]
        lights = Lights(centre, kernel, torch.ones(frames, 1, dtype=F64), torch.ones(frames, dtype=F64))
        values = {
            label: render(maps, lights, VIEW, quadrature=options)[..., 0]
            for label, options in (
                ("reference", Quadrature(path="reference")),
                ("auto", Quadrature(path="auto")),
                ("fast, order 4", Quadrature(path="fast")),
            )
        }
        reference = values["reference"]
        # A pixel no frame lights up has nothing to compare against: floor its peak.
        peak = reference.amax(-1, keepdim=True).clamp(min=1e-6 * float(reference.max()))
        # The spot checks: the pairs where auto and reference disagree most, and random lit ones.
        g = torch.Generator().manual_seed(index)
        disagree = ((values["auto"] - reference).abs() / peak).flatten()
        lit = (reference > 1e-2 * peak).flatten().nonzero()[:, 0]
        half = settings.spot_checks // 2
        picks = torch.cat([disagree.topk(half).indices, lit[torch.randperm(lit.shape[0], generator=g)[:half]]])
        brute = {"reference": [], "auto": []}
        for pair in picks.tolist():
            n, k = divmod(pair, frames)
            _, expected = reference_value(
                kernel_args,
                width,
                maps.normal[n],
                tuple(maps.roughness[n].tolist()),
                float(maps.rotation[n]),
                centre[k],
                0.0,
                1.0,
            )
            for label in brute:
                brute[label].append(abs(float(values[label][n, k]) - expected) / float(peak[n]))
        out[name] = {}
        for label in ("reference", "auto", "fast, order 4"):
            if label == "reference":
                error = torch.zeros(1, dtype=F64)
            else:
                error = ((values[label] - reference).abs() / peak).flatten()
            stats = {
                "max": float(error.max()),
                "p99.9": float(error.quantile(0.999)) if error.numel() > 1 else 0.0,
                "median": float(error.median()),
            }
            if label in brute:
                stats["brute_force_max"] = max(brute[label])
            out[name][label] = stats
            shown = f"{stats['brute_force_max']:9.2e}" if label in brute else f"{'':9s}"
            if label == "reference":
                print(f"{name:26s} {label:14s} {'':9s} {'':9s} {'':9s} {shown}", flush=True)
            else:
                print(
                    f"{name:26s} {label:14s} {stats['max']:9.2e} {stats['p99.9']:9.2e} {stats['median']:9.2e} {shown}",
                    flush=True,
                )
    return out


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "render_accuracy.yaml", argv)
    settings = load_config(args.config, Settings)
    result = {"settings": asdict(settings), "kernels": {}}
    started = time.perf_counter()
    print(f"relative error of render against the brute force, {settings.cases} random cases per kernel")
    print(f"{'kernel':26s} {'path':14s} {'max':>9s} {'median':>9s} {'spec max':>9s} {'spec med':>9s}")
    for name, (kernel, kernel_args, width) in KERNELS.items():
        paths = {"reference": Quadrature(path="reference")}
        if kernel.kind == "gaussian":
            paths["auto"] = Quadrature(path="auto")
            for order in settings.fast_orders:
                paths[f"fast, order {order}"] = Quadrature(path="fast", order=order)
        errors = {label: [] for label in paths}
        specular_errors = {label: [] for label in paths}
        for seed in range(settings.cases):
            normal, alpha, rotation, centre = random_case(seed, width)
            lights = Lights(centre[None], kernel, torch.ones(1, 1, dtype=F64), torch.ones(1, dtype=F64))
            expected, specular = reference_value(kernel_args, width, normal, alpha, rotation, centre, 0.3, 1.0)
            for k_d, target, store in ((0.3, expected, errors), (0.0, specular, specular_errors)):
                if k_d == 0.0 and seed % 2:  # the lobe is lit up in the even cases only
                    continue
                maps = SVBRDF(*pixel_tensors(normal, k_d, alpha, rotation))
                for label, options in paths.items():
                    value = render(maps, lights, VIEW, quadrature=options)[0, 0, 0].item()
                    store[label].append(abs(value - target) / max(abs(target), 1e-12))
        result["kernels"][name] = {
            label: {
                "max": max(errors[label]),
                "median": statistics.median(errors[label]),
                "specular_max": max(specular_errors[label]),
                "specular_median": statistics.median(specular_errors[label]),
            }
            for label in paths
        }
        for label, stats in result["kernels"][name].items():
            print(
                f"{name:26s} {label:14s} {stats['max']:9.2e} {stats['median']:9.2e} "
                f"{stats['specular_max']:9.2e} {stats['specular_median']:9.2e}",
                flush=True,
            )
    result["batched"] = _batch_study(settings)
    result["seconds"] = time.perf_counter() - started
    write_json(args.output / "render_accuracy.json", result)
    print(f"wrote {args.output / 'render_accuracy.json'} in {result['seconds']:.0f} s")
    return result


if __name__ == "__main__":
    main()
