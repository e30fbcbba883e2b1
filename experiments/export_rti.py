"""Exports for the RTI world measured on the demo's fit: the HSH ``.rti`` read back against the
SVBRDF's renders, OpenLIME's gloss against the maps' ``alpha``, and the glTF export through the
Khronos glTF-Validator.

Runs ``torchspec demo`` (or takes a map folder), exports ``--to rti``, reads the file back
(:func:`torchspec.export.rti.read_rti`) and relights it as RTIViewer does (``255 * sum_k c_k H_k``,
clamped) under lights held out of the fit, against ``render_display`` of the maps (the point-light
render, clipped to 1, sRGB-encoded): errors in 8-bit codes, of the file and of the float fit before
quantisation, over all pixels and split by pixels with and without a specular lobe. Then
``--to openlime`` (``alpha`` decoded from the 8-bit gloss with OpenLIME's formula) and ``--to
gltf`` (validator counts, where node and the npm package gltf-validator are installed).

    python experiments/export_rti.py [--config experiments/configs/export_rti.yaml] [--output experiments/results]
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.demo import run as run_demo
from torchspec.export import ExportWarning, export_gltf, export_openlime, export_rti
from torchspec.export.openlime import alpha_from_gloss
from torchspec.export.rti import fit_rti, hemisphere_directions, read_rti, render_display
from torchspec.io import read_svbrdf
from torchspec.model.residual_term import hsh_basis


@dataclass(frozen=True)
class Settings:
    maps: str | None = None  # a map folder; null: run torchspec demo and use its fit
    demo_size: int = 64
    fit_lights: int = 100
    fit_theta_max_deg: float = 75.0
    held_out_lights: int = 20
    held_out_theta_max_deg: float = 70.0
    irradiance: float = math.pi


def _codes(values: np.ndarray) -> np.ndarray:
    return np.clip(values, 0, 1) * 255


def _stats(error: np.ndarray) -> dict:
    """RMS, 99th percentile and largest of absolute errors in 8-bit codes."""
    error = np.abs(error)
    return {
        "rms": float(np.sqrt((error**2).mean())),
        "p99": float(np.percentile(error, 99)),
        "max": float(error.max()),
        "share_over_1": float((error > 1).mean()),
    }


def rti_errors(maps_dir: Path, settings: Settings, work: Path) -> dict:
    """The .rti export read back and relit, against the maps' renders."""
    svbrdf = read_svbrdf(maps_dir).svbrdf.to(torch.float64)
    directions = hemisphere_directions(settings.fit_lights, settings.fit_theta_max_deg)
    clock = time.perf_counter()
    manifest = export_rti(svbrdf, work / "rti", irradiance=settings.irradiance, directions=directions)
    seconds = time.perf_counter() - clock
    coefficients, scale, _ = read_rti(manifest.parent / "image.rti")
    fit = fit_rti(svbrdf, irradiance=settings.irradiance, directions=directions)
    turn = torch.tensor([[0.6, -0.8, 0], [0.8, 0.6, 0], [0, 0, 1]], dtype=torch.float64)
    held_out = hemisphere_directions(settings.held_out_lights, settings.held_out_theta_max_deg) @ turn
    lobe = (svbrdf.specular > 0).any(-1).numpy()
    result = {"seconds": seconds, "bytes": (manifest.parent / "image.rti").stat().st_size, "scale": scale.tolist()}
    for name, lights in (("fit_lights", directions), ("held_out_lights", held_out)):
        basis = hsh_basis(lights, 3).numpy()  # (K, 9)
        renders = _codes(render_display(svbrdf, lights, settings.irradiance).numpy())  # (H, W, K, 3)
        relit = _codes(np.einsum("kj,hwcj->hwkc", basis, coefficients))
        floating = _codes(np.einsum("kj,hwcj->hwkc", basis, fit.coefficients))
        result[name] = {
            "count": int(lights.shape[0]),
            "theta_deg": np.degrees(np.arccos(lights[:, 2].numpy())).tolist(),
            "file_vs_render": _stats(relit - renders),
            "file_vs_render_lobe_pixels": _stats((relit - renders)[lobe]),
            "file_vs_render_matte_pixels": _stats((relit - renders)[~lobe]) if (~lobe).any() else None,
            "float_fit_vs_render": _stats(floating - renders),
            "file_vs_float_fit": _stats(relit - floating),
        }
    result["lobe_pixels"] = int(lobe.sum())
    result["pixels"] = int(lobe.size)
    return result


def openlime_errors(maps_dir: Path, work: Path) -> dict:
    """alpha decoded from the 8-bit gloss of the openlime export against the maps' (isotropic) alpha."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ExportWarning)
        info = json.loads(export_openlime(maps_dir, work / "openlime").read_text())
    from PIL import Image

    gloss = np.asarray(Image.open(work / "openlime" / info["channels"]["gloss"]), dtype=np.float64) / 255
    svbrdf = read_svbrdf(maps_dir).svbrdf.to(torch.float64)
    alpha = svbrdf.roughness.prod(-1).sqrt().numpy()
    lobe = (svbrdf.specular > 0).any(-1).numpy()
    decoded = alpha_from_gloss(gloss, tuple(info["alphaLimits"]))
    relative = np.abs(decoded - alpha)[lobe] / alpha[lobe]
    return {
        "alphaLimits": info["alphaLimits"],
        "alpha_relative_error": {"median": float(np.median(relative)), "max": float(relative.max())},
        "warnings": [str(w.message) for w in caught],
    }


def gltf_counts(maps_dir: Path, work: Path) -> dict | str:
    """The Khronos glTF-Validator's counts for the glTF export, or why it could not run."""
    sys.path.insert(0, str(ROOT / "tests"))
    from gltf_validator import validate, validator

    if validator()[1] is None:
        return validator()[2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExportWarning)
        path = export_gltf(maps_dir, work / "gltf")
    (report,) = validate([path])
    version = subprocess.run(
        ["node", "-e", "console.log(require('gltf-validator').version())"],
        env={"NODE_PATH": str(validator()[1]), "PATH": "/usr/bin:/bin:/usr/local/bin"},
        capture_output=True,
        text=True,
    ).stdout.strip()
    keys = ("numErrors", "numWarnings", "numInfos", "numHints")
    return {"validator": version, **{k: report[k] for k in keys}, "messages": report["messages"]}


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "export_rti.yaml", argv)
    settings = load_config(args.config, Settings)
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        if settings.maps is None:
            run_demo(work / "demo", size=settings.demo_size, progress=False)
            maps_dir = work / "demo" / "maps"
        else:
            maps_dir = (ROOT / settings.maps).resolve()
        result = {
            "settings": asdict(settings),
            "maps": "torchspec demo (its fit, maps/)" if settings.maps is None else settings.maps,
            "rti": rti_errors(maps_dir, settings, work),
            "openlime": openlime_errors(maps_dir, work),
            "gltf_validator": gltf_counts(maps_dir, work),
        }
    rti = result["rti"]
    print(
        f"HSH .rti of {result['maps']}: {rti['pixels']} pixels ({rti['lobe_pixels']} with a lobe), "
        f"{rti['bytes']} bytes, exported in {rti['seconds']:.2f} s"
    )
    print(f"{'lights':>16s} {'compared':>26s} {'RMS':>6s} {'p99':>6s} {'max':>6s} {'>1 code':>8s}  (8-bit codes)")
    for lights in ("fit_lights", "held_out_lights"):
        for what in ("file_vs_render", "file_vs_render_lobe_pixels", "file_vs_render_matte_pixels",
                     "float_fit_vs_render", "file_vs_float_fit"):  # fmt: skip
            s = rti[lights][what]
            if s is not None:
                print(
                    f"{lights:>16s} {what:>26s} {s['rms']:6.2f} {s['p99']:6.1f} {s['max']:6.1f} "
                    f"{100 * s['share_over_1']:7.1f}%"
                )
    lime = result["openlime"]
    print(
        f"openlime: alphaLimits {lime['alphaLimits']}, alpha from 8-bit gloss: median relative error "
        f"{lime['alpha_relative_error']['median']:.2e}, max {lime['alpha_relative_error']['max']:.2e}"
    )
    print(f"glTF-Validator on the gltf export: {result['gltf_validator']}")
    name = Path(args.config).stem
    write_json(args.output / f"{name}.json", result)
    print(f"wrote {args.output / f'{name}.json'}")
    return result


if __name__ == "__main__":
    main()
