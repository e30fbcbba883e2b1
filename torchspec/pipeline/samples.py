"""A tile's samples prepared once for the solver, the criterion and the checks
(:class:`TileSamples`), and each sample's noise under the sensor's model (:meth:`TileSamples.inverse_noise`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..model.lights import Lights

__all__ = ["TileSamples"]


@dataclass(frozen=True)
class TileSamples:
    """The recorded values of ``n`` pixels over ``K`` frames and ``C`` channels, as the solver and
    the criterion take them.

    Attributes:
        observed: ``(n, K, C)`` the recorded values, 0 at invalid samples.
        valid: ``(n, K)`` bool, the samples used.
        weight: ``(n, K)`` the solver's weight: ``valid`` over the pixel's level.
        level: ``(n,)`` the pixel's mean value (divided by exposure and irradiance), 1 where not positive.
        count: ``(n,)`` valid samples per pixel, at least 1 (the values' dtype).
        samples: ``(n,)`` valid samples times channels (the values' dtype).
        scale: ``(1, K, C or 1)`` exposure times irradiance.
        lights, view: the frames' lights and the view ``(3,)``.
        channels: the channel names (``C``).
        visibility: ``(n, K)`` the lights' fixed visibility (cast shadows,
            :mod:`~torchspec.pipeline.shadows`), or ``None`` (every light seen). With it,
            ``observed`` holds the recorded values over the visibility, ``y / V``: the residual
            ``w (V r - y)`` of the model's prediction ``r`` is ``(w V) (r - y / V)``, so the solver
            fits the model without shadows to ``y / V`` with the weight ``w V``.
    """

    observed: Tensor
    valid: Tensor
    weight: Tensor
    level: Tensor
    count: Tensor
    samples: Tensor
    scale: Tensor
    lights: Lights
    view: Tensor
    channels: tuple[str, ...]
    visibility: Tensor | None = None

    @staticmethod
    def of(
        y: Tensor,
        valid: Tensor,
        level: Tensor,
        lights: Lights,
        view: Tensor,
        channels: tuple[str, ...],
        visibility: Tensor | None = None,
    ) -> TileSamples:
        """Prepare ``y (n, K, C)`` with ``valid (n, K)`` and the pixels' mean value ``level (n,)``;
        with ``visibility (n, K)``, ``y`` is already ``y / V`` (the class's docstring) and the
        weight is multiplied by ``V``."""
        safe_level = torch.where(level > 0, level, torch.ones_like(level))
        weight = valid.to(y.dtype) / safe_level[:, None]
        return TileSamples(
            observed=torch.where(valid[..., None], y, torch.zeros_like(y)),
            valid=valid,
            weight=weight if visibility is None else weight * visibility,
            level=safe_level,
            count=valid.sum(-1).clamp(min=1).to(y.dtype),
            samples=valid.sum(-1).to(y.dtype) * y.shape[-1],
            scale=lights.scale.to(y.dtype)[None],
            lights=lights,
            view=view,
            channels=channels,
            visibility=visibility,
        )

    def relative_rms(self, cost: Tensor, index: Tensor | slice = slice(None)) -> Tensor:
        """A fit's RMS residual relative to each pixel's level, from its solver's cost
        ``0.5 sum (r / level)^2`` over the valid samples of pixels ``index`` (NaN where a fit failed)."""
        return (2.0 * cost / (self.count[index] * len(self.channels))).sqrt()

    def inverse_noise(self, sensor: Tensor, index: Tensor, floor: float) -> Tensor:
        """One over the noise of each sample of pixels ``index (m,)``, ``(m, K, C)`` (0 for invalid
        samples): the sensor's standard deviation ``sqrt(a y + b)`` (``sensor = (a, b)``), floored at
        ``floor`` times the pixel's level (the model's own error: the quadrature, a lobe's shape).
        With a visibility ``V``, of the recorded ``y = V observed``, times ``V``: the noise of
        ``observed`` is the recorded value's over ``V``."""
        observed = self.observed[index]
        seen = None if self.visibility is None else self.visibility[index, :, None]
        recorded = observed if seen is None else observed * seen
        variance = sensor[0] * recorded.clamp(min=0.0) + sensor[1]
        smallest = floor * self.level[index, None, None] * self.scale
        sigma = torch.maximum(variance.sqrt(), smallest).clamp(min=torch.finfo(self.observed.dtype).tiny)
        inverse = self.valid[index, :, None].to(self.observed.dtype) / sigma
        return inverse if seen is None else inverse * seen
