"""The sensor's noise: a Poisson-Gaussian model fitted to the fit's own residuals.

A linear camera's recorded value ``y`` has the variance ``a y + b`` (photon shot noise plus
read noise; Foi et al. 2008), the same for every pixel. :func:`affine_noise` fits ``a`` and ``b``
to many pixels' residual sums of squares at once, robustly (a pixel the model does not explain has
a residual above its noise and must not raise everyone's): the per-pixel noise that the model
selection and the standard deviations need then comes from thousands of pixels rather than from the
few samples of one.

References:
    A. Foi, M. Trimeche, V. Katkovnik, K. Egiazarian. Practical Poissonian-Gaussian noise
    modeling and fitting for single-image raw-data. IEEE Trans. Image Processing 17(10), 2008.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["affine_noise"]


def affine_noise(
    sum_squares: Tensor, sum_values: Tensor, count: Tensor, params: Tensor | int, *, iterations: int = 40
) -> tuple[Tensor, Tensor]:
    """Fit ``variance = a value + b`` (``a, b >= 0``) to the residuals of ``N`` fitted pixels.

    Pixel ``p`` left ``sum_squares[p]`` over ``count[p]`` samples whose recorded values sum to
    ``sum_values[p]``, with ``params[p]`` parameters fitted: its mean variance
    ``s = sum_squares / (count - params)`` estimates ``a x + b`` at its mean value
    ``x = sum_values / count``. The line is the least-absolute-deviations fit (by iterative
    reweighting), then scaled so that the mean of ``s / (a x + b)`` over the pixels it explains is 1:
    the median line is robust (half of the pixels lie on either side whatever the other half's
    misfits) but a median of chi^2 values lies below their mean; the pixels a model leaves
    unexplained, ``s / (a x + b) > 1 + 4 sqrt(2 / dof)``, stay out of the mean.

    Args:
        sum_squares, sum_values, count: ``(N,)``; pixels with ``count <= params``, non-finite
            values or no residual at all (``sum_squares == 0``) are left out.
        params: ``(N,)`` or one number.
        iterations: reweighting passes.

    Returns:
        ``(a, b)``, 0-dim tensors of the inputs' dtype and device (zeros when no pixel is usable).

    Example:
        >>> x = torch.linspace(1.0, 10.0, 50, dtype=torch.float64)
        >>> a, b = affine_noise(100 * (0.01 * x + 0.002), 100 * x, torch.full_like(x, 100.0), 0)
        >>> round(float(a), 6), round(float(b), 6)
        (0.01, 0.002)
    """
    dtype, device = sum_squares.dtype, sum_squares.device
    params = torch.as_tensor(params, dtype=dtype, device=device)
    dof = count.to(dtype) - params
    # A pixel left without any residual (all its samples 0, a black border or padding, fitted
    # exactly) says nothing of the noise: a real sensor's never vanishes. Kept, such pixels would pin
    # the line to the origin (0 read noise).
    usable = (dof > 0) & sum_squares.isfinite() & sum_values.isfinite() & (count > 0) & (sum_squares > 0)
    s = (sum_squares / dof.clamp(min=1.0))[usable]
    x = (sum_values / count.to(dtype).clamp(min=1.0))[usable].clamp(min=0.0)
    zero = s.new_zeros(())
    if s.numel() == 0:
        return zero, zero
    tiny = torch.finfo(dtype).tiny
    design = torch.stack([x, torch.ones_like(x)], -1)  # (n, 2)
    # Start from the median ratio (pure shot noise), then reweight towards least absolute deviations.
    a, b = (s / x.clamp(min=tiny)).median(), zero
    typical = s.median().clamp(min=tiny)
    for _ in range(iterations):
        model = (a * x + b).clamp(min=1e-6 * typical)
        weight = 1.0 / (model * ((s - model).abs() / model).clamp(min=1e-3))
        coef = _nonnegative_solve(design, s, weight)
        a, b = coef[0], coef[1]
    ratio = s / (a * x + b).clamp(min=tiny)
    explained = ratio <= 1.0 + 4.0 * (2.0 / dof[usable].clamp(min=1.0)).sqrt()
    gain = torch.where(explained.any(), ratio[explained].mean(), torch.ones_like(a))
    return a * gain, b * gain


def _nonnegative_solve(design: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """``argmin sum w (target - design @ c)^2`` over ``c >= 0`` for two columns: the
    unconstrained solution if non-negative, else the better of the two one-column ones."""
    w = weight / weight.amax().clamp(min=torch.finfo(weight.dtype).tiny)
    weighted = design * w[:, None]
    gram, rhs = weighted.T @ design, weighted.T @ target
    both, info = torch.linalg.solve_ex(gram, rhs)
    diagonal = gram.diagonal().clamp(min=torch.finfo(weight.dtype).tiny)
    single = (rhs / diagonal).clamp(min=0.0)  # each column alone
    loss_single = -(single * rhs) + 0.5 * single * single * diagonal  # loss up to a constant
    only_a = torch.stack([single[0], single.new_zeros(())])
    only_b = torch.stack([single.new_zeros(()), single[1]])
    best_single = torch.where(loss_single[0] <= loss_single[1], only_a, only_b)
    ok = (info == 0) & (both >= 0).all()
    return torch.where(ok, both, best_single)
