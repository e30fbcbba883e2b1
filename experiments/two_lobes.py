"""Two lobes where the data demand them: ``ward-dual`` chosen by ``--model auto`` on a box of
two-lobed gloss, and nowhere else; what a single lobe costs there; and the per-pixel baseline.

A simulated painting (pigments, varnish, the gilded patch, and a box of two-lobed gloss: a sharp
varnish lobe over a broad one, :class:`torchspec.simulate.synth.DualConfig`) is rendered under a
``grid x grid`` layout of a projected Gaussian light with shot noise. It is fitted on every second
frame with ``auto``, with each model forced, and (``smooth``) with ``auto``'s choice of a lobe smoothed
over the image; per run:

- the count of each model per region (matte, varnished, gilded, dual);
- the total criterion (``chi^2 + P ln n`` over the pixels), and the solver's time;
- on the dual box: the median errors of the normal and of both lobes (``k_s``, ``alpha``, ``k_s2``,
  ``alpha2``; a one-lobe fit is scored against the sharp lobe), and the PSNR of predicting the
  frames left out (the peak: the whole capture's maximum), on the box and on the whole painting.

Then, on the dual box's pixels that ``auto`` gave ``ward-dual``: the share whose truth lies within 2
of their standard deviations, per parameter (a Gaussian estimate: 95 %); and per-pixel
``scipy.optimize.least_squares`` on ``scipy_pixels`` of them, against the fit's batched solver on all
of them at once: the same model (``ward-dual``), quadrature, weights and start (time per pixel, errors).

    python experiments/two_lobes.py [--config experiments/configs/two_lobes.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from _common import parse_args, scipy_fit

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.model.brdf import SVBRDF
from torchspec.model.geometry import angle
from torchspec.model.lights import Lights
from torchspec.model.registry import get_model
from torchspec.model.rendering import render
from torchspec.pipeline import MODEL_CODES, FitConfig, LadderConfig, fit, select_frames, starting_point
from torchspec.pipeline.samples import TileSamples
from torchspec.pipeline.solver import solve_pixels
from torchspec.report import REGIONS
from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.synth import DUAL, DualConfig, PaintingConfig, SensorConfig


@dataclass(frozen=True)
class Settings:
    size: int  # the painting is size x size pixels
    seed: int
    grid: int  # grid x grid light centres over [-0.8, 0.8]^2, those beyond radius 0.8 dropped
    kernel_sigma: float
    photons_per_unit: float  # shot noise
    frames: str  # the frames fitted (select_frames); the others are predicted
    models: tuple[str, ...]  # "auto" (required) and the forced ones
    scipy_pixels: int  # dual-box pixels fitted one by one by scipy
    smooth: float = 0.0  # > 0: one more auto run with its choice of a lobe smoothed (FitConfig.ladder.smooth)
    dual: DualConfig = field(default_factory=DualConfig)


def _relative(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return ((a.double() - b.double()) / b.double()).abs()


def _errors(s: SVBRDF, t: SVBRDF) -> dict:
    """Median errors of flat maps against the truth; the second lobe's only where ``s`` has one."""
    out = {
        "normal_deg": float(torch.rad2deg(angle(s.normal.double(), t.normal.double())).median()),
        "kd": float(_relative(s.diffuse, t.diffuse).median()),
        "ks": float(_relative(s.specular.mean(-1), t.specular.mean(-1)).median()),
        "alpha": float(_relative(s.roughness[:, 0], t.roughness[:, 0]).median()),
    }
    if s.specular2 is not None and bool((s.specular2 > 0).any()):
        out["ks2"] = float(_relative(s.specular2.mean(-1), t.specular2.mean(-1)).median())
        out["alpha2"] = float(_relative(s.roughness2[:, 0], t.roughness2[:, 0]).median())
    return out


def _psnr(svbrdf: SVBRDF, lights: Lights, view: torch.Tensor, observed: torch.Tensor, peak: float) -> float:
    """PSNR of predicting ``observed (n, K, C)`` from flat maps ``(n,)``."""
    mse = (render(svbrdf.to(torch.float64), lights, view) - observed).pow(2).mean().item()
    return 10 * math.log10(peak * peak / mse)


def _simulate(settings: Settings, path: Path) -> Path:
    config = SimulationConfig(
        scene=SceneConfig(
            kind="painting",
            painting=PaintingConfig(width=settings.size, height=settings.size, seed=settings.seed, dual=settings.dual),
        ),
        light=LightConfig(kernel="gaussian", domain="projected", sigma=settings.kernel_sigma),
        layout=LayoutConfig(kind="grid", nx=settings.grid, ny=settings.grid, extent=0.8, radius=0.8),
        sensor=SensorConfig(photons_per_unit=settings.photons_per_unit, seed=settings.seed),
    )
    write_simulation(path, simulate(config))
    return path


def _coverage(result, truth: SVBRDF, pick: torch.Tensor) -> dict:
    """Share of ``pick`` whose truth lies within 2 standard deviations, per parameter."""
    s, std = result.svbrdf.flatten(), {k: v.flatten(0, 1) for k, v in result.std.items()}
    z = {
        "k_d": ((s.diffuse - truth.diffuse) / std["diffuse"])[pick].flatten(),
        "k_s": ((s.specular[:, 0] - truth.specular.mean(-1)) / std["specular"][:, 0])[pick],
        "alpha": ((s.roughness[:, 0] - truth.roughness[:, 0]) / std["roughness"][:, 0])[pick],
        "k_s2": ((s.specular2[:, 0] - truth.specular2[:, 0]) / std["specular2"][:, 0])[pick],
        "alpha2": ((s.roughness2[:, 0] - truth.roughness2[:, 0]) / std["roughness2"][:, 0])[pick],
    }
    out = {name: float((v.abs() <= 2.0).double().mean()) for name, v in z.items()}
    # The normal's angle is 2D: 95 % within sqrt(ln 20) times its std for an isotropic Gaussian.
    error = angle(s.normal.double(), truth.normal.double())[pick]
    out["normal"] = float((error <= math.sqrt(math.log(20)) * std["normal"][pick]).double().mean())
    return out


def _baseline(settings: Settings, folder: Path, frames: list[int], chosen: torch.Tensor, truth: SVBRDF) -> dict:
    """The fit's solver on the pixels ``chosen`` at once, and per-pixel scipy on ``scipy_pixels`` of
    them: the same model (``ward-dual``), quadrature, weights and start (the fit's photometric
    stereo and FRI peak), so the two differ in the solver only."""
    capture = read_capture(folder)
    config = FitConfig(model="ward-dual")
    dtype = getattr(torch, config.compute.dtype)
    lights = capture.lights(dtype=dtype)[frames]
    view = torch.tensor(capture.view, dtype=dtype)
    y = capture.read_frames(dtype=dtype)[frames].flatten(2)[:, :, chosen].permute(2, 0, 1)  # (n, K, C)
    valid = torch.isfinite(y).all(-1)
    begun = starting_point(y, valid, lights, view, config=config)
    init = begun.svbrdf(capture.channels)
    model = get_model("ward-dual")
    t0 = time.perf_counter()
    data = TileSamples.of(y, valid, begun.level, lights, view, capture.channels)
    ours = solve_pixels("ward-dual", torch.arange(y.shape[0]), init, data, config).svbrdf
    seconds = time.perf_counter() - t0
    g = torch.Generator().manual_seed(settings.seed)
    pick = torch.randperm(y.shape[0], generator=g)[: settings.scipy_pixels].sort().values
    theirs, scipy_seconds, evaluations = scipy_fit(
        model,
        y[pick],
        begun.level[pick],
        init[pick],
        lights,
        view,
        capture.channels,
        quadrature=config.rule,
    )
    t = truth[chosen]
    return {
        "pixels": int(y.shape[0]),
        "scipy_pixels": int(pick.numel()),
        "torchspec_ms_per_pixel": 1e3 * seconds / y.shape[0],
        "scipy_ms_per_pixel": 1e3 * scipy_seconds / pick.numel(),
        "scipy_evaluations_mean": sum(evaluations) / len(evaluations),
        "torchspec": _errors(ours[pick], t[pick]),
        "torchspec_all": _errors(ours, t),
        "scipy": _errors(theirs, t[pick]),
    }


def _peak_mb() -> float | None:
    """This process's peak resident memory (``VmHWM``; ``None`` off Linux)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "two_lobes.yaml", argv)
    settings = load_config(args.config, Settings)
    if "auto" not in settings.models:
        raise ValueError(f"{args.config}: models must include 'auto' (its choices are scored); got {settings.models}.")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = _simulate(settings, Path(tmp) / "capture")
        maps = read_svbrdf(folder / "truth")
        truth, regions = maps.svbrdf.flatten(), maps.extra["regions"].round().long().flatten()
        capture = read_capture(folder)
        count = len(capture.frames)
        frames = select_frames(settings.frames, count)
        left = [i for i in range(count) if i not in frames]
        observed = capture.read_frames(dtype=torch.float64).flatten(2).permute(2, 0, 1)  # (N, K, C)
        peak = float(observed.abs().max())
        held = capture.lights(dtype=torch.float64)[left]
        view = torch.tensor(capture.view, dtype=torch.float64)
        box = regions == DUAL
        bound = {
            "dual_box": _psnr(truth[box], held, view, observed[box][:, left], peak),
            "all": _psnr(truth, held, view, observed[:, left], peak),
        }
        results = {}
        runs = [(name, FitConfig(model=name)) for name in settings.models]
        if settings.smooth > 0:
            runs.append((f"auto-smooth-{settings.smooth:g}", FitConfig(ladder=LadderConfig(smooth=settings.smooth))))
        for name, config in runs:
            t0 = time.perf_counter()
            result = fit(folder, config=config, frames=frames)
            seconds = time.perf_counter() - t0
            results[name] = result
            codes = result.model.flatten()
            s = result.svbrdf.flatten()
            rows.append(
                {
                    "model": name,
                    "models_per_region": {
                        region: dict(Counter(MODEL_CODES[int(c)] for c in codes[regions == r]))
                        for r, region in enumerate(REGIONS)
                    },
                    "criterion": result.stats["criterion"],
                    "seconds_lm": result.stats["seconds"]["lm"],
                    "seconds_total": seconds,
                    "models_tried": result.stats["models_tried"],
                    "smoothed": result.stats["smoothed"],
                    "dual_box": _errors(s[box], truth[box]),
                    "held_out_psnr_db": {
                        "dual_box": _psnr(s[box], held, view, observed[box][:, left], peak),
                        "all": _psnr(s, held, view, observed[:, left], peak),
                    },
                }
            )
        chosen = box & (results["auto"].model.flatten() == MODEL_CODES.index("ward-dual"))
        coverage = _coverage(results["auto"], truth, chosen)
        baseline = _baseline(settings, folder, frames, chosen.nonzero()[:, 0], truth)

    print(
        f"{settings.size} x {settings.size} painting, {count} frames ({len(frames)} fitted), "
        f"dual box {int(box.sum())} px"
    )
    print(
        f"{'model':16s} {'criterion':>11s} {'LM s':>6s} {'dual box: models':>34s} {'normal':>7s} {'ks %':>6s} "
        f"{'a %':>6s} {'ks2 %':>6s} {'a2 %':>6s} {'held-out dB box':>15s} {'all':>6s}"
    )
    for row in rows:
        box_models = ", ".join(f"{k} {v}" for k, v in sorted(row["models_per_region"]["dual"].items()))
        e = row["dual_box"]
        two = [f"{100 * e[k]:6.2f}" if k in e else f"{'-':>6s}" for k in ("ks2", "alpha2")]
        print(
            f"{row['model']:16s} {row['criterion']:11.4g} {row['seconds_lm']:6.1f} {box_models:>34s} "
            f"{e['normal_deg']:7.3f} {100 * e['ks']:6.2f} {100 * e['alpha']:6.2f} {two[0]} {two[1]} "
            f"{row['held_out_psnr_db']['dual_box']:15.1f} {row['held_out_psnr_db']['all']:6.1f}"
        )
    print(f"{'truth':16s} {'':>11s} {'':>6s} {'':>34s} {'':>7s} {'':>6s} {'':>6s} {'':>6s} {'':>6s} "
          f"{bound['dual_box']:15.1f} {bound['all']:6.1f}")
    for row in rows:
        if row["model"].startswith("auto"):
            regions = {r: models for r, models in row["models_per_region"].items() if r != "dual"}
            print(f"{row['model']}, other regions: {regions}; lobes taken by smoothing: {row['smoothed']}")
    print("coverage within 2 std (ward-dual pixels of the box):", {k: round(v, 3) for k, v in coverage.items()})
    print(
        f"ward-dual per pixel: torchspec's solver {baseline['torchspec_ms_per_pixel']:.2f} ms "
        f"({baseline['pixels']} box pixels at once), scipy {baseline['scipy_ms_per_pixel']:.1f} ms "
        f"({baseline['scipy_pixels']} of them one by one): "
        f"{baseline['scipy_ms_per_pixel'] / baseline['torchspec_ms_per_pixel']:.0f}x; median errors on scipy's pixels:"
    )
    for who in ("torchspec", "scipy"):
        print(f"  {who:10s}", {k: round(v, 5) for k, v in baseline[who].items()})
    peak = _peak_mb()
    print(f"peak memory of this process (every fit above): {peak} MB")
    out = {
        "settings": asdict(settings),
        "dual_box_pixels": int(box.sum()),
        "truth_held_out_psnr_db": bound,
        "rows": rows,
        "coverage": coverage,
        "baseline": baseline,
        "peak_mb": peak,
    }
    write_json(args.output / f"{Path(args.config).stem}.json", out)
    return out


if __name__ == "__main__":
    main()
