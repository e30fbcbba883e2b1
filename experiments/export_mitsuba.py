"""The Mitsuba export (``torchspec export --to mitsuba``) against the renderer of the captures.

The development captures were rendered by Mitsuba 3 with a Lambertian plus a Beckmann lobe of
Fresnel 1, under Mitsuba's normal mapping. This exports the truth of a point-light capture once
per frame, with the frame's direction and ``irradiance * exposure`` as a directional emitter,
renders the scene with Mitsuba and compares with the frame: PSNR per frame (peak: the frame's
maximum) and over the frames (peak: their maximum), the relative RMS error. Twice: as exported by
default (the material exactly ``k_d / pi + k_s Beckmann``) and with ``shadowing=True`` (Mitsuba's
default normal-map shadowing function kept, as the captures were rendered). For context, the same
frames predicted by ``torchspec render`` from the same maps with the format's Ward lobe (the data
README's ceiling of a perfect Ward fit) and the Beckmann lobe.

    python experiments/export_mitsuba.py [--config experiments/configs/export_mitsuba.yaml]
        [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _common import ROOT, parse_args

from torchspec.atomic import save_figure, write_json
from torchspec.config import load_config
from torchspec.export import export_mitsuba
from torchspec.io import read_capture
from torchspec.relight import psnr, render_capture


@dataclass(frozen=True)
class Settings:
    capture: str
    spp: int
    variant: str
    frames: tuple[int, ...] | None = None


def render_frames(
    truth: Path, capture, frames: list[int], *, spp: int, variant: str, work: Path, shadowing: bool = False
) -> torch.Tensor:
    """Mitsuba renders ``(K, C, H, W)`` float64 of the exported ``truth`` under ``frames``."""
    import mitsuba as mi

    mi.set_variant(variant)
    out = []
    for k in frames:
        frame = capture.frames[k]
        scene = export_mitsuba(
            truth,
            work / f"frame{k}",
            light=frame.direction,
            irradiance=np.asarray(frame.irradiance) * frame.exposure,
            shadowing=shadowing,
        )
        image = np.array(mi.render(mi.load_file(str(scene), spp=spp)), dtype=np.float64)
        out.append(torch.from_numpy(image[:, :, : len(capture.channels)]).permute(2, 0, 1))
    return torch.stack(out)


MODES = {"exact": False, "shadowing": True}
"""The two exports: the material exactly k_d / pi + k_s Beckmann (the default), and with Mitsuba's
normal-map shadowing function kept (``export_mitsuba(..., shadowing=True)``)."""


def _score(rendered: torch.Tensor, observed: torch.Tensor) -> dict:
    per_frame = [psnr(r, o) for r, o in zip(rendered, observed, strict=True)]
    relative = ((rendered - observed).pow(2).sum().sqrt() / observed.pow(2).sum().sqrt()).item()
    return {
        "psnr_db": psnr(rendered, observed),
        "relative_rms": relative,
        "worst_frame_psnr_db": min(per_frame),
        "per_frame_psnr_db": per_frame,
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "export_mitsuba.yaml", argv)
    settings = load_config(args.config, Settings)
    import mitsuba as mi

    folder = (ROOT / settings.capture).resolve()
    capture = read_capture(folder)
    frames = list(range(len(capture.frames))) if settings.frames is None else list(settings.frames)
    observed = capture.read_frames(frames, dtype=torch.float64)
    exports = {}
    with tempfile.TemporaryDirectory() as work:
        for mode, shadowing in MODES.items():
            rendered = render_frames(
                folder / "truth",
                capture,
                frames,
                spp=settings.spp,
                variant=settings.variant,
                work=Path(work) / mode,
                shadowing=shadowing,
            )
            exports[mode] = _score(rendered, observed)
    context = {}
    for lobe in ("ward", "beckmann"):
        report = render_capture(folder / "truth", folder, None, lobe=lobe, dtype=torch.float64)
        context[lobe] = _score(report["predicted"][frames], observed)
    theta = [math.degrees(math.acos(capture.frames[k].direction[2])) for k in frames]
    result = {
        "settings": asdict(settings),
        "mitsuba": mi.__version__,
        "frames": frames,
        "theta_deg": theta,
        "psnr_db": exports["exact"]["psnr_db"],
        "exports": exports,
        "torchspec_render": context,
    }
    columns = [("export", exports["exact"]), ("export+shadowing", exports["shadowing"])]
    columns += [(f"torchspec {lobe}", context[lobe]) for lobe in ("ward", "beckmann")]
    print("PSNR (dB) against the capture's frames; the export is rendered by Mitsuba")
    print(f"{'frame':>5s} {'theta':>6s} " + " ".join(f"{name:>17s}" for name, _ in columns))
    for j, k in enumerate(frames):
        print(f"{k:5d} {theta[j]:6.1f} " + " ".join(f"{c['per_frame_psnr_db'][j]:17.2f}" for _, c in columns))
    print(f"{'all':>5s} {'':6s} " + " ".join(f"{c['psnr_db']:17.2f}" for _, c in columns))
    print(
        f"relative RMS: export {exports['exact']['relative_rms']:.2e}, with shadowing "
        f"{exports['shadowing']['relative_rms']:.2e} (Mitsuba {mi.__version__} {settings.variant}, {settings.spp} spp)"
    )
    name = Path(args.config).stem
    write_json(args.output / f"{name}.json", result)
    _plot(result, args.output / f"{name}.png")
    print(f"wrote {args.output / f'{name}.json'} and {args.output / f'{name}.png'}")
    return result


def _plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frames = result["frames"]
    curves = [
        ("Mitsuba, export with shadowing=True", result["exports"]["shadowing"], "o-"),
        ("Mitsuba, export (exact k_d/pi + Beckmann)", result["exports"]["exact"], "D-"),
        ("torchspec render, beckmann lobe", result["torchspec_render"]["beckmann"], "s--"),
        ("torchspec render, ward lobe", result["torchspec_render"]["ward"], "^-"),
    ]
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    for label, values, style in curves:
        ax.plot(frames, values["per_frame_psnr_db"], style, ms=3, lw=0.8, label=f"{label} ({values['psnr_db']:.1f} dB)")
    ax.set(
        xlabel="frame",
        ylabel="PSNR against the capture (dB)",
        title=f"{Path(result['settings']['capture']).name}: the true maps, exported and rendered",
    )
    ax.set_ylim(20, 230)  # room for the legend above the curves
    ax.legend(fontsize=7, loc="upper left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


if __name__ == "__main__":
    main()
