"""Fig. 3 of the paper: recover a sharp specular reflectance from samples blurred by an extended light.

The paper's simulation (Sec. 5): one surface point with ``k_d = 1``, ``k_s = 1/1000``,
``alpha = 0.008`` and a random normal (experiments/configs/sim_paper_1d.yaml, sim_paper_2d.yaml), lit by a
Gaussian kernel at 50 positions along a line (1D) or a 40 x 40 grid (2D). ``torchspec fit`` runs
on the simulated capture (photometric stereo, FRI peak location, Levenberg-Marquardt), and the
*reconstruction SNR* compares the reflectance the fitted parameters predict under a point light
(``rho <n, w>``, the sharp function the blur hid) with the true one, densely over the sampled
domain: ``10 log10(sum truth^2 / sum (fit - truth)^2)``. The paper reports 43.4 dB (1D) and
52.2 dB (2D). Also: the normal's angular error, the peak's position error in the l-plane, and
the relative errors of ``alpha`` and ``k_s``; with noise-free samples and with noisy ones.

Panels (fig3.png): A 1D samples and the fitted model; B 1D reconstructed reflectance against the
truth; C 2D samples; D 2D reconstruction error.

    python experiments/fig3_simulation.py [--config experiments/configs/fig3.yaml] [--output experiments/results]
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _common import ROOT, parse_args  # noqa: E402

from torchspec.atomic import save_figure, write_json  # noqa: E402
from torchspec.config import load_config  # noqa: E402
from torchspec.model.geometry import (
    angle,  # noqa: E402
    from_plane,  # noqa: E402
)
from torchspec.model.lights import Kernel, Lights  # noqa: E402
from torchspec.model.quadrature import Quadrature  # noqa: E402
from torchspec.model.rendering import render  # noqa: E402
from torchspec.pipeline import FitConfig, fit  # noqa: E402
from torchspec.simulate import SimulationConfig, simulate, write_simulation  # noqa: E402

PAPER_DB = {"1d": 43.4, "2d": 52.2}


@dataclass(frozen=True)
class Settings:
    one_d: str  # simulation configs, relative to the repository root
    two_d: str
    dense: int  # reconstruction points along the line (1D) or per axis (2D)
    noisy_snr_db: tuple[float, ...]  # extra runs with white Gaussian noise at these SNRs (peak / noise std)
    seed: int
    fit: FitConfig
    compare_inits: tuple[str, ...]  # noise-free runs from these other starts (FitConfig.start.init), for comparison


def _point_lights(l: torch.Tensor) -> Lights:
    count = l.shape[0]
    return Lights(from_plane(l), Kernel("point"), torch.ones(count, 1, dtype=l.dtype), torch.ones(count, dtype=l.dtype))


def _run(
    kind: str, config: SimulationConfig, settings: Settings, snr_db: float | None, workdir: Path, init: str
) -> dict:
    sim = simulate(config)
    frames = sim.frames
    if snr_db is not None:
        g = torch.Generator().manual_seed(settings.seed)
        std = frames.abs().max() * 10 ** (-snr_db / 20)
        frames = frames + std * torch.randn(frames.shape, generator=g, dtype=frames.dtype)
    folder = workdir / f"{kind}-{snr_db}-{init}"
    write_simulation(folder, replace(sim, frames=frames))
    result = fit(folder, config=replace(settings.fit, start=replace(settings.fit.start, init=init)))
    truth = sim.truth.flatten().to(torch.float64)
    fitted = result.svbrdf.flatten().to(torch.float64)
    l = torch.tensor([f.direction[:2] for f in sim.capture.frames], dtype=torch.float64)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # The dense domain: the sampled line, or the sampled square.
    if kind == "1d":
        t = torch.linspace(0, 1, settings.dense, dtype=torch.float64)
        dense = l[0] + t[:, None] * (l[-1] - l[0])
    else:
        lo, hi = l.min(0).values, l.max(0).values
        ax = torch.linspace(0, 1, settings.dense, dtype=torch.float64)
        yy, xx = torch.meshgrid(lo[1] + ax * (hi[1] - lo[1]), lo[0] + ax * (hi[0] - lo[0]), indexing="ij")
        dense = torch.stack([xx, yy], -1).reshape(-1, 2)
    point = _point_lights(dense)
    true_rho = render(truth, point, view, quadrature=Quadrature(path="point"))[..., 0]  # (pixels, dense)
    fit_rho = render(fitted, point, view, quadrature=Quadrature(path="point"))[..., 0]
    # Every pixel of the (constant) surface is an independent trial: medians over them, and the worst.
    snr = 10 * torch.log10((true_rho**2).sum(-1) / ((fit_rho - true_rho) ** 2).sum(-1))
    normal = torch.rad2deg(angle(fitted.normal, truth.normal))
    peak = ((2 * fitted.normal[:, 2:] * fitted.normal)[:, :2] - (2 * truth.normal[:, 2:] * truth.normal)[:, :2]).norm(
        dim=-1
    )
    alpha = (fitted.roughness[:, 0] / truth.roughness[:, 0] - 1).abs()
    ks = (fitted.specular.mean(-1) / truth.specular.mean(-1) - 1).abs()
    kd = (fitted.diffuse.mean(-1) / truth.diffuse.mean(-1) - 1).abs()
    row = {
        "experiment": kind,
        "init": init,
        "sample_snr_db": snr_db,
        "frames": len(sim.capture.frames),
        "pixels": truth.shape[0],
        "reconstruction_snr_db": float(snr.median()),
        "reconstruction_snr_db_worst": float(snr.min()),
        "paper_db": PAPER_DB[kind],
        "normal_error_deg": float(normal.median()),
        "peak_error_l": float(peak.median()),
        "alpha_relative_error": float(alpha.median()),
        "alpha_relative_error_worst": float(alpha.max()),
        "ks_relative_error": float(ks.median()),
        "kd_relative_error": float(kd.median()),
        "lm_iterations": float(result.iterations.double().median()),
        "status": result.stats["status"],
        "seconds": result.stats["seconds"]["total"],
    }
    l = torch.tensor([f.direction[:2] for f in sim.capture.frames], dtype=torch.float64)
    true_rho, fit_rho = true_rho[0], fit_rho[0]
    curves = {
        "l": l,
        "samples": frames[:, 0].reshape(len(sim.capture.frames), -1)[:, 0].double(),
        "model": render(fitted[:1], sim_lights(sim, config), view)[0, :, 0],
        "dense": dense,
        "true": true_rho,
        "fit": fit_rho,
    }
    return {"row": row, "curves": curves}


def sim_lights(sim, config: SimulationConfig) -> Lights:
    centres = torch.tensor([f.direction for f in sim.capture.frames], dtype=torch.float64)
    count = centres.shape[0]
    kernel = Kernel(config.light.kernel, domain=config.light.domain, sigma=config.light.sigma)
    return Lights(centres, kernel, torch.ones(count, 1, dtype=torch.float64), torch.ones(count, dtype=torch.float64))


def _figure(one: dict, two: dict, grid: int):
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2))
    c = one["curves"]
    t = (c["l"] - c["l"][0]).norm(dim=-1).numpy()
    td = (c["dense"] - c["l"][0]).norm(dim=-1).numpy()
    ax = axes[0]
    ax.plot(t, c["samples"].numpy(), "o", ms=3, label="blurred samples")
    ax.plot(t, c["model"].numpy(), "-", lw=1, label="fitted model (blurred)")
    ax.set_title("A  1D: samples under the extended light")
    ax.set_xlabel("position along the line (l-plane)")
    ax.legend(fontsize=8)
    ax = axes[1]
    ax.plot(td, c["true"].numpy(), "-", lw=2, label="true reflectance (point light)")
    ax.plot(td, c["fit"].numpy(), "--", lw=1.5, label="reconstructed")
    ax.set_title(f"B  1D reconstruction: {one['row']['reconstruction_snr_db']:.1f} dB (paper 43.4)")
    ax.set_xlabel("position along the line (l-plane)")
    ax.legend(fontsize=8)
    c = two["curves"]
    ax = axes[2]
    dots = ax.scatter(
        c["l"][:, 0].numpy(), c["l"][:, 1].numpy(), c=c["samples"].numpy(), marker="s", s=12, cmap="magma"
    )
    fig.colorbar(dots, ax=ax, fraction=0.046)
    ax.set_aspect("equal")
    ax.set_title(f"C  2D: {c['l'].shape[0]} blurred samples")
    ax.set_xlabel("l_x")
    ax.set_ylabel("l_y")
    ax = axes[3]
    err = (c["fit"] - c["true"]).reshape(grid, grid).numpy()
    lo, hi = c["dense"].min(0).values, c["dense"].max(0).values
    im = ax.imshow(
        err, origin="lower", cmap="coolwarm", extent=(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))
    )
    fig.colorbar(im, ax=ax, fraction=0.046)
    ax.set_title(f"D  2D reconstruction error: {two['row']['reconstruction_snr_db']:.1f} dB (paper 52.2)")
    ax.set_xlabel("l_x")
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(__doc__, "fig3.yaml", argv)
    settings = load_config(args.config, Settings)
    configs = {
        "1d": load_config(ROOT / settings.one_d, SimulationConfig),
        "2d": load_config(ROOT / settings.two_d, SimulationConfig),
    }
    rows, clean = [], {}
    print("medians over the surface's pixels (independent noise draws); 'worst' is the worst pixel")
    print(
        f"{'exp':4s} {'sample SNR':>10s} {'recon dB':>9s} {'worst':>6s} {'paper':>6s} {'normal deg':>11s} "
        f"{'peak (l)':>9s} {'alpha err':>10s} {'worst':>7s} {'k_s err':>9s} {'LM it':>6s}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for kind, config in configs.items():
            start = settings.fit.start.init
            trials = [(None, start)] + [(snr, start) for snr in settings.noisy_snr_db]
            trials += [(None, init) for init in settings.compare_inits]
            for snr_db, init in trials:
                out = _run(kind, config, settings, snr_db, Path(tmp), init)
                row = out["row"]
                rows.append(row)
                if snr_db is None and init == start:
                    clean[kind] = out
                label = "none" if snr_db is None else f"{snr_db:.0f} dB"
                print(
                    f"{kind:4s} {init:6s} {label:>10s} {row['reconstruction_snr_db']:9.1f} "
                    f"{row['reconstruction_snr_db_worst']:6.1f} {row['paper_db']:6.1f} "
                    f"{row['normal_error_deg']:11.2e} {row['peak_error_l']:9.2e} {row['alpha_relative_error']:10.2e} "
                    f"{row['alpha_relative_error_worst']:7.2f} {row['ks_relative_error']:9.2e} "
                    f"{row['lm_iterations']:6.0f} {row['seconds']:5.1f}"
                )
    stem = Path(args.config).stem
    write_json(args.output / f"{stem}.json", {"settings": asdict(settings), "rows": rows})
    save_figure(_figure(clean["1d"], clean["2d"], settings.dense), args.output / f"{stem}.png")
    return rows


if __name__ == "__main__":
    main()
