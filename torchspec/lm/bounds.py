"""Bounds by reparametrisation for :func:`torchspec.lm.solve`: each column of the ``(N, P)``
parameters is a function ``x = f(u)`` of an unconstrained ``u`` (:class:`Bounds`), and
:func:`bounded` turns a residual function of ``x`` into one of ``u`` by the chain rule."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..config import ConfigError
from ..errors import TorchspecError
from .solver import NormalEquations, ResidualFn

__all__ = ["Bounds", "bounded"]

_KINDS = ("free", "positive", "nonnegative", "interval")


@dataclass(frozen=True)
class Bounds:
    """Per-column reparametrisations ``x = f(u)`` of ``(N, P)`` parameters, ``u`` unconstrained.

    Each entry of ``kinds`` describes one column:

    - ``"free"``: ``x = u``;
    - ``"positive"``: ``x = exp(u)``, ``x > 0``, for scale parameters spanning decades;
    - ``"nonnegative"``: ``x = softplus(u) = log(1 + exp(u))``, ``x > 0``, linear for large ``u``
      (gentler far from 0 than ``exp``);
    - ``("interval", lo, hi)``: ``x = lo + (hi - lo) sigmoid(u)``, ``lo < x < hi``, finite
      ``lo < hi``. A list ``["interval", lo, hi]`` (as from YAML) is accepted and stored as a tuple.

    Values on or beyond a bound have no preimage: :meth:`to_free` first clamps them into the open
    domain (``x >= tiny`` for ``positive`` and ``nonnegative``, ``eps <= (x - lo) / (hi - lo) <=
    1 - eps`` for ``interval``, with the dtype's ``finfo``). A start that close to a bound moves
    away only slowly (the derivative ``dx/du`` vanishes there): start inside.

    Example:
        >>> bounds = Bounds(("free", "positive", ("interval", 0.0, 1.0)))
        >>> x = torch.tensor([[-1.0, 2.0, 0.25]], dtype=torch.float64)
        >>> torch.allclose(bounds.from_free(bounds.to_free(x))[0], x)
        True
    """

    kinds: tuple

    def __post_init__(self) -> None:
        if isinstance(self.kinds, (str, bytes)) or not hasattr(self.kinds, "__iter__"):
            raise ConfigError(f"Bounds.kinds must be a sequence with one entry per column; got {self.kinds!r}.")
        kinds = []
        for j, kind in enumerate(self.kinds):
            if isinstance(kind, (tuple, list)) and len(kind) == 3 and kind[0] == "interval":
                lo, hi = kind[1], kind[2]
                numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (lo, hi))
                if not numbers or not (-math.inf < lo < hi < math.inf):
                    raise ConfigError(
                        f"Bounds.kinds[{j}] must be ('interval', lo, hi) with finite numbers lo < hi; got {kind!r}."
                    )
                kinds.append(("interval", float(lo), float(hi)))
            elif isinstance(kind, str) and kind in _KINDS[:3]:
                kinds.append(kind)
            else:
                raise ConfigError(
                    f"Bounds.kinds[{j}] must be 'free', 'positive', 'nonnegative' or ('interval', lo, hi); "
                    f"got {kind!r}."
                )
        object.__setattr__(self, "kinds", tuple(kinds))

    def _check(self, value: Tensor, name: str) -> None:
        if not isinstance(value, Tensor) or value.ndim != 2 or value.shape[-1] != len(self.kinds):
            shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise TorchspecError(f"{name} must have shape (N, P = {len(self.kinds)}) for these Bounds; got {shape}.")

    def to_free(self, x: Tensor) -> Tensor:
        """Unconstrained ``u (N, P)`` with ``from_free(u) = x (N, P)``, after clamping ``x`` into the domain."""
        self._check(x, "x")
        finfo = torch.finfo(x.dtype)
        columns = []
        for j, kind in enumerate(self.kinds):
            v = x[:, j]
            if kind == "free":
                u = v
            elif kind == "positive":
                u = v.clamp(min=finfo.tiny).log()
            elif kind == "nonnegative":
                v = v.clamp(min=finfo.tiny)
                u = v + torch.log(-torch.expm1(-v))  # log(expm1(v)), stable for small and large v
            else:
                _, lo, hi = kind
                t = ((v - lo) / (hi - lo)).clamp(min=finfo.eps, max=1.0 - finfo.eps)
                u = t.log() - torch.log1p(-t)
            columns.append(u)
        return torch.stack(columns, -1)

    def from_free(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Constrained ``x (N, P)`` and the derivative ``dx/du (N, P)`` of each column at ``u (N, P)``."""
        self._check(u, "u")
        values, slopes = [], []
        for j, kind in enumerate(self.kinds):
            v = u[:, j]
            if kind == "free":
                x, dx = v, torch.ones_like(v)
            elif kind == "positive":
                x = v.exp()
                dx = x
            elif kind == "nonnegative":
                # softplus without torch's linear threshold, accurate to the last bit for all u
                x = v.clamp(min=0) + torch.log1p(torch.exp(-v.abs()))
                dx = torch.sigmoid(v)
            else:
                _, lo, hi = kind
                s = torch.sigmoid(v)
                x = lo + (hi - lo) * s
                dx = (hi - lo) * s * torch.sigmoid(-v)
            values.append(x)
            slopes.append(dx)
        return torch.stack(values, -1), torch.stack(slopes, -1)


def bounded(residual_fn: ResidualFn, bounds: Bounds) -> ResidualFn:
    """``residual_fn`` in ``x``-space as a residual function of the free parameters ``u``.

    The returned function maps ``(u (M, P), index (M,))`` to ``r(x(u))`` and ``J_x * dx/du``
    (the chain rule, column by column), or to the :class:`NormalEquations` of those when
    ``residual_fn`` returns normal equations. Solve in ``u`` and map the result back.

    Args:
        residual_fn: ``(x (M, P), index (M,)) -> (residuals (M, R), jacobian (M, R, P))`` in ``x``.
        bounds: the reparametrisation of each column.

    Returns:
        The same kind of function, in ``u``.

    Example:
        >>> from torchspec.lm import solve
        >>> bounds = Bounds(("positive",))
        >>> def residual_fn(x, index):  # unconstrained optimum x = -1; bounded, x -> 0+
        ...     return x + 1.0, torch.ones_like(x)[:, :, None]
        >>> result = solve(bounded(residual_fn, bounds), bounds.to_free(torch.ones(1, 1, dtype=torch.float64)))
        >>> x = bounds.from_free(result.params)[0]  # exp(u) may underflow to the bound itself
        >>> bool((x >= 0).all() and (x < 1e-3).all())
        True
    """

    def free_residual_fn(u: Tensor, index: Tensor) -> tuple[Tensor, Tensor] | NormalEquations:
        x, dx = bounds.from_free(u)
        out = residual_fn(x, index)
        if isinstance(out, NormalEquations):  # J dx: dx J^T J dx and dx J^T r
            hess, grad = out.hess, out.grad
            if not isinstance(hess, Tensor) or hess.ndim != 3 or hess.shape[-1] != dx.shape[-1]:
                shape = tuple(hess.shape) if isinstance(hess, Tensor) else type(hess).__name__
                raise TorchspecError(
                    f"residual_fn's NormalEquations.hess must have shape (M, {u.shape[1]}, {u.shape[1]}); got {shape}."
                )
            return NormalEquations(out.cost, hess * dx[:, :, None] * dx[:, None, :], grad * dx)
        r, jac = out
        if not isinstance(jac, Tensor) or jac.ndim != 3 or jac.shape[-1] != dx.shape[-1]:
            shape = tuple(jac.shape) if isinstance(jac, Tensor) else type(jac).__name__
            raise TorchspecError(
                f"residual_fn's jacobian must have shape (M, R, P) = ({u.shape[0]}, R, {u.shape[1]}); got {shape}."
            )
        return r, jac * dx[:, None, :]

    return free_residual_fn
