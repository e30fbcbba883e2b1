"""Lights calibrated from the photographs (:mod:`torchspec.calibration.lights`), simulated and real.

Simulated: a procedural painting (:func:`torchspec.simulate.synth.painting`: pigments, strokes, weave,
varnish with Ward lobes, a gilded box) lit by a dome of point lights at ``radius`` image widths,
each frame with its own gain per channel drawn within +-``gain_spread``. The near light is
rendered per pixel with the format's BRDF (:func:`torchspec.model.brdf.lambert`,
:func:`torchspec.model.brdf.ward_cosine`: the same terms :func:`torchspec.model.rendering.render` sums for a
point light), each pixel with its own direction and falloff; a check renders distant lights both
ways. The sensor adds noise (:func:`torchspec.simulate.synth.sense`). The calibration sees the frames and
the directions at the image centre only. Reported: gains' and positions' relative errors, and the
normals' median angular error of Lambertian photometric stereo (:func:`torchspec.calibration.lights.lambert_fit`)
under the calibrated, the nominal (gains 1, distant lights at the centre directions) and the true lights.

Real: RTI captures (``realrti-item*``) imported with :func:`torchspec.io.rti.import_rti`, divided
by exposure, downsampled by average pooling; saturated pixels left out. Reported: the spread of the
gains, the dome radius (positions' distances), and each frame's relative RMS misfit on the same
pixels under nominal and calibrated lights.

    python experiments/light_calibration.py [--config experiments/configs/light_calibration.yaml] [--data DIR]
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.calibration.lights import calibrate_lights, lambert_fit
from torchspec.config import load_config
from torchspec.io.rti import import_rti
from torchspec.model.brdf import lambert, ward_cosine
from torchspec.model.lights import Kernel, Lights
from torchspec.model.near_lights import image_points, near_light
from torchspec.model.rendering import render_image
from torchspec.simulate.synth import PaintingConfig, SensorConfig, painting, sense


@dataclass(frozen=True)
class Simulated:
    size: int
    rings: tuple[tuple[float, int], ...]  # (elevation deg, lights) per ring of the dome
    radius: float
    gain_spread: float
    seed: int
    sensor: SensorConfig
    iterations: int


@dataclass(frozen=True)
class Real:
    name: str
    near: bool


@dataclass(frozen=True)
class Settings:
    data: str
    simulated: Simulated
    real: tuple[Real, ...]
    downsample: int
    iterations: int
    threads: int


def dome(rings, dtype=torch.float64) -> torch.Tensor:
    """Unit directions of a dome's rings, each ring's lights evenly spaced, rings staggered."""
    out = []
    for r, (elevation, count) in enumerate(rings):
        phi = (torch.arange(count, dtype=dtype) + 0.5 * (r % 2)) * 2 * math.pi / count
        e = math.radians(elevation)
        out.append(
            torch.stack([math.cos(e) * phi.cos(), math.cos(e) * phi.sin(), torch.full_like(phi, math.sin(e))], 1)
        )
    return torch.cat(out)


def render_near(svbrdf, positions: torch.Tensor, gains: torch.Tensor) -> torch.Tensor:
    """``(K, C, H, W)``: the maps under point lights at ``positions`` (per-pixel direction and
    falloff), Lambert + Ward lobe of the format, times each frame's gains."""
    height, width = svbrdf.shape
    direction, falloff = near_light(positions, image_points(height, width))  # (N, K, 3), (N, K)
    n = svbrdf.normal.reshape(-1, 1, 3)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype).expand_as(direction)
    cos = (n * direction).sum(-1).clamp_min(0)
    lobe = ward_cosine(direction, view, n.expand_as(direction), svbrdf.roughness.reshape(-1, 1, 2))
    value = (
        lambert(svbrdf.diffuse.reshape(-1, 1, 3)) * cos[..., None] + svbrdf.specular.reshape(-1, 1, 3) * lobe[..., None]
    )
    value = value * falloff[..., None] * gains[None]
    return value.reshape(height, width, *gains.shape).permute(2, 3, 0, 1)


def by_ring(rings, gain_error: torch.Tensor, position_error: torch.Tensor) -> list[dict]:
    """The largest gain and position errors of each ring of the dome."""
    out, start = [], 0
    for elevation, count in rings:
        part = slice(start, start + int(count))
        out.append(
            {
                "elevation_deg": elevation,
                "gain_max": float(gain_error[part].max()),
                "position_max": float(position_error[part].max()),
            }
        )
        start += int(count)
    return out


def angular_error(normal: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos((normal * truth).sum(-1).clamp(-1, 1)))


def simulated(config: Simulated) -> dict:
    truth, _ = painting(PaintingConfig(width=config.size, height=config.size, seed=config.seed), dtype=torch.float64)
    unit = dome(config.rings)
    k = unit.shape[0]
    gen = torch.Generator().manual_seed(config.seed)
    gains = 1 + 2 * config.gain_spread * (torch.rand(k, 3, generator=gen, dtype=torch.float64) - 0.5)
    gains = gains / gains.log().mean(0).exp()
    positions = config.radius * unit
    # the check: this per-pixel renderer against render_image, distant lights (radius 1e9)
    far = render_near(truth, 1e9 * unit, torch.ones(k, 3, dtype=torch.float64))
    reference = render_image(
        truth,
        Lights(unit, Kernel("point"), torch.ones(k, 1, dtype=torch.float64), torch.ones(k, dtype=torch.float64)),
        torch.tensor([0.0, 0, 1], dtype=torch.float64),
    )
    check = float((far - reference.permute(2, 3, 0, 1)).abs().max() / reference.abs().max())
    frames, saturated = sense(render_near(truth, positions, gains), config.sensor)
    valid = ~saturated
    start = time.perf_counter()
    cal = calibrate_lights(frames, unit, valid=valid, near=True, iterations=config.iterations)
    seconds = time.perf_counter() - start
    distant = calibrate_lights(frames, unit, valid=valid, near=False, iterations=config.iterations)
    gain_error = ((cal.gains - gains) / gains).abs()
    position_error = (cal.positions - positions).norm(dim=-1) / positions.norm(dim=-1)
    fits = {
        "true lights": lambert_fit(frames, unit, gains=gains, positions=positions, valid=valid),
        "calibrated (near)": lambert_fit(frames, unit, gains=cal.gains, positions=cal.positions, valid=valid),
        "calibrated (distant, gains only)": lambert_fit(frames, unit, gains=distant.gains, valid=valid),
        "nominal (gains 1, distant)": lambert_fit(frames, unit, valid=valid),
    }
    normals = truth.normal
    maps = {}
    for name, fit in fits.items():
        error = angular_error(fit.normal, normals)
        maps[name] = {
            "normal_median_deg": float(error.median()),
            "normal_median_deg_explained": float(error[cal.explained].median()),
        }
    return {
        "renderer_check": check,
        "frames": k,
        "size": config.size,
        "radius": config.radius,
        "seconds": seconds,
        "iterations": cal.iterations,
        "gain_rel_error": {"median": float(gain_error.median()), "max": float(gain_error.max())},
        "gain_rel_error_distant_model": {
            "median": float(((distant.gains - gains) / gains).abs().median()),
            "max": float(((distant.gains - gains) / gains).abs().max()),
        },
        "gain_std_median": float(cal.gain_std.median()),
        "position_rel_error": {"median": float(position_error.median()), "max": float(position_error.max())},
        "position_std_median": float(cal.position_std.norm(dim=-1).median()),
        "by_ring": by_ring(config.rings, gain_error.amax(1), position_error),
        "radius_median": float(cal.positions.norm(dim=-1).median()),
        "explained_fraction": float(cal.explained.double().mean()),
        "maps": maps,
    }


def read_real(folder: Path, scratch: Path, downsample: int):
    """``(frames (K, C, h, w), valid, directions (K, 3))`` of an RTI folder, exposure divided out,
    average-pooled by ``downsample``; a pooled pixel is invalid when any of its pixels is saturated."""
    imported = import_rti(folder, scratch)
    capture = imported.capture
    frames = capture.read_frames(dtype=torch.float64) / capture.exposure().to(torch.float64)[:, None, None, None]
    level = capture.saturation
    clipped = capture.read_frames(dtype=torch.float64) >= (0.999 * level if level is not None else math.inf)
    pooled = F.avg_pool2d(frames, downsample)
    valid = ~(F.max_pool2d(clipped.double(), downsample) > 0)
    return pooled, valid, capture.directions().to(torch.float64)


def per_frame(rms: torch.Tensor) -> dict:
    return {"median": float(rms.median()), "max": float(rms.max()), "values": [round(float(v), 5) for v in rms]}


def real(entry: Real, data: Path, scratch: Path, settings: Settings) -> dict:
    where = scratch / f"{entry.name}-{'near' if entry.near else 'distant'}"
    frames, valid, directions = read_real(data / entry.name, where, settings.downsample)
    start = time.perf_counter()
    cal = calibrate_lights(frames, directions, valid=valid, near=entry.near, iterations=settings.iterations)
    seconds = time.perf_counter() - start
    pixels = cal.explained
    before = lambert_fit(frames, directions, valid=valid, pixels=pixels)
    after = lambert_fit(frames, directions, gains=cal.gains, positions=cal.positions, valid=valid, pixels=pixels)
    out = {
        "name": entry.name,
        "near": entry.near,
        "shape": list(frames.shape),
        "seconds": seconds,
        "iterations": cal.iterations,
        "explained_fraction": float(pixels.double().mean()),
        "gains": {
            "min": float(cal.gains.min()),
            "max": float(cal.gains.max()),
            "log_std": float(cal.gains.log().std()),
        },
        "gain_std_median": float(cal.gain_std.median()),
        "rms_nominal": per_frame(before.rms),
        "rms_calibrated": per_frame(after.rms),
    }
    if cal.positions is not None:
        distance = cal.positions.norm(dim=-1)
        turn = angular_error(cal.directions, directions / directions.norm(dim=-1, keepdim=True))
        out["distance"] = {
            "median": float(distance.median()),
            "min": float(distance.min()),
            "max": float(distance.max()),
        }
        out["distance_std_median"] = float(cal.position_std.norm(dim=-1).median())
        out["direction_change_deg"] = {"median": float(turn.median()), "max": float(turn.max())}
    return out


def print_simulated(sim: dict) -> None:
    g, gd, p = sim["gain_rel_error"], sim["gain_rel_error_distant_model"], sim["position_rel_error"]
    print(f"simulated {sim['size']}x{sim['size']}x{sim['frames']}, dome radius {sim['radius']} widths, ", end="")
    print(f"{sim['seconds']:.1f} s, {sim['iterations']} iterations (renderer check {sim['renderer_check']:.1e})")
    print(f"  gains rel error: median {g['median']:.4f} max {g['max']:.4f}", end="")
    print(f" (distant lights, gains only: {gd['median']:.4f}, {gd['max']:.4f})")
    print(f"  positions rel error: median {p['median']:.4f} max {p['max']:.4f}; radius {sim['radius_median']:.3f}")
    rings = ", ".join(f"{r['elevation_deg']:g} deg {r['gain_max']:.4f}/{r['position_max']:.4f}" for r in sim["by_ring"])
    print(f"  max gain/position rel error per ring: {rings}")
    print(f"  {'lights':34s} {'normal median deg':>18s} {'on explained':>13s}")
    for name, row in sim["maps"].items():
        print(f"  {name:34s} {row['normal_median_deg']:18.3f} {row['normal_median_deg_explained']:13.3f}")


def print_real(row: dict) -> None:
    d = row.get("distance")
    where = f"distance {d['median']:.2f} [{d['min']:.2f}, {d['max']:.2f}]" if d else "distant"
    gains, before, after = row["gains"], row["rms_nominal"]["median"], row["rms_calibrated"]["median"]
    print(
        f"{row['name']:14s} {'near' if row['near'] else 'distant':7s} gains [{gains['min']:.3f}, {gains['max']:.3f}] ",
        end="",
    )
    print(f"log-std {gains['log_std']:.3f}; {where}; rms median {before:.4f} -> {after:.4f}; ", end="")
    print(f"explained {row['explained_fraction']:.2f}; {row['seconds']:.1f} s")


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "light_calibration.yaml", argv, options=lambda p: p.add_argument("--data", type=Path))
    settings = load_config(args.config, Settings)
    torch.set_num_threads(settings.threads)
    data = args.data if args.data is not None else (ROOT / settings.data).resolve()
    sim = simulated(settings.simulated)
    print_simulated(sim)
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for entry in settings.real:
            if not (data / entry.name).exists():
                print(f"{entry.name}: absent from {data}, skipped")
                continue
            row = real(entry, data, Path(scratch), settings)
            rows.append(row)
            print_real(row)
    result = {"simulated": sim, "real": rows}
    write_json(args.output / "light_calibration.json", result)
    return result


if __name__ == "__main__":
    main()
