"""Jacobians of :func:`torchspec.model.rendering.render` for fitting, two ways.

The parameters of a pixel, in this order (``P = 2 + C + C_s + 3``):

    a, b          the normal's tilt angles (:func:`torchspec.model.geometry.normal_from_angles`)
    k_d           C values
    k_s           C_s values (C, or 1 for grey)
    alpha_x, alpha_y, rotation
    k_s2, alpha2_x, alpha2_y   only with a second lobe (``SVBRDF.specular2``): ``C_s2 + 2`` more;
                  it shares the normal and the rotation

Pixels are independent, so each column of the Jacobian is one derivative for all pixels at once.

- ``forward``: forward-mode automatic differentiation, one JVP per parameter (``P`` passes
  through ``render``). Exactly the derivative of the value rendered, node placement included.
- ``analytic``: closed forms. ``k_d`` and ``k_s`` enter linearly; the Ward lobe's derivatives
  in the normal (its tangent frame included), roughness and rotation are evaluated at the same
  nodes as the value, held fixed, so they are the quadrature of the true derivative, which
  differs from the derivative of the quadrature by the quadrature's own error (1e-3 of the
  derivative at most on the fast path, see ``tests/test_jacobian.py``). The diffuse clamp,
  where it acts, takes its gradient from the nodes of its value
  (:func:`torchspec.model.diffuse.clamped_diffuse`).

A fit may take fewer nodes (a :class:`torchspec.model.quadrature.Quadrature` with ``order``,
``reference_order`` and ``clamp="fast"``: ``QUADRATURES["fit"]``) and fuse the node loops with
``torch.compile`` (its ``compile``). :mod:`torchspec.model.least_squares` contracts the pieces of the
Jacobian (:func:`jacobian_parts`, :func:`assemble`) into a fit's sums.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import TorchspecError
from ..lm.picks import keep
from .brdf import SVBRDF
from .diffuse import diffuse_integral
from .fusion import FIXED_SIZES, fused
from .geometry import angles_from_normal, normal_derivative, normal_from_angles
from .lights import Lights, diffuse_directions
from .lobe import at_nodes, lobe_frame, pick
from .nodes import fallback_rule, fast_rule, node_rules
from .quadrature import BUDGET, Quadrature, check_quadrature, choose_path
from .rendering import render

__all__ = [
    "jacobian",
    "parameters",
    "from_parameters",
    "jacobian_parts",
    "assemble",
    "pixels_per_chunk",
    "MODES",
]

MODES = ("analytic", "forward")


def parameters(svbrdf: SVBRDF) -> Tensor:
    """The parameter vectors ``(*, P)`` of ``svbrdf`` in the order of this module.

    Example:
        >>> n = torch.tensor([[0.0, 0.0, 1.0]])
        >>> maps = SVBRDF(n, torch.ones(1, 3), torch.ones(1, 1), torch.full((1, 2), 0.1))
        >>> parameters(maps).shape  # 2 angles, 3 k_d, 1 k_s, alpha_x, alpha_y, rotation
        torch.Size([1, 9])
    """
    rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(svbrdf.normal[..., 0])
    parts = [angles_from_normal(svbrdf.normal), svbrdf.diffuse, svbrdf.specular, svbrdf.roughness, rotation[..., None]]
    if svbrdf.specular2 is not None:
        parts += [svbrdf.specular2, svbrdf.roughness2]
    return torch.cat(parts, -1)


def from_parameters(params: Tensor, channels: tuple[str, ...], grey: bool, second: int | None = None) -> SVBRDF:
    """The SVBRDF of the parameter vectors ``params (*, P)`` of :func:`parameters`: ``grey``, one
    ``k_s``; ``second``: the second lobe's ``k_s`` count, if it has one."""
    count = len(channels)
    cs = 1 if grey else count
    at = [2, 2 + count, 2 + count + cs, 4 + count + cs]
    lobe2 = {}
    if second is not None:
        end = at[3] + 1 + second
        lobe2 = {"specular2": params[..., at[3] + 1 : end], "roughness2": params[..., end : end + 2]}
    return SVBRDF(
        normal_from_angles(params[..., :2]),
        params[..., at[0] : at[1]],
        params[..., at[1] : at[2]],
        params[..., at[2] : at[3]],
        params[..., at[3]],
        channels,
        **lobe2,
    )


def jacobian(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    *,
    mode: str = "analytic",
    quadrature: Quadrature = Quadrature(),
    diffuse_only: bool = False,
    isotropic: bool | None = None,
) -> tuple[Tensor, Tensor]:
    """Values and Jacobian of :func:`torchspec.model.rendering.render` with respect to each pixel's
    parameters (:func:`parameters`).

    Args:
        svbrdf: leading dims ``*``, ``C`` channels; ``rotation`` may be ``None`` (0).
        lights, view: as for :func:`torchspec.model.rendering.render`.
        mode: ``analytic`` or ``forward``.
        quadrature: as for :func:`torchspec.model.rendering.render`; the forward mode takes the
            renderer's own (any path, no ``order``, ``reference_order``, fast ``clamp`` or
            ``compile``).
        diffuse_only: the model without its lobe (``k_s`` taken as 0, the lobe not integrated):
            the values and the same columns, those of ``k_s`` and the lobe's shape being 0.
            Analytic mode only.
        isotropic: whether every pixel's lobe is isotropic (``alpha_x = alpha_y``: the tangent
            frame's derivatives are not needed), as a model knows it; ``None``: read from the
            roughness, one host synchronisation per call (:func:`jacobian_parts`).

    Returns:
        ``(values (*, K, C), jacobian (*, K, C, P))``.

    Raises:
        TorchspecError: a bad ``mode`` or ``quadrature``, or options the forward mode lacks.
    """
    if mode not in MODES:
        raise TorchspecError(f"mode must be one of {MODES}; got {mode!r}.")
    check_quadrature(quadrature)
    if (diffuse_only or not quadrature.default or quadrature.compile) and mode != "analytic":
        raise TorchspecError(
            "diffuse_only, and a quadrature's order, reference_order, clamp and compile, need mode='analytic'."
        )
    lead = svbrdf.shape
    flat = svbrdf.flatten()
    grey = flat.specular.shape[-1] == 1 and flat.diffuse.shape[-1] != 1
    second = None if flat.specular2 is None else flat.specular2.shape[-1]
    params = parameters(flat)
    chunk = pixels_per_chunk(lights.directions.shape[0], quadrature)
    values = jacs = None  # filled in place: the Jacobian is the largest tensor of a fit, held once
    for start in range(0, max(params.shape[0], 1), chunk):  # one (empty) chunk for no pixels
        part = params[start : start + chunk]
        if mode == "forward":

            def forward(p):
                return render(from_parameters(p, flat.channels, grey, second), lights, view, quadrature=quadrature)

            eye = torch.eye(part.shape[-1], dtype=part.dtype, device=part.device)
            columns = []
            for j in range(part.shape[-1]):
                value, column = torch.func.jvp(forward, (part,), (eye[j].expand_as(part),))
                columns.append(column)
            jac = torch.stack(columns, -1)
        else:
            parts = jacobian_parts(
                from_parameters(part, flat.channels, grey, second), lights, view, quadrature, diffuse_only, isotropic
            )
            value, jac = assemble(*parts)
        if values is None:
            values = value.new_empty((params.shape[0], *value.shape[1:]))
            jacs = jac.new_empty((params.shape[0], *jac.shape[1:]))
        values[start : start + chunk] = value
        jacs[start : start + chunk] = jac
    return values.reshape(*lead, *values.shape[1:]), jacs.reshape(*lead, *jacs.shape[1:])


def pixels_per_chunk(frames: int, quadrature: Quadrature) -> int:
    """Pixels per chunk of ``frames`` frames: :data:`~torchspec.model.quadrature.BUDGET` elements of
    the fast rule's nodes. Chunks bound the memory, as the renderer's do; smaller ones cost time
    in per-call overhead."""
    return max(1, BUDGET // (frames * quadrature.orders(None)[0] ** 2))


def _frame_derivatives(n: Tensor, rotation: Tensor) -> tuple[Tensor, Tensor]:
    """``ds/dn, dt/dn (N, 3, 3)`` of the rotated tangent frame of ``geometry.tangent_frame``."""
    eye = torch.eye(3, dtype=n.dtype, device=n.device)
    ex = eye[0].expand_as(n)
    u = ex - n[:, :1] * n
    norm = u.norm(dim=-1, keepdim=True)
    s0 = u / norm
    du = -(n[:, :, None] * ex[:, None, :] + n[:, :1, None] * eye)  # du_i / dn_j
    ds0 = (eye - s0[:, :, None] * s0[:, None, :]) @ du / norm[..., None]

    def cross_matrix(a):  # [a]x b = a x b
        z = torch.zeros_like(a[:, 0])
        return torch.stack(
            [
                torch.stack([z, -a[:, 2], a[:, 1]], -1),
                torch.stack([a[:, 2], z, -a[:, 0]], -1),
                torch.stack([-a[:, 1], a[:, 0], z], -1),
            ],
            -2,
        )

    dt0 = -cross_matrix(s0) + cross_matrix(n) @ ds0
    c, s = torch.cos(rotation)[:, None, None], torch.sin(rotation)[:, None, None]
    return c * ds0 + s * dt0, c * dt0 - s * ds0


def _lobe_gradients(lx: Tensor, ly: Tensor, pixels, frame_ds: Tensor | None, frame_dt: Tensor | None):
    """The lobe ``L`` at nodes ``(N, F, Q)`` and its derivatives, componentwise (each ``(N, F, Q)``):
    ``dL/dn`` (x, y, z) and ``dL/d(alpha_x, alpha_y, rotation)``, the rotation's ``None`` for an
    isotropic lobe. Written like :func:`torchspec.model.lobe.lobe_at`, without 3-vectors, so that
    torch.compile fuses the sums over the nodes.

    ``frame_ds = frame_dt = None`` for isotropic lobes (``alpha_x = alpha_y``): the lobe is then
    ``exp(-(|h|^2 / <h, n>^2 - 1) / alpha^2)`` whatever the tangent frame, so the frame's
    derivatives drop out and the rotation's column is 0."""
    wz, ci, front, (hx, hy, hz), hn = at_nodes(lx, ly, pixels)
    (sx, sy, sz), (tx, ty, tz) = pixels.s, pixels.t
    co = pixels.cos_view
    hn = torch.where(front, hn, torch.ones_like(hx))
    s_h = sx * hx + sy * hy + sz * hz
    t_h = tx * hx + ty * hy + tz * hz
    hs, ht = s_h * pixels.inv_ax, t_h * pixels.inv_ay
    ci_s = torch.where(front, ci, torch.ones_like(ci))
    co_s = torch.where(co > 0, co, torch.ones_like(co))
    inv_hn2 = 1.0 / (hn * hn)
    energy = (hs * hs + ht * ht) * inv_hn2
    lobe = torch.where(front, torch.exp(-energy) * torch.sqrt(ci_s / co_s) * pixels.scale, torch.zeros_like(ci))
    h = (hx, hy, hz)
    if frame_ds is None:
        # dE/dn of E = -(|h|^2 / hn^2 - 1) / alpha^2 is 2 (energy + 1 / alpha^2) h / hn.
        factor = 2.0 * (energy + pixels.inv_ax * pixels.inv_ax) / hn
        d_energy = [factor * c for c in h]
    else:
        # dE/dn with E = -(hs^2 + ht^2) / hn^2; hs = s(n).h / a_x, ht = t(n).h / a_y, hn = n.h;
        # (ds/dn)^T h and (dt/dn)^T h per component j.
        a, b = -2.0 * hs * pixels.inv_ax * inv_hn2, -2.0 * ht * pixels.inv_ay * inv_hn2
        factor = 2.0 * energy / hn
        d_energy = []
        for j in range(3):
            ds_h = sum(frame_ds[:, i, j, None, None] * h[i] for i in range(3))
            dt_h = sum(frame_dt[:, i, j, None, None] * h[i] for i in range(3))
            d_energy.append(a * ds_h + b * dt_h + factor * h[j])
    # d log L / dn = d_energy + (w / <n, w> - v / <n, v>) / 2
    w = (lx, ly, wz)
    d_normal = tuple(lobe * (d_energy[j] + 0.5 * (w[j] / ci_s - pixels.view[j] / co_s)) for j in range(3))
    d_ax = lobe * (2.0 * hs * hs * inv_hn2 - 1.0) * pixels.inv_ax
    d_ay = lobe * (2.0 * ht * ht * inv_hn2 - 1.0) * pixels.inv_ay
    if frame_ds is None:
        d_rot = None
    else:  # s and t turn with the rotation: d(s.h)/dA = t.h, d(t.h)/dA = -s.h.
        d_rot = lobe * (-2.0 * (hs * t_h * pixels.inv_ax - ht * s_h * pixels.inv_ay) * inv_hn2)
    return lobe, d_normal, (d_ax, d_ay, d_rot)


def _stack(parts: tuple, like: Tensor) -> Tensor:
    """``(*, len(parts))`` from components ``(*)``, ``None`` standing for 0."""
    return torch.stack([torch.zeros_like(like) if c is None else c for c in parts], -1)


def jacobian_parts(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    quadrature: Quadrature,
    diffuse_only: bool = False,
    isotropic: bool | None = None,
) -> tuple:
    """Per pixel of a flat ``svbrdf (N,)`` and frame, what the values and every column are made
    of (:func:`assemble`): the diffuse and specular integrals ``(N, K)``, their derivatives in the
    normal and the lobe's shape ``(N, K, 3)``, ``dn/d(angles) (N, 3, 2)``, the frames' scale
    ``(1, K, C or 1)`` and the coefficients ``k_d (N, C)``, ``k_s (N, C_s)`` (then the second
    lobe's integral, derivatives and ``k_s2``, if it has one). ``isotropic``: as for
    :func:`jacobian`; a solver step passes its model's (no host synchronisation)."""
    chosen = choose_path(lights, quadrature.path)
    compiled = quadrature.compile
    like = svbrdf.diffuse
    lights = lights.to(dtype=like.dtype, device=like.device)
    view = view.to(dtype=like.dtype, device=like.device)
    kernel, centre = lights.kernel, lights.directions
    orders = quadrature.orders(kernel)
    rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(svbrdf.normal[:, 0])
    n = svbrdf.normal
    # dn / d(a, b) (N, 3, 2) of n ~ (tan a, tan b, 1).
    dn = normal_derivative(n)

    # Diffuse: <n, d_k> and its gradient d_k; where the clamp acts, the kernel's direction over
    # the part in front of the normal's horizon.
    direction = centre if kernel.kind == "point" else diffuse_directions(lights)
    diffuse, d_diffuse = diffuse_integral(n, lights, direction, gradient=True, clamp=quadrature.clamp, compile=compiled)

    # Specular: the value's nodes, held fixed.
    if diffuse_only:
        spec = torch.zeros_like(diffuse)
        d_spec_n, d_spec_shape = d_diffuse.new_zeros(d_diffuse.shape), d_diffuse.new_zeros(d_diffuse.shape)
        no_lobe = torch.zeros_like(svbrdf.specular)
        svbrdf = SVBRDF(n, svbrdf.diffuse, no_lobe, svbrdf.roughness, rotation, svbrdf.channels)
    else:
        spec, d_spec_n, d_spec_shape = _lobe_parts(svbrdf, lights, view, chosen, orders, rotation, compiled, isotropic)

    scale = lights.scale[None]  # (1, K, C or 1)
    second = ()
    if svbrdf.specular2 is not None and not diffuse_only:
        lobe2 = SVBRDF(n, svbrdf.diffuse, svbrdf.specular2, svbrdf.roughness2, rotation, svbrdf.channels)
        parts = _lobe_parts(lobe2, lights, view, chosen, orders, rotation, compiled, isotropic)
        second = (*parts, svbrdf.specular2.contiguous())
    # Contiguous coefficients: slices of the solver's parameters sit at offsets torch.compile guards on.
    return (
        diffuse,
        d_diffuse,
        spec,
        d_spec_n,
        d_spec_shape,
        dn,
        scale,
        svbrdf.diffuse.contiguous(),
        svbrdf.specular.contiguous(),
        *second,
    )


def _lobe_parts(
    svbrdf: SVBRDF, lights: Lights, view: Tensor, chosen: str, orders, rotation, compiled: bool, isotropic=None
) -> tuple:
    """The lobe's integrals ``(N, K)`` and their derivatives in the normal and its shape
    ``(N, K, 3)`` (:func:`jacobian_parts`), on the path ``chosen`` with the orders
    ``(fast, reference)``; ``isotropic`` ``None``: read from the roughness (a host synchronisation)."""
    kernel, centre = lights.kernel, lights.directions
    n = svbrdf.normal
    if isotropic is None:
        isotropic = bool((svbrdf.roughness[:, 0] == svbrdf.roughness[:, 1]).all())
    frames = (None, None) if isotropic else _frame_derivatives(n, rotation)
    if chosen == "point":
        pixels = lobe_frame(svbrdf, view)
        frame_ds, frame_dt = frames
        lx, ly = centre[None, :, None, 0], centre[None, :, None, 1]
        lobe, d_n, d_shape = _lobe_gradients(lx, ly, pixels, frame_ds, frame_dt)
        spec = lobe[..., 0]
        d_spec_n = _stack(tuple(c[..., 0] for c in d_n), spec)
        d_spec_shape = _stack(tuple(None if c is None else c[..., 0] for c in d_shape), spec)
    else:
        pixels = lobe_frame(svbrdf, view)
        frame_ds, frame_dt = frames
        if chosen == "reference":
            rule, fallback = node_rules(kernel, centre, pixels, chosen, orders)
            spec, d_spec_n, d_spec_shape = fused(_integrate_gradients, compiled, n.shape[0])(
                kernel, centre[None], pixels, frame_ds, frame_dt, *(r.detach() for r in rule)
            )
        else:  # the fast rule's nodes, then their integration: one pass each when fused (in one,
            # the compiler would compute the pairs' moments again for each node and output)
            lx, ly, area, reaches = fused(fast_rule, compiled, n.shape[0])(
                kernel, centre[None], pixels, orders[0]
            )
            spec, d_spec_n, d_spec_shape = fused(_integrate_gradients, compiled, n.shape[0])(
                kernel,
                centre[None],
                pixels,
                frame_ds,
                frame_dt,
                lx.detach(),
                ly.detach(),
                area.detach(),
            )
            auto = chosen == "auto"
            fallback = fallback_rule(kernel, centre, pixels, reaches, orders[1], compiled) if auto else None
        if fallback is not None:
            # Broadcast unlike the main call: compiled apart (a second compilation, once).
            p, k, valid, rule = fallback
            value, d_value_n, d_value_shape = fused(_integrate_fallback, compiled, p.shape[0])(
                kernel,
                centre[k][:, None],
                pick(pixels, p),
                None if isotropic else frame_ds[p],
                None if isotropic else frame_dt[p],
                *(r.detach() for r in rule),
            )
            spec = spec.index_put((p, k), keep(valid, value[:, 0], spec[p, k]))
            d_spec_n = d_spec_n.index_put((p, k), keep(valid, d_value_n[:, 0], d_spec_n[p, k]))
            d_spec_shape = d_spec_shape.index_put((p, k), keep(valid, d_value_shape[:, 0], d_spec_shape[p, k]))

    return spec, d_spec_n, d_spec_shape


def assemble(diffuse, d_diffuse, spec, d_spec_n, d_spec_shape, dn, scale, k_d, k_s, *second) -> tuple[Tensor, Tensor]:
    """Values ``(N, K, C)`` and the Jacobian ``(N, K, C, 2 + C + C_s + 3)`` from :func:`jacobian_parts`
    (``+ C_s2 + 2`` columns with a second lobe: ``second = (spec2, d_spec2_n, d_spec2_shape, k_s2)``)."""
    count = k_d.shape[-1]
    like = k_d
    k_d = k_d[:, None, :]
    eye = torch.eye(count, dtype=like.dtype, device=like.device)

    def coefficient_columns(integral, k_s):  # dvalue/dk_s (N, K, C, C_s), for C_s = C or 1 (grey)
        grey = k_s.shape[-1] == 1 and count != 1
        basis = torch.ones(count, 1, dtype=like.dtype, device=like.device) if grey else eye
        return (integral[..., None, None] * basis) * scale[..., None]

    lobes = [(spec, d_spec_n, d_spec_shape, k_s)]
    if second:
        lobes.append(second)
    value = k_d / math.pi * diffuse[..., None] * scale
    # Columns: angles (2), k_d (C), k_s (C or 1), alpha_x, alpha_y, rotation, [k_s2, alpha2_x, alpha2_y].
    # Through the angles first (N, K, 2), then per channel: no (N, K, C, 3) products.
    d_angles = k_d[..., None] / math.pi * (d_diffuse @ dn)[:, :, None, :]
    d_kd = (diffuse[..., None, None] / math.pi * eye) * scale[..., None]  # (N, K, C, C)
    columns, d_rotation = [], 0.0
    for integral, d_n, d_shape, k_s in lobes:
        k_s = k_s[:, None, :]
        value = value + k_s * integral[..., None] * scale
        d_angles = d_angles + k_s[..., None] * (d_n @ dn)[:, :, None, :]
        d_shape = k_s[..., None] * d_shape[:, :, None, :] * scale[..., None]
        d_shape = d_shape.expand(-1, -1, count, -1)  # (N, K, C, 3), also for a grey k_s under grey irradiance
        columns.append([coefficient_columns(integral, k_s[:, 0]), d_shape[..., :2]])
        d_rotation = d_rotation + d_shape[..., 2:]  # one rotation, shared by the lobes
    columns[0].append(d_rotation)
    d_angles = d_angles * scale[..., None]  # (N, K, C, 2)
    return value, torch.cat([d_angles, d_kd, *(c for lobe in columns for c in lobe)], -1)



def _integrate_fallback(*args):
    """:func:`_integrate_gradients` of the fallback pairs ``(M, 1, Q')``: its own compiled code."""
    return _integrate_gradients(*args)


def _integrate_gradients(kernel, centre, pixels, frame_ds, frame_dt, lx, ly, area):
    """The lobe's integral against the kernel over the nodes ``(N, F, Q)`` and those of its
    derivatives (:func:`_lobe_gradients`): ``(N, F)``, ``(N, F, 3)``, ``(N, F, 3)``."""
    density = area * kernel.density_xy(lx, ly, centre[..., None, :])
    lobe, d_n, d_shape = _lobe_gradients(lx, ly, pixels, frame_ds, frame_dt)
    value = (density * lobe).sum(-1)

    def integral(parts):
        return _stack(tuple(None if c is None else (density * c).sum(-1) for c in parts), value)

    return value, integral(d_n), integral(d_shape)


FIXED_SIZES.update({_integrate_gradients, _integrate_fallback})
