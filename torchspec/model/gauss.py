"""Gauss rules, tabulated once as float64 tensors: :func:`legendre` (Gauss-Legendre on ``[-1, 1]``)
and :func:`hermite` (2D standard-normal Gauss-Hermite), and the tables they read (:func:`gauss_table`,
:func:`gauss_rule`). The light kernels (:mod:`torchspec.model.lights`), the node rules
(:mod:`torchspec.model.nodes`) and the diffuse clamp (:mod:`torchspec.model.diffuse`) take their nodes here;
:mod:`torchspec.model.quadrature` re-exports them. This module imports nothing of the package.

torch.compile takes a module's tensors as inputs of its graph, where Python floats would each
become a symbolic input and a ``torch.tensor`` call in a graph would keep it out of the AOT-autograd
cache.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = ["gauss_table", "gauss_rule", "legendre", "hermite"]


def _rule_tensors(rule, order: int) -> tuple[Tensor, Tensor]:
    """``rule(order)``'s nodes and weights as float64 tensors."""
    x, w = rule(order)
    return torch.from_numpy(np.asarray(x, dtype=np.float64)), torch.from_numpy(np.asarray(w, dtype=np.float64))


def gauss_table(rule, orders: range) -> dict[int, tuple[Tensor, Tensor]]:
    """``rule(order) -> (nodes, weights)`` (numpy) tabulated as float64 tensors for ``orders``."""
    return {n: _rule_tensors(rule, n) for n in orders}


def gauss_rule(table: dict, rule, order: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """The nodes and weights of ``order`` from ``table`` (else computed by ``rule``, which
    torch.compile cannot trace: the graph splits there), in the dtype and on the device of
    ``like``."""
    x, w = table[order] if order in table else _rule_tensors(rule, order)
    return x.to(dtype=like.dtype, device=like.device), w.to(dtype=like.dtype, device=like.device)


def _standard_hermite(order: int):
    """The standard-normal rule (weights summing to 1) in float64."""
    x, w = np.polynomial.hermite.hermgauss(order)
    return x * math.sqrt(2.0), w / math.sqrt(math.pi)


_LEGENDRE = gauss_table(np.polynomial.legendre.leggauss, range(1, 65))
_HERMITE = gauss_table(_standard_hermite, range(1, 33))


def legendre(order: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Gauss-Legendre nodes and weights ``(order,)`` on ``[-1, 1]``, in the dtype and on the
    device of ``like``.

    Example:
        >>> x, w = legendre(3, torch.zeros(1, dtype=torch.float64))
        >>> round(float(w.sum()), 12), round(float((w * x**4).sum()), 12)  # exact to degree 5
        (2.0, 0.4)
    """
    return gauss_rule(_LEGENDRE, np.polynomial.legendre.leggauss, order, like)


def hermite(order: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """2D standard-normal Gauss-Hermite rule: points ``(Q, 2)``, ``Q = order^2``, and weights
    ``(Q,)`` summing to 1, in the dtype and on the device of ``like``."""
    x, w = gauss_rule(_HERMITE, _standard_hermite, order, like)
    grid = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    return grid, (w[:, None] * w[None, :]).reshape(-1)
