"""Per-pixel model selection on the development painting: ``--model auto`` against every
model forced on every pixel, and the coverage of the per-pixel standard deviations.

On ``../shared/data/painting-dev`` (truth in ``truth/``, regions matte / varnished / gilded), per
run: the count of each model per region, the total criterion (``chi^2 + P ln n`` summed over the
pixels, with the sensor noise fitted to the residuals), the time, the LM tries per model, and the
median errors against the truth. ``auto`` must give >= 95 % of the matte pixels the diffuse model,
the gilded patch an anisotropic or coloured lobe, and a total criterion below every forced
model's.

Then, on simulated paintings with shot noise (the model the data were made with, ward-iso on the
varnish): the share of pixels whose truth lies within 2 standard deviations, per parameter
(a Gaussian estimate: 95 %; the target is 90-98 %), and the sensor noise fitted against the
simulated one.

``runs`` adds fits with other settings (:class:`torchspec.pipeline.FitConfig`, by label): ``auto`` without
``ward-dual`` (its ``ladder``), to show what trying two lobes costs where no pixel has them, and
``auto`` with its choice smoothed (``smooth``).

    python experiments/model_selection.py [--config experiments/configs/model_selection.yaml]
        [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import from_mapping, load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.model.geometry import angle
from torchspec.pipeline import MODEL_CODES, FitConfig, fit, select_frames
from torchspec.report import REGIONS, score
from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.synth import PaintingConfig, SensorConfig


@dataclass(frozen=True)
class Coverage:
    size: int  # the simulated painting's width and height
    photons_per_unit: tuple[float, ...]  # shot noise levels
    seeds: tuple[int, ...]  # painting seeds


@dataclass(frozen=True)
class Settings:
    capture: str  # relative to the repository root
    frames: str  # a SPEC of torchspec.pipeline.select_frames
    models: tuple[str, ...]  # "auto" and the forced ones
    matte_ks: float
    coverage: Coverage
    runs: dict[str, dict] = field(default_factory=dict)  # more runs: label -> FitConfig settings


def _selection(settings: Settings) -> list[dict]:
    folder = (ROOT / settings.capture).resolve()
    truth = read_svbrdf(folder / "truth")
    regions = truth.extra["regions"].round().long().flatten()
    rows = []
    frames = select_frames(settings.frames, len(read_capture(folder).frames))
    runs = [(name, FitConfig(model=name)) for name in settings.models]
    runs += [(label, from_mapping(values, FitConfig, f"runs.{label}")) for label, values in settings.runs.items()]
    for name, config in runs:
        result = fit(folder, config=config, frames=frames)
        codes = result.model.flatten()
        per_region = {
            region: dict(Counter(MODEL_CODES[int(c)] for c in codes[regions == r])) for r, region in enumerate(REGIONS)
        }
        rows.append(
            {
                "model": name,
                "models_per_region": per_region,
                "criterion": result.stats["criterion"],
                "seconds_lm": result.stats["seconds"]["lm"],
                "seconds_total": result.stats["seconds"]["total"],
                "models_tried": result.stats["models_tried"],
                "smoothed": result.stats["smoothed"],
                "sensor_noise": result.stats["sensor_noise"],
                **score(result.svbrdf, truth.svbrdf, truth.extra["regions"], settings.matte_ks),
            }
        )
    return rows


def _coverage(settings: Coverage) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for ppu in settings.photons_per_unit:
            for seed in settings.seeds:
                config = SimulationConfig(
                    scene=SceneConfig(
                        kind="painting", painting=PaintingConfig(width=settings.size, height=settings.size, seed=seed)
                    ),
                    light=LightConfig(kernel="gaussian", domain="projected", sigma=0.08),
                    layout=LayoutConfig(kind="grid", nx=10, ny=10, extent=0.8, radius=0.8),
                    sensor=SensorConfig(photons_per_unit=ppu, seed=seed),
                )
                path = Path(tmp) / f"p{ppu:g}-s{seed}"
                write_simulation(path, simulate(config))
                rows.append({"photons_per_unit": ppu, "seed": seed, **_covered(path)})
    return rows


def _covered(path: Path) -> dict:
    truth_maps = read_svbrdf(path / "truth")
    truth = truth_maps.svbrdf.flatten()
    regions = truth_maps.extra["regions"].round().long().flatten()
    result = fit(path, config=FitConfig(model="auto"))
    s, std = result.svbrdf.flatten(), {k: v.flatten(0, 1) for k, v in result.std.items()}
    pick = (regions == 1) & (result.model.flatten() == MODEL_CODES.index("ward-iso"))
    z = {
        "k_d": ((s.diffuse - truth.diffuse) / std["diffuse"])[pick].flatten(),
        "k_s": ((s.specular[:, 0] - truth.specular.mean(-1)) / std["specular"][:, 0])[pick],
        "alpha": ((s.roughness[:, 0] - truth.roughness[:, 0]) / std["roughness"][:, 0])[pick],
    }
    out = {"pixels": int(pick.sum()), "varnish_ward_iso": float(pick.sum() / (regions == 1).sum())}
    out.update({name: float((v.abs() <= 2.0).double().mean()) for name, v in z.items()})
    # The normal's angle is 2D: 95 % within sqrt(ln 20) times its std for an isotropic Gaussian.
    error = angle(s.normal.double(), truth.normal.double())[pick]
    out["normal"] = float((error <= math.sqrt(math.log(20)) * std["normal"][pick]).double().mean())
    out["sensor_a"] = result.stats["sensor_noise"]["a"][0]
    return out


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "model_selection.yaml", argv)
    settings = load_config(args.config, Settings)
    rows = _selection(settings)
    print(
        f"{'model':16s} {'criterion':>11s} {'LM s':>6s} {'matte diffuse':>13s} {'gilded':>30s} {'normal':>7s} "
        f"{'k_d %':>6s} {'var a %':>7s}"
    )
    for row in rows:
        matte = row["models_per_region"]["matte"]
        share = matte.get("diffuse", 0) / max(sum(matte.values()), 1)
        gilded = ", ".join(f"{k} {v}" for k, v in sorted(row["models_per_region"]["gilded"].items()))
        print(
            f"{row['model']:16s} {row['criterion']:11.4g} {row['seconds_lm']:6.1f} {100 * share:12.1f}% "
            f"{gilded:>30s} {row['normal_deg']:7.3f} {100 * row['kd']:6.2f} {100 * row['varnished_alpha']:7.2f}"
        )
    for row in rows:
        if row["model"] == "auto" or row["model"] in settings.runs:
            print(
                f"{row['model']}: matte {row['models_per_region']['matte']}, varnish "
                f"{row['models_per_region']['varnished']}, tried {row['models_tried']}, smoothed {row['smoothed']}"
            )
    coverage = _coverage(settings.coverage)
    print(
        f"\n{'photons/unit':>12s} {'seed':>5s} {'pixels':>6s} {'k_d':>6s} {'k_s':>6s} {'alpha':>6s} {'normal':>6s} "
        f"{'a fitted x ppu':>14s}"
    )
    for row in coverage:
        print(
            f"{row['photons_per_unit']:12g} {row['seed']:5d} {row['pixels']:6d} {row['k_d']:6.3f} {row['k_s']:6.3f} "
            f"{row['alpha']:6.3f} {row['normal']:6.3f} {row['sensor_a'] * row['photons_per_unit']:14.3f}"
        )
    out = {"settings": asdict(settings), "selection": rows, "coverage": coverage}
    write_json(args.output / f"{Path(args.config).stem}.json", out)
    return out


if __name__ == "__main__":
    main()
