"""Jacobians of :func:`torchspec.render.render` for fitting, two ways.

The parameters of a pixel, in this order (``P = 2 + C + C_s + 3``):

    a, b          the normal's tilt angles (:func:`torchspec.geometry.normal_from_angles`)
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
  (:func:`torchspec.lights.clamped_diffuse`).

A fit may take fewer nodes (``order``, ``reference_order``, ``clamp="fast"``: ``torchspec.fit``'s
``quadrature``) and fuse the node loops with ``torch.compile`` (``compile``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .brdf import SVBRDF
from .geometry import angles_from_normal, normal_derivative, normal_from_angles
from .lights import Lights, diffuse_directions
from .render import (
    BUDGET,
    CLAMPS,
    FAST_ORDER,
    FIXED_SIZES,
    REFERENCE_ORDER,
    _at_nodes,
    _diffuse,
    _fallback,
    _fast_rule,
    _fused,
    _pick,
    _pixels,
    _rules,
    choose_path,
    render,
)

__all__ = ["jacobian", "normal_equations", "sandwich_terms", "parameters", "MODES"]

MODES = ("analytic", "forward")


def parameters(svbrdf: SVBRDF) -> Tensor:
    """The parameter vectors ``(*, P)`` of ``svbrdf`` in the order of this module."""
    rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(svbrdf.normal[..., 0])
    parts = [angles_from_normal(svbrdf.normal), svbrdf.diffuse, svbrdf.specular, svbrdf.roughness, rotation[..., None]]
    if svbrdf.specular2 is not None:
        parts += [svbrdf.specular2, svbrdf.roughness2]
    return torch.cat(parts, -1)


def _svbrdf(params: Tensor, channels: tuple[str, ...], grey: bool, second: int | None = None) -> SVBRDF:
    """The SVBRDF of :func:`parameters`; ``second``: the second lobe's ``k_s`` count, if it has one."""
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
    path: str = "auto",
    order: int | None = None,
    diffuse_only: bool = False,
    clamp: str = "exact",
    compile: bool = False,
    reference_order: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Values and Jacobian of :func:`torchspec.render.render` with respect to each pixel's
    parameters (:func:`parameters`).

    Args:
        svbrdf: leading dims ``*``, ``C`` channels; ``rotation`` may be ``None`` (0).
        lights, view, path: as for :func:`torchspec.render.render`.
        mode: ``analytic`` or ``forward``.
        order: Gauss-Hermite nodes per axis of the fast rule (``FAST_ORDER`` by default), as
            for :func:`torchspec.render.render`; the analytic mode only.
        diffuse_only: the model without its lobe (``k_s`` taken as 0, the lobe not integrated):
            the values and the same columns, those of ``k_s`` and the lobe's shape being 0.
            Analytic mode only.
        clamp: the rule of the diffuse clamp (:data:`torchspec.render.CLAMPS`): ``exact``, the
            renderer's, or ``fast``, a fit's. Analytic mode only.
        reference_order: radii of the reference rule (``REFERENCE_ORDER`` by default; a tabulated
            kernel's two per pixel of its table at least), as ``order``.
        compile: fuse the integrations over nodes with ``torch.compile`` (3-4x faster on the
            CPU, after a one-off compilation of ~50 s, ~10 s from torch's cache). Analytic mode only.

    Returns:
        ``(values (*, K, C), jacobian (*, K, C, P))``.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}; got {mode!r}.")
    if clamp not in CLAMPS:
        raise ValueError(f"clamp must be one of {sorted(CLAMPS)}; got {clamp!r}.")
    custom = diffuse_only or order is not None or reference_order is not None or clamp != "exact" or compile
    if custom and mode != "analytic":
        raise ValueError("diffuse_only, order, reference_order, clamp and compile need mode='analytic'.")
    for name, value in (("order", order), ("reference_order", reference_order)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be >= 1; got {value}.")
    lead = svbrdf.shape
    flat = svbrdf.flatten()
    grey = flat.specular.shape[-1] == 1 and flat.diffuse.shape[-1] != 1
    second = None if flat.specular2 is None else flat.specular2.shape[-1]
    params = parameters(flat)
    chunk = _chunk(lights.directions.shape[0], order)
    values = jacs = None  # filled in place: the Jacobian is the largest tensor of a fit, held once
    for start in range(0, max(params.shape[0], 1), chunk):  # one (empty) chunk for no pixels
        part = params[start : start + chunk]
        if mode == "forward":

            def forward(p):
                return render(_svbrdf(p, flat.channels, grey, second), lights, view, path=path)

            eye = torch.eye(part.shape[-1], dtype=part.dtype, device=part.device)
            columns = []
            for j in range(part.shape[-1]):
                value, column = torch.func.jvp(forward, (part,), (eye[j].expand_as(part),))
                columns.append(column)
            jac = torch.stack(columns, -1)
        else:
            parts = _parts(
                _svbrdf(part, flat.channels, grey, second),
                lights,
                view,
                path,
                diffuse_only,
                (order, reference_order),
                clamp,
                compile,
            )
            value, jac = _assemble(*parts)
        if values is None:
            values = value.new_empty((params.shape[0], *value.shape[1:]))
            jacs = jac.new_empty((params.shape[0], *jac.shape[1:]))
        values[start : start + chunk] = value
        jacs[start : start + chunk] = jac
    return values.reshape(*lead, *values.shape[1:]), jacs.reshape(*lead, *jacs.shape[1:])


def _chunk(frames: int, order: int | None) -> int:
    """Pixels per chunk. Chunks bound the memory, as render's do (a few hundred MB of node tensors
    at most); smaller ones cost time in per-call overhead (8x smaller took 2x longer, analytic and
    forward)."""
    return max(1, BUDGET // (frames * (order or FAST_ORDER) ** 2))


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
    isotropic lobe. Written like :func:`torchspec.render._lobe_at`, without 3-vectors: fused by
    torch.compile, sums over the nodes of these run 2x faster than of stacked ``(N, F, Q, 3)`` ones.

    ``frame_ds = frame_dt = None`` for isotropic lobes (``alpha_x = alpha_y``): the lobe is then
    ``exp(-(|h|^2 / <h, n>^2 - 1) / alpha^2)`` whatever the tangent frame, so the frame's
    derivatives drop out and the rotation's column is 0 (1.7x faster)."""
    wz, ci, front, (hx, hy, hz), hn = _at_nodes(lx, ly, pixels)
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


def _parts(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    path: str,
    diffuse_only: bool = False,
    order: tuple[int | None, int | None] = (None, None),
    clamp: str = "exact",
    compiled: bool = False,
) -> tuple:
    """Per pixel and frame, what the values and every column are made of (:func:`_assemble`):
    the diffuse and specular integrals, their derivatives in the normal and the lobe's shape,
    ``dn/d(angles)``, the frames' scale and the coefficients."""
    chosen = choose_path(lights, path)
    like = svbrdf.diffuse
    lights = lights.to(dtype=like.dtype, device=like.device)
    view = view.to(dtype=like.dtype, device=like.device)
    kernel, centre = lights.kernel, lights.directions
    rotation = svbrdf.rotation if svbrdf.rotation is not None else torch.zeros_like(svbrdf.normal[:, 0])
    n = svbrdf.normal
    # dn / d(a, b) (N, 3, 2) of n ~ (tan a, tan b, 1).
    dn = normal_derivative(n)

    # Diffuse: <n, d_k> and its gradient d_k; where the clamp acts, the kernel's direction over
    # the part in front of the normal's horizon.
    direction = centre if kernel.kind == "point" else diffuse_directions(lights)
    diffuse, d_diffuse = _diffuse(n, lights, direction, gradient=True, clamp=clamp, compiled=compiled)

    # Specular: the value's nodes, held fixed.
    if diffuse_only:
        spec = torch.zeros_like(diffuse)
        d_spec_n, d_spec_shape = d_diffuse.new_zeros(d_diffuse.shape), d_diffuse.new_zeros(d_diffuse.shape)
        no_lobe = torch.zeros_like(svbrdf.specular)
        svbrdf = SVBRDF(n, svbrdf.diffuse, no_lobe, svbrdf.roughness, rotation, svbrdf.channels)
    else:
        spec, d_spec_n, d_spec_shape = _lobe_parts(svbrdf, lights, view, chosen, order, rotation, compiled)

    scale = lights.scale[None]  # (1, K, C or 1)
    second = ()
    if svbrdf.specular2 is not None and not diffuse_only:
        lobe2 = SVBRDF(n, svbrdf.diffuse, svbrdf.specular2, svbrdf.roughness2, rotation, svbrdf.channels)
        second = (*_lobe_parts(lobe2, lights, view, chosen, order, rotation, compiled), svbrdf.specular2.contiguous())
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


def _lobe_parts(svbrdf: SVBRDF, lights: Lights, view: Tensor, chosen: str, order, rotation, compiled: bool) -> tuple:
    """The lobe's integrals ``(N, K)`` and their derivatives in the normal and its shape
    ``(N, K, 3)`` (:func:`_parts`), on the path ``chosen``."""
    kernel, centre = lights.kernel, lights.directions
    n = svbrdf.normal
    isotropic = bool((svbrdf.roughness[:, 0] == svbrdf.roughness[:, 1]).all())
    frames = (None, None) if isotropic else _frame_derivatives(n, rotation)
    if chosen == "point":
        pixels = _pixels(svbrdf, view)
        frame_ds, frame_dt = frames
        lx, ly = centre[None, :, None, 0], centre[None, :, None, 1]
        lobe, d_n, d_shape = _lobe_gradients(lx, ly, pixels, frame_ds, frame_dt)
        spec = lobe[..., 0]
        d_spec_n = _stack(tuple(c[..., 0] for c in d_n), spec)
        d_spec_shape = _stack(tuple(None if c is None else c[..., 0] for c in d_shape), spec)
    else:
        pixels = _pixels(svbrdf, view)
        frame_ds, frame_dt = frames
        orders = {"fast": order[0] or FAST_ORDER, "reference": order[1] or REFERENCE_ORDER}
        if kernel.kind == "tabulated":
            orders["reference"] = max(orders["reference"], 2 * max(kernel.table.shape))
        if chosen == "reference":
            rule, fallback = _rules(kernel, centre, pixels, chosen, orders)
            spec, d_spec_n, d_spec_shape = _fused(_integrate_gradients, compiled, n.shape[0])(
                kernel, centre[None], pixels, frame_ds, frame_dt, *(r.detach() for r in rule)
            )
        else:  # the fast rule's nodes, then their integration: one pass each when fused (in one,
            # the compiler computes the pairs' moments again for each node and output: ~20x slower)
            lx, ly, area, reaches = _fused(_fast_rule, compiled, n.shape[0])(
                kernel, centre[None], pixels, orders["fast"]
            )
            spec, d_spec_n, d_spec_shape = _fused(_integrate_gradients, compiled, n.shape[0])(
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
            fallback = _fallback(kernel, centre, pixels, reaches, orders["reference"], compiled) if auto else None
        if fallback is not None:
            # Broadcast unlike the main call: compiled apart (a second compilation, once).
            p, k, rule = fallback
            value, d_value_n, d_value_shape = _fused(_integrate_fallback, compiled, p.shape[0])(
                kernel,
                centre[k][:, None],
                _pick(pixels, p),
                None if isotropic else frame_ds[p],
                None if isotropic else frame_dt[p],
                *(r.detach() for r in rule),
            )
            spec = spec.index_put((p, k), value[:, 0])
            d_spec_n = d_spec_n.index_put((p, k), d_value_n[:, 0])
            d_spec_shape = d_spec_shape.index_put((p, k), d_value_shape[:, 0])

    return spec, d_spec_n, d_spec_shape


def _assemble(diffuse, d_diffuse, spec, d_spec_n, d_spec_shape, dn, scale, k_d, k_s, *second) -> tuple[Tensor, Tensor]:
    """Values ``(N, K, C)`` and the Jacobian ``(N, K, C, 2 + C + C_s + 3)`` from :func:`_parts`
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


def _normal(parts: tuple, observed: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``0.5 |r|^2 (N,)``, ``J^T J`` and ``J^T r`` of ``r = weight (value - observed)`` in all of
    :func:`_assemble`'s columns, ``J = weight dvalue/dparams`` (one pass over the frames when
    fused; every model shares the compiled code, and picks its columns after)."""
    value, jac = _assemble(*parts)
    r = (value - observed) * weight
    js = jac * weight[..., None]
    return 0.5 * (r * r).sum((1, 2)), torch.einsum("nkcp,nkcq->npq", js, js), torch.einsum("nkcp,nkc->np", js, r)


def _normal_gram(parts: tuple, observed: Tensor, weight: Tensor, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_normal` for ``torch.compile``, already in the model's parameters: the same sums from the
    nine quantities per pixel and frame that every column is made of (the diffuse and specular
    integrals, their derivatives in the two angles and the lobe's shape), without the Jacobian.

    ``J^T J = sum_c S_c^T A_c G_c A_c^T S_c`` with ``G_c = sum_k w_c^2 f f^T`` the Gram matrix of
    the quantities ``f`` (9 x 9 per channel), ``A_c`` the seven rows of channel ``c``'s Jacobian
    (angles, its ``k_d``, its ``k_s``, shape) as combinations of them (the coefficients), and
    ``S_c = rows[0, c]`` those rows as the model's parameters (:func:`_channel_rows`). Each sum over
    the frames is one fused reduction: 4x faster than :func:`_normal` compiled (its Jacobian and
    its contraction by batched products of small matrices), within float rounding of it.
    """
    diffuse, d_diffuse, spec, d_spec_n, d_spec_shape, dn, scale, k_d, k_s = parts
    value = (k_d[:, None, :] / math.pi * diffuse[..., None] + k_s[:, None, :] * spec[..., None]) * scale
    r = (value - observed) * weight
    ws = weight * scale  # (N, K, C): each sample's weight in the columns
    # Sums over the last axis, not products of small matrices (which the compiler leaves as bmm calls).
    diffuse_angles = (d_diffuse[..., None] * dn[:, None]).sum(-2)  # (N, K, 2)
    spec_angles = (d_spec_n[..., None] * dn[:, None]).sum(-2)
    f = torch.cat([diffuse[..., None], spec[..., None], diffuse_angles, spec_angles, d_spec_shape], -1)  # (N, K, 9)
    gram = ((ws * ws)[..., None, None] * (f[:, :, None, :, None] * f[:, :, None, None, :])).sum(1)  # (N, C, 9, 9)
    moment = ((ws * r)[..., None] * f[:, :, None, :]).sum(1)  # (N, C, 9)
    kd, ks = k_d / math.pi, k_s.expand_as(k_d)  # (N, C)
    z, one = torch.zeros_like(kd), torch.ones_like(kd)
    coefficients = torch.stack(  # (N, C, 7, 9); stacked, 1.3x faster than columns built directly
        [
            torch.stack([z, z, kd, z, ks, z, z, z, z], -1),  # the angles: k_d / pi dD + k_s dS
            torch.stack([z, z, z, kd, z, ks, z, z, z], -1),
            torch.stack([one / math.pi, z, z, z, z, z, z, z, z], -1),  # k_d: D / pi
            torch.stack([z, one, z, z, z, z, z, z, z], -1),  # k_s: S
            torch.stack([z, z, z, z, z, z, ks, z, z], -1),  # the shape: k_s dS
            torch.stack([z, z, z, z, z, z, z, ks, z], -1),
            torch.stack([z, z, z, z, z, z, z, z, ks], -1),
        ],
        -2,
    )
    columns = (rows[:, :, :, :, None] * coefficients[:, :, :, None, :]).sum(2)  # (N, C, P, 9)
    half = (columns[..., :, None, :] * gram[:, :, None, :, :]).sum(-1)  # (N, C, P, 9)
    hess = (half[:, :, :, None, :] * columns[:, :, None, :, :]).sum((1, -1))
    grad = (columns * moment[:, :, None, :]).sum((1, -1))
    return 0.5 * (r * r).sum((1, 2)), hess, grad


def _channel_rows(select: Tensor, channels: int, grey: bool) -> Tensor:
    """``(C, 7, P)``: the seven columns of channel ``c``'s Jacobian that are not 0 (the two angles,
    its ``k_d``, its ``k_s`` or the grey one, the lobe's shape) as the model's parameters ``select``."""
    last, ks = select.shape[0], 2 + channels
    picks = [[0, 1, 2 + c, ks if grey else ks + c, last - 3, last - 2, last - 1] for c in range(channels)]
    return select[torch.tensor(picks, device=select.device)]


def normal_equations(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    observed: Tensor,
    weight: Tensor,
    select: Tensor,
    *,
    path: str = "auto",
    order: int | None = None,
    reference_order: int | None = None,
    diffuse_only: bool = False,
    clamp: str = "exact",
    compile: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """The least-squares normal equations of ``r = weight (render - observed)`` in the parameters
    ``params @ select``, without the Jacobian ``(N, K, C, P)`` in memory: what Levenberg-Marquardt
    needs (:class:`torchspec.lm.NormalEquations`).

    Args:
        svbrdf: ``N`` pixels (flat), ``C`` channels.
        observed: ``(N, K, C)``; weight: ``(N, K, C)`` (0 drops a sample).
        select: ``(2 + C + C_s + 3, P)``: the model's parameters as combinations of this
            module's columns (:meth:`torchspec.models.Model.selection`).
        path, order, reference_order, diffuse_only, clamp, compile: as for :func:`jacobian`;
            with ``compile`` the assembly and the sums over frames are fused too.

    Returns:
        ``(cost (N,), J^T J (N, P, P), J^T r (N, P))``, ``cost = 0.5 |r|^2``.
    """
    options = dict(path=path, orders=(order, reference_order), diffuse_only=diffuse_only, clamp=clamp, compile=compile)
    return _contract(_normal, svbrdf, lights, view, observed, (weight,), select, gram=_normal_gram, **options)


def _contract(
    function, svbrdf, lights, view, observed, weights, select, *, path, orders, diffuse_only, clamp, compile, gram=None
):
    """``function(parts, observed, *weights) -> (cost, matrix, matrix or vector)`` over chunks of
    pixels, the matrices and vectors taken to the model's columns ``select``; compiled, ``gram``
    instead when given (the same, in the model's columns from :func:`_channel_rows`)."""
    if clamp not in CLAMPS:
        raise ValueError(f"clamp must be one of {sorted(CLAMPS)}; got {clamp!r}.")
    n, k = svbrdf.diffuse.shape[0], lights.directions.shape[0]
    expected = (n, k, svbrdf.diffuse.shape[-1])
    names = ("weight",) if len(weights) == 1 else ("noise_weight", "fit_weight")
    for name, value in zip(("observed", *names), (observed, *weights), strict=True):
        if tuple(value.shape) != expected:
            raise ValueError(f"{name} must have shape {expected}; got {tuple(value.shape)}.")
    chunk = _chunk(k, orders[0])
    # One memory layout for the compiled code whatever the caller's (a weight broadcast over channels, ...).
    observed, weights = observed.contiguous(), [w.contiguous() for w in weights]
    count = svbrdf.diffuse.shape[-1]
    grey = svbrdf.specular.shape[-1] == 1 and count != 1
    channel_rows = None
    if compile and gram is not None and svbrdf.specular2 is None:  # gram: one lobe
        # (1, C, 7, P): a first axis of 1 is never taken for the batch (torchspec.render._compiled),
        # and the models' parameter counts P share one compiled graph.
        channel_rows = _channel_rows(select, count, grey)[None]
        torch._dynamo.maybe_mark_dynamic(channel_rows, 3)
    out = []
    for start in range(0, max(n, 1), chunk):
        part = svbrdf[start : start + chunk]
        parts = _parts(part, lights, view, path, diffuse_only, orders, clamp, compile)
        rows = slice(start, start + chunk)
        if channel_rows is not None and part.diffuse.shape[0] > 1:
            out.append(
                _fused(gram, True, part.diffuse.shape[0])(
                    parts, observed[rows], *[w[rows] for w in weights], channel_rows
                )
            )
            continue
        fused = _fused(function, compile, part.diffuse.shape[0])
        cost, first, second, *rest = fused(parts, observed[rows], *[w[rows] for w in weights])
        second = second @ select if second.dim() == 2 else select.T @ second @ select
        out.append((cost, select.T @ first @ select, second, *rest))
    return tuple(torch.cat(column) for column in zip(*out, strict=True))


def _sandwich(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``0.5 chi^2 (N,)`` with ``noise`` (one over each sample's noise), then ``J^T W^2 J`` and
    ``J^T W^2 S W^2 J`` with ``W`` the fit's weights and ``S`` the samples' variances (in one pass)."""
    return _sandwich_sums(*_assemble(*parts), observed, noise, fit)[:3]


def _sandwich_sums(value: Tensor, jac: Tensor, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple:
    """:func:`_sandwich`'s sums from the values and the Jacobian, and the noise-weighted residual."""
    r = (value - observed) * noise
    sigma = torch.where(noise > 0, 1.0 / torch.where(noise > 0, noise, torch.ones_like(noise)), torch.zeros_like(noise))
    bread = jac * fit[..., None]
    meat = bread * (fit * sigma)[..., None]
    return (
        0.5 * (r * r).sum((1, 2)),
        torch.einsum("nkcp,nkcq->npq", bread, bread),
        torch.einsum("nkcp,nkcq->npq", meat, meat),
        r,
    )


def _sandwich_samples(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple:
    """:func:`_sandwich`, and per sample ``(N, K)``: the squared residual in units of the noise summed
    over channels, and the mean over the valid channels of the samples less the diffuse part; then
    the lobe's signal-to-noise ratio ``(N,)``, the norm of its part of the values in noise units."""
    value, jac = _assemble(*parts)
    cost, bread, meat, r = _sandwich_sums(value, jac, observed, noise, fit)
    diffuse, _, spec, _, _, _, scale, k_d, k_s, *second = parts
    valid = (noise > 0).to(observed.dtype)
    lambertian = k_d[:, None, :] / math.pi * diffuse[..., None] * scale
    excess = ((observed - lambertian) * valid).sum(-1) / valid.sum(-1).clamp(min=1.0)
    lobe = k_s[:, None, :] * spec[..., None]
    if second:  # both lobes
        lobe = lobe + second[3][:, None, :] * second[0][..., None]
    lobe = lobe * scale * noise  # the lobes' part, in units of the noise
    return cost, bread, meat, (r * r).sum(-1), excess, (lobe * lobe).sum((1, 2)).sqrt()


def sandwich_terms(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    observed: Tensor,
    noise_weight: Tensor,
    fit_weight: Tensor,
    select: Tensor,
    *,
    path: str = "auto",
    order: int | None = None,
    reference_order: int | None = None,
    diffuse_only: bool = False,
    clamp: str = "exact",
    compile: bool = False,
    samples: bool = False,
) -> tuple[Tensor, ...]:
    """What the covariance of a weighted least-squares estimate needs, in one pass over the frames:
    the estimate minimised ``|W (render - observed)|^2`` (``W = fit_weight``) while each sample has
    the variance ``1 / noise_weight^2``; its covariance is ``A^-1 B A^-1`` (the sandwich; the
    inverse Fisher information when ``W`` is ``noise_weight``).

    Args:
        svbrdf, lights, view, observed, select, path, order, reference_order, diffuse_only, clamp,
            compile: as for :func:`normal_equations`.
        noise_weight: ``(N, K, C)`` one over each sample's noise (0 drops a sample).
        fit_weight: ``(N, K, C)`` the weights the estimate was fitted with.
        samples: also return, per sample ``(N, K)``, the squared residual in units of the noise
            (summed over channels) and the samples less the model's diffuse part (mean over the
            valid channels), and per pixel the lobe's signal-to-noise ratio (the norm of the lobe's
            part of the values in units of the noise; both lobes' with a second): what
            :mod:`torchspec.flags` needs, from the same pass.

    Returns:
        ``(0.5 chi^2 (N,), A = J^T W^2 J (N, P, P), B = J^T W^2 S W^2 J (N, P, P))`` with ``chi^2``
        the residual in units of the noise and ``S`` the samples' variances; with ``samples``,
        then ``z2 (N, K)``, ``excess (N, K)`` and ``lobe_snr (N,)``.
    """
    options = dict(path=path, orders=(order, reference_order), diffuse_only=diffuse_only, clamp=clamp, compile=compile)
    function = _sandwich_samples if samples else _sandwich
    return _contract(function, svbrdf, lights, view, observed, (noise_weight, fit_weight), select, **options)


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
