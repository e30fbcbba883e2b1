"""Cramer-Rao bounds: closed forms for locating a lowpass periodic pulse, and the Fisher
information of any differentiable forward model by automatic differentiation.

The closed forms cover the sampling model of :mod:`torchspec.start.fri.pulses`: ``N`` uniform
samples (``N >= 2M + 1`` per axis) of ``s(t) = sum_{|m| <= M} a_m cos(2 pi m (t - x) / tau)``
with white Gaussian noise of std ``sigma``. The ``a_m`` enter only through ``sum m^2 a_m^2``;
unknown amplitudes ``a_m`` (an unknown symmetric kernel) do not raise the bound, because the
derivative with respect to the location is orthogonal to those with respect to real ``a_m``.

References:
    Blu, Dragotti, Vetterli, Marziliano, Coulot, "Sparse sampling of signal innovations",
    IEEE Signal Processing Magazine 2008, Sec. "Uncertainty relation" (one Dirac).
    Kay, "Fundamentals of Statistical Signal Processing: Estimation Theory", ch. 3.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from ..errors import TorchspecError

__all__ = ["location_1d", "location_2d", "fisher_information", "bound"]


def _positive(name: str, value) -> None:
    if isinstance(value, Tensor):
        if not bool((value > 0).all()):
            raise TorchspecError(f"{name} must be > 0; got a tensor with values <= 0.")
    elif not value > 0:
        raise TorchspecError(f"{name} must be > 0; got {value!r}.")


def location_1d(spectrum: Tensor, *, num_samples: int, noise_sigma: float | Tensor, period: float = 1.0) -> Tensor:
    """Variance bound of the location of a lowpass periodic pulse from uniform samples.

    ``CRB(x) = tau^2 sigma^2 / (8 pi^2 N sum_{m=1}^{M} m^2 a_m^2)``.

    Args:
        spectrum: ``(*, M + 1)``: ``a_0..a_M`` of the sampled signal (amplitude included).
        num_samples: ``N >= 2M + 1``.
        noise_sigma: per-sample noise std, a number or a tensor broadcasting with ``*``.
        period: ``tau``.

    Returns:
        ``(*)`` variance of any unbiased estimate of the location, in ``period`` units squared.

    Example:
        >>> from torchspec.start.fri import pulses
        >>> a = pulses.spectrum("gaussian", torch.tensor(0.05, dtype=torch.float64), 8)
        >>> float(location_1d(a, num_samples=17, noise_sigma=0.1)) > 0
        True
    """
    bands = spectrum.shape[-1] - 1
    if num_samples < 2 * bands + 1:
        raise TorchspecError(
            f"num_samples must be >= 2M + 1 = {2 * bands + 1} for a spectrum of shape {tuple(spectrum.shape)}; "
            f"got {num_samples}."
        )
    _positive("noise_sigma", noise_sigma)
    _positive("period", period)
    m = torch.arange(bands + 1, dtype=spectrum.dtype, device=spectrum.device)
    energy = (m**2 * spectrum**2).sum(-1)
    return period**2 * noise_sigma**2 / (8.0 * math.pi**2 * num_samples * energy)


def location_2d(
    spectrum: Tensor,
    *,
    num_samples: Sequence[int],
    noise_sigma: float | Tensor,
    period: Sequence[float] = (1.0, 1.0),
) -> Tensor:
    """Covariance bound of the 2D location of a lowpass periodic pulse on a uniform grid.

    ``J_jk = 4 pi^2 N1 N2 / (sigma^2 tau_j tau_k) sum_m m_j m_k a_m^2``, bound ``J^{-1}``.

    Args:
        spectrum: ``(*, 2 M1 + 1, 2 M2 + 1)`` real, even (see :func:`torchspec.start.fri.pulses.outer`).
        num_samples: ``(N1, N2)``, ``N_j >= 2 M_j + 1``.
        noise_sigma: per-sample noise std.
        period: ``(tau1, tau2)``.

    Returns:
        ``(*, 2, 2)`` covariance bound; its trace bounds the mean squared distance.
    """
    bands = ((spectrum.shape[-2] - 1) // 2, (spectrum.shape[-1] - 1) // 2)
    for axis in range(2):
        if num_samples[axis] < 2 * bands[axis] + 1:
            raise TorchspecError(
                f"num_samples[{axis}] must be >= {2 * bands[axis] + 1} for a spectrum of shape "
                f"{tuple(spectrum.shape)}; got {num_samples[axis]}."
            )
    _positive("noise_sigma", noise_sigma)
    for p in period:
        _positive("period", p)
    like = dict(dtype=spectrum.dtype, device=spectrum.device)
    m1 = torch.arange(-bands[0], bands[0] + 1, **like)[:, None] / period[0]
    m2 = torch.arange(-bands[1], bands[1] + 1, **like)[None, :] / period[1]
    power = spectrum**2
    j11 = (m1 * m1 * power).sum((-2, -1))
    j12 = (m1 * m2 * power).sum((-2, -1))
    j22 = (m2 * m2 * power).sum((-2, -1))
    fisher = torch.stack([torch.stack([j11, j12], -1), torch.stack([j12, j22], -1)], -2)
    noise = torch.as_tensor(noise_sigma, **like)
    fisher = fisher * (4.0 * math.pi**2 * num_samples[0] * num_samples[1]) / noise[..., None, None] ** 2
    return torch.linalg.inv(fisher)


def fisher_information(
    forward: Callable[[Tensor], Tensor], params: Tensor, noise_sigma: float | Tensor
) -> Tensor:
    """Fisher information of ``params`` for Gaussian observations ``forward(params) + noise``.

    ``F = J^T diag(1 / sigma^2) J`` with the Jacobian ``J`` from forward-mode AD (one JVP per
    parameter), batched: ``forward`` maps ``(*, P)`` to ``(*, N)`` and each problem's outputs
    may depend only on its own parameters.

    Args:
        forward: the noise-free model, differentiable with forward-mode AD.
        params: ``(*, P)`` the parameters at which to evaluate.
        noise_sigma: noise std, a number or a tensor broadcasting with ``(*, N)``.

    Returns:
        ``(*, P, P)``.

    Example:
        >>> f = lambda p: p[..., :1] * torch.arange(3.0, dtype=p.dtype)
        >>> fisher_information(f, torch.ones(1, dtype=torch.float64), 1.0)
        tensor([[5.]], dtype=torch.float64)
    """
    if params.dim() < 1:
        raise TorchspecError(f"params must have shape (*, P); got shape {tuple(params.shape)}.")
    _positive("noise_sigma", noise_sigma)
    eye = torch.eye(params.shape[-1], dtype=params.dtype, device=params.device)
    columns = [torch.func.jvp(forward, (params,), (eye[j].expand_as(params),))[1] for j in range(params.shape[-1])]
    jac = torch.stack(columns, -1)  # (*, N, P)
    weight = 1.0 / torch.as_tensor(noise_sigma, dtype=params.dtype, device=params.device) ** 2
    weight = weight.expand(jac.shape[:-1]) if weight.dim() else weight
    return jac.transpose(-1, -2) @ (jac * (weight[..., None] if weight.dim() else weight))


def bound(fisher: Tensor) -> Tensor:
    """The Cramer-Rao covariance bound ``F^{-1}`` ``(*, P, P)``; NaN where ``F`` is singular
    (a parameter the observations do not determine)."""
    inverse, info = torch.linalg.inv_ex(fisher)
    return torch.where((info == 0)[..., None, None], inverse, torch.full_like(inverse, math.nan))
