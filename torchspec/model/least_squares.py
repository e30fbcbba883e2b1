"""The sums a least-squares fit of the measurement model needs, in one pass over the frames and
without the Jacobian ``(N, K, C, P)`` in memory: the normal equations that Levenberg-Marquardt
solves (:func:`normal_equations`) and the sandwich terms of an estimate's covariance
(:func:`sandwich_terms`), in the parameters ``params @ select`` of a model
(:meth:`torchspec.model.registry.Model.selection`) of :mod:`torchspec.model.jacobian`'s columns.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..errors import TorchspecError
from .brdf import SVBRDF
from .fusion import fused
from .jacobian import assemble, jacobian_parts, pixels_per_chunk
from .lights import Lights
from .quadrature import Quadrature, check_quadrature

__all__ = ["normal_equations", "sandwich_terms", "jacobian_sandwich_terms"]


def _normal(parts: tuple, observed: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``0.5 |r|^2 (N,)``, ``J^T J`` and ``J^T r`` of ``r = weight (value - observed)`` in all of
    :func:`assemble`'s columns, ``J = weight dvalue/dparams`` (one pass over the frames when
    fused; every model shares the compiled code, and picks its columns after)."""
    value, jac = assemble(*parts)
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
    the frames is one fused reduction (no Jacobian, no batched products of small matrices); the
    result equals :func:`_normal`'s within float rounding.
    """
    value, f, scale = _quantities(parts, compiled=True)
    k_d, k_s = parts[7:]
    r = (value - observed) * weight
    ws = weight * scale  # (N, K, C): each sample's weight in the columns
    gram = ((ws * ws)[..., None, None] * (f[:, :, None, :, None] * f[:, :, None, None, :])).sum(1)  # (N, C, 9, 9)
    moment = ((ws * r)[..., None] * f[:, :, None, :]).sum(1)  # (N, C, 9)
    columns = (rows[:, :, :, :, None] * _coefficients(k_d, k_s)[:, :, :, None, :]).sum(2)  # (N, C, P, 9)
    half = (columns[..., :, None, :] * gram[:, :, None, :, :]).sum(-1)  # (N, C, P, 9)
    hess = (half[:, :, :, None, :] * columns[:, :, None, :, :]).sum((1, -1))
    grad = (columns * moment[:, :, None, :]).sum((1, -1))
    return 0.5 * (r * r).sum((1, 2)), hess, grad


def _normal_gram_eager(parts: tuple, observed: Tensor, weight: Tensor, rows: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_normal_gram` without ``torch.compile``: the same sums as batched matrix products
    (``einsum``), from the nine quantities per pixel and frame, never the Jacobian ``(N, K, C, P)``
    nor a product per sample of them: under point lights the Jacobian's assembly and contraction
    are most of a solver step, and this takes 0.55-0.8 of :func:`_normal`'s time on 2048-4096
    pixels (``ward-iso-colour``, 36 lights, CPU), about as much on a few pixels or under a kernel's
    quadrature. Equal to :func:`_normal` within float rounding (``tests/test_models.py``)."""
    value, f, scale, columns = _gram_parts(parts, rows)
    r = (value - observed) * weight
    ws = weight * scale
    moment = torch.einsum("nkc,nki->nci", ws * r, f)  # (N, C, 9)
    return 0.5 * (r * r).sum((1, 2)), _gram_hessian(f, columns, ws), torch.einsum("ncpi,nci->np", columns, moment)


def _quantities(parts: tuple, compiled: bool) -> tuple[Tensor, Tensor, Tensor]:
    """One lobe's values ``(N, K, C)``, the nine quantities ``f (N, K, 9)`` every column of its
    Jacobian is made of (the diffuse and specular integrals, their derivatives in the two angles and
    the lobe's shape) and each sample's scale ``(N, K, C)`` (irradiance, exposure), from
    :func:`~torchspec.model.jacobian.jacobian_parts`; ``compiled``: in the form ``torch.compile`` fuses."""
    diffuse, d_diffuse, spec, d_spec_n, d_spec_shape, dn, scale, k_d, k_s = parts
    value = (k_d[:, None, :] / math.pi * diffuse[..., None] + k_s[:, None, :] * spec[..., None]) * scale
    if compiled:  # sums over the last axis, not products of small matrices (the compiler leaves bmm calls)
        diffuse_angles = (d_diffuse[..., None] * dn[:, None]).sum(-2)  # (N, K, 2)
        spec_angles = (d_spec_n[..., None] * dn[:, None]).sum(-2)
    else:  # eager: a batched product, 5x faster than that sum
        diffuse_angles, spec_angles = d_diffuse @ dn, d_spec_n @ dn
    f = torch.cat([diffuse[..., None], spec[..., None], diffuse_angles, spec_angles, d_spec_shape], -1)
    return value, f, scale


def _gram_parts(parts: tuple, rows: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_quantities` (eager), and the model's columns per channel as combinations of ``f``
    ``(N, C, P, 9)``: the Jacobian of sample ``(k, c)`` is ``scale columns_c f_k`` (``rows``:
    :func:`_channel_rows`)."""
    value, f, scale = _quantities(parts, compiled=False)
    return value, f, scale, torch.einsum("cap,ncaj->ncpj", rows[0], _coefficients(*parts[7:]))


def _gram_hessian(f: Tensor, columns: Tensor, ws: Tensor) -> Tensor:
    """``J^T W^2 J (N, P, P)`` with each sample's weight ``ws (N, K, C)`` (its scale included), from
    :func:`_gram_parts`'s quantities and columns: the Gram matrix of ``f`` per channel, then the columns."""
    gram = torch.einsum("nkci,nkj->ncij", (ws * ws)[..., None] * f[:, :, None, :], f)  # (N, C, 9, 9)
    return torch.einsum("ncpj,ncqj->npq", torch.einsum("ncpi,ncij->ncpj", columns, gram), columns)


def _coefficients(k_d: Tensor, k_s: Tensor) -> Tensor:
    """``(N, C, 7, 9)``: the seven non-zero columns of channel ``c``'s Jacobian (the two angles, its
    ``k_d``, its ``k_s``, the lobe's shape) as combinations of :func:`_normal_gram`'s nine quantities."""
    kd, ks = k_d / math.pi, k_s.expand_as(k_d)  # (N, C)
    z, one = torch.zeros_like(kd), torch.ones_like(kd)
    return torch.stack(
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
    quadrature: Quadrature = Quadrature(),
    diffuse_only: bool = False,
    isotropic: bool | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The least-squares normal equations of ``r = weight (render - observed)`` in the parameters
    ``params @ select``, without the Jacobian ``(N, K, C, P)`` in memory: what Levenberg-Marquardt
    needs (:class:`torchspec.lm.NormalEquations`).

    Args:
        svbrdf: ``N`` pixels (flat), ``C`` channels.
        observed: ``(N, K, C)``; weight: ``(N, K, C)`` (0 drops a sample).
        select: ``(2 + C + C_s + 3, P)``: the model's parameters as combinations of this
            module's columns (:meth:`torchspec.model.registry.Model.selection`).
        quadrature, diffuse_only, isotropic: as for :func:`torchspec.model.jacobian.jacobian`; with
            ``quadrature.compile`` the assembly and the sums over frames are fused too.

    Returns:
        ``(cost (N,), J^T J (N, P, P), J^T r (N, P))``, ``cost = 0.5 |r|^2``.
    """
    options = dict(quadrature=quadrature, diffuse_only=diffuse_only, isotropic=isotropic)
    grams = dict(gram=_normal_gram, gram_eager=_normal_gram_eager)
    return _contract(_normal, svbrdf, lights, view, observed, (weight,), select, **grams, **options)


def _contract(
    function,
    svbrdf,
    lights,
    view,
    observed,
    weights,
    select,
    *,
    quadrature,
    diffuse_only,
    isotropic=None,
    gram=None,
    gram_eager=None,
):
    """``function(parts, observed, *weights) -> (cost, matrix, matrix or vector, ...)`` over chunks of
    pixels, the matrices and vectors taken to the model's columns ``select``; for one lobe, ``gram``
    instead when compiled and ``gram_eager`` when not, where given (the same outputs, already in the
    model's columns: their last argument is :func:`_channel_rows`)."""
    check_quadrature(quadrature)
    compile = quadrature.compile
    n, k = svbrdf.diffuse.shape[0], lights.directions.shape[0]
    expected = (n, k, svbrdf.diffuse.shape[-1])
    names = ("weight",) if len(weights) == 1 else ("noise_weight", "fit_weight")
    for name, value in zip(("observed", *names), (observed, *weights), strict=True):
        if tuple(value.shape) != expected:
            raise TorchspecError(f"{name} must have shape {expected}; got {tuple(value.shape)}.")
    chunk = pixels_per_chunk(k, quadrature)
    # One memory layout for the compiled code whatever the caller's (a weight broadcast over channels, ...).
    observed, weights = observed.contiguous(), [w.contiguous() for w in weights]
    count = svbrdf.diffuse.shape[-1]
    grey = svbrdf.specular.shape[-1] == 1 and count != 1
    channel_rows = None
    if (gram if compile else gram_eager) is not None and svbrdf.specular2 is None:  # grams: one lobe
        # (1, C, 7, P): a first axis of 1 is never taken for the batch (torchspec.model.fusion.compiled),
        # and the models' parameter counts P share one compiled graph.
        channel_rows = _channel_rows(select, count, grey)[None]
        if compile:
            torch._dynamo.maybe_mark_dynamic(channel_rows, 3)
    out = []
    for start in range(0, max(n, 1), chunk):
        part = svbrdf[start : start + chunk]
        parts = jacobian_parts(part, lights, view, quadrature, diffuse_only, isotropic)
        rows = slice(start, start + chunk)
        if channel_rows is not None and compile and part.diffuse.shape[0] > 1:
            out.append(
                fused(gram, True, part.diffuse.shape[0])(
                    parts, observed[rows], *[w[rows] for w in weights], channel_rows
                )
            )
            continue
        if channel_rows is not None and not compile:
            out.append(gram_eager(parts, observed[rows], *[w[rows] for w in weights], channel_rows))
            continue
        sums = fused(function, compile, part.diffuse.shape[0])
        cost, first, second, *rest = sums(parts, observed[rows], *[w[rows] for w in weights])
        second = second @ select if second.dim() == 2 else select.T @ second @ select
        out.append((cost, select.T @ first @ select, second, *rest))
    return tuple(torch.cat(column) for column in zip(*out, strict=True))


def _sandwich(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``0.5 chi^2 (N,)`` with ``noise`` (one over each sample's noise), then ``J^T W^2 J`` and
    ``J^T W^2 S W^2 J`` with ``W`` the fit's weights and ``S`` the samples' variances (in one pass)."""
    return _sandwich_sums(*assemble(*parts), observed, noise, fit)[:3]


def _sandwich_gram(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor, rows: Tensor) -> tuple:
    """:func:`_sandwich` of one lobe in the model's columns ``rows`` (:func:`_channel_rows`), from the
    Gram matrices of :func:`_gram_parts`' quantities (no Jacobian; equal within rounding)."""
    return _sandwich_gram_sums(parts, observed, noise, fit, rows)[:3]


def _sandwich_sums(value: Tensor, jac: Tensor, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple:
    """:func:`_sandwich`'s sums from the values and the Jacobian, and the noise-weighted residual."""
    r = (value - observed) * noise
    bread = jac * fit[..., None]
    meat = bread * (fit * _deviation(noise))[..., None]
    return (
        0.5 * (r * r).sum((1, 2)),
        torch.einsum("nkcp,nkcq->npq", bread, bread),
        torch.einsum("nkcp,nkcq->npq", meat, meat),
        r,
    )


def _sandwich_gram_sums(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor, rows: Tensor) -> tuple:
    """:func:`_sandwich_sums` of one lobe from :func:`_gram_parts` (the values too)."""
    value, f, scale, columns = _gram_parts(parts, rows)
    r = (value - observed) * noise
    bread = fit * scale
    meat = bread * fit * _deviation(noise)
    return 0.5 * (r * r).sum((1, 2)), _gram_hessian(f, columns, bread), _gram_hessian(f, columns, meat), r


def _deviation(noise: Tensor) -> Tensor:
    """Each sample's noise deviation from one over it, ``noise``; 0 where ``noise`` is 0 (dropped)."""
    return torch.where(noise > 0, 1.0 / torch.where(noise > 0, noise, torch.ones_like(noise)), torch.zeros_like(noise))


def _sandwich_samples(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor) -> tuple:
    """:func:`_sandwich`, and per sample ``(N, K)``: the squared residual in units of the noise summed
    over channels, and the mean over the valid channels of the samples less the diffuse part; then
    the lobe's signal-to-noise ratio ``(N,)``, the norm of its part of the values in noise units."""
    value, jac = assemble(*parts)
    cost, bread, meat, r = _sandwich_sums(value, jac, observed, noise, fit)
    return cost, bread, meat, *_sample_terms(parts, r, observed, noise)


def _sandwich_samples_gram(parts: tuple, observed: Tensor, noise: Tensor, fit: Tensor, rows: Tensor) -> tuple:
    """:func:`_sandwich_samples` of one lobe in the model's columns ``rows`` (:func:`_sandwich_gram`)."""
    cost, bread, meat, r = _sandwich_gram_sums(parts, observed, noise, fit, rows)
    return cost, bread, meat, *_sample_terms(parts, r, observed, noise)


def _sample_terms(parts: tuple, r: Tensor, observed: Tensor, noise: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`_sandwich_samples`' per-sample terms from the noise-weighted residual ``r``."""
    diffuse, _, spec, _, _, _, scale, k_d, k_s, *second = parts
    lambertian = k_d[:, None, :] / math.pi * diffuse[..., None] * scale
    lobe = k_s[:, None, :] * spec[..., None]
    if second:  # both lobes
        lobe = lobe + second[3][:, None, :] * second[0][..., None]
    return _per_sample(r, observed, noise, lambertian, lobe * scale)


def _per_sample(r: Tensor, observed: Tensor, noise: Tensor, lambertian: Tensor, lobe: Tensor) -> tuple:
    """``z2 (N, K)``, ``excess (N, K)`` and ``lobe_snr (N,)`` (:func:`sandwich_terms`' ``samples``)
    from the noise-weighted residual ``r``, the diffuse part of the values ``lambertian`` and the
    lobes' part ``lobe`` (all ``(N, K, C)``)."""
    valid = (noise > 0).to(observed.dtype)
    excess = ((observed - lambertian) * valid).sum(-1) / valid.sum(-1).clamp(min=1.0)
    lobe = lobe * noise  # the lobes' part, in units of the noise
    return (r * r).sum(-1), excess, (lobe * lobe).sum((1, 2)).sqrt()


def jacobian_sandwich_terms(
    value: Tensor,
    jac: Tensor,
    diffuse: Tensor,
    observed: Tensor,
    noise_weight: Tensor,
    fit_weight: Tensor,
    *,
    samples: bool = False,
) -> tuple[Tensor, ...]:
    """:func:`sandwich_terms` from the values ``value (N, K, C)`` and their Jacobian ``jac
    (N, K, C, P)`` already in the model's parameters (any lobe's:
    :meth:`torchspec.model.registry.Model.forward_jacobian`), and the values' diffuse part ``diffuse
    (N, K, C)`` (the lobes' part is ``value - diffuse``); the same outputs, from the same sums.

    Example:
        >>> one = torch.ones(1, 2, 1, dtype=torch.float64)
        >>> cost, a, b = jacobian_sandwich_terms(one, one[..., None], 0 * one, 0 * one, one, one)
        >>> float(cost), float(a), float(b)
        (1.0, 2.0, 2.0)
    """
    cost, bread, meat, r = _sandwich_sums(value, jac, observed, noise_weight, fit_weight)
    if not samples:
        return cost, bread, meat
    return cost, bread, meat, *_per_sample(r, observed, noise_weight, diffuse, value - diffuse)


def sandwich_terms(
    svbrdf: SVBRDF,
    lights: Lights,
    view: Tensor,
    observed: Tensor,
    noise_weight: Tensor,
    fit_weight: Tensor,
    select: Tensor,
    *,
    quadrature: Quadrature = Quadrature(),
    diffuse_only: bool = False,
    samples: bool = False,
) -> tuple[Tensor, ...]:
    """What the covariance of a weighted least-squares estimate needs, in one pass over the frames:
    the estimate minimised ``|W (render - observed)|^2`` (``W = fit_weight``) while each sample has
    the variance ``1 / noise_weight^2``; its covariance is ``A^-1 B A^-1`` (the sandwich; the
    inverse Fisher information when ``W`` is ``noise_weight``).

    Args:
        svbrdf, lights, view, observed, select, quadrature, diffuse_only: as for
            :func:`normal_equations`.
        noise_weight: ``(N, K, C)`` one over each sample's noise (0 drops a sample).
        fit_weight: ``(N, K, C)`` the weights the estimate was fitted with.
        samples: also return, per sample ``(N, K)``, the squared residual in units of the noise
            (summed over channels) and the samples less the model's diffuse part (mean over the
            valid channels), and per pixel the lobe's signal-to-noise ratio (the norm of the lobe's
            part of the values in units of the noise; both lobes' with a second): what
            :mod:`torchspec.pipeline.flags` needs, from the same pass.

    Returns:
        ``(0.5 chi^2 (N,), A = J^T W^2 J (N, P, P), B = J^T W^2 S W^2 J (N, P, P))`` with ``chi^2``
        the residual in units of the noise and ``S`` the samples' variances; with ``samples``,
        then ``z2 (N, K)``, ``excess (N, K)`` and ``lobe_snr (N,)``.
    """
    options = dict(quadrature=quadrature, diffuse_only=diffuse_only)
    function, eager = (_sandwich_samples, _sandwich_samples_gram) if samples else (_sandwich, _sandwich_gram)
    weights = (noise_weight, fit_weight)
    return _contract(function, svbrdf, lights, view, observed, weights, select, gram_eager=eager, **options)

