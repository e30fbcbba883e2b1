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

from .atomic import save_figure
from .model.brdf import SVBRDF
from .model.geometry import angle, from_plane
from .model.lights import Kernel, Lights
from .model.registry import MODELS
from .model.rendering import render

__all__ = [
    "MODEL_COLOURS",
    "EXTRA_COLOURS",
    "model_colours",
    "REGIONS",
    "REGION_COLOURS",
    "STAT_LABELS",
    "display",
    "heldout_psnr",
    "relit_strip",
    "relit_title",
    "score",
    "shared_limit",
    "stat_label",
    "write_fit_previews",
    "write_previews",
    "write_report",
]

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
    s = svbrdf.flatten()
    t = truth.flatten().to(device=s.normal.device)  # the fit's device (a fit on CUDA, a truth read on the CPU)
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
    like, device = observed.dtype, svbrdf.normal.device  # rendered where the maps are
    lights, view = lights.to(device=device, dtype=like), view.to(device=device, dtype=like)
    predicted = render(svbrdf.to(dtype=like), lights, view).permute(2, 3, 0, 1)
    mse = (predicted - observed.to(device)).pow(2).mean().item()
    return 10 * math.log10(peak * peak / mse) if mse > 0 else math.inf


def display(linear: Tensor | np.ndarray, white: float) -> np.ndarray:
    """Linear values scaled so that ``white`` is 1, clipped, and sRGB-encoded for a screen."""
    x = np.clip(np.asarray(linear, dtype=np.float64) / white, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def _rgb(image: np.ndarray) -> np.ndarray:
    return np.repeat(image[..., None], 3, -1) if image.ndim == 2 or image.shape[-1] == 1 else image[..., :3]


MODEL_COLOURS = ("#bdbdbd", "#1f77b4", "#2ca02c", "#ff7f0e", "#d62728")
"""The colour of each built-in model code (``MODEL_CODES``: diffuse, ward-iso, ward-iso-colour,
ward-aniso, ward-dual), the same in ``report.png`` and ``previews/model.png``."""
EXTRA_COLOURS = ("#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#7f7f7f")
"""The colours of the codes of models registered after the built-in ones, in turn."""
REGION_COLOURS = ("#e0d7c6", "#8c564b", "#d4a017", "#9467bd")
"""The colour of each region code (:data:`REGIONS`)."""

STAT_LABELS = {
    "normal_deg": "normal error, median (deg)",
    "normal_deg_p90": "normal error, 90th percentile (deg)",
    "kd": "k_d relative error, median",
    "matte_share_ks0": "matte pixels fitted without a lobe (share)",
    "heldout_psnr_db": "held-out frames, PSNR of the fit (dB)",
    "truth_heldout_psnr_db": "held-out frames, PSNR of the truth (dB)",
}
_STAT_PARTS = {
    "normal_deg": "normal error (deg)",
    "kd": "k_d rel. error",
    "ks": "k_s rel. error",
    "alpha": "alpha rel. error",
    "ks2": "2nd lobe k_s rel. error",
    "alpha2": "2nd lobe alpha rel. error",
}


def stat_label(key: str) -> str:
    """The words for a key of :func:`score` (``matte_share_ks0`` -> ``matte pixels fitted without a
    lobe (share)``, ``varnished_ks`` -> ``varnished: k_s rel. error``); the key itself otherwise."""
    if key in STAT_LABELS:
        return STAT_LABELS[key]
    for region in REGIONS:
        rest = key.removeprefix(f"{region}_")
        if rest != key and rest in _STAT_PARTS:
            return f"{region}: {_STAT_PARTS[rest]}"
    return key


def shared_limit(*maps: np.ndarray | None, quantile: float = 0.99) -> float:
    """A robust top of a colour scale shared by ``maps`` (e.g. a fit and its truth): the largest of
    their ``quantile``-th quantiles, so that one outlier does not squash the scale; > 0."""
    tops = [float(np.quantile(m[np.isfinite(m)], quantile)) for m in maps if m is not None and np.isfinite(m).any()]
    return max(tops + [1e-6])


def model_colours(count: int | None = None) -> tuple[str, ...]:
    """A colour for each of ``count`` model codes (by default the registered models'):
    :data:`MODEL_COLOURS`, then :data:`EXTRA_COLOURS` in turn.

    Example:
        >>> model_colours(7)[5:]
        ('#9467bd', '#8c564b')
    """
    count = len(MODELS) if count is None else count
    extra = max(count - len(MODEL_COLOURS), 0)
    return (MODEL_COLOURS + tuple(EXTRA_COLOURS[i % len(EXTRA_COLOURS)] for i in range(extra)))[:count]


def _categorical(colours: tuple[str, ...]):
    from matplotlib.colors import BoundaryNorm, ListedColormap

    return ListedColormap(colours), BoundaryNorm(np.arange(len(colours) + 1) - 0.5, len(colours))


def _key(ax, names: tuple[str, ...], colours: tuple[str, ...], codes: np.ndarray) -> None:
    """A colour key of the categories present in ``codes`` beside ``ax``."""
    from matplotlib.patches import Patch

    present = set(np.unique(np.round(codes[np.isfinite(codes)])).astype(int).tolist())
    handles = [Patch(color=c, label=n) for i, (n, c) in enumerate(zip(names, colours, strict=True)) if i in present]
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.02),
        ncol=2,
        fontsize=7,
        frameon=False,
        handlelength=1.0,
        columnspacing=0.8,
    )


def _preview(path: Path, image: np.ndarray, title: str, *, cmap=None, vmin=None, vmax=None, key=None) -> None:
    """A readable preview: the map enlarged (nearest), titled, with a colourbar for a scalar map
    or a colour key for a categorical one (``key``: names and colours)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.6 if key or cmap else 4.4, 4.4))
    norm = None
    if key is not None:
        cmap, norm = _categorical(key[1])
        vmin = vmax = None
    im = ax.imshow(image, cmap=cmap, norm=norm, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    if key is not None:
        _key(ax, key[0], key[1], image)
    elif cmap is not None:
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def relit_strip(
    svbrdf: SVBRDF, kernel: Kernel, view: Tensor, *, count: int = 8, theta_deg: float = 30.0
) -> tuple[Tensor, Tensor]:
    """Renders ``(count, H, W, C)`` of the maps under a light (``kernel``) circling the zenith at
    ``theta_deg``, and its directions ``(count, 3)``."""
    like = svbrdf.diffuse
    psi = torch.arange(count, dtype=torch.float64, device=like.device) * (2 * math.pi / count)
    radius = math.sin(math.radians(theta_deg))
    directions = from_plane(torch.stack([radius * torch.cos(psi), radius * torch.sin(psi)], -1)).to(like)
    irradiance = torch.ones(count, 1, dtype=like.dtype, device=like.device)
    lights = Lights(directions, kernel, irradiance, torch.ones(count, dtype=like.dtype, device=like.device))
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
    white: float = 1.0,
) -> list[Path]:
    """PNG previews of fitted maps (leading dims ``(H, W)``) in ``folder``, each enlarged and
    titled, scalar maps with a colourbar: ``normal.png`` (``RGB = (n + 1) / 2``), ``diffuse.png``
    (sRGB-encoded, ``white`` shown white), ``specular.png`` and ``roughness.png`` (false colour, the scale from 0 to the
    99th percentile of the fit and ``truth``: one outlier does not squash it), ``specular2.png``
    and ``roughness2.png`` for a second lobe (where some pixel has one), and where given
    ``model.png`` (the model codes of :data:`torchspec.pipeline.MODEL_CODES` in
    :data:`MODEL_COLOURS`, with a key), ``residual.png``, ``quality.png`` and, against ``truth``,
    ``normal_error.png`` (degrees) and ``diffuse_error.png`` (relative). Returns the paths written."""
    folder = Path(folder)
    s = svbrdf.to(device="cpu", dtype=torch.float64)
    t = truth.to(device="cpu", dtype=torch.float64) if truth is not None else None
    written = []

    def save(name, image, title, **options):
        path = folder / name
        _preview(path, image, title, **options)
        written.append(path)

    save("normal.png", ((s.normal.numpy() + 1) / 2).clip(0, 1), "normal (RGB = (n + 1) / 2)")
    shown = "diffuse k_d (sRGB)" + (f", {white:.3g} shown white" if white != 1.0 else "")
    save("diffuse.png", _rgb(display(s.diffuse.numpy(), white)), shown)
    ks, alpha = s.specular.mean(-1).numpy(), s.roughness.mean(-1).numpy()
    true_ks = t.specular.mean(-1).numpy() if t is not None else None
    true_alpha = t.roughness.mean(-1).numpy() if t is not None else None
    save("specular.png", ks, "specular k_s (mean of channels)", cmap="magma", vmin=0.0, vmax=shared_limit(ks, true_ks))
    top = shared_limit(alpha, true_alpha)
    save("roughness.png", alpha, "roughness alpha (mean of axes)", cmap="viridis", vmin=0.0, vmax=top)
    if s.specular2 is not None and bool((s.specular2 > 0).any()):
        ks2, alpha2 = s.specular2.mean(-1).numpy(), s.roughness2.mean(-1).numpy()
        save("specular2.png", ks2, "second lobe k_s", cmap="magma", vmin=0.0, vmax=shared_limit(ks2))
        save("roughness2.png", alpha2, "second lobe alpha", cmap="viridis", vmin=0.0, vmax=shared_limit(alpha2))
    if model is not None:
        codes = model.cpu().numpy().astype(np.float64)
        save("model.png", codes, "model of each pixel", key=(tuple(MODELS), model_colours()))
    if residual is not None:
        r = np.log10(np.clip(residual.cpu().double().numpy(), 1e-6, None))
        save("residual.png", r, "log10 relative residual", cmap="inferno", vmin=-6.0, vmax=0.0)
    if quality is not None:
        save(
            "quality.png", quality.cpu().double().numpy(), "quality (0: untrusted)", cmap="viridis", vmin=0.0, vmax=1.0
        )
    if t is not None:
        error = torch.rad2deg(angle(s.normal, t.normal)).numpy()
        top = max(1.0, float(np.quantile(error, 0.99)))
        save("normal_error.png", error, "normal error (deg)", cmap="inferno", vmin=0.0, vmax=top)
        kd = np.log10(np.clip(_relative(s.diffuse, t.diffuse).amax(-1).numpy(), 1e-5, None))
        save("diffuse_error.png", kd, "log10 relative k_d error", cmap="inferno", vmin=-5.0, vmax=0.0)
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
    theta_deg: float = 30.0,
) -> None:
    """One PNG page: the fitted maps, the error maps against ``truth`` (``k_s`` and ``alpha`` on
    scales shared with the truth's, to the 99th percentile), the model and region maps with colour
    keys (:data:`MODEL_COLOURS`, :data:`REGION_COLOURS`), the relit strip (fitted above, true
    below; the light ``theta_deg`` from the zenith), the ``scores`` in words (:func:`stat_label`)
    and the ``notes`` (timings, counts)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = fit.svbrdf.to(device="cpu", dtype=torch.float64)
    t = truth.to(device="cpu", dtype=torch.float64) if truth is not None else None
    count = strip.shape[0]
    white = float(np.quantile((true_strip if true_strip is not None else strip).double().cpu().numpy(), 0.995))
    ks, alpha = s.specular.mean(-1).numpy(), s.roughness.mean(-1).numpy()
    true_ks = t.specular.mean(-1).numpy() if t is not None else None
    true_alpha = t.roughness.mean(-1).numpy() if t is not None else None
    ks_top, alpha_top = shared_limit(ks, true_ks), shared_limit(alpha, true_alpha)
    residual = np.log10(np.clip(fit.residual.cpu().double().numpy(), 1e-6, None))
    # (title, image, colour map, (vmin, vmax) or None, categorical key or None)
    panels = [
        ("normal, RGB = (n+1)/2", ((s.normal.numpy() + 1) / 2).clip(0, 1), None, None, None),
        ("k_d (sRGB)", _rgb(display(s.diffuse.numpy(), 1.0)), None, None, None),
        ("k_s (fit)", ks, "magma", (0.0, ks_top), None),
        ("alpha (fit)", alpha, "viridis", (0.0, alpha_top), None),
        ("model", fit.model.cpu().double().numpy(), None, None, (tuple(MODELS), model_colours())),
        ("log10 rel. residual", residual, "inferno", None, None),
    ]
    if t is not None:
        kd_error = np.log10(np.clip(_relative(s.diffuse, t.diffuse).amax(-1).numpy(), 1e-5, None))
        panels += [
            ("normal error (deg)", torch.rad2deg(angle(s.normal, t.normal)).numpy(), "inferno", None, None),
            ("log10 rel. k_d error", kd_error, "inferno", None, None),
            ("k_s (truth)", true_ks, "magma", (0.0, ks_top), None),
            ("alpha (truth)", true_alpha, "viridis", (0.0, alpha_top), None),
        ]
    if regions is not None:
        panels.append(("regions (truth)", regions.cpu().double().numpy(), None, None, (REGIONS, REGION_COLOURS)))
    columns = 6
    rows_of_maps = math.ceil(len(panels) / columns)
    strips = [("fitted", strip)] + ([("true", true_strip)] if true_strip is not None else [])
    map_height, strip_height, text_height = 3.1 * rows_of_maps, 2.0 * len(strips), 2.2
    fig = plt.figure(figsize=(17, map_height + strip_height + text_height + 0.5))
    top, middle, bottom = fig.subfigures(3, 1, height_ratios=[map_height, strip_height, text_height])
    axes = top.subplots(rows_of_maps, columns, squeeze=False, gridspec_kw={"wspace": 0.5, "hspace": 0.5})
    for ax in axes.flat:
        ax.axis("off")
    for ax, (name, image, cmap, limits, key) in zip(axes.flat, panels, strict=False):
        norm = None
        if key is not None:
            cmap, norm = _categorical(key[1])
        vmin, vmax = limits if limits is not None else (None, None)
        im = ax.imshow(image, cmap=cmap, norm=norm, vmin=vmin, vmax=vmax, interpolation="nearest")
        if key is not None:
            _key(ax, key[0], key[1], image)
        elif cmap is not None:
            top.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        ax.set_title(name, fontsize=9)
    axes = middle.subplots(len(strips), count, squeeze=False)
    for row, (label, images) in enumerate(strips):
        for k in range(count):
            ax = axes[row, k]
            ax.imshow(_rgb(display(images[k].double().cpu().numpy(), white)), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if k == 0:
                ax.set_ylabel(f"{label}, relit", fontsize=8)
    middle.suptitle(relit_title(theta_deg), fontsize=9)
    lines = [
        f"{stat_label(name)}: {value:.4g}" if isinstance(value, float) else f"{stat_label(name)}: {value}"
        for name, value in scores.items()
    ]
    half = (len(lines) + 1) // 2
    text = {"fontsize": 8, "family": "monospace", "va": "top"}
    bottom.text(0.01, 0.97, "\n".join(["errors against the truth:", *lines[:half]]), **text)
    bottom.text(0.35, 0.97, "\n".join(["", *lines[half:]]), **text)
    bottom.text(0.68, 0.97, "\n".join(notes), wrap=True, **text)
    fig.suptitle(title, fontsize=12)
    save_figure(fig, Path(path), dpi=72)


def relit_title(theta_deg: float) -> str:
    """The relit strip's title, its light's angle said both ways."""
    return (
        f"relit by a light circling the zenith, {theta_deg:g} deg from it (elevation {90 - theta_deg:g} deg above "
        "the surface)"
    )


PREVIEW_LIGHT = (-0.5, 0.5, 0.7071)
"""The direction of ``relit.png``'s light in :func:`write_fit_previews`: 45 degrees above the
horizon from the upper left, the usual raking light of a photographed relief (the fitted frame
nearest to it is taken)."""

PREVIEW_PIXELS = 1024
"""The longest side of :func:`write_fit_previews`' maps: a larger fit is shown one pixel in N."""


def write_fit_previews(folder: str | Path, fit, capture, *, largest: int = PREVIEW_PIXELS) -> list[Path]:
    """PNG previews of a fit (:class:`torchspec.pipeline.Fit`) of ``capture``
    (:class:`torchspec.io.Capture`) in ``folder``: :func:`write_previews`' maps (``k_d`` white at
    its 99th percentile), the model, residual and quality maps, and ``relit.png``: the photograph
    of the fitted frame whose light is nearest :data:`PREVIEW_LIGHT` beside the maps relit by that
    frame's light (the physical model alone, as a renderer uses the maps; a near light taken as
    distant), both encoded alike for display, white at the photograph's 99th percentile. A fit of
    more than ``largest`` pixels a side is shown one pixel in ``ceil(side / largest)``. Returns the
    paths written."""
    h, w = fit.quality.shape
    step = max(1, math.ceil(max(h, w) / largest))
    pick = (slice(None, None, step), slice(None, None, step))
    svbrdf = fit.svbrdf[pick].to(device="cpu", dtype=torch.float64)
    kd = svbrdf.diffuse.flatten()
    white = float(torch.quantile(kd[:: max(1, kd.numel() // 1_000_000)], 0.99)) if kd.numel() else 1.0
    written = write_previews(
        folder, svbrdf, model=fit.model[pick], residual=fit.residual[pick], quality=fit.quality[pick],
        white=white if white > 0 else 1.0,
    )  # fmt: skip
    lights = capture.lights(dtype=torch.float64)
    frames = list(fit.stats["frames"])
    toward = torch.tensor(PREVIEW_LIGHT, dtype=torch.float64, device=lights.directions.device)
    k = frames[int((lights.directions[frames] @ toward).argmax())]
    view = torch.tensor(capture.view, dtype=torch.float64, device=lights.directions.device)
    relit = render(svbrdf.flatten(), lights[[k]], view).reshape(*svbrdf.shape, -1)  # (h, w, C)
    photo = capture.read_frames([k], dtype=torch.float64, nonfinite="keep")[0].permute(1, 2, 0)[pick]
    finite = photo[photo.isfinite()]
    top = float(torch.quantile(finite[:: max(1, finite.numel() // 1_000_000)], 0.99)) if finite.numel() else 1.0
    path = Path(folder) / "relit.png"
    _side_by_side(
        path,
        [_rgb(display(torch.nan_to_num(photo).numpy(), top)), _rgb(display(relit.numpy(), top))],
        [f"photograph: frame {k} ({capture.frames[k].file})", "the maps relit by its light (no residual term)"],
    )
    return [*written, path]


def _side_by_side(path: Path, images: list[np.ndarray], titles: list[str]) -> None:
    """``images`` side by side, each titled, in one PNG (written atomically)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(images), figsize=(4.4 * len(images), 4.6))
    for ax, image, title in zip(axes, images, titles, strict=True):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
