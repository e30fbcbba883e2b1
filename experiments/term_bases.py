"""What a residual term's basis could buy: bases of the light direction fitted to what torchspec's
physical maps leave of the photographs, on ``rti_relight``'s protocol and captures.

Each capture is reduced and imported as :mod:`rti_relight` does (its ``load_reduced``: 8-bit codes
box-averaged by ``downsample``, imported with the default ``--transfer auto``); every fifth light
(``i % 5 == 2``) is left out; :func:`torchspec.fit` runs on the others without a residual term and
its maps are rendered under every light (near lights at the dome radius the fit found, as
``torchspec render`` does). The residual ``r`` is then the photographs' codes less the maps' render
encoded by the import's transfer, and each basis below is fitted to ``r`` on the fitted frames, per
pixel and channel, everywhere (no choice of pixels, no blend: what the basis itself can carry),
and evaluated at the left-out lights. Scores: 8-bit PSNR of the left-out photographs, as
``rti_relight``. Rows:

- ``PTM``, ``HSH``, ``RBF``: the baselines on the codes (``rti_relight``'s).
- ``maps``: the physical maps alone; ``maps + HSH3``: the current term's basis (9 functions).
- ``maps + RBF``: Relight's Gaussian radial basis interpolation of ``r`` (as the RBF row: one
  function per fitted light, width twice the mean nearest-neighbour spacing, ridge 0.1).
- ``maps + PCA J``: the ``J`` leading principal components of ``r`` over the light directions
  (the right singular vectors of the pixels-by-lights matrix), each carried to any direction by
  that RBF interpolation, the pixel's coefficients by least squares: ``J`` numbers per pixel and
  channel, as HSH's 9, with a basis learned from the capture.
- ``maps + centres J``: Gaussians about ``J`` of the fitted lights (farthest-point order from the
  highest), width the mean nearest-neighbour spacing of those centres, Tikhonov 1e-3.
- ``RBF + maps / 4``: RBF of the codes plus a quarter of what the maps add to their own RBF
  interpolation (a fixed blend of the two predictors).

    python experiments/term_bases.py [--config experiments/configs/term_bases.yaml] [--output experiments/results]
"""

from __future__ import annotations

import math
import tempfile
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from _common import ROOT, parse_args
from rti_relight import BASES, _encoded, load_reduced, polynomial, rbf, scores

import torchspec
from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.model.rendering import render_image
from torchspec.model.residual_term import hsh_basis
from torchspec.relight import render_near


@dataclass(frozen=True)
class Settings:
    data: str  # the folder of the captures, relative to the repository's root (or absolute)
    captures: tuple[str, ...]  # folders of `data`; a SynthRTI one: its Dome/
    downsample: int = 4  # box-average factor of the frames
    threads: int = 2  # torch threads
    left_out: int = 2  # frames i % 5 == left_out are predicted
    sizes: tuple[int, ...] = (9, 16, 25)  # J of the PCA and centre bases
    ridge: float = 0.1  # the RBF interpolation's ridge


def _gauss(a: torch.Tensor, b: torch.Tensor, width: float) -> torch.Tensor:
    return torch.exp(-(torch.cdist(a, b) ** 2) / (2 * width**2))


def _spacing(d: torch.Tensor) -> float:
    """The mean distance from each of the directions ``d (K, 3)`` to its nearest other one."""
    distance = torch.cdist(d, d).masked_fill(torch.eye(len(d), dtype=torch.bool), math.inf)
    return float(distance.min(-1).values.mean())


def _maps_codes(capture, fitted: list[int], transfer) -> tuple[torch.Tensor, float]:
    """The codes ``(K, C, H, W)`` of the maps fitted on ``fitted`` frames without a term, rendered
    under every light of ``capture``; and the fit's seconds."""
    config = torchspec.FitConfig.from_dict({"term": {"order": 0}, "quadrature": {"compile": False}})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = torchspec.fit(capture, config=config, frames=fitted)
    lights = capture.lights(dtype=torch.float64)
    svbrdf = fit.svbrdf.to(torch.float64)
    view = torch.tensor(capture.view, dtype=torch.float64)
    radius = (fit.stats.get("lights") or {}).get("radius")
    if radius is not None:
        values = render_near(svbrdf, lights, radius * lights.directions, view)
    else:
        values = render_image(svbrdf, lights, view)
    return _encoded(transfer, values.permute(2, 3, 0, 1)), fit.stats["seconds"]["total"]


def _learned(df, dp, r, sizes, ridge) -> dict[str, torch.Tensor]:
    """``maps + PCA J`` and ``maps + centres J`` predictions of the residual ``r (Kf, N)`` at the
    left-out directions ``dp`` from the fitted ones ``df``: ``(Kp, N)`` each."""
    width = 2 * _spacing(df)
    gram = _gauss(df, df, width)
    solve = torch.linalg.inv(gram + ridge * torch.eye(len(df), dtype=gram.dtype))
    _, _, vh = torch.linalg.svd(r.T, full_matrices=False)
    out = {}
    for j in sizes:
        weights = solve @ vh[:j].T  # (Kf, J): the RBF weights of each component
        at_fitted, at_left_out = gram @ weights, _gauss(dp, df, width) @ weights
        coefficients = torch.linalg.lstsq(at_fitted, r).solution
        out[f"maps + PCA {j}"] = at_left_out @ coefficients
        index = [int(df[:, 2].argmax())]
        for _ in range(j - 1):
            index.append(int(torch.cdist(df, df[index]).min(-1).values.argmax()))
        centres = df[index]
        spread = _spacing(centres)
        at_fitted, at_left_out = _gauss(df, centres, spread), _gauss(dp, centres, spread)
        normal = at_fitted.T @ at_fitted
        damping = 1e-3 * normal.diagonal().mean() * torch.eye(j, dtype=normal.dtype)
        out[f"maps + centres {j}"] = at_left_out @ torch.linalg.solve(normal + damping, at_fitted.T @ r)
    return out


def run_capture(folder: Path, scratch: Path, settings: Settings) -> dict:
    source = folder / "Dome" if (folder / "Dome").is_dir() else folder
    capture, _, codes, imported = load_reduced(source, scratch, settings.downsample)
    transfer = imported.transfer
    count, shape = len(capture.frames), codes.shape[1:]
    predicted = [i for i in range(count) if i % 5 == settings.left_out]
    fitted = [i for i in range(count) if i % 5 != settings.left_out]
    d = capture.directions()
    df, dp, truth = d[fitted], d[predicted], codes[predicted]
    maps, seconds = _maps_codes(capture, fitted, transfer)
    r = (codes - maps)[fitted].reshape(len(fitted), -1)
    rows = {name: polynomial(basis, df, codes[fitted], dp)[0] for name, basis in BASES.items()}
    rows["RBF"] = rbf(df, codes[fitted], dp, settings.ridge)[0]
    rows["maps"] = maps[predicted]
    rows["maps + HSH3"] = maps[predicted] + polynomial(hsh_basis, df, r.reshape(len(fitted), *shape), dp)[0]
    rows["maps + RBF"] = maps[predicted] + rbf(df, r.reshape(len(fitted), *shape), dp, settings.ridge)[0]
    for name, value in _learned(df, dp, r, settings.sizes, settings.ridge).items():
        rows[name] = maps[predicted] + value.reshape(len(predicted), *shape)
    own = rbf(df, maps[fitted], dp, settings.ridge)[0]
    rows["RBF + maps / 4"] = rows["RBF"] + (maps[predicted] - own) / 4
    return {
        "capture": folder.name,
        "size": [capture.width, capture.height],
        "frames": count,
        "transfer": str(transfer),
        "fit_seconds": seconds,
        "psnr_db": {name: scores(value, truth, transfer)["psnr_db"] for name, value in rows.items()},
    }


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "term_bases.yaml", argv)
    settings = load_config(args.config, Settings)
    torch.set_num_threads(settings.threads)
    data = Path(settings.data) if Path(settings.data).is_absolute() else ROOT / settings.data
    results, started = [], time.perf_counter()
    with tempfile.TemporaryDirectory() as scratch:
        for name in settings.captures:
            results.append(run_capture(data / name, Path(scratch), settings))
            print(f"\n{name}")
            for method, value in results[-1]["psnr_db"].items():
                print(f"  {method:20s} {value:6.2f} dB")
    out = {"settings": asdict(settings), "seconds": time.perf_counter() - started, "captures": results}
    write_json(Path(args.output) / f"{Path(args.config).stem}.json", out)
    return out


if __name__ == "__main__":
    main()
