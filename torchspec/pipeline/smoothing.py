"""Smoothing: the choice between a lobe and none, regularised over the image (``FitConfig.ladder.smooth``).

Each tile fits its lobed pixels without a lobe too (:func:`plain_alternative`, a
:class:`PlainFit`); over the whole image :func:`smooth_choice` picks each pixel's side and
:func:`smooth` gives the pixels that lose their lobe their fit without one.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ..errors import TorchspecError
from .checks import quality_of, solver_flags, with_flags
from .records import PlainFit  # re-exported: the records live in records
from .result import Fit
from .samples import TileSamples
from .selection import assess, plain_start
from .settings import FitConfig
from .solver import solve_pixels
from .start import StartingPoint

__all__ = ["SMOOTH_SWEEPS", "PlainFit", "plain_alternative", "smooth", "smooth_choice"]


def plain_alternative(
    start: StartingPoint,
    chosen: PlainFit,
    code: Tensor,
    sensor: Tensor,
    few: Tensor,
    data: TileSamples,
    config: FitConfig,
    tried: dict[str, int],
) -> PlainFit:
    """A tile's fits without a lobe: ``chosen`` (the tile's outputs) where the chosen model
    ``code (n,)`` is ``diffuse``, a fit of the ``diffuse`` model elsewhere (counted in ``tried``)."""
    criterion = torch.where(code == 0, chosen.criterion, torch.full_like(chosen.criterion, math.inf))
    plain = replace(chosen, criterion=criterion)
    index = (code > 0).nonzero()[:, 0]
    if not index.numel():
        return plain
    start_plain = plain_start(start, data.channels)[index]
    fit = assess(solve_pixels("diffuse", index, start_plain, data, config), data, sensor, config)
    tried["diffuse"] = tried.get("diffuse", 0) + index.numel()
    few_at, result = few[index], fit.result
    alone = with_flags(
        solver_flags(result.status, few_at),
        ("undetermined", ~fit.std["normal"].isfinite() & ~few_at),
        ("misfit", fit.unexplained),
    )
    for key, value in (
        ("normal", fit.svbrdf.normal),
        ("diffuse", fit.svbrdf.diffuse),
        ("criterion", fit.criterion),
        ("status", result.status),
        ("iterations", result.iterations),
        ("residual", torch.nan_to_num(data.relative_rms(result.cost, index), nan=math.inf)),
        ("quality", quality_of(start.diffuse.quality[index], result.status, alone)),
        ("flags", alone),
        ("std_normal", fit.std["normal"]),
        ("std_diffuse", fit.std["diffuse"]),
    ):
        getattr(plain, key)[index] = value
    return plain


SMOOTH_SWEEPS = 50
"""The most sweeps of :func:`smooth_choice` (each lowers the total; it stops at the first that changes nothing)."""


def smooth_choice(lobed: Tensor, plain: Tensor, weight: float, sweeps: int = SMOOTH_SWEEPS) -> Tensor:
    """Per pixel of an image, a lobe or none: ``(H, W)`` bool, from the criterion of each pixel's
    fit with a lobe ``lobed (H, W)`` and without ``plain (H, W)`` (``inf`` where there is none), a
    local minimum of

        E = sum_p criterion(p) + weight * (pairs of 4-neighbours on different sides)

    by iterated conditional modes: from each pixel's own choice, each pixel takes the side that
    lowers ``E`` given its neighbours, the two colours of a checkerboard in turn (a pixel's
    neighbours are all of the other colour, so each update lowers ``E`` and the sweeps end). A tie
    keeps the pixel's side; a pixel with one of the two fits only keeps it.

    Raises:
        ValueError: ``lobed`` and ``plain`` are not ``(H, W)`` alike.

    Example:
        >>> inf = float("inf")
        >>> lobed = torch.tensor([[1.0, 1.0, 1.0], [1.0, 0.0, 1.0], [inf, 1.0, 1.0]])
        >>> plain = torch.tensor([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
        >>> smooth_choice(lobed, plain, 0.0).int().tolist()
        [[0, 0, 0], [0, 1, 0], [0, 0, 0]]
        >>> smooth_choice(lobed, plain, 1.0).any().item()  # four neighbours outweigh its gain of 1
        False
    """
    if lobed.shape != plain.shape or lobed.dim() != 2:
        raise TorchspecError(
            f"smooth_choice: lobed and plain must be (H, W) alike; got {tuple(lobed.shape)} and {tuple(plain.shape)}."
        )
    choice = lobed < plain
    h, w = choice.shape

    def neighbours(x: Tensor) -> Tensor:  # the sum over each pixel's 4-neighbours (0 beyond the border)
        padded = torch.nn.functional.pad(x[None, None], (1, 1, 1, 1))[0, 0]
        return padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]

    count = neighbours(torch.ones_like(lobed))
    rows = torch.arange(h, device=lobed.device)[:, None]
    colour = (rows + torch.arange(w, device=lobed.device)[None, :]) % 2
    for _ in range(sweeps):
        before = choice
        for turn in (0, 1):
            with_lobe = neighbours(choice.to(lobed.dtype))
            e_lobed = lobed + weight * (count - with_lobe)
            e_plain = plain + weight * with_lobe
            side = torch.where(e_lobed < e_plain, True, torch.where(e_plain < e_lobed, False, choice))
            choice = torch.where(colour == turn, side, choice)
        if torch.equal(choice, before):
            break
    return choice


def smooth(joined: Fit, plain: PlainFit, weight: float) -> tuple[Fit, int]:
    """:func:`smooth_choice` on an image's fit: the pixels it leaves without a lobe take their fit
    without one (``plain``) in every output (maps, criterion, deviations, flags, checks, ...).
    Returns the fit and how many pixels changed side."""
    model, criterion = joined.model, joined.criterion
    lobed = torch.where(model > 0, criterion, torch.full_like(criterion, math.inf))
    choice = smooth_choice(lobed, plain.criterion, weight)
    drop = (model > 0) & ~choice  # the pixels that lose their lobe; the others keep the fit they have
    if not bool(drop.any()):
        return joined, 0
    svbrdf = joined.svbrdf
    zero = {
        name: torch.where(drop[..., None] if value.dim() == 3 else drop, torch.zeros_like(value), value)
        for name in ("specular", "roughness", "rotation", "specular2", "roughness2")
        if (value := getattr(svbrdf, name)) is not None
    }
    svbrdf = replace(
        svbrdf,
        normal=torch.where(drop[..., None], plain.normal, svbrdf.normal),
        diffuse=torch.where(drop[..., None], plain.diffuse, svbrdf.diffuse),
        **zero,
    )
    swapped = {
        key: torch.where(drop, getattr(plain, key), getattr(joined, key))
        for key in ("criterion", "status", "iterations", "residual", "quality", "flags")
    }
    checks = {key: torch.where(drop, torch.full_like(value, math.nan), value) for key, value in joined.checks.items()}
    std = dict(joined.std)
    std["normal"] = torch.where(drop, plain.std_normal, std["normal"])
    std["diffuse"] = torch.where(drop[..., None], plain.std_diffuse, std["diffuse"])
    for key in std:
        if key not in ("normal", "diffuse"):  # the lobe's: none
            std[key] = torch.where(drop[..., None], torch.full_like(std[key], math.nan), std[key])
    smoothed = replace(
        joined,
        svbrdf=svbrdf,
        model=torch.where(drop, torch.zeros_like(model), model),
        lobe=joined.lobe & ~drop,
        std=std,
        checks=checks,
        **swapped,
    )
    return smoothed, int(drop.sum())
