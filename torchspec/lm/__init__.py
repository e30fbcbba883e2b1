"""Batched Levenberg-Marquardt for many small, independent nonlinear least-squares problems.

- :mod:`torchspec.lm.solver`: :func:`solve`, its settings :class:`LMConfig`, its result
  :class:`LMResult` and the status codes (:data:`STATUS`); the module docstring states the
  algorithm (steps, acceptance, damping, convergence and failure).
- :mod:`torchspec.lm.bounds`: bounds by reparametrisation, :class:`Bounds` and :func:`bounded`.
"""

from .bounds import Bounds, bounded
from .solver import (
    CONVERGED,
    DIVERGED,
    MAX_ITERATIONS,
    SINGULAR,
    STATUS,
    LMConfig,
    LMResult,
    NormalEquations,
    ResidualFn,
    solve,
)

__all__ = [
    "CONVERGED",
    "MAX_ITERATIONS",
    "SINGULAR",
    "DIVERGED",
    "STATUS",
    "LMConfig",
    "LMResult",
    "Bounds",
    "ResidualFn",
    "NormalEquations",
    "bounded",
    "solve",
]
