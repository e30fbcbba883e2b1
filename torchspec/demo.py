"""``torchspec demo``: the whole job on an embedded default.

Simulates a small painting (pigments, canvas weave, brush strokes, varnish, a gilded patch) under
a 12 x 12 grid of an extended Gaussian light clipped to the l-plane radius 0.8, with shot noise;
fits it (:func:`torchspec.pipeline.fit`); and writes, in the output folder:

- ``capture/``: the simulated capture, with its ``truth/``;
- ``maps/``: the fitted SVBRDF (EXR maps, residual, quality, ``svbrdf.json``);
- ``previews/``: the maps as PNG (normal, diffuse, specular, roughness, model, error maps);
- ``relit.png``: the fitted maps relit by a light circling the zenith, above the truth relit;
- ``report.png`` and ``report.json``: one page with the maps, the errors against the truth,
  the held-out PSNR (frames left out of the fit) and the timings.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import torch

from .atomic import save_figure, write_json
from .io import read_capture
from .outputs import check_output
from .pipeline import ComputeConfig, FitConfig, fit, select_frames, write_fit
from .report import display, heldout_psnr, relit_strip, relit_title, score, write_previews, write_report
from .simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from .simulate.synth import PaintingConfig, SensorConfig

__all__ = ["run", "DEFAULT_OUTPUT"]

DEFAULT_OUTPUT = Path("torchspec-demo")


def scene(size: int = 64, seed: int = 777) -> SimulationConfig:
    """The demo's simulation: a ``size`` x ``size`` painting, 88 frames, photon noise."""
    return SimulationConfig(
        name="torchspec-demo",
        scene=SceneConfig(kind="painting", painting=PaintingConfig(width=size, height=size, seed=seed)),
        light=LightConfig(kernel="gaussian", domain="projected", sigma=0.08),
        layout=LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8),
        sensor=SensorConfig(photons_per_unit=1e5, seed=seed),
    )


def run(
    output: str | Path | None = None,
    *,
    size: int = 64,
    seed: int = 777,
    progress: bool = True,
    overwrite: bool = False,
    device: str = "auto",
) -> dict:
    """Run the demo into ``output`` (default ``./torchspec-demo``); returns ``report.json``'s content.
    The fit computes on ``device`` (``FitConfig.compute.device``: ``auto``, ``cpu``, ``cuda[:N]``).

    ``output`` is checked before any work: a folder that holds files (an earlier demo's too) is
    refused unless ``overwrite`` (:func:`torchspec.outputs.check_output`).
    """
    output = check_output(output if output is not None else DEFAULT_OUTPUT, overwrite=overwrite)
    clock = time.perf_counter()
    config = scene(size, seed)
    simulation = simulate(config, root=output / "capture", progress=progress)
    write_simulation(output / "capture", simulation, overwrite=overwrite)
    simulate_seconds = time.perf_counter() - clock
    print(
        f"torchspec demo: simulated a {size}x{size} painting under {len(simulation.capture.frames)} frames "
        f"of a Gaussian light (sigma 0.08) in {simulate_seconds:.1f} s: {output / 'capture'}"
    )

    capture = read_capture(output / "capture")
    truth, regions = simulation.truth.to(torch.float32), simulation.regions
    # Every second frame is fitted, the others held out to test the maps' predictions.
    fitted_frames = select_frames("::2", len(capture.frames))
    held = [k for k in range(len(capture.frames)) if k not in set(fitted_frames)]
    fit_config = FitConfig(model="auto", compute=ComputeConfig(device=device))
    result = fit(capture, config=fit_config, frames=fitted_frames, progress=progress)
    write_fit(output / "maps", result, overwrite=overwrite)
    fit_seconds = result.stats["seconds"]["total"]
    print(
        f"  fitted on {len(fitted_frames)} frames in {fit_seconds:.1f} s, models chosen per pixel "
        f"{result.stats['models']} "
        f"({result.stats['pixels_per_second']:.0f} pixels/s): {output / 'maps'}"
    )

    lights = capture.lights(dtype=torch.float64)
    view = torch.tensor(capture.view, dtype=torch.float64, device=result.svbrdf.normal.device)
    stack = capture.read_frames(dtype=torch.float64)
    index = torch.tensor(held)  # on the CPU: it picks from the capture's lights and frames, read on the CPU
    held_lights = lights[index]
    peak = float(stack.abs().max())
    scores = score(result.svbrdf, truth, regions)
    scores["heldout_psnr_db"] = heldout_psnr(result.svbrdf.to(torch.float64), held_lights, view, stack[index], peak)
    scores["truth_heldout_psnr_db"] = heldout_psnr(truth.to(torch.float64), held_lights, view, stack[index], peak)

    write_previews(
        output / "previews",
        result.svbrdf,
        model=result.model,
        residual=result.residual,
        quality=result.quality,
        truth=truth,
    )
    strip, _ = relit_strip(result.svbrdf.to(torch.float64), lights.kernel, view)
    true_strip, _ = relit_strip(truth.to(torch.float64), lights.kernel, view)
    _write_strip(output / "relit.png", strip, true_strip)
    notes = _notes(result, simulate_seconds, fit_seconds, len(held), len(fitted_frames))
    write_report(
        output / "report.png",
        title=f"torchspec demo: a simulated {size}x{size} painting, models chosen per pixel",
        fit=result,
        truth=truth,
        regions=regions,
        scores=scores,
        strip=strip,
        true_strip=true_strip,
        notes=notes,
    )
    summary = {
        "size": size,
        "frames": len(capture.frames),
        "fitted_frames": len(fitted_frames),
        "scores": scores,
        "seconds": {"simulate": simulate_seconds, "fit": fit_seconds, "total": time.perf_counter() - clock},
        "fit": result.stats,
        "simulation": asdict(config),
    }
    write_json(output / "report.json", summary)
    print(
        f"  median errors against the truth: normal {scores['normal_deg']:.3f} deg, k_d {100 * scores['kd']:.2f} %, "
        f"varnish k_s {100 * scores['varnished_ks']:.1f} %, alpha {100 * scores['varnished_alpha']:.1f} %; "
        f"matte pixels without a lobe {100 * scores['matte_share_ks0']:.1f} %"
    )
    print(f"  untrusted pixels (flags.exr): {result.stats['untrusted']} of {result.stats['pixels']}")
    print(
        f"  held-out frames predicted at {scores['heldout_psnr_db']:.1f} dB PSNR "
        f"(the true maps: {scores['truth_heldout_psnr_db']:.1f} dB)"
    )
    print(
        f"  wrote {output / 'report.png'}, {output / 'relit.png'}, {output / 'previews'}/*.png "
        f"in {summary['seconds']['total']:.1f} s"
    )
    return summary


def _write_strip(path: Path, strip, true_strip) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    count = strip.shape[0]
    white = float(true_strip.double().quantile(0.995)) if true_strip.numel() < 2**24 else float(true_strip.max())
    fig, axes = plt.subplots(2, count, figsize=(1.6 * count, 3.6))
    for row, (label, images) in enumerate((("fitted", strip), ("true", true_strip))):
        for k in range(count):
            ax = axes[row, k]
            ax.imshow(display(images[k].cpu().numpy(), white), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if k == 0:
                ax.set_ylabel(label, fontsize=9)
    fig.suptitle(relit_title(30.0), fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def _notes(result, simulate_seconds: float, fit_seconds: float, held: int, fitted: int) -> list[str]:
    """The report's notes on a fit: times, lobes, the solver's status, flags and held-out frames."""
    stats = result.stats
    return [
        f"simulated in {simulate_seconds:.1f} s; fitted in {fit_seconds:.1f} s on {torch.get_num_threads()} threads",
        f"pixels with a lobe: {stats['lobe_pixels']} of {stats['pixels']}",
        "solver: " + ", ".join(f"{name} {count}" for name, count in stats["status"].items() if count),
        f"untrusted pixels (quality 0): {stats['untrusted']}",
        "flags (flags.exr): " + (", ".join(f"{n} {c}" for n, c in stats["flags"].items() if c) or "none"),
        "  misfit: the model's residual is above the noise",
        "  (information: the values are that model's best fit)",
        f"held-out frames: {held} (fitted on {fitted})",
    ]
