"""Reflectance models a pixel can be fitted with, and their parameter packing.

Each model is a subset of the Ward parameters of :mod:`torchspec.jacobian` with bounds:

===================  ===============================================  ======================
model                parameters (in this order)                       bounds
===================  ===============================================  ======================
``diffuse``          normal angles a, b; k_d (C)                      k_d >= 0
``ward-iso``         + grey k_s (1); alpha                            k_s >= 0, alpha in ALPHA_BOUNDS
``ward-iso-colour``  + k_s (C); alpha                                 k_s >= 0, alpha in ALPHA_BOUNDS
``ward-aniso``       + k_s (C); alpha_x, alpha_y; rotation            k_s >= 0, alpha in ALPHA_BOUNDS
``ward-dual``        + grey k_s (1); alpha; grey k_s2 (1); alpha2     k_s, k_s2 >= 0, both alpha in
                                                                      ALPHA_BOUNDS
===================  ===============================================  ======================

``ward-dual`` is two isotropic grey lobes on one normal, a sharp and a broad one: a varnish over a
glossy layer, whose highlight a single Ward lobe cannot shape (its core too wide or its skirt too
narrow). The lobes are interchangeable in the model; :meth:`Model.unpack` names the sharper one the
first (``SVBRDF.specular``) and the broader the second (``SVBRDF.specular2``).

Bounds are kept by reparametrisation in the solver (:class:`torchspec.lm.Bounds`): softplus for
the coefficients, which may reach 0, and a sigmoid for the roughness.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .brdf import SVBRDF
from .errors import TorchspecError
from .geometry import angles_from_normal, normal_from_angles
from .jacobian import jacobian
from .least_squares import normal_equations
from .lights import Lights
from .lm import Bounds, NormalEquations
from .quadrature import Quadrature

__all__ = ["Model", "MODELS", "get_model", "ALPHA_BOUNDS"]

ALPHA_BOUNDS = (1e-3, 1.0)
"""The roughness a fit may take: below, the lobe is narrower than any light kernel resolves; above,
the Ward lobe no longer describes a gloss. A lobe that fades into the diffuse (``k_s -> 0``) leaves
``alpha`` undetermined: the bounds keep it finite."""


@dataclass(frozen=True)
class Model:
    """A reflectance model: which Ward parameters are free.

    Attributes:
        name: its name in configs and ``svbrdf.json``.
        lobe: has a specular lobe.
        grey: one ``k_s`` for every channel.
        anisotropic: ``alpha_x``, ``alpha_y`` and a rotation, else one ``alpha``.
        dual: a second isotropic grey lobe (``ward-dual``).
    """

    name: str
    lobe: bool
    grey: bool = True
    anisotropic: bool = False
    dual: bool = False

    def size(self, channels: int) -> int:
        """``P``, the number of parameters for ``channels`` channels."""
        if not self.lobe:
            return 2 + channels
        return 2 + channels + (1 if self.grey else channels) + (3 if self.anisotropic else 1) + (2 if self.dual else 0)

    def bounds(self, channels: int, least: float = ALPHA_BOUNDS[0]) -> Bounds:
        """The solver's reparametrisation of each parameter; ``least``: the smallest roughness
        (at least :data:`ALPHA_BOUNDS`' low end; :func:`torchspec.layout.resolvable_roughness`)."""
        kinds = ["free", "free"] + ["nonnegative"] * channels
        if self.lobe:
            kinds += ["nonnegative"] * (1 if self.grey else channels)
            alpha = ("interval", max(least, ALPHA_BOUNDS[0]), ALPHA_BOUNDS[1])
            kinds += [alpha, alpha, "free"] if self.anisotropic else [alpha]
            if self.dual:
                kinds += ["nonnegative", alpha]
        return Bounds(tuple(kinds))

    def pack(self, svbrdf: SVBRDF) -> Tensor:
        """``(N, P)`` parameters of a flat ``svbrdf``.

        ``ward-dual`` from an SVBRDF with one lobe (a smaller model's fit) starts its lobes either
        side of it: half its ``k_s`` each, at ``alpha / 2`` and ``2 alpha`` (within the bounds)."""
        parts = [angles_from_normal(svbrdf.normal), svbrdf.diffuse]
        if self.lobe:
            ks = svbrdf.specular
            ks = ks.mean(-1, keepdim=True) if self.grey else ks.expand_as(svbrdf.diffuse)
            alpha = svbrdf.roughness
            if self.anisotropic:
                rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(alpha[:, 0])
                parts += [ks, alpha, rotation[:, None]]
            elif not self.dual:
                parts += [ks, alpha.mean(-1, keepdim=True)]
            elif svbrdf.specular2 is not None:
                ks2 = svbrdf.specular2.mean(-1, keepdim=True)
                parts += [ks, alpha.mean(-1, keepdim=True), ks2, svbrdf.roughness2.mean(-1, keepdim=True)]
            else:
                alpha = alpha.mean(-1, keepdim=True)
                low, high = ALPHA_BOUNDS
                sharp, broad = (0.5 * alpha).clamp(2 * low, high / 2), (2.0 * alpha).clamp(2 * low, high / 2)
                parts += [0.5 * ks, sharp, 0.5 * ks, broad]
        return torch.cat(parts, -1)

    def unpack(self, params: Tensor, channels: tuple[str, ...], order: bool = False) -> SVBRDF:
        """A flat :class:`~torchspec.SVBRDF` (``k_s = 0``, ``alpha = 0`` without a lobe).

        ``order``: ``ward-dual``'s sharper lobe first (the solver's parameters keep the order they
        started in)."""
        c = len(channels)
        normal = normal_from_angles(params[:, :2])
        kd = params[:, 2 : 2 + c]
        if not self.lobe:
            zero = params.new_zeros((params.shape[0], 1))
            return SVBRDF(normal, kd, zero, zero.expand(-1, 2).clone(), None, channels)
        at = 2 + c + (1 if self.grey else c)
        ks = params[:, 2 + c : at]
        if self.anisotropic:
            return SVBRDF(normal, kd, ks, params[:, at : at + 2], params[:, at + 2], channels)
        alpha = params[:, at : at + 1]
        if not self.dual:
            return SVBRDF(normal, kd, ks, alpha.expand(-1, 2), None, channels)
        ks2, alpha2 = params[:, at + 1 : at + 2], params[:, at + 2 : at + 3]
        if order:
            swap = alpha2 < alpha
            ks, ks2 = torch.where(swap, ks2, ks), torch.where(swap, ks, ks2)
            alpha, alpha2 = torch.where(swap, alpha2, alpha), torch.where(swap, alpha, alpha2)
        return SVBRDF(normal, kd, ks, alpha.expand(-1, 2), None, channels, ks2, alpha2.expand(-1, 2))

    def select(self, full: Tensor, channels: int) -> Tensor:
        """This model's columns ``(..., P)`` of a Jacobian in :mod:`torchspec.jacobian`'s order
        ``(..., 2 + C + C_s + 3)`` (``+ 3`` for ``ward-dual``: its second ``k_s`` and ``alpha``);
        an isotropic ``alpha`` moves both ``alpha_x`` and ``alpha_y``."""
        cs = full.shape[-1] - 5 - channels - (3 if self.dual else 0)
        if not self.lobe:
            return full[..., : 2 + channels]
        at = 2 + channels + cs
        shape = full[..., at:]
        if self.anisotropic:
            return full
        picked = [full[..., :at], shape[..., :1] + shape[..., 1:2]]
        if self.dual:  # after the rotation: k_s2, alpha2_x, alpha2_y
            picked += [shape[..., 3:4], shape[..., 4:5] + shape[..., 5:6]]
        return torch.cat(picked, -1)

    def selection(self, channels: int, like: Tensor) -> Tensor:
        """:meth:`select` as a matrix ``(2 + C + C_s + 3 [+ 3], P)``: ``select(J) = J @ selection``."""
        cs = 1 if self.grey else channels
        eye = torch.eye(5 + channels + cs + (3 if self.dual else 0), dtype=like.dtype, device=like.device)
        return self.select(eye, channels)

    def residuals(
        self,
        observed: Tensor,
        weight: Tensor,
        lights: Lights,
        view: Tensor,
        channels: tuple[str, ...],
        *,
        quadrature: Quadrature = Quadrature(),
        normal: bool = False,
    ) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor] | NormalEquations]:
        """The solver's residual function for these pixels: ``(params (M, P), index (M,)) ->
        (residuals (M, K C), jacobian (M, K C, P))`` with ``residual = weight (rendered -
        observed)``.

        Args:
            observed: ``(N, K, C)`` recorded values.
            weight: ``(N, K)`` or ``(N, K, C)``: 0 drops a sample; a per-pixel scale evens the
                costs of bright and dark pixels.
            quadrature: the model's quadrature (:class:`torchspec.quadrature.Quadrature`).
            normal: return the :class:`~torchspec.lm.NormalEquations` instead
                (:func:`torchspec.least_squares.normal_equations`): the same solver steps without
                the Jacobian in memory, and with ``quadrature.compile`` one fused pass over the
                frames.
        """
        w = weight if weight.dim() == 3 else weight[..., None]
        if normal:
            select = self.selection(len(channels), observed)

            def equations(params: Tensor, index: Tensor) -> NormalEquations:
                svbrdf = self.unpack(params, channels)
                wi = w[index].expand(-1, -1, len(channels))
                out = normal_equations(
                    svbrdf,
                    lights,
                    view,
                    observed[index],
                    wi,
                    select,
                    quadrature=quadrature,
                    diffuse_only=not self.lobe,
                    isotropic=not self.anisotropic,
                )
                return NormalEquations(*out)

            return equations

        def fn(params: Tensor, index: Tensor) -> tuple[Tensor, Tensor]:
            svbrdf = self.unpack(params, channels)
            value, full = jacobian(
                svbrdf, lights, view, quadrature=quadrature, diffuse_only=not self.lobe, isotropic=not self.anisotropic
            )
            wi = w[index]
            r = ((value - observed[index]) * wi).flatten(1)
            jac = self.select(full, len(channels)) * wi[..., None]
            return r, jac.flatten(1, 2)

        return fn


MODELS = {
    m.name: m
    for m in (
        Model("diffuse", lobe=False),
        Model("ward-iso", lobe=True, grey=True),
        Model("ward-iso-colour", lobe=True, grey=False),
        Model("ward-aniso", lobe=True, grey=False, anisotropic=True),
        Model("ward-dual", lobe=True, grey=True, dual=True),
    )
}


def get_model(name: str) -> Model:
    """The model called ``name``; a clear error lists the known ones.

    Example:
        >>> get_model("ward-iso").size(3)  # 2 angles, 3 k_d, a grey k_s, one alpha
        7
    """
    if name not in MODELS:
        raise TorchspecError(f"model must be one of {sorted(MODELS)}; got {name!r}.")
    return MODELS[name]
