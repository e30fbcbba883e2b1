"""Scores against a truth, PNG previews of a fit, relit renders and a one-page report.

- :func:`score`: median errors of fitted maps against true ones (normal angle, relative ``k_d``,
  ``k_s``, ``alpha``; per region when a region map is given) and the share of matte pixels fitted
  without a lobe;
- :func:`heldout_psnr`: how well maps predict frames (e.g. frames left out of the fit);
- :func:`write_previews`: the maps as PNG (the normal in the usual ``RGB = (n + 1) / 2``
  encoding, ``k_d`` and relit renders gamma-encoded for display), the model and error maps;
- :func:`relit_strip`: renders of fitted (and true) maps under a light moving around the zenith;
- :func:`write_report`: one PNG page with the maps, the errors and the strip.

Every file is written atomically.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .atomic import atomic_path, save_figure
from .brdf import SVBRDF
from .geometry import angle, from_plane
from .lights import Kernel, Lights
from .models import MODELS
from .rendering import render

__all__ = ["REGIONS", "score", "heldout_psnr", "write_previews", "relit_strip", "write_report", "display"]

REGIONS = ("matte", "varnished", "gilded", "dual")
"""Region codes of a simulated painting's ``regions`` map (``truth/regions.exr``)."""


def _relative(a: Tensor, b: Tensor) -> Tensor:
    return ((a.double() - b.double()) / b.double()).abs()


def score(svbrdf: SVBRDF, truth: SVBRDF, regions: Tensor | None = None, matte_ks: float = 1e-3) -> dict:
    """Median errors of ``svbrdf`` against ``truth`` (same leading dims): the normal's angle in
    degrees (median and 90th percentile), the relative error of ``k_d`` over all pixels; with
    ``regions`` (codes of :data:`REGIONS`) also per region, ``k_s`` (channel mean) and ``alpha``
    (mean of both axes) on the lobed regions, and the share of matte pixels whose fitted ``k_s``
    stays below ``matte_ks``; where the truth has a second lobe and the fit one too, its
    ``k_s`` and ``alpha`` (``<region>_ks2``, ``<region>_alpha2``)."""
    s, t = svbrdf.flatten(), truth.flatten()
    normal = torch.rad2deg(angle(s.normal.double(), t.normal.double()))
    kd = _relative(s.diffuse, t.diffuse)
    out = {
        "normal_deg": float(normal.median()),
        "normal_deg_p90": float(normal.quantile(0.9)),
        "kd": float(kd.median()),
    }
    if regions is None:
        return out
    r = regions.reshape(-1).round().long().to(s.normal.device)
    ks = _relative(s.specular.mean(-1), t.specular.mean(-1))
    alpha = _relative(s.roughness, t.roughness).mean(-1)
    if bool((r == 0).any()):
        out["matte_share_ks0"] = float((s.specular[r == 0].amax(-1) < matte_ks).double().mean())
    for code, name in enumerate(REGIONS):
        m = r == code
        if not bool(m.any()):
            continue
        out[f"{name}_normal_deg"] = float(normal[m].median())
        out[f"{name}_kd"] = float(kd[m].median())
        if name != "matte":
            out[f"{name}_ks"] = float(ks[m].median())
            out[f"{name}_alpha"] = float(alpha[m].median())
        if t.specular2 is not None and s.specular2 is not None and bool((t.specular2[m] > 0).any()):
            out[f"{name}_ks2"] = float(_relative(s.specular2[m].mean(-1), t.specular2[m].mean(-1)).median())
            out[f"{name}_alpha2"] = float(_relative(s.roughness2[m], t.roughness2[m]).mean(-1).median())
    return out


def heldout_psnr(svbrdf: SVBRDF, lights: Lights, view: Tensor, observed: Tensor, peak: float) -> float:
    """PSNR (dB) of predicting ``observed (K, C, H, W)`` under ``lights`` from the maps, with
    ``peak`` as the signal's peak (e.g. the whole capture's maximum)."""
    like = observed.dtype
    predicted = render(svbrdf.to(dtype=like), lights.to(dtype=like), view.to(like)).permute(2, 3, 0, 1)
    mse = (predicted - observed).pow(2).mean().item()
    return 10 * math.log10(peak * peak / mse) if mse > 0 else math.inf


def display(linear: Tensor | np.ndarray, white: float) -> np.ndarray:
    """Linear values scaled so that ``white`` is 1, clipped, and sRGB-encoded for a screen."""
    x = np.clip(np.asarray(linear, dtype=np.float64) / white, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[..., None], 3, -1) if image.ndim == 2 or image.shape[-1] == 1 else image[..., :3]


def _save_png(path: Path, image: np.ndarray, cmap: str | None = None, vmin=None, vmax=None) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        plt.imsave(tmp, image, cmap=cmap, vmin=vmin, vmax=vmax, format="png")


def relit_strip(
    svbrdf: SVBRDF, kernel: Kernel, view: Tensor, *, count: int = 8, theta_deg: float = 30.0
) -> tuple[Tensor, Tensor]:
    """Renders ``(count, H, W, C)`` of the maps under a light (``kernel``) circling the zenith at
    ``theta_deg``, and its directions ``(count, 3)``."""
    like = svbrdf.diffuse
    psi = torch.arange(count, dtype=torch.float64) * (2 * math.pi / count)
    radius = math.sin(math.radians(theta_deg))
    directions = from_plane(torch.stack([radius * torch.cos(psi), radius * torch.sin(psi)], -1)).to(like)
    lights = Lights(directions, kernel, torch.ones(count, 1, dtype=like.dtype), torch.ones(count, dtype=like.dtype))
    values = render(svbrdf, lights, view.to(like))  # (H, W, K, C)
    return values.permute(2, 0, 1, 3), directions


def write_previews(
    folder: str | Path,
    svbrdf: SVBRDF,
    *,
    model: Tensor | None = None,
    residual: Tensor | None = None,
    quality: Tensor | None = None,
    truth: SVBRDF | None = None,
) -> list[Path]:
    """PNG previews of fitted maps (leading dims ``(H, W)``) in ``folder``: ``normal.png``
    (``RGB = (n + 1) / 2``), ``diffuse.png`` (sRGB-encoded), ``specular.png`` and
    ``roughness.png`` (false colour), ``specular2.png`` and ``roughness2.png`` for a second lobe
    (where some pixel has one), and where given ``model.png`` (the model codes of
    :data:`torchspec.pipeline.MODEL_CODES`, 0 diffuse to 4 ward-dual),
    ``residual.png``, ``quality.png`` and, against ``truth``, ``normal_error.png`` (degrees) and
    ``diffuse_error.png`` (relative). Returns the paths written."""
    folder = Path(folder)
    s = svbrdf.to(device="cpu", dtype=torch.float64)
    written = []

    def save(name, image, cmap=None, vmin=None, vmax=None):
        path = folder / name
        _save_png(path, image, cmap, vmin, vmax)
        written.append(path)

    save("normal.png", ((s.normal.numpy() + 1) / 2).clip(0, 1))
    save("diffuse.png", _rgb(display(s.diffuse.numpy(), 1.0)))
    ks = s.specular.mean(-1).numpy()
    save("specular.png", ks, "magma", 0.0, max(float(ks.max()), 1e-6))
    save("roughness.png", s.roughness.mean(-1).numpy(), "viridis", 0.0, max(float(s.roughness.max()), 1e-6))
    if s.specular2 is not None and bool((s.specular2 > 0).any()):
        ks2 = s.specular2.mean(-1).numpy()
        save("specular2.png", ks2, "magma", 0.0, float(ks2.max()))
        save("roughness2.png", s.roughness2.mean(-1).numpy(), "viridis", 0.0, float(s.roughness2.max()))
    if model is not None:
        save("model.png", model.cpu().numpy().astype(np.float64), "viridis", 0.0, float(len(MODELS) - 1))
    if residual is not None:
        r = residual.cpu().double().numpy()
        save("residual.png", np.log10(np.clip(r, 1e-6, None)), "inferno", -6.0, 0.0)
    if quality is not None:
        save("quality.png", quality.cpu().double().numpy(), "viridis", 0.0, 1.0)
    if truth is not None:
        t = truth.to(device="cpu", dtype=torch.float64)
        error = torch.rad2deg(angle(s.normal, t.normal)).numpy()
        save("normal_error.png", error, "inferno", 0.0, max(1.0, float(np.quantile(error, 0.99))))
        kd = _relative(s.diffuse, t.diffuse).amax(-1).numpy()
        save("diffuse_error.png", np.log10(np.clip(kd, 1e-5, None)), "inferno", -5.0, 0.0)
    return written


def write_report(
    path: str | Path,
    *,
    title: str,
    fit,
    truth: SVBRDF | None,
    regions: Tensor | None,
    scores: dict,
    strip: Tensor,
    true_strip: Tensor | None,
    notes: list[str],
) -> None:
    """One PNG page: the fitted maps, the error maps against ``truth``, the relit strip (fitted
    above, true below), the ``scores`` and the ``notes`` (timings, counts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = fit.svbrdf.to(device="cpu", dtype=torch.float64)
    count = strip.shape[0]
    white = float(np.quantile((true_strip if true_strip is not None else strip).double().numpy(), 0.995))
    panels = [
        ("normal (RGB = (n + 1) / 2)", ((s.normal.numpy() + 1) / 2).clip(0, 1), None, None),
        ("k_d", _rgb(display(s.diffuse.numpy(), 1.0)), None, None),
        ("k_s (mean of channels)", s.specular.mean(-1).numpy(), "magma", None),
        ("alpha (mean of axes)", s.roughness.mean(-1).numpy(), "viridis", None),
        (
            "model: 0 diffuse, 1 ward-iso, 2 ward-iso-colour, 3 ward-aniso",
            fit.model.cpu().double().numpy(),
            "viridis",
            (0, 3),
        ),
        (
            "log10 relative residual",
            np.log10(np.clip(fit.residual.cpu().double().numpy(), 1e-6, None)),
            "inferno",
            None,
        ),
    ]
    if truth is not None:
        t = truth.to(device="cpu", dtype=torch.float64)
        kd_error = np.log10(np.clip(_relative(s.diffuse, t.diffuse).amax(-1).numpy(), 1e-5, None))
        panels += [
            ("normal error (deg)", torch.rad2deg(angle(s.normal, t.normal)).numpy(), "inferno", None),
            ("log10 relative k_d error", kd_error, "inferno", None),
            ("true k_s", t.specular.mean(-1).numpy(), "magma", None),
            ("true alpha", t.roughness.mean(-1).numpy(), "viridis", None),
        ]
    if regions is not None:
        names = ", ".join(f"{i} {n}" for i, n in enumerate(REGIONS))
        panels.append((f"regions ({names})", regions.cpu().numpy(), "tab10", (0, 9)))
    columns = 6
    rows_of_maps = math.ceil(len(panels) / columns)
    strips = [("fitted", strip)] + ([("true", true_strip)] if true_strip is not None else [])
    fig = plt.figure(figsize=(15, 2.6 * rows_of_maps + 1.9 * len(strips) * 8 / count + 2.6))
    top, middle, bottom = fig.subfigures(3, 1, height_ratios=[2.6 * rows_of_maps, 1.9 * len(strips), 2.4])
    axes = top.subplots(rows_of_maps, columns, squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (name, image, cmap, limits) in zip(axes.flat, panels, strict=False):
        vmin, vmax = limits if limits is not None else (None, None)
        im = ax.imshow(image, cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
        if cmap is not None and limits is None:
            top.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        ax.set_title(name, fontsize=8)
    axes = middle.subplots(len(strips), count, squeeze=False)
    for row, (label, images) in enumerate(strips):
        for k in range(count):
            ax = axes[row, k]
            ax.imshow(_rgb(display(images[k].double().cpu().numpy(), white)), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if k == 0:
                ax.set_ylabel(f"{label}, relit", fontsize=8)
    middle.suptitle("relit by a light circling the zenith", fontsize=9)
    lines = [
        f"{name}: {value:.4g}" if isinstance(value, float) else f"{name}: {value}" for name, value in scores.items()
    ]
    half = (len(lines) + 1) // 2
    bottom.text(
        0.01,
        0.95,
        "\n".join(["errors against the truth (medians; relative unless in deg or dB):", *lines[:half]]),
        fontsize=8,
        family="monospace",
        va="top",
    )
    bottom.text(0.36, 0.95, "\n".join(["", *lines[half:]]), fontsize=8, family="monospace", va="top")
    bottom.text(0.68, 0.95, "\n".join(notes), fontsize=8, family="monospace", va="top", wrap=True)
    fig.suptitle(title, fontsize=12)
    save_figure(fig, Path(path), dpi=90)
