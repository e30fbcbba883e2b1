"""The solver stage: batched Levenberg-Marquardt (:func:`torchspec.lm.solve`) of one model's
parameters on a set of pixels, from a starting point (:func:`solve_pixels`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace

from torch import Tensor

from ..lm import Bounds, LMResult, bounded, solve
from ..model.brdf import SVBRDF
from ..model.registry import get_model
from .samples import TileSamples
from .settings import FitConfig

__all__ = ["Solved", "solve_pixels", "compiled_or_eager"]

_COMPILE_FAILED = []  # a compilation that failed once in this process is not tried again


def compiled_or_eager(run: Callable, compile: bool):
    """``run(True)`` (with ``torch.compile``) when ``compile`` and no compilation has failed in
    this process, else ``run(False)``; a failed compilation warns and runs ``run(False)``."""
    if compile and not _COMPILE_FAILED:
        try:
            return run(True)
        except Exception as error:  # no C++ compiler, an unsupported device, ...: the same work without
            _COMPILE_FAILED.append(error)
            warnings.warn(f"torch.compile failed ({type(error).__name__}: {error}); fitting without it.", stacklevel=3)
    return run(False)


@dataclass(frozen=True)
class Solved:
    """One model's solution on pixels ``index`` of a tile.

    Attributes:
        name: the model (:data:`torchspec.model.registry.MODELS`).
        index: ``(m,)`` the tile's pixels fitted.
        svbrdf: ``(m,)`` the fitted maps.
        result: the solver's :class:`torchspec.lm.LMResult` (status, iterations, cost).
    """

    name: str
    index: Tensor
    svbrdf: SVBRDF
    result: LMResult


def solve_pixels(name: str, index: Tensor, start: SVBRDF, data: TileSamples, config: FitConfig) -> Solved:
    """Fit model ``name`` to pixels ``index (m,)`` of ``data`` from ``start (m,)``, minimising the
    residual weighted by ``data.weight`` (``config.lm`` and ``config.rule``)."""
    model = get_model(name)
    channels = data.channels
    least = config.least_roughness(data.lights)
    bounds = model.bounds(len(channels), least)
    rule = config.rule
    params = bounds.to_free(inside(model.pack(start), bounds))
    observed, weight = data.observed[index], data.weight[index]

    def run(compile: bool):
        fn = model.residuals(
            observed, weight, data.lights, data.view, channels, quadrature=replace(rule, compile=compile), normal=True
        )
        return solve(bounded(fn, bounds), params, config=config.lm)

    result = compiled_or_eager(run, config.quadrature.compile)
    return Solved(name, index, model.unpack(bounds.from_free(result.params)[0], channels, order=True), result)


def inside(params: Tensor, bounds: Bounds) -> Tensor:
    """``params (m, P)`` with each interval parameter (a roughness) moved to at least 1.5 times its
    low end: a start on the bound would move away only slowly (:class:`torchspec.lm.Bounds`)."""
    out = params.clone()
    for j, kind in enumerate(bounds.kinds):
        if isinstance(kind, tuple) and kind[1] > 0:
            out[:, j] = out[:, j].clamp(min=min(1.5 * kind[1], 0.5 * (kind[1] + kind[2])))
    return out
