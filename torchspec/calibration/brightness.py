"""Frames much darker or brighter than their neighbours in light direction (``torchspec info``): a
flash that fired weakly, a lamp that dimmed, a frame taken at another exposure than recorded.

Each frame is compared with its :data:`NEIGHBOURS` nearest frames in light direction, nearest
along its ring of the dome first (:func:`ring_neighbours`: a difference in elevation counts
:data:`ELEVATION_WEIGHT` times one along the ring, since brightness changes faster with elevation
than with azimuth), pixel by pixel on a regular grid of about :data:`SAMPLES` pixels: the pixel's
value over the frame's exposure times irradiance, over the cosine of the light's polar angle (a
Lambertian surface's falloff), against the median of the neighbours' (:func:`brightness_ratios`).
A frame's ratio is the median of its pixels' ratios; it is flagged (:func:`departures`) when the
ratio is below :data:`DARKER` with three quarters of its pixels darker than their neighbours'
median, or above :data:`BRIGHTER` with three quarters brighter (the whole frame, not a shadow or
a highlight on part of it), and its neighbours agree with each other (:data:`AGREE`: not the
frames about a mirror's highlight).

Frames within :data:`MIN_ELEVATION_DEG` of the horizon are neither judged nor neighbours: there
cast shadows rule and a degree of elevation changes a frame's brightness several times over
(realrti-item7's frames at 0 to 8 degrees differ tenfold from one to the next).

On the shared data the frames judged lie within 0.87 .. 1.17 of their neighbours (realrti-item9, a
coin), 0.99 .. 1.01 (painting-dev, painting-dev-relight, synthrti-object1-m1); realrti-item7's
frame 31, visibly dark, is 0.50 (its neighbours agree within 1.00) and flagged, the others
0.92 .. 1.09; realrti-item3 falls steeply with azimuth: frames 36 and 37 are 0.65 and 0.57, but
among neighbours that disagree by 1.6 and 1.7, and are not. A mirror's frames about its highlight
(mirror-dev-1d-point) range over 0.02 .. 105 among neighbours that disagree up to 65000-fold; a
chrome sphere's photographs are not judged (:data:`MIN_SHARE`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "AGREE",
    "BRIGHTER",
    "DARKER",
    "ELEVATION_WEIGHT",
    "MIN_ELEVATION_DEG",
    "MIN_SHARE",
    "NEIGHBOURS",
    "SAMPLES",
    "brightness_ratios",
    "departures",
    "ring_neighbours",
    "sample_grid",
]

DARKER = 2 / 3
"""A frame is flagged as dark below this ratio to its neighbours (a third darker)."""
BRIGHTER = 2.5
"""... and as bright above this one: a glossy surface's highlight makes a whole frame brighter than
its neighbours (1.45 times at the zenith in ``tests/test_brightness.py``, 1.5 on realrti-item3),
where nothing but the light makes one darker."""
MIN_ELEVATION_DEG = 10.0
"""Frames whose light is lower above the horizon are not judged, nor neighbours."""
NEIGHBOURS = 4
"""Frames a frame is compared with."""
ELEVATION_WEIGHT = 3.0
"""A degree of elevation counts as this many degrees along the ring (:func:`ring_neighbours`)."""
AGREE = 1.25
"""A frame is judged only among neighbours that agree: all but the one farthest from their median
within this factor of each other (a mirror's frames about its highlight differ a hundredfold from
one to the next, a dome's neighbours a few percent: a median of 1.03 on realrti-item7, 1.04 on
realrti-item9)."""
SAMPLES = 4096
"""About this many pixels of each frame are compared (a regular grid)."""
MIN_SHARE = 0.5
"""A frame is judged only on at least this share of its pixels (those its neighbours light, and
not saturated): a chrome sphere's photographs, black but for a highlight, are not judged."""
_DIM_PIXEL = 0.05
"""Pixels whose neighbours' median is below this share of the frame's brightest are left out
(their ratio is the sensor's noise)."""


def sample_grid(height: int, width: int, samples: int = SAMPLES) -> tuple[slice, slice]:
    """The rows and columns of a regular grid of about ``samples`` pixels of a ``height x width``
    frame (every pixel of a small one)."""
    step = max(1, int(math.sqrt(height * width / max(samples, 1))))
    return slice(step // 2, height, step), slice(step // 2, width, step)


def ring_neighbours(directions: Tensor, count: int = NEIGHBOURS, min_elevation_deg: float = MIN_ELEVATION_DEG):
    """Each frame's ``count`` nearest frames in light direction, ``(K, count)`` indices, and which
    frames are judged, ``(K,)`` bool (at least :data:`MIN_ELEVATION_DEG` above the horizon, and
    ``count + 1`` such frames in all; a frame not judged has no neighbours: its row is ``-1``).

    The distance of two lights is ``sqrt((w d_el)^2 + (d_az cos(el))^2)``, ``d_el`` and ``d_az``
    their differences in elevation and azimuth, ``el`` their mean elevation, ``w``
    :data:`ELEVATION_WEIGHT`: the frames of the same ring of a dome come first."""
    directions = directions.double()
    elevation = torch.asin(directions[:, 2].clamp(-1, 1))
    azimuth = torch.atan2(directions[:, 1], directions[:, 0])
    judged = elevation >= math.radians(min_elevation_deg)
    if int(judged.sum()) <= count:
        judged = torch.zeros_like(judged)
    along = torch.remainder(azimuth[:, None] - azimuth[None] + math.pi, 2 * math.pi) - math.pi
    along = along * torch.cos((elevation[:, None] + elevation[None]) / 2)
    distance = torch.hypot(ELEVATION_WEIGHT * (elevation[:, None] - elevation[None]), along)
    distance = distance.masked_fill(~judged[None], math.inf).fill_diagonal_(math.inf)
    chosen = distance.argsort(1)[:, :count]
    return torch.where(judged[:, None], chosen, torch.full_like(chosen, -1)), judged


def brightness_ratios(values: Tensor, directions: Tensor, count: int = NEIGHBOURS) -> dict[str, Tensor]:
    """Each frame's brightness against its :func:`ring_neighbours`.

    Args:
        values: ``(K, P)`` the frames' sampled pixels over their exposure times irradiance (a
            channel mean); NaN where a pixel is not to be compared (saturated, NaN or Inf, unread).
        directions: ``(K, 3)`` the frames' light directions.

    Returns:
        ``ratio`` ``(K,)``: the median over the frame's pixels of its value over the cosine of its
        light's polar angle, against the median of its neighbours' so (NaN: not judged, or fewer
        than :data:`MIN_SHARE` of its pixels to compare: saturated, NaN, or dark in the neighbours);
        ``low``, ``high`` ``(K,)``: the lower and upper quartiles of those pixels' ratios;
        ``spread`` ``(K,)``: how far the neighbours agree: each one's median ratio to that median,
        the largest over the smallest of all but the one farthest from 1;
        ``neighbours`` ``(K, count)`` and ``judged`` ``(K,)`` of :func:`ring_neighbours`.
    """
    neighbours, judged = ring_neighbours(directions, count)
    cosine = directions[:, 2].double().clamp(min=math.sin(math.radians(MIN_ELEVATION_DEG)))
    shaded = values.double() / cosine.to(values.device)[:, None]
    nan = torch.full((len(values),), math.nan, dtype=torch.float64, device=values.device)
    out = {"ratio": nan.clone(), "low": nan.clone(), "high": nan.clone(), "spread": nan.clone()}
    quartiles = torch.tensor([0.25, 0.5, 0.75], dtype=torch.float64, device=values.device)
    for k in torch.nonzero(judged).flatten().tolist():
        reference = shaded[neighbours[k].to(values.device)].nanquantile(0.5, dim=0)  # of 4: the two middle ones' mean
        bright = reference[torch.isfinite(reference)]
        if bright.numel() == 0:
            continue
        kept = torch.isfinite(shaded[k]) & (reference > _DIM_PIXEL * bright.max()) & torch.isfinite(reference)
        if int(kept.sum()) >= MIN_SHARE * int(torch.isfinite(shaded[k]).sum()) and bool(kept.any()):
            low, middle, high = torch.quantile(shaded[k][kept] / reference[kept], quartiles).tolist()
            out["low"][k], out["ratio"][k], out["high"][k] = low, middle, high
            theirs = (shaded[neighbours[k].to(values.device)][:, kept] / reference[kept]).nanquantile(0.5, dim=1)
            closest = theirs[theirs.log().abs().argsort()[:-1]]  # all but the one farthest from the reference
            out["spread"][k] = float(closest.max() / closest.min())
    return {**out, "neighbours": neighbours, "judged": judged}


def departures(ratios: dict[str, Tensor]) -> list[int]:
    """The frames of :func:`brightness_ratios` that are darker than :data:`DARKER` (and three
    quarters of their pixels darker than their neighbours') or brighter than :data:`BRIGHTER`
    (three quarters brighter), among neighbours that agree (``spread`` below :data:`AGREE`)."""
    ratio, low, high = ratios["ratio"], ratios["low"], ratios["high"]
    dark = (ratio < DARKER) & (high < 1)
    bright = (ratio > BRIGHTER) & (low > 1)
    return torch.nonzero((dark | bright) & (ratios["spread"] < AGREE)).flatten().tolist()
