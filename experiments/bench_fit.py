"""Speed, memory and accuracy of ``torchspec fit`` on a large simulated capture, against per-pixel
``scipy.optimize.least_squares`` on the same model.

A procedural painting of ``size x size`` pixels is rendered under a full ``grid x grid`` layout
of a projected Gaussian light (144 frames by default), recorded with shot noise, and written as a
capture (cached between runs). ``torchspec fit`` then runs on it in a fresh process (time from
reading the frames to the maps; peak memory is that process's own peak RSS, VmHWM), with ``threads`` torch
threads (and, from ``COMPILE_PIXELS`` pixels, torch.compile: its compilation is in the time, and
the graphs it found in its on-disk cache are counted; a first run on a machine compiles them all,
which takes longer). Run with ``TORCHINDUCTOR_CACHE_DIR`` set to an empty folder for a first run's time.
The baseline fits a random sample of the lobed pixels one by one with
``scipy.optimize.least_squares`` (trust region reflective, bounds as in the fit, the analytic
Jacobian of :func:`torchspec.model.jacobian.jacobian` with the fit's quadrature), from the same FRI
start; its time per pixel (the fastest of ``scipy_repeats`` timings of the same loop) is scaled
to the whole image. Accuracy is scored against the truth on the same pixels.

    python experiments/bench_fit.py [--config experiments/configs/bench_fit.yaml] [--output experiments/results]
"""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from _common import parse_args, scipy_fit

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import angle
from torchspec.model.registry import get_model
from torchspec.pipeline import FitConfig, starting_point
from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.synth import PaintingConfig, SensorConfig


@dataclass(frozen=True)
class Settings:
    size: int  # the painting is size x size pixels
    grid: int  # grid x grid light centres ...
    extent: float  # ... over [-extent, extent]^2 of the l-plane (all kept: 0.65 keeps the corners above 23 deg)
    kernel_sigma: float
    photons_per_unit: float  # shot noise of the simulated camera
    seed: int
    threads: int
    scipy_pixels: int  # lobed pixels fitted one by one by scipy
    cache: str  # folder for the simulated capture (reused when its settings match)
    scipy_repeats: int = 3  # scipy's loop is timed this many times, the fastest kept (the machine's load varies)
    fit: FitConfig = field(default_factory=FitConfig)


def _capture(settings: Settings, device: str = "cpu") -> Path:
    """The simulated capture (cached in ``settings.cache``), rendered on ``device`` when made."""
    key = json.dumps(
        {
            k: v
            for k, v in asdict(settings).items()
            if k in ("size", "grid", "extent", "kernel_sigma", "photons_per_unit", "seed")
        },
        sort_keys=True,
    )
    folder = (
        Path(settings.cache).expanduser() / f"painting-{settings.size}-{hashlib.sha1(key.encode()).hexdigest()[:8]}"
    )
    if (folder / "capture.json").exists():
        return folder
    config = SimulationConfig(
        name="bench-fit",
        scene=SceneConfig(
            kind="painting", painting=PaintingConfig(width=settings.size, height=settings.size, seed=settings.seed)
        ),
        light=LightConfig(kernel="gaussian", domain="projected", sigma=settings.kernel_sigma),
        layout=LayoutConfig(kind="grid", nx=settings.grid, ny=settings.grid, extent=settings.extent, radius=2.0),
        sensor=SensorConfig(photons_per_unit=settings.photons_per_unit, seed=settings.seed),
    )
    start = time.perf_counter()
    simulation = simulate(config, root=folder, device=device)
    write_simulation(folder, simulation, overwrite=True)  # a cache: an unfinished one is redone
    print(f"simulated {folder} in {time.perf_counter() - start:.0f} s")
    return folder


_CHILD = """
import json, resource, sys, time, torch
from torchspec.config import from_mapping
from torchspec.pipeline import FitConfig, fit, write_fit
torch.set_num_threads({threads})
config = from_mapping(json.loads(sys.argv[1]), FitConfig)
start = time.perf_counter()
result = fit(sys.argv[2], config=config)
seconds = time.perf_counter() - start
write_fit(sys.argv[3], result)
# The process's own peak (VmHWM): ru_maxrss keeps the parent's RSS at the fork across exec, so a
# parent that had just simulated the capture (~8 GB) would be reported as the fit's peak.
try:
    with open("/proc/self/status") as status:
        peak = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:"))
except (OSError, StopIteration):  # not Linux: ru_maxrss (KiB on Linux, bytes on macOS)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
# torch.compile's graphs found in its on-disk cache (hits) or compiled (misses): a first run on a
# machine compiles them all, which the time includes.
from torch._dynamo.utils import counters
cache = {{k: int(counters["inductor"].get("fxgraph_cache_" + k, 0)) for k in ("hit", "miss")}}
out = {{"seconds": seconds, "peak_mb": peak / 1024, "stats": result.stats, "compile_cache": cache}}
print(json.dumps(out, default=str))
"""


def _fit_in_child(settings: Settings, capture: Path, maps: Path) -> dict:
    code = _CHILD.format(threads=settings.threads)
    done = subprocess.run(
        [sys.executable, "-c", code, json.dumps(asdict(settings.fit)), str(capture), str(maps)],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        raise RuntimeError(f"the fit failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _scores(svbrdf: SVBRDF, truth: SVBRDF) -> dict:
    """Median errors: normal and k_d over every pixel, k_s and alpha over the truly lobed ones."""
    lobe = truth.specular.amax(-1) > 0
    ks = (svbrdf.specular.double().mean(-1) / truth.specular.double().mean(-1)) - 1
    alpha = (svbrdf.roughness[:, 0].double() / truth.roughness[:, 0].double()) - 1
    return {
        "normal_deg": float(torch.rad2deg(angle(svbrdf.normal.double(), truth.normal.double())).median()),
        "kd": float(((svbrdf.diffuse.double() - truth.diffuse.double()) / truth.diffuse.double()).abs().median()),
        "ks": float(ks[lobe].abs().median()) if lobe.any() else None,
        "alpha": float(alpha[lobe].abs().median()) if lobe.any() else None,
    }


def _scipy(settings: Settings, capture_dir: Path, pick: torch.Tensor) -> tuple[SVBRDF, float, list[int]]:
    """Per-pixel scipy least_squares from the fit's own start: returns the maps, seconds, evaluations."""
    torch.set_num_threads(settings.threads)
    capture = read_capture(capture_dir)
    dtype = getattr(torch, settings.fit.compute.dtype)
    lights = capture.lights(dtype=dtype)
    view = torch.tensor(capture.view, dtype=dtype)
    stack = capture.read_frames(dtype=dtype).flatten(2)  # (K, C, H W)
    y = stack[:, :, pick].permute(2, 0, 1)  # (n, K, C)
    # The fit's own start (photometric stereo, then the FRI peak), as the fit would make it.
    begun = starting_point(y, torch.isfinite(y).all(-1), lights, view, config=settings.fit)
    if settings.fit.model == "auto":  # the baseline fits one model; auto picks among several per pixel
        raise ValueError("bench_fit compares one model with scipy: set fit.model to one of the models, not 'auto'.")
    model = get_model(settings.fit.model)
    channels = capture.channels
    return scipy_fit(
        model,
        y,
        begun.level,
        begun.svbrdf(channels),
        lights,
        view,
        channels,
        path=settings.fit.quadrature.path,
        quadrature=settings.fit.rule,
        repeats=settings.scipy_repeats,
    )


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(__doc__, "bench_fit.yaml", argv)
    settings = load_config(args.config, Settings)
    capture = _capture(settings)
    truth = read_svbrdf(capture / "truth").svbrdf.flatten()
    pixels = settings.size * settings.size
    frames = len(read_capture(capture).frames)
    with tempfile.TemporaryDirectory() as tmp:
        ours = _fit_in_child(settings, capture, Path(tmp) / "maps")
        maps = read_svbrdf(Path(tmp) / "maps").svbrdf.flatten()
    lobed = (truth.specular.amax(-1) > 0) & ~(read_svbrdf(capture / "truth").extra["regions"].reshape(-1) == 2)
    g = torch.Generator().manual_seed(settings.seed)
    candidates = lobed.nonzero()[:, 0]
    pick = candidates[torch.randperm(candidates.numel(), generator=g)[: settings.scipy_pixels]].sort().values
    baseline, scipy_seconds, evaluations = _scipy(settings, capture, pick)
    per_pixel = scipy_seconds / pick.numel()
    rows = [
        {
            "method": "torchspec fit",
            "pixels": pixels,
            "frames": frames,
            "seconds": ours["seconds"],
            "pixels_per_second": pixels / ours["seconds"],
            "peak_mb": ours["peak_mb"],
            "all_pixels": _scores(maps, truth),
            "sampled_pixels": _scores(maps[pick], truth[pick]),
            "lm_iterations_mean_lobe": ours["stats"]["iterations"]["mean_lobe"],
            "stage_seconds": ours["stats"]["seconds"],
            "compile_cache": ours["compile_cache"],
        },
        {
            "method": f"scipy least_squares, per pixel (best of {max(1, settings.scipy_repeats)})",
            "pixels": int(pick.numel()),
            "frames": frames,
            "seconds": scipy_seconds,
            "pixels_per_second": 1.0 / per_pixel,
            "seconds_for_all_pixels": per_pixel * pixels,
            "peak_mb": None,
            "sampled_pixels": _scores(baseline, truth[pick]),
            "evaluations_mean": float(np.mean(evaluations)),
        },
    ]
    speedup = per_pixel * pixels / ours["seconds"]
    print(f"{size_label(settings)}, {frames} frames, {settings.threads} threads, {settings.fit.compute.dtype}")
    print(
        f"{'method':44s} {'pixels':>8s} {'seconds':>9s} {'pixels/s':>9s} {'peak MB':>8s} "
        f"{'normal deg':>10s} {'k_d %':>6s} {'k_s %':>6s} {'alpha %':>7s}  (sampled lobed pixels)"
    )
    for row in rows:
        sc = row["sampled_pixels"]
        peak = "-" if row["peak_mb"] is None else f"{row['peak_mb']:.0f}"
        print(
            f"{row['method']:44s} {row['pixels']:8d} {row['seconds']:9.1f} {row['pixels_per_second']:9.1f} {peak:>8s} "
            f"{sc['normal_deg']:10.4f} {100 * sc['kd']:6.2f} {100 * sc['ks']:6.2f} {100 * sc['alpha']:7.2f}"
        )
    print(
        f"scipy for all {pixels} pixels: {per_pixel * pixels:.0f} s (extrapolated): torchspec is {speedup:.1f}x faster"
    )
    cache = ours["compile_cache"]
    print(f"torch.compile graphs: {cache['hit']} from its cache, {cache['miss']} compiled (their time is in the fit's)")
    write_json(
        args.output / f"{Path(args.config).stem}.json",
        {"settings": asdict(settings), "torch": torch.__version__, "rows": rows, "speedup": speedup},
    )
    return rows


def size_label(settings: Settings) -> str:
    return f"{settings.size} x {settings.size} pixels"


if __name__ == "__main__":
    main()
