"""The reflectance model of ``docs/capture-format.md``: Lambert plus the Ward lobe (isotropic or
anisotropic with a rotation angle), as broadcasting tensor functions, and the per-pixel
:class:`SVBRDF` parameters they take.

    rho = k_d / pi + k_s exp(-tan^2(theta_h) (cos^2(phi_h) / a_x^2 + sin^2(phi_h) / a_y^2))
                     / (4 pi a_x a_y sqrt(<n, w_i> <n, w_o>))

with ``h`` in the lobe frame ``(s, t, n)`` of :func:`torchspec.model.geometry.tangent_frame`. Since
``tan^2(theta_h) cos^2(phi_h) = (h.s)^2 / (h.n)^2`` for any scale of ``h``, the exponent uses
the unnormalised ``h = w_i + w_o``. Back-facing directions give 0, with zero gradients; values
and gradients stay finite at grazing angles.

References:
    Ward, "Measuring and modeling anisotropic reflection", SIGGRAPH 1992.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch
from torch import Tensor

from ..errors import TorchspecError
from .geometry import dot, tangent_frame

__all__ = ["SVBRDF", "lambert", "ward", "ward_cosine", "beckmann_cosine", "reflectance"]


def _default_channels(count: int) -> tuple[str, ...]:
    return {1: ("Y",), 3: ("R", "G", "B")}.get(count, tuple(f"C{c}" for c in range(count)))


@dataclass(frozen=True)
class SVBRDF:
    """Per-pixel Ward parameters with common leading dims ``*`` (``(H, W)`` for maps, ``(N,)``
    for a batch of pixels).

    Attributes:
        normal: ``(*, 3)`` unit shading normals, surface frame.
        diffuse: ``(*, C)`` ``k_d`` (the diffuse BRDF is ``k_d / pi``).
        specular: ``(*, C)`` or ``(*, 1)`` (grey) ``k_s``; 0 for a pixel with no lobe.
        roughness: ``(*, 2)`` ``alpha_x, alpha_y`` (equal when isotropic; 0 where ``k_s = 0``).
        rotation: ``(*)`` lobe rotation ``A`` in radians, or ``None`` for 0.
        channels: the ``C`` channel names; by default ``("R", "G", "B")`` for 3 channels,
            ``("Y",)`` for 1.
        specular2, roughness2: a second Ward lobe (``(*, C)`` or ``(*, 1)``, and ``(*, 2)``), or
            ``None`` for none: it shares the normal and the rotation, and adds to the first (the
            ``ward-dual`` model of :mod:`torchspec.model.registry`: a sharp and a broad gloss, a varnish
            over a glossy layer). 0 where a pixel has no second lobe.
    """

    normal: Tensor
    diffuse: Tensor
    specular: Tensor
    roughness: Tensor
    rotation: Tensor | None = None
    channels: tuple[str, ...] | None = None
    specular2: Tensor | None = None
    roughness2: Tensor | None = None

    def __post_init__(self):
        lead = tuple(self.normal.shape[:-1])
        count = self.diffuse.shape[-1]
        checks = [
            ("normal", self.normal, (3,)),
            ("diffuse", self.diffuse, (count,)),
            ("roughness", self.roughness, (2,)),
        ]
        for name, value, tail in checks:
            if tuple(value.shape) != lead + tail:
                raise TorchspecError(
                    f"SVBRDF.{name} must have shape {lead + tail} (leading dims of normal {tuple(self.normal.shape)}); "
                    f"got {tuple(value.shape)}."
                )
        if tuple(self.specular.shape) not in (lead + (count,), lead + (1,)):
            raise TorchspecError(
                f"SVBRDF.specular must have shape {lead + (count,)} or {lead + (1,)}; got {tuple(self.specular.shape)}."
            )
        if (self.specular2 is None) != (self.roughness2 is None):
            raise TorchspecError("SVBRDF.specular2 and roughness2 (a second lobe) must be given together.")
        if self.specular2 is not None:
            if tuple(self.specular2.shape) not in (lead + (count,), lead + (1,)):
                raise TorchspecError(
                    f"SVBRDF.specular2 must have shape {lead + (count,)} or {lead + (1,)}; "
                    f"got {tuple(self.specular2.shape)}."
                )
            if tuple(self.roughness2.shape) != lead + (2,):
                raise TorchspecError(
                    f"SVBRDF.roughness2 must have shape {lead + (2,)}; got {tuple(self.roughness2.shape)}."
                )
        if self.rotation is not None and tuple(self.rotation.shape) != lead:
            raise TorchspecError(f"SVBRDF.rotation must have shape {lead}; got {tuple(self.rotation.shape)}.")
        channels = _default_channels(count) if self.channels is None else tuple(self.channels)
        if len(channels) != count:
            raise TorchspecError(f"SVBRDF.channels must name {count} channels (diffuse has {count}); got {channels}.")
        object.__setattr__(self, "channels", channels)

    @property
    def shape(self) -> torch.Size:
        """The leading dims ``*``."""
        return self.normal.shape[:-1]

    def _map(self, fn) -> SVBRDF:
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        for name in ("normal", "diffuse", "specular", "roughness", "specular2", "roughness2"):
            if values[name] is not None:
                values[name] = fn(values[name], 1)
        if values["rotation"] is not None:
            values["rotation"] = fn(values["rotation"], 0)
        return SVBRDF(**values)

    def second(self) -> SVBRDF | None:
        """The second lobe as the first of an SVBRDF (the same normal, ``k_d`` and rotation), or
        ``None`` without one."""
        if self.specular2 is None:
            return None
        return SVBRDF(self.normal, self.diffuse, self.specular2, self.roughness2, self.rotation, self.channels)

    def reshape(self, *shape: int) -> SVBRDF:
        """The same parameters with leading dims ``shape`` (``-1`` allowed)."""
        return self._map(lambda v, tail: v.reshape(*shape, *v.shape[v.dim() - tail :]))

    def flatten(self) -> SVBRDF:
        """Leading dims flattened to ``(N,)``."""
        return self.reshape(-1)

    def to(self, *args, **kwargs) -> SVBRDF:
        """Every tensor moved or cast like :meth:`torch.Tensor.to`."""
        return self._map(lambda v, tail: v.to(*args, **kwargs))

    def __getitem__(self, index) -> SVBRDF:
        """Index the leading dims (a slice, a mask, an index tensor)."""
        return self._map(lambda v, tail: v[index])


def lambert(k_d: Tensor) -> Tensor:
    """The diffuse BRDF ``k_d / pi``."""
    return k_d / math.pi


def ward_cosine(
    wi: Tensor, wo: Tensor, n: Tensor, alpha: Tensor, rotation: Tensor | None = None
) -> Tensor:
    """The Ward lobe without ``k_s``, times ``<n, w_i>``: ``(*)``, broadcasting.

    ``exp(E) sqrt(<n, w_i> / <n, w_o>) / (4 pi a_x a_y)``, the specular integrand of a light
    from ``w_i`` for ``k_s = 1``: bounded where the BRDF itself grows (``<n, w_i> -> 0``).

    Args:
        wi, wo: ``(*, 3)`` unit light and view directions.
        n: ``(*, 3)`` unit normals.
        alpha: ``(*, 2)`` roughness ``a_x, a_y``; 0 (no lobe) gives 0.
        rotation: ``(*)`` lobe rotation, radians.
    """
    ci, co = dot(n, wi), dot(n, wo)
    # alpha = 0 is the format's "no lobe" (k_s = 0): it contributes 0, not 0 * inf.
    front = (ci > 0) & (co > 0) & (alpha[..., 0] > 0) & (alpha[..., 1] > 0)
    alpha = torch.where(front[..., None], alpha, torch.ones_like(alpha))
    one = torch.ones_like(ci)
    ci_s, co_s = torch.where(front, ci, one), torch.where(front, co, one)
    s, t = tangent_frame(n, rotation)
    h = wi + wo
    hn = torch.where(front, dot(h, n), one)  # > 0 in front: it is ci + co
    exponent = -((dot(h, s) / alpha[..., 0]) ** 2 + (dot(h, t) / alpha[..., 1]) ** 2) / (hn * hn)
    value = torch.exp(exponent) * torch.sqrt(ci_s / co_s) / (4.0 * math.pi * alpha[..., 0] * alpha[..., 1])
    return torch.where(front, value, torch.zeros_like(value))


def ward(wi: Tensor, wo: Tensor, n: Tensor, k_s: Tensor, alpha: Tensor, rotation: Tensor | None = None) -> Tensor:
    """The specular BRDF ``(*, C)``: ``k_s (*, C) or (*, 1)`` times the Ward lobe; 0 back-facing.

    It grows as ``1 / sqrt(<n, w_i>)`` at grazing light (Ward's normalisation): render with
    :func:`ward_cosine`, which carries the cosine of the measurement.
    """
    ci = dot(n, wi)
    safe = torch.where(ci > 0, ci, torch.ones_like(ci))
    lobe = torch.where(ci > 0, ward_cosine(wi, wo, n, alpha, rotation) / safe, torch.zeros_like(ci))
    return k_s * lobe[..., None]


def reflectance(wi: Tensor, wo: Tensor, svbrdf: SVBRDF) -> Tensor:
    """The full BRDF ``rho (*, C) = k_d / pi + Ward`` (+ the second lobe's) of ``svbrdf`` for
    directions ``(*, 3)``; 0 for back-facing directions."""
    n = svbrdf.normal
    front = ((dot(n, wi) > 0) & (dot(n, wo) > 0))[..., None]
    diffuse = torch.where(front, lambert(svbrdf.diffuse), torch.zeros_like(svbrdf.diffuse))
    value = diffuse + ward(wi, wo, n, svbrdf.specular, svbrdf.roughness, svbrdf.rotation)
    if svbrdf.specular2 is not None:
        value = value + ward(wi, wo, n, svbrdf.specular2, svbrdf.roughness2, svbrdf.rotation)
    return value


def _smith_g1(v: Tensor, m: Tensor, n: Tensor, s: Tensor, t: Tensor, alpha: Tensor) -> Tensor:
    """Smith's masking for the Beckmann distribution with Mitsuba 3's rational approximation."""
    cos = dot(v, n)
    vs, vt = dot(v, s), dot(v, t)
    sin2 = (vs * vs + vt * vt).clamp(min=torch.finfo(cos.dtype).tiny)
    projected = torch.sqrt((vs * alpha[..., 0]) ** 2 + (vt * alpha[..., 1]) ** 2) / torch.sqrt(sin2)
    tan = torch.sqrt(sin2) / cos.abs().clamp(min=torch.finfo(cos.dtype).tiny)
    a = 1.0 / (projected * tan).clamp(min=torch.finfo(cos.dtype).tiny)
    g = torch.where(a < 1.6, (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a), torch.ones_like(a))
    return torch.where((dot(v, m) * cos > 0) & (sin2 > 0), g, torch.where(sin2 > 0, torch.zeros_like(g), 1.0))


def beckmann_cosine(
    wi: Tensor, wo: Tensor, n: Tensor, alpha: Tensor, rotation: Tensor | None = None
) -> Tensor:
    """A Beckmann microfacet lobe with Smith masking and no Fresnel (``F = 1``), times
    ``<n, w_i>``: ``D G1(w_i) G1(w_o) / (4 <n, w_o>)``, for comparison with physically based
    renderers (the development captures are rendered with it; ``alpha`` means what Ward's does
    in the exponent). Not the format's model: fits use :func:`ward_cosine`.
    """
    ci, co = dot(n, wi), dot(n, wo)
    front = (ci > 0) & (co > 0) & (alpha[..., 0] > 0) & (alpha[..., 1] > 0)
    alpha = torch.where(front[..., None], alpha, torch.ones_like(alpha))
    s, t = tangent_frame(n, rotation)
    h = wi + wo
    h = h / h.norm(dim=-1, keepdim=True).clamp(min=torch.finfo(h.dtype).tiny)
    hn = torch.where(front, dot(h, n), torch.ones_like(ci))
    hs, ht = dot(h, s) / alpha[..., 0], dot(h, t) / alpha[..., 1]
    d = torch.exp(-(hs * hs + ht * ht) / (hn * hn)) / (math.pi * alpha[..., 0] * alpha[..., 1] * hn**4)
    g = _smith_g1(wi, h, n, s, t, alpha) * _smith_g1(wo, h, n, s, t, alpha)
    value = d * g / (4.0 * torch.where(front, co, torch.ones_like(co)))
    return torch.where(front, value, torch.zeros_like(value))
