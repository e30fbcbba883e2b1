"""The statistics that judge one prediction against another: :func:`predicts_better`, the rule by
which the fit keeps a larger model (:mod:`torchspec.pipeline.selection`) and a pixel keeps its
residual term (:mod:`torchspec.model.residual_term`). It knows nothing of models or lights, only of
residuals in noise units, so that both can use it without importing each other.
"""

from __future__ import annotations

from torch import Tensor

__all__ = ["predicts_better"]


def predicts_better(candidate: Tensor, current: Tensor, z: float) -> Tensor:
    """``(m,)`` bool: ``candidate``'s left-out residuals ``(m, S, K, C)`` predict better than
    ``current``'s by more than the noise would make them.

    With ``d = e_current^2 - e_candidate^2`` per sample, in noise units, the candidate's
    improvement ``sum d`` must exceed ``z`` standard deviations of what noise alone would give it:
    two models whose predictions differ by ``delta`` on a sample differ in ``d`` by ``2 e delta``,
    of variance ``4 delta^2`` (``e`` of unit variance), so the bound is ``2 z sqrt(sum delta^2)``.
    Averaged over the schemes; in every scheme the candidate must predict better.
    """
    gain = (current.square() - candidate.square()).sum((2, 3))  # (m, S)
    spread = 2.0 * (current - candidate).square().sum((2, 3)).sqrt()
    return (gain.mean(1) > z * spread.mean(1)) & (gain > 0).all(1)
