"""The prediction stage: how well a fit predicts the frames it was not fitted to.

``auto`` chooses each pixel's model by what it predicts, not by how well it fits the frames it saw
(a larger model always fits those better: it also fits the model's error, a lobe of another
shape, shadows, errors of the lights). The frames are split into folds (:func:`light_folds`): the
frames of each fold are left out, the model refitted on the others, and the left-out frames
predicted (:func:`held_out`). The refit is one Gauss-Newton step from the solution on all frames
(the solver's objective without the fold's samples, from where its gradient on all samples
vanishes): exact for a model linear in its parameters, and for the small changes a fold makes
(approximate leave-group-out cross-validation); a parameter the other folds do not determine (a
lobe whose peak only the left-out frames saw) takes a large step, and its prediction fails as a
refit's would. Cost: one evaluation of the model's Jacobian per fitted model and pixel.

A larger model is kept only where it predicts the left-out samples better than the model chosen
so far by more than the noise would make it (:func:`torchspec.statistics.predicts_better`,
re-exported here).
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from ..lm import bounded
from ..model.brdf import SVBRDF
from ..model.lobes import WARD
from ..model.registry import Model, get_model
from ..model.rendering import render
from ..statistics import predicts_better  # re-exported: the rule lives with the statistics
from .samples import TileSamples
from .settings import FitConfig
from .solver import compiled_or_eager

__all__ = [
    "CHUNK_SAMPLES",
    "DAMPING",
    "light_folds",
    "held_out",
    "held_out_refit",
    "predicts_better",
    "second_lobe_held_out",
]

CHUNK_SAMPLES = 1 << 24
"""Pixels are taken in chunks of at most this many Jacobian entries (pixels x samples x parameters)."""
DAMPING = 1e-4
"""The refit's damping, relative to ``diag(J^T J)``: a parameter the other folds do not determine
takes a large but finite step."""


def light_folds(directions: Tensor, folds: int, regions: bool = True) -> Tensor:
    """Each frame's fold, per scheme: ``(S, K)`` long in ``[0, folds)``.

    The first scheme scatters the folds over the light domain (the frames ordered row by row in the
    l-plane, each row's folds in turn from a shift of the previous row's), so that each fold's
    frames have neighbours in the others; with ``regions``, the second leaves out whole regions of
    the domain: ``folds`` sectors of equal count about the lights' centre, by azimuth. Every fold
    holds at least half the mean count of frames.

    Args:
        directions: ``(K, 3)`` the frames' light directions.
        folds: the folds per scheme (at most ``K // 2``, at least 2: each of at least two frames).
    """
    k = directions.shape[0]
    device = directions.device
    plane = directions[:, :2].double().cpu()
    folds = max(2, min(folds, k // 2))
    # Row by row (y descending, then x), each row's folds shifted from the previous row's, so that
    # a light's neighbours along its row and across rows fall in other folds.
    rows = torch.round(plane[:, 1] / max(float(_spacing(plane)), 1e-9)).long()
    order = sorted(range(k), key=lambda i: (-int(rows[i]), float(plane[i, 0])))
    shift = 1 if folds <= 3 else 2
    scattered = torch.empty(k, dtype=torch.long)  # on the CPU, as plane: filled frame by frame, moved at the end
    row, rank, at = None, 0, -1
    for i in order:
        if int(rows[i]) != row:
            row, rank, at = int(rows[i]), 0, at + 1
        scattered[i] = (rank + shift * at) % folds
        rank += 1
    if bool((torch.bincount(scattered, minlength=folds) < 0.5 * k / folds).any()):  # short rows
        scattered[torch.tensor(order)] = torch.arange(k) % folds  # on the CPU, as scattered
    schemes = [scattered]
    if regions:
        centred = plane - plane.mean(0)
        azimuth = torch.atan2(centred[:, 1], centred[:, 0])
        sector = torch.empty(k, dtype=torch.long)  # on the CPU, as plane: moved with the schemes at the end
        sector[torch.argsort(azimuth)] = (torch.arange(k) * folds) // k  # on the CPU, as sector
        schemes.append(sector)
    return torch.stack(schemes).to(device)


def _spacing(plane: Tensor) -> Tensor:
    """The median distance from a light to its nearest neighbour in the l-plane."""
    if plane.shape[0] < 2:
        return plane.new_tensor(1.0)
    distance = torch.cdist(plane, plane)
    distance.fill_diagonal_(math.inf)
    return distance.min(-1).values.median()


def held_out(
    model: Model,
    svbrdf: SVBRDF,
    index: Tensor,
    data: TileSamples,
    inverse_noise: Tensor,
    folds: Tensor,
    config: FitConfig,
) -> Tensor:
    """The residuals of each sample predicted with its fold left out, in units of its noise:
    ``(m, S, K, C)`` (0 for invalid samples).

    Args:
        model: the fitted model; svbrdf: its solution on pixels ``index (m,)`` of ``data``.
        inverse_noise: ``(m, K, C)`` one over each sample's noise
            (:meth:`~torchspec.pipeline.samples.TileSamples.inverse_noise`).
        folds: ``(S, K)`` each frame's fold per scheme (:func:`light_folds`).
        config: the fit's settings (the quadrature).
    """
    m, k, c = index.shape[0], data.observed.shape[1], data.observed.shape[2]
    schemes = folds.shape[0]
    out = data.observed.new_zeros((m, schemes, k, c))
    if m == 0:
        return out
    bounds = model.bounds(c, config.least_roughness(data.lights))
    p = model.size(c)
    chunk = max(1, CHUNK_SAMPLES // (k * c * p))
    member = _members(folds, data.observed.dtype)
    for start in range(0, m, chunk):
        rows = slice(start, start + chunk)
        at = index[rows]
        r, jac = _linearised(model, bounds, svbrdf[rows], at, data, config)
        predicted = _fold_refits(r, jac[:, None], member)[:, 0]
        # r = (render - observed) / level on valid samples: to noise units.
        scale = data.level[at, None, None, None] * inverse_noise[rows, None]
        out[rows] = predicted * scale
    return out


def held_out_refit(
    model: Model,
    svbrdf: SVBRDF,
    index: Tensor,
    data: TileSamples,
    inverse_noise: Tensor,
    folds: Tensor,
    config: FitConfig,
) -> Tensor:
    """:func:`held_out`'s residuals ``(m, S, K, C)`` from refits by the solver: each fold's frames
    left out, ``config.ladder.refit`` Levenberg-Marquardt steps from the solution on all frames, all folds
    of all pixels in one batch (``S x folds`` times the pixels), then the left-out frames rendered."""
    from .solver import solve_pixels  # the solver stage imports this one's settings

    m, k, c = index.shape[0], data.observed.shape[1], data.observed.shape[2]
    schemes, count = folds.shape[0], int(folds.max()) + 1
    out = data.observed.new_zeros((m, schemes, k, c))
    if m == 0:
        return out
    copies = schemes * count
    keep = (folds[:, None, :] != torch.arange(count, device=folds.device)[None, :, None]).reshape(copies, 1, k)
    at = index.repeat(copies)
    weight = (data.weight[index][None] * keep.to(data.weight.dtype)).reshape(copies * m, k)
    rows = torch.arange(copies * m, device=index.device)
    folded = replace(
        data,
        observed=data.observed[at],
        valid=data.valid[at],
        weight=weight,
        level=data.level[at],
        count=data.count[at],
        samples=data.samples[at],
        visibility=None if data.visibility is None else data.visibility[at],
    )
    start = svbrdf[torch.arange(m, device=index.device).repeat(copies)]
    settings = replace(config, lm=replace(config.lm, max_iterations=config.ladder.refit))
    solved = solve_pixels(model.name, rows, start, folded, settings)
    rule = replace(config.rule, compile=False)
    predicted = render(solved.svbrdf, data.lights, data.view, quadrature=rule, lobe=model.lobe or WARD)
    residual = ((predicted - folded.observed) * inverse_noise.repeat(copies, 1, 1)).reshape(schemes, count, m, k, c)
    # Each frame takes its own fold's refit.
    pick = folds[:, None, None, :, None].expand(schemes, 1, m, k, c)
    return residual.gather(1, pick)[:, 0].permute(1, 0, 2, 3)


def second_lobe_held_out(
    svbrdf: SVBRDF,
    index: Tensor,
    data: TileSamples,
    inverse_noise: Tensor,
    folds: Tensor,
    config: FitConfig,
    roughness: Tensor,
) -> Tensor:
    """:func:`held_out`'s residuals of one lobe plus a second, grey lobe of roughness
    ``roughness (G,)`` on the same normal, linearised at height 0: ``(m, G, S, K, C)``.

    The model is ``ward-iso`` at ``svbrdf`` (its roughness averaged over the axes), where the
    Jacobian is taken, and the column of the second lobe's ``k_s2``: the rendered lobe of height 1,
    exact (the rendering is linear in ``k_s2``; its roughness moves nothing at height 0, so it is
    held at each value of ``roughness``). Each fold's refit is one Gauss-Newton step of all these
    parameters on the frames of the other folds, as in :func:`held_out`, without the bound
    ``k_s2 >= 0``. What ``ward-dual`` could predict, to first order in its second lobe, at the cost
    of one Jacobian and ``G`` renders per pixel instead of a fit (``auto`` tries ``ward-dual``
    only where this predicts better: ``FitConfig.ladder.dual_gate``).
    """
    model = get_model("ward-iso")
    m, k, c = index.shape[0], data.observed.shape[1], data.observed.shape[2]
    g, schemes = roughness.shape[0], folds.shape[0]
    out = data.observed.new_zeros((m, g, schemes, k, c))
    if m == 0:
        return out
    bounds = model.bounds(c, config.least_roughness(data.lights))
    p = model.size(c) + 1
    chunk = max(1, CHUNK_SAMPLES // (k * c * p * g))
    member = _members(folds, data.observed.dtype)
    for start in range(0, m, chunk):
        rows = slice(start, start + chunk)
        at = index[rows]
        maps = svbrdf[rows]
        r, jac = _linearised(model, bounds, maps, at, data, config)
        n = r.shape[0]
        # The second lobe's column per roughness: its rendering at height 1, weighted as r.
        alpha = roughness.to(r)[None, :, None].expand(n, g, 2)
        unit = SVBRDF(
            maps.normal[:, None].expand(n, g, 3),
            maps.diffuse.new_zeros((n, g, c)),
            maps.diffuse.new_ones((n, g, 1)),
            alpha,
            None,
            data.channels,
        )
        lobe = render(unit, data.lights, data.view, quadrature=replace(config.rule, compile=False))  # (n, G, K, C)
        column = lobe * data.weight[at][:, None, :, None]
        full = torch.cat([jac[:, None].expand(n, g, k, c, p - 1), column[..., None]], -1)  # (n, G, K, C, P)
        scale = data.level[at, None, None, None, None] * inverse_noise[rows, None, None]
        out[rows] = _fold_refits(r, full, member) * scale
    return out


def _linearised(model: Model, bounds, maps: SVBRDF, at: Tensor, data: TileSamples, config: FitConfig):
    """``model``'s residuals ``(n, K, C)`` and Jacobian ``(n, K, C, P)`` in the solver's free
    parameters (``bounds``) at ``maps``, the pixels ``at (n,)`` of ``data``."""
    free = bounds.to_free(model.pack(maps))
    weight = data.weight[at]

    def run(fused: bool):
        quadrature = replace(config.rule, compile=fused)
        fn = model.residuals(data.observed[at], weight, data.lights, data.view, data.channels, quadrature=quadrature)
        return bounded(fn, bounds)(free, torch.arange(free.shape[0], device=free.device))

    r, jac = compiled_or_eager(run, config.quadrature.compile)
    n, k, c = at.shape[0], data.observed.shape[1], data.observed.shape[2]
    return r.view(n, k, c), jac.view(n, k, c, -1)


def _members(folds: Tensor, dtype) -> Tensor:
    """``(S, F, K)``: 1 where frame ``k`` is in fold ``f`` of scheme ``s`` (``folds (S, K)``)."""
    count = int(folds.max()) + 1
    return (folds[:, None, :] == torch.arange(count, device=folds.device)[None, :, None]).to(dtype)


def _fold_refits(r: Tensor, jac: Tensor, member: Tensor) -> Tensor:
    """Each sample's residual after one damped Gauss-Newton step on the frames of the other folds:
    ``(n, G, S, K, C)`` from ``r (n, K, C)``, ``G`` alternative Jacobians ``jac (n, G, K, C, P)``
    and ``member (S, F, K)`` (frame ``k`` is in fold ``f`` of scheme ``s``: each frame in one fold
    per scheme)."""
    n, g, k, c, p = jac.shape
    schemes, count = member.shape[:2]
    flat = jac.reshape(n * g, k, c, p)
    rows = r[:, None].expand(n, g, k, c).reshape(n * g, k, c)
    # Per fold: its J^T J and J^T r, one batched product over its frames and channels; then the
    # normal equations without it (the scheme's folds hold every frame once).
    fold_jj = jac.new_zeros((n * g, schemes, count, p, p))
    fold_jr = jac.new_zeros((n * g, schemes, count, p))
    for s in range(schemes):
        for f in range(count):
            frames = member[s, f].nonzero()[:, 0]
            part = flat[:, frames].reshape(n * g, -1, p)
            fold_jj[:, s, f] = part.transpose(1, 2) @ part
            fold_jr[:, s, f] = (part.transpose(1, 2) @ rows[:, frames].reshape(n * g, -1, 1))[..., 0]
    rest_jj = (fold_jj.sum(2, keepdim=True) - fold_jj).view(n, g, schemes, count, p, p)
    rest_jr = (fold_jr.sum(2, keepdim=True) - fold_jr).view(n, g, schemes, count, p)
    step = _damped_solve(rest_jj, -rest_jr)  # (n, G, S, F, P)
    # Each frame takes its own fold's step: predicted residual r + J step.
    per_frame = torch.einsum("sfk,ngsfp->ngskp", member, step)
    return r[:, None, None] + (jac[:, :, None] * per_frame[..., None, :]).sum(-1)


def _damped_solve(matrix: Tensor, rhs: Tensor) -> Tensor:
    """``(matrix + DAMPING diag(matrix)) x = rhs``, batched; 0 where singular even so."""
    diagonal = matrix.diagonal(dim1=-2, dim2=-1)
    damping = DAMPING * diagonal + torch.finfo(matrix.dtype).eps * diagonal.amax(-1, keepdim=True)
    damped = matrix + torch.diag_embed(damping.clamp(min=torch.finfo(matrix.dtype).tiny))
    solution, info = torch.linalg.solve_ex(damped, rhs)
    ok = (info == 0)[..., None] & solution.isfinite().all(-1, keepdim=True)
    return torch.where(ok, solution, torch.zeros_like(solution))
