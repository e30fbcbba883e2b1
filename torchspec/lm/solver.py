"""Batched Levenberg-Marquardt for many small, independent nonlinear least-squares problems.

``solve`` minimises ``0.5 ||r_n(x_n)||^2`` for ``N`` problems at once, each with ``P``
parameters and ``R`` residuals, given a function that returns the residuals and their Jacobian
for any subset of the problems. It knows nothing about what the parameters mean; bounds are
handled by reparametrisation (:mod:`torchspec.lm.bounds`). The solver only ever uses the cost,
``J^T J`` and ``J^T r``, so a function may return those instead (:class:`NormalEquations`) and
never hold the Jacobian ``(M, R, P)``, the largest tensor of a fit.

Per problem, all state lives in tensors of shape ``(N,)``:

- Step: ``(J^T J + lambda D) step = -J^T r`` with Marquardt's scaling ``D = diag(J^T J)``, each
  entry floored at ``eps * max(diag(J^T J))`` (and at ``tiny``), solved by
  ``torch.linalg.cholesky_ex`` after a symmetric scaling by ``D^{-1/2}`` (so columns of very
  different scales lose no accuracy). A system that is not positive definite, or a step that is
  not finite, is a rejected step.
- Acceptance: a step is accepted when the residuals and Jacobian at the trial point are finite
  and the cost strictly decreases, so the parameters are always the best seen and never worse
  than the start. NaN never reaches the parameters.
- Damping (Nielsen's rule): with ``rho`` = actual / predicted reduction, an accepted step sets
  ``lambda *= max(1/3, 1 - (2 rho - 1)^3)`` and ``nu = 2``; a rejected one ``lambda *= nu``,
  ``nu *= 2`` (so repeated rejections raise ``lambda`` faster and faster). ``lambda`` is floored
  at the dtype's ``eps``.
- Convergence (after MINPACK, Moré 1978), tolerances floored at ``16 eps`` of the dtype (below
  that a cost reduction is rounding noise, and float32 problems would wander for many steps):

  * ``ftol``: an accepted step with actual and predicted reductions both ``<= ftol * cost``;
  * ``xtol``: an accepted step with ``||step|| <= xtol * (||x|| + xtol)`` (2-norms);
  * ``gtol``: at the start and after each accepted step, every column of ``J`` is nearly
    orthogonal to ``r``: ``|J_j^T r| <= gtol * ||J_j|| * ||r||`` (the cosine test, invariant to
    the scale of the parameters and of the residuals). It holds exactly when ``r = 0`` or when a
    column of ``J`` is zero, so a zero-residual start or an identically zero Jacobian is
    ``CONVERGED`` at once, with 0 iterations;
  * stall: a rejected step whose predicted reduction is ``<= 16 eps * cost`` (the model promises
    nothing above the cost's rounding: the best point is as good as this precision can tell);
  * the next step: at each check, the undamped Gauss-Newton step ``s = -(J^T J)^-1 g`` from the
    current point passes the ``xtol`` test. It is taken without evaluating the point it reaches,
    whose cost is then the Gauss-Newton model's, ``cost + g^T s / 2`` (exact for a linear
    problem, within ``O(|s|^3)`` otherwise, ``s`` being below ``xtol``): the evaluation would only
    confirm the convergence. Skipped where ``J^T J`` is singular.

  In float32 the cost resolves parameters to about ``sqrt(eps)`` of their statistical scale only.
- Failure: when a rejection pushes ``lambda`` above ``max_damping`` (before the stall test
  holds), the problem stops as ``SINGULAR``: no step reduces the cost, though the model promises
  a gain (a Jacobian inconsistent with the residuals, or a discontinuous model), or the damped
  system is not solvable. It stops as ``DIVERGED`` instead if that last trial point was solvable
  but its residuals or Jacobian were not finite (the model is not finite anywhere near the best
  point). A problem whose residuals or Jacobian are not finite at the start is ``DIVERGED`` at
  once, with 0 iterations: its parameters are returned unchanged, its cost and initial cost are
  ``inf``.

Converged and failed problems are frozen. The loop runs at most ``max_iterations`` steps; every
``check_every`` steps (and before the first) it counts the running problems, which is the solver's
only host synchronisation: it stops when none is left and otherwise drops the finished ones, so
``residual_fn`` is then called on a compacted subset of the rows, with their indices. The models'
residual functions add none (``tests/test_host_sync.py``): under an extended kernel they pick the
pixel-frame pairs whose diffuse clamp and whose lobe reach the horizon with picks of a size fixed
at the check (:mod:`torchspec.lm.picks`), whose counts the check reads in the same
synchronisation; where a pick held more pairs than its size, the steps since the last check are
taken again from it with larger sizes (the results are those of exact picks).

References:
    Marquardt, "An algorithm for least-squares estimation of nonlinear parameters", SIAM J.
    Appl. Math. 11 (1963).
    Moré, "The Levenberg-Marquardt algorithm: implementation and theory", Numerical Analysis,
    Lecture Notes in Mathematics 630 (1978).
    Nielsen, "Damping parameter in Marquardt's method", IMM-REP-1999-05, DTU (1999).
    Madsen, Nielsen, Tingleff, "Methods for non-linear least squares problems", IMM DTU (2004), 3.2.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ..config import ConfigError
from ..errors import TorchspecError
from .picks import Capacities

__all__ = [
    "CONVERGED",
    "MAX_ITERATIONS",
    "SINGULAR",
    "DIVERGED",
    "STATUS",
    "LMConfig",
    "LMResult",
    "ResidualFn",
    "NormalEquations",
    "solve",
]

CONVERGED, MAX_ITERATIONS, SINGULAR, DIVERGED = 0, 1, 2, 3
STATUS = ("converged", "max iterations", "singular", "diverged")
"""Message of each status code, indexed by the code."""

_ROUNDING = 16
"""Tolerances are floored at this many ``eps`` of the dtype."""


class NormalEquations(NamedTuple):
    """What a residual function may return instead of ``(residuals, jacobian)``: the cost
    ``0.5 |r|^2 (M,)``, ``J^T J (M, P, P)`` and ``J^T r (M, P)``, the only things the solver uses."""

    cost: Tensor
    hess: Tensor
    grad: Tensor


ResidualFn = Callable[[Tensor, Tensor], "tuple[Tensor, Tensor] | NormalEquations"]
"""``residual_fn(params (M, P), index (M,) long) -> (residuals (M, R), jacobian (M, R, P))``, or
the :class:`NormalEquations` of those."""


@dataclass(frozen=True)
class LMConfig:
    """Settings of :func:`solve`.

    Attributes:
        max_iterations: LM steps (accepted or rejected) per problem, ``>= 1``.
        check_every: steps between the all-converged checks and compactions (the only host
            synchronisations), ``>= 1``; ``None``: 1 on the CPU, where a check costs nothing and
            every step on a finished problem is wasted, and 4 on other devices, where a
            synchronisation stalls the queue.
        damping: initial ``lambda``, relative to ``diag(J^T J)``, ``> 0``.
        ftol: relative cost-reduction tolerance, ``>= 0``.
        xtol: relative step-size tolerance, ``>= 0``.
        gtol: tolerance on the cosine between ``r`` and each column of ``J``, ``>= 0``.
        max_damping: a problem whose ``lambda`` exceeds this after a rejection stops as
            ``SINGULAR`` (or ``DIVERGED``), ``> damping``.
    """

    max_iterations: int = 50
    check_every: int | None = None
    damping: float = 1e-3
    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-10
    max_damping: float = 1e12

    def __post_init__(self) -> None:
        for name in ("max_iterations", "check_every"):
            value = getattr(self, name)
            if name == "check_every" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"LMConfig.{name} must be an integer >= 1; got {value!r}.")
        for name in ("damping", "max_damping"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 < value < math.inf):
                raise ConfigError(f"LMConfig.{name} must be a finite number > 0; got {value!r}.")
        for name in ("ftol", "xtol", "gtol"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 <= value < math.inf):
                raise ConfigError(f"LMConfig.{name} must be a finite number >= 0 (0 disables it); got {value!r}.")
        if self.max_damping <= self.damping:
            raise ConfigError(
                f"LMConfig.max_damping must be > damping = {self.damping!r}; got {self.max_damping!r}. "
                "Raise max_damping or lower damping."
            )


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`solve`, one entry per problem.

    Attributes:
        params: ``(N, P)`` best parameters seen (the start for ``DIVERGED`` at the start).
        cost: ``(N,)`` ``0.5 * sum r^2`` at ``params`` (``inf`` when not finite at the start; the
            Gauss-Newton model's after a last step under ``xtol``, see the module docstring).
        initial_cost: ``(N,)`` the cost at the start (``inf`` when not finite).
        status: ``(N,)`` int8 codes, messages in :data:`STATUS`.
        iterations: ``(N,)`` int32 LM steps taken (accepted or rejected) until the problem stopped.
        damping: ``(N,)`` final ``lambda``.
    """

    params: Tensor
    cost: Tensor
    initial_cost: Tensor
    status: Tensor
    iterations: Tensor
    damping: Tensor

    def messages(self) -> list[str]:
        """The status message of each problem (a host synchronisation)."""
        return [STATUS[code] for code in self.status.tolist()]

    def counts(self) -> dict[str, int]:
        """Number of problems per status message, every message present (a host synchronisation)."""
        tally = torch.bincount(self.status.long().cpu(), minlength=len(STATUS)).tolist()
        return {message: int(n) for message, n in zip(STATUS, tally, strict=True)}


def _checked_output(out, x: Tensor) -> tuple[Tensor, Tensor]:
    """The residuals and Jacobian returned by ``residual_fn``, detached, after checking their shapes."""
    m, p = x.shape
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        raise TorchspecError(
            f"residual_fn must return a pair (residuals (M, R), jacobian (M, R, P)); got {type(out).__name__}."
        )
    r, jac = out
    if not isinstance(r, Tensor) or r.ndim != 2 or r.shape[0] != m:
        shape = tuple(r.shape) if isinstance(r, Tensor) else type(r).__name__
        raise TorchspecError(
            f"residual_fn's residuals must have shape (M, R) = ({m}, R) for params of shape {(m, p)}; got {shape}."
        )
    expected = (m, r.shape[1], p)
    if not isinstance(jac, Tensor) or tuple(jac.shape) != expected:
        shape = tuple(jac.shape) if isinstance(jac, Tensor) else type(jac).__name__
        raise TorchspecError(
            f"residual_fn's jacobian must have shape (M, R, P) = {expected} for residuals of shape "
            f"{tuple(r.shape)} and params of shape {(m, p)}; got {shape}."
        )
    for name, value in (("residuals", r), ("jacobian", jac)):
        if value.dtype != x.dtype or value.device != x.device:
            raise TorchspecError(
                f"residual_fn's {name} must have the dtype and device of params ({x.dtype}, {x.device}); "
                f"got ({value.dtype}, {value.device}). Compute them from the params passed in."
            )
    return r.detach(), jac.detach()


def _checked_normal(out: NormalEquations, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The :class:`NormalEquations` returned by ``residual_fn``, detached, after checking them."""
    m, p = x.shape
    for name, shape in (("cost", (m,)), ("hess", (m, p, p)), ("grad", (m, p))):
        value = getattr(out, name)
        if not isinstance(value, Tensor) or tuple(value.shape) != shape:
            got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
            raise TorchspecError(
                f"residual_fn's NormalEquations.{name} must have shape {shape} for params of shape {(m, p)}; got {got}."
            )
        if value.dtype != x.dtype or value.device != x.device:
            raise TorchspecError(
                f"residual_fn's NormalEquations.{name} must have the dtype and device of params "
                f"({x.dtype}, {x.device}); got ({value.dtype}, {value.device})."
            )
    return out.cost.detach(), out.hess.detach(), out.grad.detach()


def _evaluate(
    residual_fn: ResidualFn, x: Tensor, index: Tensor, capacities: Capacities | None = None, exact: bool = False
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Cost ``(M,)``, ``J^T J`` ``(M, P, P)``, ``J^T r`` ``(M, P)`` and finiteness ``(M,)`` at ``x``,
    the residual function's picks under ``capacities`` (exact with ``exact``), if given.

    Rows that are not finite get cost ``inf``, ``J^T J = I`` and ``J^T r = 0`` so that later
    batched algebra on them stays harmless (their values are never used).
    """
    out = residual_fn(x, index) if capacities is None else capacities.evaluate(residual_fn, x, index, exact=exact)
    if isinstance(out, NormalEquations):
        cost, hess, grad = _checked_normal(out, x)
    else:
        r, jac = _checked_output(out, x)
        jt = jac.transpose(-1, -2)
        cost = 0.5 * (r * r).sum(-1)
        hess = jt @ jac
        grad = (jt @ r.unsqueeze(-1)).squeeze(-1)
    # A NaN or inf anywhere in J reaches the diagonal of J^T J; one in r reaches the cost.
    finite = cost.isfinite() & hess.diagonal(dim1=-2, dim2=-1).isfinite().all(-1) & grad.isfinite().all(-1)
    eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
    cost = torch.where(finite, cost, torch.full_like(cost, math.inf))
    hess = torch.where(finite[:, None, None], hess, eye)
    grad = torch.where(finite[:, None], grad, torch.zeros_like(grad))
    return cost, hess, grad, finite


def _gradient_small(grad: Tensor, hess: Tensor, cost: Tensor, gtol: float) -> Tensor:
    """``|J_j^T r| <= gtol ||J_j|| ||r||`` for every column ``j``: ``(M,)`` bool."""
    tiny = torch.finfo(grad.dtype).tiny
    column = hess.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
    # |J_j^T r| / ||J_j|| <= ||r|| (Cauchy-Schwarz): no overflow; a zero column has J_j^T r = 0.
    projected = grad.abs() / column.clamp(min=tiny)
    return (projected <= gtol * (2.0 * cost).sqrt()[:, None]).all(-1)


@dataclass
class _State:
    """The active problems: everything ``(M, ...)``, ``index`` their rows in the batch."""

    index: Tensor
    x: Tensor
    cost: Tensor
    hess: Tensor
    grad: Tensor
    damping: Tensor
    nu: Tensor
    running: Tensor
    status: Tensor
    iterations: Tensor

    def take(self, keep: Tensor) -> _State:
        return _State(**{name: value[keep] for name, value in vars(self).items()})


def _column_scale(hess: Tensor) -> Tensor:
    """``(M, P)``: the diagonal of ``J^T J``, floored at ``eps`` of its largest entry (a zero
    column keeps a finite scale)."""
    finfo = torch.finfo(hess.dtype)
    diag = hess.diagonal(dim1=-2, dim2=-1)
    return torch.maximum(diag, (finfo.eps * diag.amax(-1, keepdim=True)).clamp(min=finfo.tiny))


def _newton_stop(state: _State, xtol: float) -> _State:
    """Stop the running problems whose undamped Gauss-Newton step ``s = -(J^T J)^-1 g`` passes the
    ``xtol`` test, ``||s|| <= xtol (||x|| + xtol)``: take it without evaluating the point reached,
    whose cost is the model's ``cost + g^T s / 2`` (skipped where ``J^T J`` is singular)."""
    inv = _column_scale(state.hess).rsqrt()
    chol, info = torch.linalg.cholesky_ex(state.hess * inv[:, :, None] * inv[:, None, :])
    step = -inv * torch.cholesky_solve((state.grad * inv).unsqueeze(-1), chol).squeeze(-1)
    small = step.norm(dim=-1) <= xtol * (state.x.norm(dim=-1) + xtol)
    done = state.running & (info == 0) & step.isfinite().all(-1) & small
    gain = (-0.5 * (state.grad * step).sum(-1)).clamp(min=0.0)  # the model's reduction, >= 0
    state.x = torch.where(done[:, None], state.x + step, state.x)
    state.cost = torch.where(done, (state.cost - gain).clamp(min=0.0), state.cost)
    state.iterations = state.iterations + done.to(torch.int32)
    state.running = state.running & ~done
    state.status = torch.where(done, CONVERGED, state.status).to(torch.int8)
    return state


def _step(state: _State, residual_fn: ResidualFn, config: LMConfig, capacities: Capacities | None = None) -> _State:
    """One LM step of every running problem, the residual function's picks under ``capacities``;
    the others are left as they are. ``state`` itself is left as it is (the solver may take the
    step again from it)."""
    x, cost, hess, grad, lam, running = state.x, state.cost, state.hess, state.grad, state.damping, state.running
    finfo = torch.finfo(x.dtype)
    ftol, xtol, gtol = (max(tol, _ROUNDING * finfo.eps) for tol in (config.ftol, config.xtol, config.gtol))

    scale = _column_scale(hess)
    # Solved in the variables s_j = sqrt(scale_j) step_j: S (J^T J) S + lambda I with a unit-ish
    # diagonal, so that columns of very different scales cost no accuracy in the factorisation.
    inv = scale.rsqrt()
    system = hess * inv[:, :, None] * inv[:, None, :] + torch.diag_embed(lam[:, None].expand_as(inv))
    chol, info = torch.linalg.cholesky_ex(system)
    step = inv * torch.cholesky_solve(-(grad * inv).unsqueeze(-1), chol).squeeze(-1)
    solvable = running & (info == 0) & step.isfinite().all(-1)
    step = torch.where(solvable[:, None], step, torch.zeros_like(step))

    trial = x + step
    cost_t, hess_t, grad_t, finite_t = _evaluate(residual_fn, trial, state.index, capacities)
    usable = solvable & finite_t
    actual = torch.where(usable, cost - cost_t, torch.zeros_like(cost))
    predicted = 0.5 * (lam * (scale * step * step).sum(-1) - (step * grad).sum(-1))
    accept = usable & (actual > 0)

    small_cost = accept & (actual <= ftol * cost) & (predicted <= ftol * cost)
    small_step = accept & (step.norm(dim=-1) <= xtol * (x.norm(dim=-1) + xtol))
    small_grad = accept & _gradient_small(grad_t, hess_t, cost_t, gtol)
    # A rejected step whose promised gain is below the cost's rounding: nothing left to gain.
    stalled = solvable & ~accept & (predicted <= _ROUNDING * finfo.eps * cost)
    converged = running & (small_cost | small_step | small_grad | stalled)

    positive = predicted > 0
    rho = torch.where(positive, actual / torch.where(positive, predicted, torch.ones_like(predicted)), 0.0)
    shrink = (1.0 - (2.0 * rho - 1.0) ** 3).clamp(min=1.0 / 3.0)
    lam_next = torch.where(accept, lam * shrink, lam * state.nu).clamp(min=finfo.eps)
    nu_next = torch.where(accept, torch.full_like(state.nu, 2.0), 2.0 * state.nu)
    stuck = running & ~converged & ~accept & (lam_next > config.max_damping)
    failure = torch.where(solvable & ~finite_t, DIVERGED, SINGULAR).to(torch.int8)

    a1, a2 = accept[:, None], accept[:, None, None]
    return _State(
        index=state.index,
        x=torch.where(a1, trial, x),
        cost=torch.where(accept, cost_t, cost),
        hess=torch.where(a2, hess_t, hess),
        grad=torch.where(a1, grad_t, grad),
        damping=torch.where(running, lam_next, lam),
        nu=torch.where(running, nu_next, state.nu),
        running=running & ~converged & ~stuck,
        status=torch.where(converged, CONVERGED, torch.where(stuck, failure, state.status)).to(torch.int8),
        iterations=state.iterations + running.to(torch.int32),
    )


def _check_params(params) -> None:
    """Raise :class:`~torchspec.errors.TorchspecError` unless ``params`` is ``(N, P >= 1)`` floating."""
    if not isinstance(params, Tensor) or params.ndim != 2 or not params.is_floating_point():
        got = f"shape {tuple(params.shape)}, dtype {params.dtype}" if isinstance(params, Tensor) else type(params)
        raise TorchspecError(f"params must be a 2-D floating tensor (N, P); got {got}. Stack the problems as rows.")
    if params.shape[1] < 1:
        raise TorchspecError(f"params must have at least one column (N, P >= 1); got shape {tuple(params.shape)}.")


def _start(residual_fn: ResidualFn, x0: Tensor, out: LMResult, config: LMConfig, capacities: Capacities) -> _State:
    """Every problem at its start ``x0 (N, P)``, evaluated (its picks exact, setting the first
    ``capacities``): ``DIVERGED`` where not finite, ``CONVERGED`` where the ``gtol`` test holds,
    running otherwise; fills ``out.initial_cost``."""
    n = x0.shape[0]
    index = torch.arange(n, device=x0.device)
    cost, hess, grad, finite = _evaluate(residual_fn, x0, index, capacities, exact=True)
    out.initial_cost.copy_(cost)
    gtol = max(config.gtol, _ROUNDING * torch.finfo(x0.dtype).eps)
    start_converged = finite & _gradient_small(grad, hess, cost, gtol)
    return _State(
        index=index,
        x=x0.clone(),
        cost=cost,
        hess=hess,
        grad=grad,
        damping=out.damping.clone(),
        nu=torch.full((n,), 2.0, dtype=x0.dtype, device=x0.device),
        running=finite & ~start_converged,
        status=torch.where(finite, torch.where(start_converged, CONVERGED, MAX_ITERATIONS), DIVERGED).to(torch.int8),
        iterations=out.iterations.clone(),
    )


def solve(
    residual_fn: ResidualFn,
    params: Tensor,
    *,
    config: LMConfig = LMConfig(),
    progress: Callable[[int, int], object] | None = None,
) -> LMResult:
    """Minimise ``0.5 ||r_n(x_n)||^2`` for ``N`` independent problems by Levenberg-Marquardt.

    ``residual_fn(x, index)`` gets the parameters ``x (M, P)`` of ``M <= N`` problems and their
    rows ``index (M,)`` (int64, on the device of ``params``) in the original batch, and returns
    their residuals ``(M, R)`` and Jacobian ``d r / d x`` ``(M, R, P)`` (or their
    :class:`NormalEquations`), in the dtype and on the device of ``x``. Use ``index`` to pick each
    problem's own data (``data[index]``): after each check the finished problems are dropped, so
    row ``m`` of ``x`` is problem ``index[m]``, not ``m``. Each problem's outputs must depend on
    its own row only. Outputs are detached. Its picks of pairs
    (:func:`torchspec.lm.picks.pick_pairs`) are exact at the start and of a size fixed at the
    last check in the steps; a step whose pick overflowed is taken again, so ``residual_fn`` may
    be called more than once at the same point.

    Args:
        residual_fn: see above; shapes are checked on every call.
        params: ``(N, P)`` floating starting points; dtype and device of everything computed.
        config: the solver's settings.
        progress: called as ``progress(done, total)`` at each check (e.g. a tqdm update hook),
            ``done`` the number of problems that have stopped; last with ``done == total``.

    Returns:
        An :class:`LMResult` with ``(N, ...)`` fields; see the module docstring for the statuses.

    Raises:
        TorchspecError: ``params`` is not a 2-D floating tensor with ``P >= 1``, or ``residual_fn``
            returns the wrong shapes, dtype or device.

    Example:
        >>> t = torch.linspace(0, 1, 20, dtype=torch.float64)
        >>> y = torch.stack([2.0 * torch.exp(-3.0 * t), 0.5 * torch.exp(-1.0 * t)])  # (N=2, R=20)
        >>> def residual_fn(x, index):
        ...     e = torch.exp(-x[:, 1:] * t)
        ...     return x[:, :1] * e - y[index], torch.stack([e, -x[:, :1] * t * e], -1)
        >>> result = solve(residual_fn, torch.ones(2, 2, dtype=torch.float64))
        >>> result.counts()["converged"], torch.allclose(result.params, torch.tensor([[2.0, 3.0], [0.5, 1.0]]).double())
        (2, True)
    """
    _check_params(params)
    n = params.shape[0]
    like = dict(dtype=params.dtype, device=params.device)
    x0 = params.detach().clone()
    out = LMResult(
        params=x0,
        cost=torch.full((n,), math.inf, **like),
        initial_cost=torch.full((n,), math.inf, **like),
        status=torch.full((n,), MAX_ITERATIONS, dtype=torch.int8, device=params.device),
        iterations=torch.zeros(n, dtype=torch.int32, device=params.device),
        damping=torch.full((n,), float(config.damping), **like),
    )
    if n == 0:
        if progress is not None:
            progress(0, 0)
        return out

    capacities = Capacities()
    state = _start(residual_fn, x0, out, config, capacities)
    every = config.check_every or (1 if params.device.type == "cpu" else 4)
    _iterate(state, residual_fn, out, config, every, capacities, progress)
    return out


def _iterate(
    state: _State,
    residual_fn: ResidualFn,
    out: LMResult,
    config: LMConfig,
    every: int,
    capacities: Capacities,
    progress: Callable[[int, int], object] | None,
) -> None:
    """:func:`solve`'s steps from ``state``, checked every ``every`` steps (the one host
    synchronisation): the running problems are counted and ``out`` filled; where a residual
    function's pick held more pairs than its capacity (:mod:`torchspec.lm.picks`), the steps
    since the last check are taken again from it, with capacities that hold them."""
    n = out.params.shape[0]
    xtol = max(config.xtol, _ROUNDING * torch.finfo(out.params.dtype).eps)
    saved, at, k = state, 0, 0  # the state after the last check, and its step
    while True:
        if k > 0:
            state = _step(state, residual_fn, config, capacities)
        if k % every == 0 or k == config.max_iterations:
            state = _newton_stop(state, xtol)
            running, overflowed = capacities.check(state.running.sum())  # the host synchronisation
            if overflowed:  # a pick was cut short: its steps again, from the last check
                state, k = saved, at + 1
                continue
            for name in ("params", "cost", "status", "iterations", "damping"):
                getattr(out, name)[state.index] = getattr(state, "x" if name == "params" else name)
            last = running == 0 or k == config.max_iterations
            if progress is not None:
                progress(n if last else n - running, n)
            if last:
                break
            if running < state.running.shape[0]:
                state = state.take(state.running.nonzero().squeeze(-1))
            saved, at = state, k
        k += 1
