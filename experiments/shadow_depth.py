"""How deep the height integrated from reduced normals should be (``torchspec.pipeline.shadows.DEPTHS``).

SynthRTI's deep relief with its *true* normals (``Dome/normals.png``), reduced as
``rti_relight.py`` reduces the photographs (box average, renormalised): the height integrated
from them (:func:`torchspec.model.height.height_from_normals`), scaled by each depth, gives each
light's visibility (:func:`torchspec.model.visibility.frame_visibility`, penumbra ``softness_deg``);
per pixel and channel, least squares on the Dome lights of ``a V max(n.l, 0) + b l_z`` (Lambert
times the visibility plus the indirect light of :mod:`torchspec.model.indirect`, ``a, b >= 0``)
predicts the Test lights, scored as ``rti_relight.py`` scores (8-bit PSNR). Also the height
integrated from the full-resolution normals, then reduced; and HSH for reference. No fit: what the
physical model can reach with the right normals, and how the depth of the height moves it.

    python experiments/shadow_depth.py [--config experiments/configs/shadow_depth.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import ROOT, parse_args
from rti_relight import BASES, _encoded, _reduce, load_reduced, polynomial, scores

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io.images import read_photo
from torchspec.model.height import height_from_normals
from torchspec.model.visibility import frame_visibility


@dataclass(frozen=True)
class Settings:
    data: str  # the folder of the captures, relative to the repository's root (or absolute)
    captures: tuple[str, ...]  # SynthRTI folders (Dome/ with normals.png, Test/)
    downsample: int = 4
    depths: tuple[float, ...] = (1.0, 1.25, 1.5, 2.0)
    softness_deg: float = 2.0


def _unit(n: torch.Tensor) -> torch.Tensor:
    return n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)


def predict(height, normal, dome, test, observed, softness):
    """``(K_test, C, H, W)``: the least-squares fit of module's model on ``dome``'s frames
    ``observed``, under ``test``'s lights (each ``(capture, lights)``)."""
    rows, cols, _ = normal.shape

    def design(capture, lights):
        d = capture.directions().double()
        seen = frame_visibility(height, lights, None, softness=softness).permute(2, 0, 1)  # (K, H, W)
        lit = (normal[None] * d[:, None, None, :]).sum(-1).clamp(min=0)
        lz = d[:, 2, None, None].expand_as(lit)
        return torch.stack([seen * lit, lz], -1).reshape(len(d), rows * cols, 2).permute(1, 0, 2)  # (P, K, 2)

    a, b = design(*dome), design(*test)
    y = observed.reshape(observed.shape[0], observed.shape[1], -1).permute(2, 0, 1)  # (P, K, C)
    x = torch.linalg.lstsq(a, y).solution.clamp(min=0)
    return (b @ x).permute(1, 2, 0).reshape(b.shape[1], observed.shape[1], rows, cols)


def run_capture(folder: Path, scratch: Path, settings: Settings) -> dict:
    capture, linear, codes, imported = load_reduced(folder / "Dome", scratch, settings.downsample)
    transfer = imported.transfer
    target, _, target_codes = load_reduced(folder / "Test", scratch, settings.downsample, transfer)[:3]
    full = torch.from_numpy(read_photo(folder / "Dome" / "normals.png").pixels).double().permute(2, 0, 1)[None] * 2 - 1
    normal = _unit(_reduce(full, settings.downsample)[0].permute(1, 2, 0))
    reduced = height_from_normals(normal)
    fine = height_from_normals(_unit(full[0].permute(1, 2, 0)))
    fine = torch.nn.functional.avg_pool2d(fine[None, None], settings.downsample)[0, 0] / settings.downsample
    dome = (capture, capture.lights(dtype=torch.float64))
    test = (target, target.lights(dtype=torch.float64))
    softness = math.radians(settings.softness_deg)

    def psnr(height):
        values = predict(height, normal, dome, test, linear, softness)
        return scores(_encoded(transfer, values), target_codes, transfer)["psnr_db"]

    hsh, _ = polynomial(BASES["HSH"], capture.directions(), codes, target.directions())
    return {
        "capture": folder.name,
        "size": [capture.width, capture.height],
        "hsh_psnr_db": scores(hsh, target_codes, transfer)["psnr_db"],
        "depths": {str(depth): psnr(reduced * depth) for depth in settings.depths},
        "full_resolution_height_psnr_db": psnr(fine),
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "shadow_depth.yaml", argv)
    settings = load_config(args.config, Settings)
    data = Path(settings.data) if Path(settings.data).is_absolute() else ROOT / settings.data
    with tempfile.TemporaryDirectory() as scratch:
        results = [run_capture(data / name, Path(scratch), settings) for name in settings.captures]
    out = {"settings": asdict(settings), "captures": results}
    args.output.mkdir(parents=True, exist_ok=True)
    write_json(args.output / f"{Path(args.config).stem}.json", out)
    for result in results:
        print(f"{result['capture']} ({result['size'][0]}x{result['size'][1]}), Dome -> Test, true normals")
        print(f"  HSH                               {result['hsh_psnr_db']:6.2f} dB")
        for depth, value in result["depths"].items():
            print(f"  V Lambert + b l_z, depth {float(depth):4.2f}     {value:6.2f} dB")
        print(f"  full-resolution height, reduced    {result['full_resolution_height_psnr_db']:6.2f} dB")
    return out


if __name__ == "__main__":
    main()
