"""Specular lobes as objects the renderer takes (as PyTorch3D's renderer takes a shader): what
:func:`torchspec.model.rendering.render` integrates against each frame's light, per unit ``k_s``.

A lobe gives its value times the cosine at directions (:meth:`Lobe.cosine`, broadcasting like
:func:`torchspec.model.brdf.ward_cosine`); the renderer integrates it on the nodes of
:mod:`torchspec.model.nodes` (placed from the Ward lobe of the same roughness: its mirror point and
width) and a fit takes its Jacobian by forward-mode automatic differentiation
(:meth:`torchspec.model.registry.Model.residuals`), so a new lobe needs neither an integration rule nor
hand derivatives. Ward's lobe (:data:`WARD`) keeps its own fused node integration and closed-form
Jacobian (:mod:`torchspec.model.lobe`, :mod:`torchspec.model.jacobian`): it is :attr:`Lobe.analytic`.

Example:
    >>> as_lobe("ward") is WARD, as_lobe(BECKMANN).analytic
    (True, False)
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor

from ..errors import TorchspecError
from .brdf import beckmann_cosine, ward_cosine

__all__ = ["Lobe", "WardLobe", "BeckmannLobe", "WARD", "BECKMANN", "LOBES", "as_lobe"]


class Lobe:
    """A specular lobe: a name and its value at directions.

    Attributes:
        name: its name in messages.
        analytic: the renderer and the fit know this lobe's closed forms (Ward's only); any other
            lobe is integrated on the nodes and differentiated by forward-mode AD.
    """

    name: str = "lobe"
    analytic: bool = False

    def cosine(self, wi: Tensor, wo: Tensor, n: Tensor, alpha: Tensor, rotation: Tensor | None = None) -> Tensor:
        """The lobe for ``k_s = 1`` times ``<n, w_i>``: ``(*)``, broadcasting.

        Args:
            wi, wo: ``(*, 3)`` unit light and view directions.
            n: ``(*, 3)`` unit normals.
            alpha: ``(*, 2)`` roughness ``a_x, a_y`` (its meaning is the lobe's; 0 gives 0).
            rotation: ``(*)`` lobe rotation in radians, or ``None`` for 0.
        """
        raise NotImplementedError(f"{type(self).__name__}.cosine")


@dataclass(frozen=True)
class WardLobe(Lobe):
    """Ward's lobe (:func:`torchspec.model.brdf.ward_cosine`), the format's model, with its fast paths."""

    name: str = "ward"
    analytic: bool = True

    def cosine(self, wi: Tensor, wo: Tensor, n: Tensor, alpha: Tensor, rotation: Tensor | None = None) -> Tensor:
        return ward_cosine(wi, wo, n, alpha, rotation)


@dataclass(frozen=True)
class BeckmannLobe(Lobe):
    """The Beckmann microfacet lobe of :func:`torchspec.model.brdf.beckmann_cosine` (physically based
    renderers'), to tell a model's residual from an integration's."""

    name: str = "beckmann"

    def cosine(self, wi: Tensor, wo: Tensor, n: Tensor, alpha: Tensor, rotation: Tensor | None = None) -> Tensor:
        return beckmann_cosine(wi, wo, n, alpha, rotation)


WARD = WardLobe()
BECKMANN = BeckmannLobe()
LOBES = {lobe.name: lobe for lobe in (WARD, BECKMANN)}
"""The lobes a renderer's ``lobe=`` may name by a string."""


def as_lobe(lobe: str | Lobe) -> Lobe:
    """``lobe`` as an object: a :class:`Lobe` as it is, a name of :data:`LOBES` its lobe."""
    if isinstance(lobe, Lobe):
        return lobe
    if lobe not in LOBES:
        raise TorchspecError(f"lobe must be one of {tuple(LOBES)} or a torchspec.model.lobes.Lobe; got {lobe!r}.")
    return LOBES[lobe]
