"""Batched Levenberg-Marquardt for many small, independent nonlinear least-squares problems.

- :mod:`torchspec.lm.solver`: :func:`solve`, its settings :class:`LMConfig`, its result
  :class:`LMResult` and the status codes (:data:`STATUS`); the module docstring states the
  algorithm (steps, acceptance, damping, convergence and failure).
- :mod:`torchspec.lm.bounds`: bounds by reparametrisation, :class:`Bounds` and :func:`bounded`.
- :mod:`torchspec.lm.picks`: a residual function's picks of pairs, of a size fixed at the solver's
  check (no host synchronisation in a step), their overflow seen there and its steps taken again.
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
