"""The sandwich terms of a fit's covariance for any model, its lobe without closed forms included:
:func:`torchspec.model.least_squares.sandwich_terms`' outputs from the forward-mode Jacobian of the
model's own parameters (:meth:`torchspec.model.registry.Model.forward_jacobian`), in chunks of pixels.

Ward's models have their own fused pass (:func:`~torchspec.model.least_squares.sandwich_terms`, without
the Jacobian in memory); this one renders the values, their ``P`` directional derivatives and the
diffuse part per chunk, so a registered model's fit is assessed (its deviations, the peak checks)
as the built-in ones are. For a Ward model both agree within rounding (``tests/test_model_registry.py``).
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from ..errors import TorchspecError
from .brdf import SVBRDF
from .jacobian import pixels_per_chunk
from .least_squares import jacobian_sandwich_terms
from .lights import Lights
from .lobes import WARD
from .quadrature import Quadrature
from .registry import Model
from .rendering import render

__all__ = ["forward_sandwich_terms"]


def forward_sandwich_terms(
    model: Model,
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    observed: Tensor,
    noise_weight: Tensor,
    fit_weight: Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
    samples: bool = False,
) -> tuple[Tensor, ...]:
    """:func:`torchspec.model.least_squares.sandwich_terms` of ``model``'s fit ``svbrdf`` (``N`` pixels,
    flat), in ``model``'s parameters, from its forward-mode Jacobian: the same outputs
    ``(0.5 chi^2 (N,), A (N, P, P), B (N, P, P))`` and with ``samples`` ``z2 (N, K)``,
    ``excess (N, K)``, ``lobe_snr (N,)`` (the diffuse part being the rendering without the lobes).

    Args:
        model: the fitted model (any lobe); observed, noise_weight, fit_weight: ``(N, K, C)``.
        quadrature: the model's (:class:`torchspec.model.quadrature.Quadrature`), taken without
            ``torch.compile`` (forward-mode AD through the eager renderer).

    Raises:
        TorchspecError: an array of another shape than ``(N, K, C)``.
    """
    n, c = svbrdf.diffuse.shape
    k = lights.directions.shape[0]
    for name, value in (("observed", observed), ("noise_weight", noise_weight), ("fit_weight", fit_weight)):
        if tuple(value.shape) != (n, k, c):
            raise TorchspecError(f"{name} must have shape {(n, k, c)}; got {tuple(value.shape)}.")
    quadrature = replace(quadrature, compile=False)
    params = model.pack(svbrdf)
    plain = replace(
        svbrdf,
        specular=torch.zeros_like(svbrdf.specular),
        specular2=None if svbrdf.specular2 is None else torch.zeros_like(svbrdf.specular2),
    )
    chunk = max(1, pixels_per_chunk(k, quadrature) // max(1, params.shape[-1]))
    out = []
    for start in range(0, max(n, 1), chunk):
        rows = slice(start, start + chunk)
        value, jac = model.forward_jacobian(params[rows], lights, view, svbrdf.channels, quadrature)
        diffuse = render(plain[rows], lights, view, quadrature=quadrature, lobe=model.lobe or WARD)
        out.append(
            jacobian_sandwich_terms(
                value, jac, diffuse, observed[rows], noise_weight[rows], fit_weight[rows], samples=samples
            )
        )
    return tuple(torch.cat(column) for column in zip(*out, strict=True))
