"""Relighting: predict every frame of a capture from SVBRDF maps (``torchspec render``).

Reads the maps (a fit, or a capture's ``truth/``) and the capture's light list, renders each frame
with :func:`torchspec.model.rendering.render_image` (memory is bounded by a chunk of rows; near lights,
frames with a ``position`` or a fit that calibrated them (:func:`fit_positions`), block by block
as the fit sees them: :func:`render_near`), and
writes the predicted frames under the manifest's file names with a copy of the manifest, so the
output is itself a capture. Against the capture's own frames it reports the PSNR (peak: the
capture's maximum) and the relative RMS error.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..errors import TorchspecError
from ..io import Capture, CaptureError, Maps, read_capture, read_svbrdf, write_capture
from ..io.scale import capture_at
from ..model.brdf import SVBRDF
from ..model.indirect import flat_maps
from ..model.lights import Lights
from ..model.near_lights import lights_at
from ..model.quadrature import Quadrature
from ..model.rendering import TILE_PIXELS, render, render_image
from ..model.residual_term import MAP_NAME, WEIGHT_MAP, ResidualTerm
from ..model.visibility import SOFTNESS, frame_visibility
from ..outputs import check_apart, check_output
from ..pipeline.plan import device_of
from ..pipeline.tiling import tiling_of

__all__ = [
    "capture_places",
    "capture_for",
    "fit_positions",
    "fitted_scales",
    "psnr",
    "render_capture",
    "render_near",
    "shaded_render",
    "indirect_light",
    "residual_term_of",
    "shadow_terms",
    "softness_of",
]


def render_near(
    svbrdf: SVBRDF,
    lights: Lights,
    positions: torch.Tensor,
    view: torch.Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
    lobe: str = "ward",
    term: ResidualTerm | None = None,
    seen: torch.Tensor | None = None,
) -> torch.Tensor:
    """``(H, W, K, C)``: maps of leading dims ``(H, W)`` under near lights at ``positions (K, 3)``
    (:mod:`torchspec.model.near_lights`), in the square blocks a fit of them uses
    (:func:`torchspec.pipeline.tiling.tiling_of`), each under the lights as seen from its centre,
    times the lights' visibility ``seen (H, W, K, 1)`` where given (cast shadows:
    :func:`shadow_terms`), with the fit's residual ``term`` (leading dims ``(H, W)``) applied
    under the same lights (after the visibility: the term of a fit with cast shadows corrects
    the prediction with its shadows, :func:`torchspec.pipeline.tile.residual_term`)."""
    height, width = svbrdf.shape
    positions = positions.to(svbrdf.normal)
    tiling = tiling_of(height, width, TILE_PIXELS, positions)
    flat = svbrdf.flatten()
    coefficients = None if term is None else term.coefficients.reshape(height * width, *term.coefficients.shape[-2:])
    out = None
    for first, stop in tiling.ranges:
        index = tiling.order[first:stop].to(svbrdf.normal.device)
        centre = tiling.points[tiling.order[first:stop].to(tiling.points.device)].mean(0)
        near = lights_at(lights, positions, centre)
        values = render(flat[index], near, view, quadrature=quadrature, lobe=lobe)
        if seen is not None:
            values = values * seen.reshape(height * width, *seen.shape[2:])[index]
        if term is not None:
            weight = None if term.weight is None else term.weight.reshape(-1)[index]
            part = ResidualTerm(coefficients[index], term.chosen.reshape(-1)[index], weight=weight, domain=term.domain)
            values = part.apply(values, near)
        out = values.new_empty((height * width, *values.shape[1:])) if out is None else out
        out[index] = values
    return out.reshape(height, width, *out.shape[1:])


def shaded_render(
    svbrdf: SVBRDF,
    lights: Lights,
    view: torch.Tensor,
    positions: torch.Tensor | None = None,
    *,
    seen: torch.Tensor | None = None,
    bounce: torch.Tensor | None = None,
    term: ResidualTerm | None = None,
    quadrature: Quadrature = Quadrature(),
    lobe: str = "ward",
    progress: bool = False,
) -> torch.Tensor:
    """``(H, W, K, C)``: maps under ``lights`` as a fit predicts its frames: rendered (near
    lights at ``positions (K, 3)`` block by block, :func:`render_near`), times the visibility
    ``seen (H, W, K, 1)``, with the residual ``term`` applied, plus the indirect light ``bounce
    (H, W, K, C)`` (:func:`shadow_terms`; ``None``: no shadows, no indirect light). The term comes
    after the visibility because a fit with cast shadows fits it on the recorded values against
    the rendering times the visibility, and on the values less the indirect light
    (:func:`torchspec.pipeline.tile.residual_term`)."""
    if positions is not None:
        values = render_near(svbrdf, lights, positions, view, quadrature=quadrature, lobe=lobe, term=term, seen=seen)
    else:
        values = render_image(svbrdf, lights, view, quadrature=quadrature, lobe=lobe, progress=progress)
        values = values if seen is None else values * seen
        values = values if term is None else term.apply(values, lights)
    return values if bounce is None else values + bounce


def indirect_light(
    svbrdf: SVBRDF,
    share: torch.Tensor,
    lights: Lights,
    view: torch.Tensor,
    positions: torch.Tensor | None = None,
    *,
    quadrature: Quadrature = Quadrature(),
) -> torch.Tensor:
    """``(H, W, K, C)`` the indirect light of maps fitted with cast shadows: each pixel's indirect
    share ``share (H, W)`` (``indirect.exr``) times its flat diffuse under ``lights``
    (:mod:`torchspec.model.indirect`), near lights at ``positions (K, 3)`` block by block as
    :func:`render_near` lights them."""
    flat = flat_maps(svbrdf)
    if positions is not None:
        values = render_near(flat, lights, positions, view, quadrature=quadrature)
    else:
        values = render_image(flat, lights, view, quadrature=quadrature)
    return values * share.to(values)[..., None, None]


def shadow_terms(
    svbrdf: SVBRDF,
    height: torch.Tensor,
    share: torch.Tensor | None,
    softness: float,
    lights: Lights,
    view: torch.Tensor,
    positions: torch.Tensor | None = None,
    *,
    quadrature: Quadrature = Quadrature(),
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What maps fitted with cast shadows add to their rendering ``r (H, W, K, C)`` under
    ``lights``, ``r V + b D``: the visibility ``V (H, W, K, 1)`` over ``height`` (``height.exr``)
    with the penumbra ``softness`` (radians, :func:`softness_of`), and the indirect light ``b D (H,
    W, K, C)`` of ``share`` (``indirect.exr``; ``None``: none, and ``None`` returned), near lights at
    ``positions (K, 3)`` as :func:`render_near` lights them."""
    seen = frame_visibility(height, lights, positions, softness=softness)[..., None]
    if share is None:
        return seen, None
    return seen, indirect_light(svbrdf, share, lights, view, positions, quadrature=quadrature)


def softness_of(maps: Maps) -> float:
    """The penumbra's width (radians) the fit chose for the cast shadows of ``maps``' height
    (``svbrdf.json``'s ``height.softness_deg``; absent: :data:`torchspec.model.visibility.SOFTNESS`)."""
    found = (maps.meta.get("height") or {}).get("softness_deg")
    return SOFTNESS if found is None else math.radians(float(found))


def capture_places(name: str, maps_folder: str | Path) -> list[Path]:
    """Where the capture that ``svbrdf.json``'s ``fit.capture`` names (``name``) may be, in order:
    as written (an absolute path), beside the maps' folder ``maps_folder`` as written (a relative
    one, as older fits wrote it), or by its folder's name beside the maps (maps and capture moved
    together)."""
    beside = Path(maps_folder).resolve().parent
    return list(dict.fromkeys([Path(name), beside / name, beside / Path(name).name]))


def fitted_scales(exposure, irradiance, lights: dict) -> tuple[np.ndarray, bool]:
    """Each fitted frame's ``exposure x irradiance`` ``(F, C)`` (``exposure (F,)``, ``irradiance
    (F, C)``), times the gains the fit calibrated (``svbrdf.json``'s ``fit.lights``: ``gains`` where
    ``calibrated`` lists ``irradiance``; one per frame and channel, or per frame), and whether it did:
    each photograph's brightness over the maps' render under a unit light."""
    products = np.asarray(exposure, dtype=np.float64)[:, None] * np.asarray(irradiance, dtype=np.float64)
    calibrated = "irradiance" in (lights.get("calibrated") or []) and lights.get("gains") is not None
    if calibrated:
        gains = np.asarray(lights["gains"], dtype=np.float64)
        products = products * (gains if gains.shape == products.shape else gains.reshape(products.shape[0], -1))
    return products, calibrated


def fit_positions(capture: Capture, meta: dict) -> tuple[torch.Tensor | None, str]:
    """The near lights' positions ``(K, 3)`` (float64; ``None``: distant lights) under which maps
    predict ``capture``'s frames, and what they come from: the capture's (``frames[k].position``),
    unless the fit calibrated them from the photographs (``meta``: ``svbrdf.json``, its
    ``fit.lights``: :func:`torchspec.pipeline.calibration.calibrated`): one dome radius (every frame at
    that distance along its direction), or the positions of the frames it fitted (``fit.frames``;
    the others keep the capture's, else lie at the calibrated positions' median distance along
    their direction). Calibrated gains are not used: a frame the fit left out has none.

    Raises:
        TorchspecError: ``fit.lights.positions`` is not one position for each of ``fit.frames``,
            or names a frame the capture does not have.
    """
    fit = meta.get("fit") or {}
    record = fit.get("lights") or {}
    calibrated = record.get("calibrated") or []
    directions, positions = capture.directions(), capture.positions()
    if "radius" in calibrated and record.get("radius") is not None:
        radius = float(record["radius"])
        return radius * directions, f"the fit's dome radius, {radius:g} widths"
    if "position" in calibrated and record.get("positions") is not None:
        frames = fit.get("frames") or []
        found = torch.tensor(record["positions"], dtype=torch.float64, device=directions.device)
        if tuple(found.shape) != (len(frames), 3) or not all(0 <= k < len(directions) for k in frames):
            raise TorchspecError(
                f"svbrdf.json: fit.lights.positions ({tuple(found.shape)}) is not a position for each of fit.frames "
                f"of {capture.manifest} ({len(directions)} frames): use the maps with the capture they were fitted from"
            )
        base = positions if positions is not None else found.norm(dim=-1).median() * directions
        index = torch.tensor(frames, dtype=torch.long, device=base.device)
        return base.index_put((index,), found), "the fit's calibrated positions"
    return positions, "the capture's positions"


def residual_term_of(maps: Maps, svbrdf_dir: Path | str, device: torch.device) -> ResidualTerm | None:
    """The fit's residual term (``residual_term.exr``, ``FitConfig.term.order``) of ``maps``
    read from ``svbrdf_dir``, on ``device``; ``None`` when the maps have none."""
    if MAP_NAME not in maps.extra:
        return None
    source = str(Path(svbrdf_dir) / f"{MAP_NAME}.exr")
    encoding = (maps.meta.get(MAP_NAME) or {}).get("encoding")  # the photographs' encoding; absent: sRGB
    weight = maps.extra.get(WEIGHT_MAP)
    return ResidualTerm.from_map(
        maps.extra[MAP_NAME].to(device), len(maps.svbrdf.channels), source,
        None if weight is None else weight.to(device), encoding,
    )  # fmt: skip


def capture_for(maps: Maps, capture: Capture) -> Capture:
    """``capture`` as the maps were fitted from it: read at the crop and downsample their
    ``svbrdf.json`` records (``fit.scale``, :mod:`torchspec.io.scale`), clipped boxes kept at the
    level the capture records; the capture itself when the maps record none.

    Raises:
        CaptureError: the maps were fitted from a capture of another size.
    """
    return capture_at(capture, (maps.meta.get("fit") or {}).get("scale"))


def psnr(predicted: torch.Tensor, observed: torch.Tensor) -> float:
    """PSNR in dB with the observed maximum as the peak."""
    mse = (predicted.double() - observed.double()).pow(2).mean().item()
    peak = observed.double().abs().max().item()
    return math.inf if mse == 0 else 10.0 * math.log10(peak * peak / mse)


def render_capture(
    svbrdf_dir: Path | str,
    capture_dir: Path | str,
    output_dir: Path | str | None,
    *,
    light: Path | dict | None = None,
    path: str = "auto",
    dtype: torch.dtype = torch.float32,
    lobe: str = "ward",
    overwrite: bool = False,
    progress: bool = False,
    term: bool = True,
    device: str | torch.device = "auto",
    shadows: bool = True,
) -> dict:
    """Predict a capture's frames from the maps in ``svbrdf_dir``; write them to ``output_dir``
    (unless ``None``) and compare with the capture's frames. The frames are computed on
    ``device`` (``auto``: CUDA when present, :func:`torchspec.pipeline.plan.device_of`).

    ``output_dir`` is checked before any work: a folder that holds files is refused unless
    ``overwrite`` (:func:`torchspec.outputs.check_output`); the capture's folder or the maps', one
    inside them or one holding them, always (:func:`torchspec.outputs.check_apart`). ``progress``
    shows a bar over the pixels (on stderr). A residual term in the maps (``residual_term.exr``,
    :mod:`torchspec.model.residual_term`) is added to the physical prediction unless ``term`` is false; the
    frames are then clamped at 0 where the term takes them below black, as a photograph holds no
    negative light (the output is a capture that ``info`` and ``read_capture`` read).
    Maps fitted with cast shadows (``height.exr``, ``FitConfig.shadows``) are rendered times each
    light's visibility over that height (:func:`torchspec.model.visibility.frame_visibility`) unless
    ``shadows`` is false.
    Maps fitted at a crop or downsample (``svbrdf.json``'s ``fit.scale``) are compared with the
    capture read at it (:func:`capture_for`); the frames written are then that size.

    Returns:
        ``{"frames", "psnr_db", "relative_rms", "per_frame_psnr_db", "predicted"}``; the
        predicted frames are ``(K, C, H, W)``.
    """
    if output_dir is not None:
        check_apart(output_dir, capture_dir, "the capture")  # its frames would be replaced by the predicted ones
        check_apart(output_dir, svbrdf_dir, "the maps' folder")
        check_output(output_dir, overwrite=overwrite)
    maps = read_svbrdf(svbrdf_dir)
    capture = capture_for(maps, read_capture(capture_dir))
    svbrdf = maps.svbrdf
    if tuple(svbrdf.shape) != (capture.height, capture.width):
        raise CaptureError(
            f"{Path(svbrdf_dir)}: the maps are {svbrdf.shape[1]}x{svbrdf.shape[0]} but {capture.manifest} "
            f"is {capture.width}x{capture.height}."
        )
    if tuple(svbrdf.channels) != tuple(capture.channels):
        raise CaptureError(
            f"{Path(svbrdf_dir)}: the maps have channels {svbrdf.channels}, {capture.manifest} has {capture.channels}."
        )
    where = device_of(device)
    svbrdf = svbrdf.to(where)
    lights = capture.lights(light=light, dtype=dtype).to(device=where)
    view = torch.tensor(capture.view, dtype=dtype, device=where)
    quadrature = Quadrature(path=path)
    found = residual_term_of(maps, svbrdf_dir, where) if term else None
    positions = fit_positions(capture, maps.meta)[0]
    near = None if positions is None else positions.to(where, dtype)
    seen = bounce = None
    height = maps.extra.get("height") if shadows else None
    if height is not None:  # cast shadows: the visibility over the fit's height, as the fit saw it
        share = maps.extra.get("indirect")  # the light the lit surroundings reflect into the shadows
        share = None if share is None else share.to(where, dtype)
        softness = softness_of(maps)
        seen, bounce = shadow_terms(
            svbrdf.to(dtype), height.to(where, dtype), share, softness, lights, view, near, quadrature=quadrature
        )
    values = shaded_render(svbrdf.to(dtype), lights, view, near, seen=seen, bounce=bounce, term=found,
                           quadrature=quadrature, lobe=lobe, progress=progress)  # fmt: skip
    if found is not None:  # a smooth term can dip below black (a cast shadow); a frame holds no negative light
        values = values.clamp(min=0)
    predicted = values.permute(2, 3, 0, 1).cpu().contiguous()  # (K, C, H, W), on the CPU: written and scored
    if output_dir is not None:
        write_capture(Path(output_dir), capture, predicted.float(), overwrite=overwrite)
    # As recorded: sensor noise may dip below 0; NaN or Inf pixels (warned about) are left out of the scores.
    observed = capture.read_frames(dtype=torch.float64, nonfinite="keep")
    finite = observed.isfinite()
    observed = torch.where(finite, observed, torch.zeros_like(observed))
    scored = torch.where(finite, predicted, torch.zeros_like(predicted))
    per_frame = [psnr(scored[k], observed[k]) for k in range(scored.shape[0])]
    residual = (scored.double() - observed).pow(2).sum().sqrt() / observed.pow(2).sum().sqrt()
    return {
        "frames": predicted.shape[0],
        "psnr_db": psnr(scored, observed),
        "relative_rms": residual.item(),
        "per_frame_psnr_db": per_frame,
        "predicted": predicted,
    }
