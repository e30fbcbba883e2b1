"""Cast shadows on a known relief (issue 39, items 1 and 2): the height integrated from normals, and
the batched horizon / visibility against a brute-force ray march.

A relief (:func:`torchspec.simulate.relief.relief`: Gaussian bumps and a ridge, ``size x size`` pixels) gives
exact normals. They are integrated back (:func:`torchspec.model.height.height_from_normals`):

- exact normals, unweighted (the DCT solve);
- noisy normals: every normal turned by a Gaussian angle of ``noise_deg`` (std per axis), and a
  ``noisy_fraction`` of the pixels by ``noisy_deg``, integrated unweighted and weighted by
  ``1 / std^2`` (the std each pixel was drawn with, as a fit's ``std_normal_deg`` would give it).

Reported: the RMS height error in pixels (both fields mean 0) and the time. Then ``lights`` lights at
random azimuths and elevations in ``elevation_deg``: :func:`torchspec.model.visibility.horizon` (samples every
``step`` pixels, finer near the pixel) against a march in float64 every ``brute_step`` pixels over
the same bilinear field (four taps indexed directly): the horizon's error (mean, 99th percentile,
max, degrees) and the agreement of the hard visibility (light above the horizon) everywhere and
away from the shadow's edge (light more than 2 degrees from the true horizon).

    python experiments/shadows_synthetic.py [--config experiments/configs/shadows_synthetic.yaml]
                                            [--output experiments/results]
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import torch
from _common import parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.model.height import height_from_normals
from torchspec.model.visibility import elevation, horizon, marched_horizon, visibility
from torchspec.simulate.relief import ReliefConfig, relief

F64 = torch.float64


@dataclass(frozen=True)
class Settings:
    size: int = 128
    seed: int = 0
    relief: ReliefConfig = field(default_factory=ReliefConfig)
    noise_deg: float = 2.0
    noisy_fraction: float = 0.1
    noisy_deg: float = 25.0
    lights: int = 12
    elevation_deg: tuple[float, float] = (10.0, 50.0)
    step: float = 0.5
    brute_step: float = 0.0625


def brute_horizon(height, directions, start, step, rows_per_chunk=8):
    """The reference horizon (:func:`torchspec.model.visibility.marched_horizon`)."""
    return marched_horizon(height, directions, start, step, rows_per_chunk)


def _turn(normal, std_rad, g):
    """Normals turned by Gaussian tilts of ``std_rad (H, W)`` about both tangent axes."""
    delta = torch.randn(*normal.shape[:-1], 2, generator=g, dtype=F64) * std_rad[..., None]
    v = normal / normal[..., 2:]
    v = torch.cat([v[..., :2] + delta, v[..., 2:]], -1)  # a slope perturbation: about the angle near flat
    return v / v.norm(dim=-1, keepdim=True)


def _timed(fn, *args, **kwargs):
    start = time.perf_counter()
    value = fn(*args, **kwargs)
    return value, time.perf_counter() - start


def run(settings: Settings) -> dict:
    g = torch.Generator().manual_seed(settings.seed)
    shape = relief(settings.relief, settings.size, settings.size)
    truth = shape.height

    def rms(h):
        return float((h - truth).square().mean().sqrt())

    exact, t_exact = _timed(height_from_normals, shape.normal)
    std = torch.full(truth.shape, math.radians(settings.noise_deg), dtype=F64)
    std = torch.where(
        torch.rand(truth.shape, generator=g, dtype=F64) < settings.noisy_fraction, math.radians(settings.noisy_deg), std
    )
    noisy = _turn(shape.normal, std, g)
    plain, t_plain = _timed(height_from_normals, noisy)
    weighted, t_weighted = _timed(height_from_normals, noisy, 1.0 / std.square())
    heights = {
        "relief_std_px": float(truth.std()),
        "relief_range_px": float(truth.max() - truth.min()),
        "exact_unweighted": {"rms_px": rms(exact), "seconds": t_exact},
        "noisy_unweighted": {"rms_px": rms(plain), "seconds": t_plain},
        "noisy_weighted": {"rms_px": rms(weighted), "seconds": t_weighted},
    }

    lo, hi = (math.radians(v) for v in settings.elevation_deg)
    phi = 2 * math.pi * torch.rand(settings.lights, generator=g, dtype=F64)
    el = lo + (hi - lo) * torch.rand(settings.lights, generator=g, dtype=F64)
    dirs = torch.stack([el.cos() * phi.cos(), el.cos() * phi.sin(), el.sin()], -1)
    fast, t_fast = _timed(horizon, truth, dirs, step=settings.step)
    soft, t_soft = _timed(visibility, truth, dirs, step=settings.step)
    reference, t_brute = _timed(brute_horizon, truth, dirs, settings.step, settings.brute_step)
    seen = reference > -1.5  # rays that stay in the image for a while
    err = torch.rad2deg((fast - reference)[seen].abs())
    e = elevation(dirs).expand_as(reference)
    lit, fast_lit = e > reference, soft > 0.5
    away = (e - reference).abs() > math.radians(2.0)
    shadows = {
        "lights": settings.lights,
        "shadowed_fraction": float((~lit).to(F64).mean()),
        "horizon_error_deg": {
            "mean": float(err.mean()),
            "p99": float(torch.quantile(err, 0.99)),
            "max": float(err.max()),
        },
        "agreement": float((lit == fast_lit).to(F64).mean()),
        "agreement_away_from_edge": float((lit == fast_lit)[away].to(F64).mean()),
        "seconds": {"horizon": t_fast, "visibility": t_soft, "brute_force": t_brute},
    }
    return {"settings": asdict(settings), "height": heights, "shadows": shadows}


def table(result: dict) -> str:
    h, s = result["height"], result["shadows"]
    lines = [
        f"relief: std {h['relief_std_px']:.3f} px, range {h['relief_range_px']:.3f} px",
        "| height from normals | RMS error (px) | time (s) |",
        "| --- | --- | --- |",
    ]
    for name in ("exact_unweighted", "noisy_unweighted", "noisy_weighted"):
        lines.append(f"| {name} | {h[name]['rms_px']:.4f} | {h[name]['seconds']:.3f} |")
    e = s["horizon_error_deg"]
    lines += [
        "",
        f"| visibility vs brute force ({s['lights']} lights) | value |",
        "| --- | --- |",
        f"| shadowed fraction (brute force) | {s['shadowed_fraction']:.4f} |",
        f"| horizon error mean / p99 / max (deg) | {e['mean']:.3f} / {e['p99']:.3f} / {e['max']:.3f} |",
        f"| hard visibility agreement | {100 * s['agreement']:.2f} % |",
        f"| agreement > 2 deg from the edge | {100 * s['agreement_away_from_edge']:.2f} % |",
        f"| time horizon / visibility / brute (s) | {s['seconds']['horizon']:.2f} / "
        f"{s['seconds']['visibility']:.2f} / {s['seconds']['brute_force']:.1f} |",
    ]
    return "\n".join(lines)


def main(argv=None) -> dict:
    args = parse_args(__doc__, "shadows_synthetic.yaml", argv)
    settings = load_config(args.config, Settings)
    result = run(settings)
    args.output.mkdir(parents=True, exist_ok=True)
    write_json(args.output / "shadows_synthetic.json", result)
    print(table(result))
    return result


if __name__ == "__main__":
    main()
