"""Light directions from a chrome sphere (torchspec.calibration.sphere): the outline from the mask against the
one found automatically (find_sphere), each scored against the reference directions lights.txt.

    python experiments/sphere_chrome.py [--config experiments/configs/sphere_chrome.yaml] [--output DIR] [--data DIR]

Prints the outline of each, its distance to the mask's (centre, radius; pixels) and the angle
between the recovered and the reference directions (median, largest; degrees), with the median
per-light uncertainty; writes experiments/results/sphere_chrome.json.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from torchspec.atomic import write_json
from torchspec.calibration.sphere import circle_from_mask, find_sphere, sphere_directions
from torchspec.config import load_config
from torchspec.io.images import read_photo
from torchspec.io.lp import read_light_file
from torchspec.io.rti import photographs

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class Config:
    data: str
    level: float = 0.5


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=HERE / "configs" / "sphere_chrome.yaml")
    parser.add_argument("--output", type=Path, default=HERE / "results")
    parser.add_argument("--data", type=Path, help="the chrome-sphere folder (default: the config's, from the root)")
    args = parser.parse_args(argv)
    config = load_config(args.config, Config)
    folder = args.data or (HERE.parent / config.data).resolve()
    images = photographs(folder)
    frames = torch.stack([torch.from_numpy(read_photo(path).pixels).permute(2, 0, 1) for path in images])
    truth = torch.tensor([e.direction for e in read_light_file(folder / "lights.txt").entries], dtype=torch.float64)
    mask = circle_from_mask(folder / "chrome.mask.png")
    start = time.perf_counter()
    found = find_sphere(frames)
    seconds = time.perf_counter() - start
    rows = {}
    for name, circle in (("mask", mask), ("auto", found)):
        result = sphere_directions(frames, circle, level=config.level)
        angle = torch.rad2deg(torch.acos((result.directions * truth).sum(-1).clamp(-1, 1)))
        half = truth + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # where lights.txt puts each highlight
        half = half / half.norm(dim=-1, keepdim=True)
        expected = torch.stack([circle.cx + circle.r * half[:, 0], circle.cy - circle.r * half[:, 1]], -1)
        offset = (result.highlights - expected).norm(dim=-1)
        rows[name] = {
            "circle": [circle.cx, circle.cy, circle.r],
            "centre_error_px": float(((circle.cx - mask.cx) ** 2 + (circle.cy - mask.cy) ** 2) ** 0.5),
            "radius_error_px": circle.r - mask.r,
            "angle_median_deg": float(angle.median()),
            "angle_max_deg": float(angle.max()),
            "angles_deg": angle.tolist(),
            "uncertainty_median_deg": float(result.uncertainty_deg.median()),
            "within_uncertainty": int((angle <= result.uncertainty_deg).sum()),
            "highlight_offset_px": offset.tolist(),
            "highlight_offset_median_px": float(offset.median()),
            "highlight_offset_max_px": float(offset.max()),
        }
    rows["auto"]["seconds"] = seconds
    print(
        "| outline | cx, cy, r (px) | centre / radius vs mask (px) | angle median / largest (deg) | "
        "uncertainty median (deg) | highlight vs lights.txt's, median / largest (px) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for name, row in rows.items():
        cx, cy, r = row["circle"]
        print(
            f"| {name} | {cx:.2f}, {cy:.2f}, {r:.2f} | {row['centre_error_px']:.2f} / {row['radius_error_px']:+.2f} | "
            f"{row['angle_median_deg']:.2f} / {row['angle_max_deg']:.2f} | {row['uncertainty_median_deg']:.2f} | "
            f"{row['highlight_offset_median_px']:.2f} / {row['highlight_offset_max_px']:.2f} |"
        )
    print(f"auto detection: {seconds:.2f} s")
    record = {"config": vars(config) | {"data": config.data}, "frames": [p.name for p in images], "rows": rows}
    args.output.mkdir(parents=True, exist_ok=True)
    write_json(args.output / "sphere_chrome.json", record)
    return record


if __name__ == "__main__":
    main()
