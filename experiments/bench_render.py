"""Benchmark of the measurement model: render, and render with its Jacobian, per path.

For ``pixels x frames x channels`` (65,536 x 144 x 3 by default, the scale of fitting a tile):
pixel-frames per second, seconds per call and peak memory (the rise of ``ru_maxrss``, each row in
a fresh process), and the relative error against the reference quadrature at high order on a
subset of the pixels. Paths: ``point`` (a point light), ``fast`` and ``auto`` (a projected
Gaussian kernel; ``auto`` sends pairs whose kernel-lobe product reaches the horizon to the
reference rule), ``fast`` fused by ``torch.compile``, ``fast`` with an angular Gaussian kernel of the
same width (in radians), eager and fused, ``reference``, and the Jacobian in its
``analytic`` and ``forward`` modes. The baseline a user would otherwise write is Monte Carlo:
light directions drawn from the kernel, the BRDF averaged over them.

    python experiments/bench_render.py [--config experiments/configs/bench_render.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import multiprocessing
import resource
import statistics
import time
from dataclasses import asdict, dataclass

import torch


@dataclass(frozen=True)
class Settings:
    pixels: int
    grid: int
    radius: float
    kernel_sigma: float
    slow_pixels: int
    accuracy_pixels: int
    monte_carlo_samples: int
    repeats: int
    seed: int


ROWS = [
    ("point", "forward"),
    ("fast", "forward"),
    ("auto", "forward"),
    ("fast, compiled", "forward"),
    ("fast, angular", "forward"),
    ("fast, compiled, angular", "forward"),
    ("reference", "forward"),
    ("Monte Carlo (baseline)", "forward"),
    ("auto", "jacobian, analytic"),
    ("auto", "jacobian, forward mode"),
]


def _scene(settings: Settings, count: int, point: bool, angular: bool = False):
    from torchspec.model.brdf import SVBRDF
    from torchspec.model.geometry import normal_from_angles
    from torchspec.model.lights import Kernel, Lights

    g = torch.Generator().manual_seed(settings.seed)
    side = settings.radius / math.sqrt(2.0)
    axis = torch.linspace(-side, side, settings.grid)
    gx, gy = torch.meshgrid(axis, axis, indexing="ij")
    l = torch.stack([gx, gy], -1).reshape(-1, 2)
    centre = torch.cat([l, torch.sqrt(1.0 - (l * l).sum(-1))[:, None]], -1)
    domain = "angular" if angular else "projected"
    kernel = Kernel("point") if point else Kernel("gaussian", domain, settings.kernel_sigma)
    lights = Lights(centre, kernel, torch.ones(centre.shape[0], 3), torch.ones(centre.shape[0]))
    maps = SVBRDF(
        normal_from_angles(0.08 * torch.randn(count, 2, generator=g)),
        torch.rand(count, 3, generator=g),
        0.3 * torch.rand(count, 1, generator=g),
        0.02 + 0.3 * torch.rand(count, 2, generator=g),
        math.pi * torch.rand(count, generator=g),
    )
    return maps, lights, torch.tensor([0.0, 0.0, 1.0])


def _monte_carlo(maps, lights, view, samples, seed):
    """The kernel sampled: ``samples`` directions per frame (shared by the pixels), BRDF averaged."""
    from torchspec.model.brdf import reflectance
    from torchspec.model.geometry import from_plane

    g = torch.Generator().manual_seed(seed)
    sigma = lights.kernel.sigma
    offsets = sigma * torch.randn(lights.directions.shape[0], samples, 2, generator=g)
    l = lights.directions[:, None, :2] + offsets
    inside = ((l * l).sum(-1) < 1.0).to(l.dtype)
    w = from_plane(l)  # (K, S, 3)
    n = maps.normal[:, None, None, :]
    rho = reflectance(w[None], view, _broadcast(maps))  # (N, K, S, C)
    cos = (n * w[None]).sum(-1).clamp(min=0.0)
    return (rho * (cos * inside)[..., None]).mean(-2) * lights.scale[None]


def _broadcast(maps):
    from torchspec.model.brdf import SVBRDF

    rotation = None if maps.rotation is None else maps.rotation[:, None, None]
    return SVBRDF(
        maps.normal[:, None, None],
        maps.diffuse[:, None, None],
        maps.specular[:, None, None],
        maps.roughness[:, None, None],
        rotation,
        maps.channels,
    )


def _row(settings: Settings, path: str, what: str) -> dict:
    from torchspec.model.jacobian import jacobian
    from torchspec.model.quadrature import Quadrature
    from torchspec.model.rendering import render

    torch.manual_seed(settings.seed)
    label = path
    slow = path in ("reference", "Monte Carlo (baseline)") or "forward mode" in what
    count = settings.slow_pixels if slow else settings.pixels
    maps, lights, view = _scene(settings, count, point=(path == "point"), angular=path.endswith("angular"))
    compiled = "compiled" in path
    if path.startswith("fast"):
        path = "fast"

    def call():
        if path == "Monte Carlo (baseline)":
            return _monte_carlo(maps, lights, view, settings.monte_carlo_samples, settings.seed)
        quadrature = Quadrature(path=path, compile=compiled)
        if what.startswith("jacobian"):
            mode = "analytic" if "analytic" in what else "forward"
            return jacobian(maps, lights, view, mode=mode, quadrature=quadrature)[0]
        return render(maps, lights, view, quadrature=quadrature)

    if compiled:  # compile (every chunk shape) outside the timing
        render(maps, lights, view, quadrature=Quadrature(path=path, compile=True))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    runs = []
    for _ in range(1 if (slow or "forward mode" in what) else settings.repeats):
        start = time.perf_counter()
        value = call()
        runs.append(time.perf_counter() - start)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    seconds = statistics.median(runs)
    # Accuracy against the reference at high order, in float64, on a subset.
    sub = maps[: settings.accuracy_pixels].to(torch.float64)
    exact = Quadrature(path="point" if path == "point" else "reference", reference_order=32)
    reference = render(sub, lights.to(torch.float64), view.double(), quadrature=exact)
    got = value[: settings.accuracy_pixels].double()
    error = ((got - reference).abs() / reference.abs().clamp(min=1e-12)).max().item()
    return {
        "path": label,
        "what": what,
        "pixels": count,
        "frames": lights.directions.shape[0],
        "seconds": seconds,
        "seconds_for_65536": seconds * 65536 / count,
        "pixel_frames_per_second": count * lights.directions.shape[0] / seconds,
        "peak_memory_mb": (peak - before) / 1024,
        "max_relative_error": error,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    from _common import parse_args

    from torchspec.atomic import write_json
    from torchspec.config import load_config

    args = parse_args(__doc__, "bench_render.yaml", argv)
    settings = load_config(args.config, Settings)
    context = multiprocessing.get_context("spawn")
    rows = []
    print(f"{settings.pixels} pixels x {settings.grid**2} frames x 3 channels, {torch.get_num_threads()} threads")
    header = ("path", "what", "pixels", "M px-fr/s", "s (65536 px)", "peak MB", "max rel err")
    print("{:24s} {:24s} {:>7s} {:>10s} {:>13s} {:>8s} {:>12s}".format(*header))
    for path, what in ROWS:
        with context.Pool(1) as pool:
            row = pool.apply(_row, (settings, path, what))
        rows.append(row)
        print(
            f"{row['path']:24s} {row['what']:24s} {row['pixels']:7d} {row['pixel_frames_per_second'] / 1e6:10.3f} "
            f"{row['seconds_for_65536']:13.2f} {row['peak_memory_mb']:8.0f} {row['max_relative_error']:12.2e}",
            flush=True,
        )
    write_json(
        args.output / "bench_render.json", {"settings": asdict(settings), "torch": torch.__version__, "rows": rows}
    )
    print(f"wrote {args.output / 'bench_render.json'}")
    return rows


if __name__ == "__main__":
    main()
