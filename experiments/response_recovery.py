"""The camera's response recovered from the photographs (``torchspec import``'s ``--transfer auto``).

A simulated painting (``torchspec simulate``: Lambert + Ward, point lights on an l-plane grid) is
exposed so that its brightest 0.5 % of values clip, encoded as 8-bit PNG photographs without a
colour profile by each known curve (sRGB, a power 1.8 and 2.4, linear, and a film-like curve: a
logistic S curve of slope 4 applied to the values encoded by a power 1/2.2), written with a
``dirs.lp``, and imported twice: with the curve estimated (the default) and with the true curve
given. Per curve: the estimate's family and its largest error in linear units over codes
``[0, 1]`` (against the true curve inverted numerically), its reported uncertainty, and the fits'
maps (the default fit, ``torchspec fit``) from the estimated curve against those from the true
curve: the model chosen, the normals' angle (median and 99th percentile, degrees), ``k_d``,
``k_s`` and ``alpha`` (median relative difference where both fits have a lobe), and both against
the truth.

    python experiments/response_recovery.py [--config experiments/configs/response_recovery.yaml]
"""

from __future__ import annotations

import tempfile
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from _common import parse_args
from PIL import Image

import torchspec
from torchspec.atomic import write_json
from torchspec.calibration.response import ResponseCurve
from torchspec.config import load_config
from torchspec.io.images import Transfer
from torchspec.io.rti import import_rti
from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate
from torchspec.simulate.synth import PaintingConfig


@dataclass(frozen=True)
class Settings:
    size: int = 64  # the painting's width and height (pixels)
    seed: int = 777  # the painting's seed
    grid: int = 8  # point lights on a grid x grid l-plane grid ...
    radius: float = 0.95  # ... clipped to this radius
    clip_share: float = 0.005  # the share of values exposed above the clipping level
    curves: tuple[str, ...] = ("srgb", "power 1.8", "power 2.4", "linear", "film")
    threads: int = 2


def _film(x: torch.Tensor) -> torch.Tensor:
    low, high = torch.sigmoid(torch.tensor(-2.0)), torch.sigmoid(torch.tensor(2.0))
    return (torch.sigmoid(4 * (x.clamp(min=0) ** (1 / 2.2) - 0.5)) - low) / (high - low)


ENCODE = {
    "srgb": Transfer("srgb").encode,
    "power 1.8": lambda x: x.clamp(min=0) ** (1 / 1.8),
    "power 2.4": lambda x: x.clamp(min=0) ** (1 / 2.4),
    "linear": lambda x: x,
    "film": _film,
}
TRUE = {  # the transfer that decodes each exactly
    "srgb": Transfer("srgb"),
    "power 1.8": Transfer("gamma", 1.8),
    "power 2.4": Transfer("gamma", 2.4),
    "linear": Transfer("linear"),
    "film": Transfer("response", curve=ResponseCurve((2.2,), (0.0,), (4.0,))),
}


def photographs(folder: Path, frames: torch.Tensor, directions: torch.Tensor, encode) -> None:
    """``frames (K, C, H, W)`` in [0, 1] (clipped at 1) encoded and written as 8-bit PNGs with a ``dirs.lp``."""
    folder.mkdir(parents=True)
    lines = [str(len(frames))]
    for k, frame in enumerate(frames):
        codes = (encode(frame.clamp(0, 1)) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        Image.fromarray(codes).save(folder / f"image{k:02d}.png")
        lines.append(f"image{k:02d}.png " + " ".join(f"{v:.6f}" for v in directions[k].tolist()))
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")


def curve_error(transfer: Transfer, encode) -> float:
    """The largest difference, in linear units over codes [0, 1], of ``transfer`` from ``encode``'s inverse."""
    grid = torch.linspace(0, 1, 1001, dtype=torch.float64)
    x = torch.linspace(0, 1, 400_001, dtype=torch.float64)
    truth = torch.from_numpy(np.interp(grid.numpy(), encode(x).numpy(), x.numpy()))
    return float((transfer.decode(grid[:, None])[:, 0] - truth).abs().max())


def compare(a, b, lobes: torch.Tensor) -> dict:
    """Maps ``a`` against ``b`` (SVBRDFs): normals in degrees, relative k_d, and k_s, alpha where ``lobes``."""
    cos = (a.normal * b.normal).sum(-1).clamp(-1, 1)
    angle = torch.rad2deg(torch.acos(cos)).flatten().double()

    def rel(x, y, where=None):
        r = ((x - y).abs() / y.abs().clamp(min=1e-6)).double()
        if where is not None:
            r = r[where]
        return float(r.median()) if r.numel() else None

    return {
        "normal_deg_median": float(angle.median()),
        "normal_deg_p99": float(angle.quantile(0.99)),
        "kd_rel_median": rel(a.diffuse, b.diffuse),
        "ks_rel_median": rel(a.specular.mean(-1), b.specular.mean(-1), lobes),
        "alpha_rel_median": rel(a.roughness[..., 0], b.roughness[..., 0], lobes),
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "response_recovery.yaml", argv)
    settings = load_config(args.config, Settings)
    torch.set_num_threads(settings.threads)
    config = SimulationConfig(
        name="response",
        scene=SceneConfig(painting=PaintingConfig(width=settings.size, height=settings.size, seed=settings.seed)),
        light=LightConfig(kernel="point"),
        layout=LayoutConfig(
            kind="grid", nx=settings.grid, ny=settings.grid, extent=settings.radius, radius=settings.radius
        ),
    )
    simulation = simulate(config)
    frames = simulation.frames.double()
    level = float(torch.quantile(frames.flatten()[::7], 1 - settings.clip_share))
    frames = frames / level
    directions = simulation.capture.directions()
    truth = simulation.truth
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for name in settings.curves:
            folder = Path(scratch) / name.replace(" ", "-")
            photographs(folder / "photos", frames, directions, ENCODE[name])
            fits, row = {}, {"curve": name}
            for label, transfer in (("estimated", None), ("true", TRUE[name])):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    clock = time.perf_counter()
                    imported = import_rti(folder / "photos", folder / label, transfer=transfer)
                    seconds = time.perf_counter() - clock
                    fits[label] = torchspec.fit(imported.capture)
                if label == "estimated":
                    estimate = imported.response
                    row.update(
                        family=None if estimate is None else estimate.family,
                        transfer=str(imported.transfer),
                        curve_params=None if estimate is None else estimate.curve.to_json(),
                        max_error=curve_error(imported.transfer, ENCODE[name]),
                        reported_std=None if estimate is None else max(estimate.std),
                        import_seconds=seconds,
                    )
            a, b = fits["estimated"], fits["true"]
            both = a.lobe & b.lobe
            row["same_model_share"] = float((a.model == b.model).double().mean())
            row["estimated_vs_true"] = compare(a.svbrdf, b.svbrdf, both)
            # the maps' k_d and k_s are of the exposed frames: the truth's over the exposure level
            scaled = replace(truth, diffuse=truth.diffuse / level, specular=truth.specular / level).to(torch.float64)
            glossy = both & (truth.specular.mean(-1) > 0)
            row["estimated_vs_truth"] = compare(a.svbrdf.to(torch.float64), scaled, glossy)
            row["true_vs_truth"] = compare(b.svbrdf.to(torch.float64), scaled, glossy)
            rows.append(row)
            versus = row["estimated_vs_true"]
            print(
                f"{name:10s} -> {row['family']}: max error {row['max_error']:.4f} "
                f"(reported +-{row['reported_std'] or 0:.4f}); same model {100 * row['same_model_share']:.1f} %, "
                f"normals {versus['normal_deg_median']:.3f} deg (p99 {versus['normal_deg_p99']:.3f}), "
                f"k_d {versus['kd_rel_median']:.4f}, k_s {versus['ks_rel_median']}, alpha {versus['alpha_rel_median']}"
            )
    out = {"settings": asdict(settings), "frames": len(directions), "clip_level": level, "rows": rows}
    write_json(Path(args.output) / f"{Path(args.config).stem}.json", out)
    return out


if __name__ == "__main__":
    main()
