"""Speed against accuracy: time per pixel (log) against error (log) for every method and
setting of the fit, with the Pareto front marked, and the baselines a user would otherwise pick.

A simulated painting (the capture of ``bench_fit``, smaller: ``size x size`` pixels, a full
``grid x grid`` layout of a projected Gaussian light, shot noise) is fitted by each row of the
config, in this process, on ``threads`` torch threads, eager (no torch.compile: its one-off
compilation would swamp a small image; ``bench_fit`` times the compiled fit of a large one). Rows:

- ``start``: the starting point alone (photometric stereo and the specular start: FRI with a
  method and ``M`` coefficients, a naive start, or a dense point-light grid of candidate peaks);
- ``fit``: the whole fit from a start, with the solver's iterations, the quadrature and the tile
  size varied;
- ``scipy``: per-pixel ``scipy.optimize.least_squares`` on the same model from the same start
  (``bench_fit``'s baseline), on a sample of lobed pixels, its time per pixel as measured.

Error: the median angular error of the normal and the median relative error of ``alpha`` over the
truly lobed pixels (the gilding left out: its lobe is anisotropic and coloured), against the truth.
Time: the fastest of ``repeats`` runs, over the pixels of the image.

    python experiments/speed_accuracy.py [--config experiments/configs/speed_accuracy.yaml]
        [--output experiments/results]
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from _common import parse_args  # noqa: E402
from bench_fit import Settings as BenchSettings  # noqa: E402
from bench_fit import _capture, _scipy, _scores  # noqa: E402

from torchspec.atomic import save_figure, write_json  # noqa: E402
from torchspec.config import load_config  # noqa: E402
from torchspec.io import read_capture, read_svbrdf  # noqa: E402
from torchspec.pipeline import FitConfig, fit, starting_point  # noqa: E402


@dataclass(frozen=True)
class Row:
    label: str
    kind: str  # start | fit | scipy
    fit: FitConfig = field(default_factory=FitConfig)


@dataclass(frozen=True)
class Settings:
    capture: BenchSettings  # the simulated capture (size, grid, light, noise), threads and scipy sample
    repeats: int  # timing: the fastest of this many runs
    rows: tuple[Row, ...]


def _lobed(folder: Path) -> torch.Tensor:
    truth = read_svbrdf(folder / "truth")
    regions = truth.extra["regions"].reshape(-1).round().long()
    return (truth.svbrdf.flatten().specular.amax(-1) > 0) & (regions != 2)


def _timed(repeats: int, run):
    best, out = float("inf"), None
    for _ in range(max(1, repeats)):
        begin = time.perf_counter()
        out = run()
        best = min(best, time.perf_counter() - begin)
    return out, best


def _start_row(folder: Path, config: FitConfig, repeats: int):
    capture = read_capture(folder)
    dtype = getattr(torch, config.compute.dtype)
    lights, view = capture.lights(dtype=dtype), torch.tensor(capture.view, dtype=dtype)
    y = capture.read_frames(dtype=dtype).flatten(2).permute(2, 0, 1)  # (H W, K, C)
    valid = torch.isfinite(y).all(-1)

    def run():
        return starting_point(y, valid, lights, view, config=config).svbrdf(capture.channels)

    return _timed(repeats, run)


def _fit_row(folder: Path, config: FitConfig, repeats: int):
    out, seconds = _timed(repeats, lambda: fit(folder, config=config))
    return out.svbrdf.flatten(), seconds, out.stats["iterations"]["mean_lobe"]


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error (lower is better)."""
    front = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i):
            front.append(i)
    return front


def main(argv: list[str] | None = None) -> list[dict]:
    args = parse_args(__doc__, "speed_accuracy.yaml", argv)
    settings = load_config(args.config, Settings)
    bench = settings.capture
    torch.set_num_threads(bench.threads)
    folder = _capture(bench)
    truth = read_svbrdf(folder / "truth").svbrdf.flatten()
    lobed = _lobed(folder)
    pixels = truth.normal.shape[0]
    rows = []
    for row in settings.rows:
        config = replace(row.fit, compile=False)
        iterations = None
        if row.kind == "start":
            maps, seconds = _start_row(folder, config, settings.repeats)
            count = pixels
        elif row.kind == "fit":
            maps, seconds, iterations = _fit_row(folder, config, settings.repeats)
            count = pixels
        elif row.kind == "scipy":
            candidates = lobed.nonzero()[:, 0]
            g = torch.Generator().manual_seed(bench.seed)
            pick = candidates[torch.randperm(candidates.numel(), generator=g)[: bench.scipy_pixels]].sort().values
            fitted, seconds, _ = _scipy(replace(bench, fit=config, scipy_repeats=settings.repeats), folder, pick)
            scores = _scores(fitted, truth[pick])
            rows.append({"label": row.label, "kind": row.kind, "seconds_per_pixel": seconds / pick.numel(), **scores})
            continue
        else:
            raise ValueError(f"rows[].kind must be start, fit or scipy; got {row.kind!r} in {row.label!r}.")
        scores = _scores(maps[lobed], truth[lobed])
        rows.append(
            {
                "label": row.label,
                "kind": row.kind,
                "seconds_per_pixel": seconds / count,
                "lm_iterations_mean_lobe": iterations,
                "settings": asdict(config),
                **scores,
            }
        )
    for key in ("normal_deg", "alpha"):
        for i in pareto([(r["seconds_per_pixel"], r[key]) for r in rows]):
            rows[i].setdefault("pareto", []).append(key)
    print(f"{bench.size} x {bench.size} pixels, {bench.grid**2} frames, {bench.threads} threads, eager")
    print(f"{'row':34s} {'us/pixel':>9s} {'normal deg':>10s} {'alpha %':>8s} {'LM it':>6s}  pareto")
    for r in rows:
        it = r.get("lm_iterations_mean_lobe")
        print(
            f"{r['label'][:34]:34s} {1e6 * r['seconds_per_pixel']:9.1f} {r['normal_deg']:10.4f} "
            f"{100 * r['alpha']:8.2f} {'-' if it is None else f'{it:.1f}':>6s}  {','.join(r.get('pareto', []))}"
        )
    stem = Path(args.config).stem
    write_json(args.output / f"{stem}.json", {"settings": asdict(settings), "torch": torch.__version__, "rows": rows})
    save_figure(_figure(rows, bench), args.output / f"{stem}.png")
    return rows


def _figure(rows: list[dict], bench: BenchSettings):
    fig, axes = plt.subplots(1, 2, figsize=(14, 6))
    colours = {"start": "tab:orange", "fit": "tab:blue", "scipy": "tab:red"}
    for ax, key, name in (
        (axes[0], "normal_deg", "median normal error (deg)"),
        (axes[1], "alpha", "median |alpha error| (relative)"),
    ):
        for r in rows:
            on_front = key in r.get("pareto", [])
            ax.scatter(
                r["seconds_per_pixel"] * 1e6,
                max(r[key], 1e-6),
                c=colours[r["kind"]],
                marker="*" if on_front else "o",
                s=140 if on_front else 40,
                edgecolors="k",
                linewidths=0.5,
            )
            ax.annotate(
                r["label"],
                (r["seconds_per_pixel"] * 1e6, max(r[key], 1e-6)),
                fontsize=6,
                xytext=(3, 3),
                textcoords="offset points",
            )
        front = sorted((r["seconds_per_pixel"] * 1e6, max(r[key], 1e-6)) for r in rows if key in r.get("pareto", []))
        ax.plot(*zip(*front, strict=True), "k--", lw=0.8, label="Pareto front")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("time per pixel (us, log)")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", ls="", color=c, label=k) for k, c in colours.items()]
    axes[0].legend(handles=[*handles, plt.Line2D([], [], ls="--", color="k", label="Pareto front")], fontsize=8)
    fig.suptitle(
        f"speed against accuracy: {bench.size} x {bench.size} px, {bench.grid**2} frames, "
        f"{bench.threads} threads (stars: Pareto front)"
    )
    fig.tight_layout()
    return fig


if __name__ == "__main__":
    main()
