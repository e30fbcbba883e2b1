"""The measurement model of ``docs/capture-format.md``: what a pixel records under each frame's
extended light, differentiable in every SVBRDF parameter.

    value[p, k, c] = exposure_k irradiance_k,c integral D_k(l) rho_c(w(l), view; p) <n_p, w(l)> dl

(see :mod:`torchspec.model.lights` for the density ``D_k`` in the l-plane). Two terms:

- diffuse, ``k_d / pi integral D_k <n, w>^+``: the effective direction ``d_k`` of each frame gives
  it exactly as ``k_d / pi <n, d_k>`` when the kernel lies in the normal's hemisphere; where the
  kernel reaches behind the normal's horizon, the smaller of the parts in front of and behind it
  is integrated, piecewise between the horizon's crossings (:func:`torchspec.model.diffuse.diffuse_integral`).
- specular, ``k_s integral D_k(l) S(l) dl`` with ``S`` the Ward lobe times the cosine
  (:func:`torchspec.model.brdf.ward_cosine`), integrated on the nodes of :mod:`torchspec.model.nodes`.

Paths of the specular term, chosen by :func:`torchspec.model.quadrature.choose_path`:

- ``point``: a point light, one exact evaluation per frame.
- ``fast``: Gauss-Hermite, ``order^2`` nodes per pixel and frame, on the product of the two
  factors' Gaussians (:func:`torchspec.model.nodes.fast_rule`); its error against the reference is
  measured by ``experiments/render_accuracy.py``.
- ``reference``: polar Gauss-Legendre, accurate for any kernel, ``reference_order`` radii
  setting the accuracy (:func:`torchspec.model.nodes.reference_rule`).
- ``auto``: ``fast``, and ``reference`` for the pairs whose product reaches the horizon.

Nodes are placed from the parameters (the lobe's mirror point and width) and autograd follows
them, so the gradient is exactly that of the value computed - the consistent Jacobian that
Levenberg-Marquardt needs - and converges to the true derivative with the quadrature. Pixels are
processed in chunks so that memory stays bounded for (pixels x frames x nodes)
(:data:`torchspec.model.quadrature.BUDGET` elements).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..lm.picks import keep
from ..progress import bar
from .brdf import SVBRDF, lambert
from .diffuse import diffuse_integral
from .fusion import FIXED_SIZES, fused
from .geometry import from_plane
from .lights import Lights, diffuse_directions
from .lobe import lobe_at, lobe_frame, pick
from .lobes import WARD, Lobe, as_lobe
from .nodes import node_rules
from .quadrature import BUDGET, Quadrature, check_quadrature, choose_path

__all__ = ["render", "render_image", "LOBES", "ROW_CHUNKS", "TILE_PIXELS"]

LOBES = ("ward", "beckmann")
"""The lobes ``lobe=`` names by a string (:data:`torchspec.model.lobes.LOBES`); any
:class:`torchspec.model.lobes.Lobe` object is taken too."""
ROW_CHUNKS = 32
""":func:`render_image` renders an image in about this many chunks of rows (a progress bar that moves)."""
TILE_PIXELS = 4096
"""... and at most this many pixels a chunk (memory bounded by a chunk of rows)."""


def render(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
    lobe: str | Lobe = "ward",
) -> Tensor:
    """Predicted values of every pixel under every frame: ``(*, K, C)``.

    Args:
        svbrdf: parameters with leading dims ``*`` and ``C`` channels (or grey ``k_s``), and a
            second lobe if it has one.
        lights: ``K`` frames; the kernel must be known (not ``unknown``).
        view: ``(3,)`` unit direction towards the camera.
        quadrature: the path, the fast and reference rules' orders and the diffuse clamp's rule
            (:class:`torchspec.model.quadrature.Quadrature`); its ``compile`` fuses the specular node
            integration with ``torch.compile``.
        lobe: ``ward`` (the format's model) or ``beckmann`` (:func:`torchspec.model.brdf.beckmann_cosine`,
            the physically based renderers' lobe, to tell a model's residual from an integration's),
            or any :class:`torchspec.model.lobes.Lobe` (integrated on the same nodes as Beckmann's).

    Returns:
        ``(*, K, C)`` in the dtype and on the device of ``svbrdf``.

    Raises:
        TorchspecError: a bad ``lobe``, ``view`` shape, irradiance channel count, or a path that
            does not fit the kernel.

    Example:
        >>> import torch
        >>> from torchspec.model.lights import Kernel, Lights
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> lights = Lights(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), Kernel("point"), one, one[0])
        >>> maps = SVBRDF(torch.tensor([[0.0, 0, 1]], dtype=torch.float64), one, one * 0, one.expand(1, 2) * 0)
        >>> round(float(render(maps, lights, torch.tensor([0.0, 0, 1], dtype=torch.float64))), 6)  # k_d / pi
        0.31831
    """
    lobe = as_lobe(lobe)
    chosen = _check(svbrdf, lights, view, quadrature)
    count = svbrdf.diffuse.shape[-1]
    lead = svbrdf.shape
    flat = svbrdf.flatten()
    like = flat.diffuse
    lights = lights.to(dtype=like.dtype, device=like.device)
    view = view.to(dtype=like.dtype, device=like.device)
    orders = quadrature.orders(lights.kernel)
    fast, reference = orders
    direction = lights.directions if lights.kernel.kind == "point" else diffuse_directions(lights)

    nodes_per_pair = {"point": 1, "auto": fast**2, "fast": fast**2, "reference": 2 * reference**2}[chosen]
    chunk = max(1, BUDGET // (lights.directions.shape[0] * nodes_per_pair))
    out = []
    for start in range(0, max(flat.shape[0], 1), chunk):  # one (empty) chunk for no pixels
        part = flat[start : start + chunk]
        specular = _specular(part, lights, view, chosen, orders, quadrature.compile, lobe)
        diffuse = diffuse_integral(part.normal, lights, direction, clamp=quadrature.clamp)
        value = lambert(part.diffuse)[:, None, :] * diffuse[..., None] + part.specular[:, None, :] * specular[..., None]
        second = part.second()
        if second is not None:
            value = _add_second_lobe(value, second, lights, view, chosen, orders, quadrature.compile, lobe)
        out.append(value * lights.scale[None])
    return torch.cat(out).reshape(*lead, lights.directions.shape[0], count)


def render_image(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
    lobe: str | Lobe = "ward",
    progress: bool = False,
    desc: str = "render",
) -> Tensor:
    """:func:`render` of an image, ``(H, W, K, C)`` for maps of leading dims ``(H, W)``, in chunks of
    rows (about :data:`ROW_CHUNKS` of them, at most :data:`TILE_PIXELS` pixels each), with a progress
    bar over the rows (on stderr, when ``progress`` and stderr is a terminal; :func:`torchspec.progress.bar`).

    Example:
        >>> import torch
        >>> from torchspec.model.lights import Kernel, Lights
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> lights = Lights(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), Kernel("point"), one, one[0])
        >>> n = torch.tensor([0.0, 0, 1], dtype=torch.float64).expand(5, 4, 3)
        >>> maps = SVBRDF(n, torch.ones(5, 4, 1, dtype=torch.float64), torch.zeros(5, 4, 1), torch.zeros(5, 4, 2))
        >>> render_image(maps, lights, torch.tensor([0.0, 0, 1], dtype=torch.float64)).shape
        torch.Size([5, 4, 1, 1])
    """
    if len(svbrdf.shape) != 2:
        raise TorchspecError(f"render_image needs maps of leading dims (H, W); got {tuple(svbrdf.shape)}.")
    height, width = svbrdf.shape
    rows = max(1, min(-(-height // ROW_CHUNKS), TILE_PIXELS // max(width, 1)))
    parts = []
    with bar(height, desc=desc, unit="row", enabled=progress) as shown:
        for top in range(0, height, rows):
            parts.append(render(svbrdf[top : top + rows], lights, view, quadrature=quadrature, lobe=lobe))
            shown.update(parts[-1].shape[0])
    return torch.cat(parts)


def _check(svbrdf: SVBRDF, lights: Lights, view: Tensor, quadrature: Quadrature) -> str:
    """The specular path of :func:`render`'s arguments, once they are checked."""
    check_quadrature(quadrature)
    if view.shape != (3,):
        raise TorchspecError(f"view must have shape (3,); got {tuple(view.shape)}.")
    count = svbrdf.diffuse.shape[-1]
    if lights.irradiance.shape[1] not in (1, count):
        raise TorchspecError(
            f"lights.irradiance must have 1 or {count} channels (the SVBRDF's {svbrdf.channels}); "
            f"got {lights.irradiance.shape[1]}."
        )
    return choose_path(lights, quadrature.path)


def _add_second_lobe(value: Tensor, second: SVBRDF, lights, view, path, orders, compile, lobe) -> Tensor:
    """``value (N, K, C)`` plus the second lobe ``second (N,)`` (:meth:`SVBRDF.second`), on the
    pixels that have one (all when its ``k_s`` needs a derivative)."""
    count = value.shape[-1]
    lobed = (second.specular > 0).any(-1)
    tangent = torch.autograd.forward_ad.unpack_dual(second.specular).tangent
    if (torch.is_grad_enabled() and second.specular.requires_grad) or tangent is not None:
        lobed = torch.ones_like(lobed)
    index = lobed.nonzero()[:, 0]
    if index.numel():
        picked = second[index]
        lobe2 = _specular(picked, lights, view, path, orders, compile, lobe)
        lobe2 = (picked.specular[:, None, :] * lobe2[..., None]).expand(-1, -1, count)
        value = value.index_add(0, index, lobe2)
    return value


def _specular(svbrdf, lights, view, path, orders, compile=False, lobe: Lobe = WARD) -> Tensor:
    """``integral D_k S dl`` for the pixels of ``svbrdf (N,)`` and every frame: ``(N, K)``, on the
    path ``path`` (:func:`torchspec.model.quadrature.choose_path`) with the orders ``(fast, reference)``.

    Nodes are placed from the parameters (the lobe's mirror point and width) and autograd
    follows them, so the gradient is exactly that of the value computed.
    """
    kernel, centre = lights.kernel, lights.directions
    pixels = lobe_frame(svbrdf, view)
    integrate = (
        fused(_integrate, compile, svbrdf.normal.shape[0]) if lobe.analytic else _integrate_lobe(svbrdf, view, lobe)
    )
    if path == "point":
        if not lobe.analytic:
            return lobe.cosine(
                centre[None],
                view,
                svbrdf.normal[:, None],
                svbrdf.roughness[:, None],
                None if svbrdf.rotation is None else svbrdf.rotation[:, None],
            )
        return lobe_at(centre[None, :, None, 0], centre[None, :, None, 1], pixels)[..., 0]
    (lx, ly, area), fallback = node_rules(kernel, centre, pixels, path, orders)
    value = integrate(kernel, centre[None], pixels, lx, ly, area)
    if fallback is not None:  # auto: the pairs whose product reaches the horizon, by the reference rule
        p, k, valid, (lx, ly, area) = fallback
        if lobe.analytic:
            exact = _integrate(kernel, centre[k][:, None], pick(pixels, p), lx, ly, area)[:, 0]
        else:
            exact = integrate(kernel, centre[k][:, None], None, lx, ly, area, index=p)[:, 0]
        value = value.index_put((p, k), keep(valid, exact, value[p, k]))
    return value


def _integrate(kernel, centre, pixels, lx, ly, area) -> Tensor:
    density = kernel.density_xy(lx, ly, centre[..., None, :])
    return (area * density * lobe_at(lx, ly, pixels)).sum(-1)


FIXED_SIZES.add(_integrate)


def _integrate_lobe(svbrdf: SVBRDF, view: Tensor, lobe: Lobe):
    """The node integration with ``lobe`` (:meth:`torchspec.model.lobes.Lobe.cosine`) in place of Ward's."""

    def integrate(kernel, centre, pixels, lx, ly, area, index=None):
        part = svbrdf if index is None else svbrdf[index]
        shape = (-1,) + (1,) * (lx.dim() - 1)
        w = from_plane(torch.stack(torch.broadcast_tensors(lx, ly), -1))
        rotation = None if part.rotation is None else part.rotation.reshape(shape)
        value = lobe.cosine(w, view, part.normal.reshape(*shape, 3), part.roughness.reshape(*shape, 2), rotation)
        return (area * kernel.density_xy(lx, ly, centre[..., None, :]) * value).sum(-1)

    return integrate
