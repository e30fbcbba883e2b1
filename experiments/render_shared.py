"""``torchspec render`` of the development captures' truth against their frames.

Each capture of ``../shared/data`` was rendered by an independent path tracer (Mitsuba 3) with a
Beckmann microfacet lobe and ``F = 1``; its ``truth/`` holds the maps. Rendering those maps with
the format's Ward lobe leaves the residual the data's README describes as the ceiling of a
perfect Ward fit; rendering them with the Beckmann lobe (``render(..., lobe="beckmann")``)
removes the model difference and leaves what the integration and the path tracer's Monte Carlo
noise leave. Per capture: PSNR (peak = the capture's maximum) and relative RMS error per lobe.

    python experiments/render_shared.py [--config experiments/configs/render_shared.yaml] [--output experiments/results]
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import ROOT, parse_args

from torchspec.atomic import save_figure, write_json
from torchspec.config import load_config
from torchspec.relight import render_capture


@dataclass(frozen=True)
class Entry:
    name: str
    light: str | None = None


@dataclass(frozen=True)
class Settings:
    data: str
    captures: tuple[Entry, ...]
    lobes: tuple[str, ...]


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(__doc__, "render_shared.yaml", argv)
    settings = load_config(args.config, Settings)
    data = (ROOT / settings.data).resolve()
    rows = []
    print(f"{'capture':22s} {'lobe':9s} {'PSNR dB':>8s} {'rel RMS %':>10s} {'worst frame dB':>15s}")
    for entry in settings.captures:
        folder = data / entry.name
        for lobe in settings.lobes:
            report = render_capture(
                folder / "truth",
                folder,
                None,
                light=folder / entry.light if entry.light else None,
                lobe=lobe,
                dtype=torch.float64,
            )
            row = {
                "capture": entry.name,
                "lobe": lobe,
                "psnr_db": report["psnr_db"],
                "relative_rms": report["relative_rms"],
                "per_frame_psnr_db": report["per_frame_psnr_db"],
            }
            rows.append(row)
            print(
                f"{entry.name:22s} {lobe:9s} {row['psnr_db']:8.2f} {100 * row['relative_rms']:10.2f} "
                f"{min(row['per_frame_psnr_db']):15.2f}",
                flush=True,
            )
    write_json(args.output / "render_shared.json", {"settings": asdict(settings), "rows": rows})
    _plot(rows, args.output / "render_shared.png")
    print(f"wrote {args.output / 'render_shared.json'} and {args.output / 'render_shared.png'}")
    return rows


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["capture"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.5 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        for row in (r for r in rows if r["capture"] == name):
            ax.plot(row["per_frame_psnr_db"], ".-", ms=3, lw=0.8, label=f"{row['lobe']} ({row['psnr_db']:.1f} dB)")
        ax.set(title=name, xlabel="frame", ylabel="PSNR (dB)")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
