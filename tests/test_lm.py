"""The batched Levenberg-Marquardt solver over a zoo of problems with known optima."""

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares

from torchspec.lm import (
    CONVERGED,
    DIVERGED,
    MAX_ITERATIONS,
    SINGULAR,
    STATUS,
    Bounds,
    LMConfig,
    LMResult,
    NormalEquations,
    bounded,
    solve,
)

F64 = torch.float64

TOLERANCES = {
    # params: error against the exact optimum, for parameters of order 1. Steps are accepted on the
    #   cost, which resolves parameters only to about sqrt(eps) of their statistical scale in float32.
    # fit: parameter error against scipy's MINPACK fit (default tolerances here, tight ones there).
    # cost: relative error of the final cost against the reference cost.
    # zero_cost: final cost of a problem whose optimal cost is 0.
    torch.float32: dict(params=2e-3, fit=5e-4, cost=1e-5, zero_cost=1e-10),
    torch.float64: dict(params=1e-8, fit=5e-7, cost=1e-10, zero_cost=1e-20),
}


@pytest.fixture
def tol(dtype):
    return TOLERANCES[dtype]


def _max_err(a, b):
    return (a.double() - b.double()).abs().max().item()


def _assert_outputs(result: LMResult, n, p, like):
    """Shapes, dtypes and devices of every field, and the invariant final cost <= initial cost."""
    assert result.params.shape == (n, p) and result.params.dtype == like.dtype
    for name in ("cost", "initial_cost", "damping"):
        value = getattr(result, name)
        assert value.shape == (n,) and value.dtype == like.dtype and value.device == like.device, name
    assert result.status.shape == (n,) and result.status.dtype == torch.int8
    assert result.iterations.shape == (n,) and result.iterations.dtype == torch.int32
    assert result.params.device == like.device
    assert bool((result.cost <= result.initial_cost).all()), "a problem ended worse than it started"


# ---------------------------------------------------------------------------------------------
# the zoo


def _linear(n, r, p, seed, dtype=F64, device="cpu"):
    """Per-problem A (N, R, P) and b (N, R): r = A x - b."""
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(n, r, p, dtype=F64, generator=g)
    b = torch.randn(n, r, dtype=F64, generator=g)
    a, b = a.to(dtype=dtype, device=device), b.to(dtype=dtype, device=device)

    def residual_fn(x, index):
        return (a[index] @ x[:, :, None]).squeeze(-1) - b[index], a[index]

    return residual_fn, a, b


def _rosenbrock(a):
    """r = (10 (x2 - x1^2), a - x1) with a per-problem ``a (N,)``: optimum (a, a^2), cost 0."""

    def residual_fn(x, index):
        x1, x2 = x[:, 0], x[:, 1]
        r = torch.stack([10.0 * (x2 - x1 * x1), a[index] - x1], -1)
        zero, one = torch.zeros_like(x1), torch.ones_like(x1)
        jac = torch.stack([torch.stack([-20.0 * x1, 10.0 * one], -1), torch.stack([-one, zero], -1)], -2)
        return r, jac

    return residual_fn


def _powell(x):
    """Powell's singular function: optimum 0 with a singular Jacobian there."""
    x1, x2, x3, x4 = x.unbind(-1)
    s5, s10 = math.sqrt(5.0), math.sqrt(10.0)
    zero, one = torch.zeros_like(x1), torch.ones_like(x1)
    r = torch.stack([x1 + 10 * x2, s5 * (x3 - x4), (x2 - 2 * x3) ** 2, s10 * (x1 - x4) ** 2], -1)
    jac = torch.stack(
        [
            torch.stack([one, 10 * one, zero, zero], -1),
            torch.stack([zero, zero, s5 * one, -s5 * one], -1),
            torch.stack([zero, 2 * (x2 - 2 * x3), -4 * (x2 - 2 * x3), zero], -1),
            torch.stack([2 * s10 * (x1 - x4), zero, zero, -2 * s10 * (x1 - x4)], -1),
        ],
        -2,
    )
    return r, jac


T = torch.linspace(-1.0, 1.0, 60, dtype=F64)


def _peak_model(params, t):
    """y = A exp(-(t - mu)^2 / (2 s^2)) + c and its Jacobian, params (M, 4) = (A, mu, s, c)."""
    amp, mu, s, c = (params[:, j : j + 1] for j in range(4))
    z = (t - mu) / s
    e = torch.exp(-0.5 * z * z)
    y = amp * e + c
    jac = torch.stack([e, amp * e * z / s, amp * e * z * z / s, torch.ones_like(e)], -1)
    return y, jac


def _peaks(n, seed, noise=0.02):
    """Planted Gaussian peaks with noise: truth (N, 4), data (N, 60), a start near the truth (N, 4)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 4, dtype=F64, generator=g)
    truth = torch.stack([1 + 2 * u[:, 0], 0.6 * u[:, 1] - 0.3, 0.15 + 0.25 * u[:, 2], 0.4 * u[:, 3] - 0.2], -1)
    data = _peak_model(truth, T)[0] + noise * torch.randn(n, T.numel(), dtype=F64, generator=g)
    start = truth * torch.tensor([1.3, 1.0, 1.3, 1.0], dtype=F64) + torch.tensor([0.0, 0.1, 0.0, 0.1], dtype=F64)
    return truth, data, start


def _peak_fn(data):
    def residual_fn(x, index):
        y, jac = _peak_model(x, T.to(x.dtype))
        return y - data[index], jac

    return residual_fn


# ---------------------------------------------------------------------------------------------


def test_linear_least_squares_matches_lstsq(dtype, device, tol):
    residual_fn, a, b = _linear(200, 30, 4, seed=0, dtype=dtype, device=device)
    result = solve(residual_fn, torch.zeros(200, 4, dtype=dtype, device=device))
    _assert_outputs(result, 200, 4, a)
    a64, b64 = a.double().cpu(), b.double().cpu()
    result = LMResult(*(getattr(result, f).cpu() for f in LMResult.__dataclass_fields__))
    expected = torch.linalg.lstsq(a64, b64[..., None]).solution.squeeze(-1)
    err = _max_err(result.params, expected)
    assert err <= tol["params"], f"max error {err:.3g}"
    assert result.counts()["converged"] == 200, result.counts()
    most = result.iterations.max().item()
    assert most <= 4, f"a linear problem took {most} steps"
    best = 0.5 * ((a64 @ expected[..., None]).squeeze(-1) - b64).pow(2).sum(-1)
    rel = ((result.cost.double() - best) / best).abs().max().item()
    assert rel <= tol["cost"], f"relative cost error {rel:.3g}"


def test_rosenbrock(dtype, tol):
    a = torch.linspace(0.5, 2.0, 16, dtype=dtype)
    start = torch.tensor([-1.2, 1.0], dtype=dtype).expand(16, 2)
    result = solve(_rosenbrock(a), start, config=LMConfig(max_iterations=100))
    _assert_outputs(result, 16, 2, a)
    assert result.counts()["converged"] == 16, result.counts()
    err = _max_err(result.params, torch.stack([a, a * a], -1))
    assert err <= tol["params"], f"max error {err:.3g}"
    assert result.cost.max().item() <= tol["zero_cost"], f"max cost {result.cost.max().item():.3g}"
    # the classic problem from the classic start
    classic = solve(_rosenbrock(torch.ones(1, dtype=dtype)), start[:1])
    err = _max_err(classic.params, torch.ones(1, 2))
    assert classic.status.item() == CONVERGED and err <= tol["params"], f"max error {err:.3g}"


def test_gaussian_peaks_recover_planted_and_match_scipy(dtype, tol):
    truth, data, start = _peaks(256, seed=1)
    result = solve(_peak_fn(data.to(dtype)), start.to(dtype))
    _assert_outputs(result, 256, 4, data.to(dtype))
    assert result.counts()["converged"] == 256, result.counts()
    err = _max_err(result.params, truth)
    assert err <= 0.05, f"max error against the planted parameters {err:.3g}"  # noise 0.02, 60 samples
    for n in range(6):

        def fun(x, n=n):
            return (_peak_model(torch.from_numpy(x)[None], T)[0][0] - data[n]).numpy()

        def jac(x):
            return _peak_model(torch.from_numpy(x)[None], T)[1][0].numpy()

        ref = least_squares(fun, start[n].numpy(), jac=jac, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
        err = float(np.abs(result.params[n].double().numpy() - ref.x).max())
        assert err <= tol["fit"], f"problem {n}: max error against scipy {err:.3g}"
        rel = abs(result.cost[n].item() - ref.cost) / ref.cost
        assert rel <= tol["cost"], f"problem {n}: relative cost error against scipy {rel:.3g}"


def test_powell_singular(dtype, tol):
    """Convergence is only linear near the singular optimum, and the normal equations square the
    Jacobian's vanishing singular values: the cost gets tiny, then the steps creep (max iterations)."""
    start = torch.tensor([3.0, -1.0, 0.0, 1.0], dtype=F64) * torch.linspace(0.5, 2.0, 8, dtype=F64)[:, None]
    result = solve(lambda x, index: _powell(x), start.to(dtype))
    _assert_outputs(result, 8, 4, start.to(dtype))
    worst = result.cost.max().item()
    assert worst <= tol["zero_cost"], f"max cost {worst:.3g}"
    assert set(result.status.tolist()) <= {CONVERGED, MAX_ITERATIONS}, result.counts()
    err = result.params.double().norm(dim=-1).max().item()
    assert err <= 1e-3, f"max distance to the optimum {err:.3g}"


def test_zero_residual_and_zero_jacobian(dtype):
    """Both are CONVERGED at once by the gradient test (J^T r = 0 exactly), with 0 iterations."""
    target = torch.tensor([[1.0, -2.0], [0.5, 3.0]], dtype=dtype)

    def residual_fn(x, index):  # rows 0-1: r = x - target (started at the target); row 2: r = (1, 2), J = 0
        r = torch.where(index[:, None] < 2, x - target[index.clamp(max=1)], torch.tensor([1.0, 2.0], dtype=dtype))
        eye = torch.eye(2, dtype=dtype).expand(x.shape[0], 2, 2)
        return r, torch.where(index[:, None, None] < 2, eye, torch.zeros_like(eye))

    start = torch.cat([target, torch.tensor([[7.0, 8.0]], dtype=dtype)])
    result = solve(residual_fn, start)
    assert result.status.tolist() == [CONVERGED] * 3
    assert result.iterations.tolist() == [0, 0, 0]
    assert torch.equal(result.params, start)
    assert result.cost.tolist() == [0.0, 0.0, 2.5]


def test_nan_at_start_is_diverged_and_isolated(dtype, tol):
    residual_fn, a, b = _linear(10, 8, 3, seed=2, dtype=dtype)
    bad_b = b.clone()
    bad_b[3, 5] = math.nan
    bad_a = a.clone()
    bad_a[7, 0, 1] = math.inf

    def broken(x, index):
        return (bad_a[index] @ x[:, :, None]).squeeze(-1) - bad_b[index], bad_a[index]

    start = torch.randn(10, 3, dtype=F64, generator=torch.Generator().manual_seed(3)).to(dtype)
    result = solve(broken, start)
    clean = solve(residual_fn, start)
    _assert_outputs(result, 10, 3, start)
    bad = torch.zeros(10, dtype=torch.bool)
    bad[[3, 7]] = True
    assert result.status[bad].tolist() == [DIVERGED, DIVERGED]
    assert torch.equal(result.params[bad], start[bad]), "a diverged problem's parameters moved"
    assert result.cost[bad].isinf().all() and result.initial_cost[bad].isinf().all()
    assert result.iterations[bad].tolist() == [0, 0]
    assert (result.status[~bad] == CONVERGED).all()
    err = _max_err(result.params[~bad], clean.params[~bad])
    assert err == 0.0, f"the other problems changed: max error {err:.3g}"
    assert result.messages()[3] == "diverged" and result.counts()["diverged"] == 2


def test_nan_at_a_trial_point_is_rejected(dtype, tol):
    """r = log(x) - log(c), J = 1/x, from x = 10 c: the Gauss-Newton step lands at x < 0."""
    c = torch.tensor([0.5, 2.0, 7.0], dtype=dtype)
    seen = []

    def residual_fn(x, index):
        seen.append(x.clone())
        return torch.log(x) - torch.log(c[index])[:, None], (1.0 / x)[:, :, None]

    result = solve(residual_fn, 10 * c[:, None])
    assert all(s.isfinite().all() for s in seen), "NaN reached the parameters"
    assert (result.status == CONVERGED).all(), result.messages()
    err = _max_err(result.params[:, 0] / c, torch.ones(3))
    assert err <= tol["params"], f"max relative error {err:.3g}"


def test_max_iterations(dtype):
    start = torch.tensor([[-1.2, 1.0]], dtype=dtype)
    result = solve(_rosenbrock(torch.ones(1, dtype=dtype)), start, config=LMConfig(max_iterations=3))
    assert result.status.item() == MAX_ITERATIONS and result.iterations.item() == 3
    assert result.messages() == ["max iterations"]
    assert result.cost.item() < result.initial_cost.item()


def _wrong_sign(x, index):
    """A Jacobian that points the wrong way: every step increases the cost."""
    return x.clone(), -torch.ones_like(x)[:, :, None]


def _nan_around(x, index):
    """Finite only at the start points 1 and -2: every trial point is NaN."""
    at_start = (x == 1.0) | (x == -2.0)
    return torch.where(at_start, x, math.nan), torch.ones_like(x)[:, :, None]


@pytest.mark.parametrize("residual_fn,status", [(_wrong_sign, SINGULAR), (_nan_around, DIVERGED)])
def test_failure_when_lambda_exceeds_max_damping(residual_fn, status, dtype):
    """Rejections push lambda past max_damping before the steps' promised gain falls to the cost's
    rounding (which would count as converged): the best point is kept, the cause is named."""
    start = torch.tensor([[1.0], [-2.0]], dtype=dtype)
    result = solve(residual_fn, start, config=LMConfig(max_damping=1e5))
    assert result.status.tolist() == [status, status], result.messages()
    assert torch.equal(result.params, start)
    assert torch.equal(result.cost, result.initial_cost)
    assert (result.damping > 1e5).all() and (result.iterations < 10).all()


def test_cost_never_increases_on_hard_starts(dtype):
    """Gaussian peaks from far starts: whatever each problem's status, it never ends worse."""
    truth, data, _ = _peaks(300, seed=4)
    g = torch.Generator().manual_seed(5)
    start = truth + torch.randn(300, 4, dtype=F64, generator=g) * torch.tensor([1.0, 0.5, 0.1, 0.5], dtype=F64)
    start[:, 2] = start[:, 2].abs() + 0.02
    fn = _peak_fn(data.to(dtype))
    result = solve(fn, start.to(dtype), config=LMConfig(max_iterations=20))
    _assert_outputs(result, 300, 4, start.to(dtype))
    finite = result.cost.isfinite()
    assert finite.all(), result.counts()
    recomputed = 0.5 * fn(result.params, torch.arange(300))[0].pow(2).sum(-1)
    err = ((recomputed - result.cost).abs() / result.cost).max().item()
    assert err <= 1e-5 if dtype == torch.float32 else err <= 1e-12, f"reported vs recomputed cost: max error {err:.3g}"


# ---------------------------------------------------------------------------------------------
# compaction and the index argument


def test_index_follows_the_compaction():
    """Problems that stop at very different times (from 0 to many steps), each with its own data:
    every call's rows get their own data, and later calls see only the unfinished ones."""
    n = 40
    g = torch.Generator().manual_seed(6)
    a = 0.5 + 1.5 * torch.rand(n, dtype=F64, generator=g)
    start = torch.stack([a, a * a], -1)
    far = torch.arange(n) % 3 == 1
    start[far] = torch.tensor([-1.2, 1.0], dtype=F64)
    start[torch.arange(n) % 3 == 2] += 0.01  # near: a few steps
    inner = _rosenbrock(a)
    calls = []

    def residual_fn(x, index):
        calls.append(index.clone())
        assert index.dtype == torch.int64 and x.shape[0] == index.shape[0]
        return inner(x, index)

    progress = []
    config = LMConfig(check_every=1, max_iterations=100)
    result = solve(residual_fn, start, config=config, progress=lambda done, total: progress.append((done, total)))
    assert result.counts()["converged"] == n, result.counts()
    err = _max_err(result.params, torch.stack([a, a * a], -1))
    assert err <= 1e-8, f"max error {err:.3g}"
    sizes = [c.numel() for c in calls]
    assert sizes[0] == n and sizes[-1] < n and sorted(sizes, reverse=True) == sizes, sizes
    assert set(calls[-1].tolist()) <= set(torch.nonzero(far).squeeze(-1).tolist())
    assert all(bool((c[1:] > c[:-1]).all()) for c in calls), "rows must stay in their original order"
    iterations = result.iterations
    assert iterations[~far & (torch.arange(n) % 3 == 0)].max().item() == 0
    assert iterations[far].min().item() > iterations[~far].max().item()
    assert progress[-1] == (n, n) and [d for d, _ in progress] == sorted(d for d, _ in progress)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 6), check_every=st.integers(1, 5))
def test_batch_equals_problems_alone(seed, n, check_every):
    truth, data, start = _peaks(n, seed=seed, noise=0.05)
    start = start + 0.2 * torch.randn(n, 4, dtype=F64, generator=torch.Generator().manual_seed(seed + 1))
    start[:, 2] = start[:, 2].abs() + 0.05
    config = LMConfig(check_every=check_every, max_iterations=20)
    fn = _peak_fn(data)
    batch = solve(fn, start, config=config)
    for k in range(n):
        alone = solve(_peak_fn(data[k : k + 1]), start[k : k + 1], config=config)
        err = _max_err(batch.params[k], alone.params[0])
        scale = 1.0 + alone.params.abs().max().item()
        assert err <= 1e-7 * scale, (
            f"problem {k}: max error {err:.3g} (batch {batch.status[k]}, alone {alone.status[0]})"
        )
        rel = abs(batch.cost[k].item() - alone.cost.item()) / max(alone.cost.item(), 1e-300)
        assert rel <= 1e-9, f"problem {k}: relative cost error {rel:.3g}"


# ---------------------------------------------------------------------------------------------
# bounds


def test_positive_parameter_ends_at_its_bound(dtype):
    """x = (x0, x1): r = (x0 + 1, x1 - 2, x0 x1 - 0.5); x0 is positive, its free optimum is negative."""
    bounds = Bounds(("positive", "free"))
    seen = []

    def residual_fn(x, index):
        seen.append(x[:, 0].clone())
        x0, x1 = x[:, 0], x[:, 1]
        r = torch.stack([x0 + 1.0, x1 - 2.0, x0 * x1 - 0.5], -1)
        zero, one = torch.zeros_like(x0), torch.ones_like(x0)
        jac = torch.stack([torch.stack([one, zero], -1), torch.stack([zero, one], -1), torch.stack([x1, x0], -1)], -2)
        return r, jac

    x_start = torch.tensor([[1.0, 0.0], [3.0, 1.0], [0.1, 5.0]], dtype=dtype)
    result = solve(bounded(residual_fn, bounds), bounds.to_free(x_start), config=LMConfig(max_iterations=100))
    x = bounds.from_free(result.params)[0]
    assert all(bool((s >= 0).all()) for s in seen), "a positive parameter went negative"
    assert (x[:, 0] < 1e-3).all(), f"x0 = {x[:, 0].tolist()}"
    # the free parameter is then optimal for x0 = 0
    err = _max_err(x[:, 1], torch.full((3,), 2.0))
    assert err <= 1e-3, f"max error {err:.3g}"
    assert (result.status != DIVERGED).all(), result.messages()


def test_interval_parameter_stays_inside(dtype):
    bounds = Bounds((("interval", -1.0, 0.5),))
    target = torch.tensor([0.2, 3.0, -4.0], dtype=dtype)  # inside, above, below

    def residual_fn(x, index):
        return x - target[index, None], torch.ones_like(x)[:, :, None]

    result = solve(bounded(residual_fn, bounds), bounds.to_free(torch.zeros(3, 1, dtype=dtype)))
    x = bounds.from_free(result.params)[0][:, 0]
    assert (x >= -1.0).all() and (x <= 0.5).all()
    err = max(abs(x[0].item() - 0.2), abs(x[1].item() - 0.5), abs(x[2].item() + 1.0))
    assert err <= 1e-3, f"max error {err:.3g}"


def test_round_trips(dtype):
    finfo = torch.finfo(dtype)
    top = math.log10(finfo.max) - 1
    low = math.log10(finfo.tiny) + 1
    x = torch.logspace(low, top, 400, dtype=F64).to(dtype)
    for kind in ("positive", "nonnegative"):
        bounds = Bounds((kind,))
        u = bounds.to_free(x[:, None])
        back, slope = bounds.from_free(u)
        # the rounding of u, relative eps |u|, becomes a relative error of x through exp
        err = ((back[:, 0] - x) / x / (1 + u[:, 0].abs())).abs().max().item()
        assert err <= 2 * finfo.eps, f"{kind}: max relative error / (1 + |u|) {err:.3g}"
        assert slope.isfinite().all() and (slope >= 0).all()
    bounds = Bounds((("interval", -2.0, 3.0),))
    inside = torch.linspace(-2.0, 3.0, 401, dtype=dtype)[1:-1]
    back = bounds.from_free(bounds.to_free(inside[:, None]))[0][:, 0]
    err = (back - inside).abs().max().item()
    assert err <= 16 * finfo.eps, f"interval: max error {err:.3g}"
    # on or beyond a bound: clamped into the open domain, finite
    edge = Bounds(("positive", "nonnegative", ("interval", 0.0, 1.0)))
    beyond = torch.tensor([[0.0, 0.0, 0.0], [-1.0, -1.0, 2.0]], dtype=dtype)
    u = edge.to_free(beyond)
    assert u.isfinite().all(), u
    x_back = edge.from_free(u)[0]
    assert (x_back >= 0).all() and (x_back[:, 2] <= 1).all()
    # the free column is the identity
    free = torch.tensor([[-3.0], [0.0], [1e30]], dtype=dtype)
    assert torch.equal(Bounds(("free",)).to_free(free), free)


def test_bounded_jacobian_matches_autograd():
    bounds = Bounds(("free", "positive", "nonnegative", ("interval", -1.0, 2.0)))
    g = torch.Generator().manual_seed(7)
    u = torch.randn(5, 4, dtype=F64, generator=g)
    t = torch.linspace(0, 1, 6, dtype=F64)

    def model(x):
        return x[:, :1] + x[:, 1:2] * torch.sin(x[:, 2:3] * t) + x[:, 3:4] ** 2 * t

    def residual_fn(x, index):
        one = torch.ones_like(t).expand(x.shape[0], -1)
        jac = torch.stack(
            [one, torch.sin(x[:, 2:3] * t), x[:, 1:2] * t * torch.cos(x[:, 2:3] * t), 2 * x[:, 3:4] * t], -1
        )
        return model(x), jac

    r, jac = bounded(residual_fn, bounds)(u, torch.arange(5))
    full = torch.autograd.functional.jacobian(lambda v: model(bounds.from_free(v)[0]), u)  # (N, R, N, P)
    expected = full[torch.arange(5), :, torch.arange(5)]
    torch.testing.assert_close(r, model(bounds.from_free(u)[0]))
    err = _max_err(jac, expected)
    assert err <= 1e-12, f"max error {err:.3g}"
    # and the slopes themselves against finite differences
    h = 1e-6
    slope = bounds.from_free(u)[1]
    x_plus, x_minus = bounds.from_free(u + h)[0], bounds.from_free(u - h)[0]
    err = _max_err((x_plus - x_minus) / (2 * h), slope)
    assert err <= 1e-8, f"max error {err:.3g}"


# ---------------------------------------------------------------------------------------------
# the call


def test_empty_batch(dtype):
    def residual_fn(x, index):
        raise AssertionError("not called for N = 0")

    result = solve(residual_fn, torch.zeros(0, 3, dtype=dtype))
    _assert_outputs(result, 0, 3, torch.zeros(0, dtype=dtype))
    assert result.counts() == {message: 0 for message in STATUS}


def test_bad_calls_name_the_shapes():
    residual_fn, _, _ = _linear(4, 5, 3, seed=8)
    with pytest.raises(ValueError, match=r"params must be a 2-D floating tensor.*shape \(3,\)"):
        solve(residual_fn, torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match=r"params must be a 2-D floating tensor.*torch.int64"):
        solve(residual_fn, torch.zeros(4, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"residuals must have shape \(M, R\) = \(4, R\).*got \(5,\)"):
        solve(lambda x, i: (torch.zeros(5, dtype=F64), torch.zeros(4, 5, 3, dtype=F64)), torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"jacobian must have shape \(M, R, P\) = \(4, 5, 3\).*got \(4, 3, 5\)"):
        solve(
            lambda x, i: (torch.zeros(4, 5, dtype=F64), torch.zeros(4, 3, 5, dtype=F64)), torch.zeros(4, 3, dtype=F64)
        )
    with pytest.raises(ValueError, match="must return a pair"):
        solve(lambda x, i: torch.zeros(4, 5, dtype=F64), torch.zeros(4, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"dtype and device of params \(torch.float32"):
        solve(lambda x, i: (torch.zeros(4, 5, dtype=F64), torch.zeros(4, 5, 3, dtype=F64)), torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"u must have shape \(N, P = 2\).*got \(4, 3\)"):
        Bounds(("free", "positive")).from_free(torch.zeros(4, 3))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(max_iterations=0), "max_iterations must be an integer >= 1; got 0"),
        (dict(check_every=2.0), "check_every must be an integer >= 1; got 2.0"),
        (dict(damping=-1.0), "damping must be a finite number > 0; got -1.0"),
        (dict(ftol=math.nan), "ftol must be a finite number >= 0"),
        (dict(max_damping=1e-4), "max_damping must be > damping"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LMConfig(**kwargs)


@pytest.mark.parametrize(
    "kinds,match",
    [
        (("free", "postive"), r"kinds\[1\] must be 'free'.*got 'postive'"),
        ((("interval", 2.0, 1.0),), r"kinds\[0\] must be \('interval', lo, hi\).*lo < hi"),
        ("positive", "must be a sequence"),
    ],
)
def test_bounds_errors(kinds, match):
    with pytest.raises(ValueError, match=match):
        Bounds(kinds)


def test_bounds_accepts_lists():
    assert Bounds(["free", ["interval", 0, 1]]).kinds == ("free", ("interval", 0.0, 1.0))


@pytest.mark.parametrize("dtype", [F64])
def test_normal_equations_give_the_same_solve(dtype):
    """A residual function that returns the NormalEquations of its residuals takes the same steps
    (bounded too), and its shapes are checked."""
    truth, data, start = _peaks(16, seed=3)
    fn = _peak_fn(data.to(dtype))

    def normal(x, index):
        r, jac = fn(x, index)
        jt = jac.transpose(1, 2)
        return NormalEquations(0.5 * (r * r).sum(-1), jt @ jac, (jt @ r[..., None])[..., 0])

    bounds = Bounds(("free", "positive", "free", "positive"))
    for wrap in (lambda f: f, lambda f: bounded(f, bounds)):
        x0 = start.to(dtype) if wrap(fn) is fn else bounds.to_free(start.abs().to(dtype) + 0.1)
        a, b = solve(wrap(fn), x0), solve(wrap(normal), x0)
        torch.testing.assert_close(b.params, a.params, rtol=1e-10, atol=1e-12)
        assert torch.equal(a.status, b.status) and torch.equal(a.iterations, b.iterations)

    def wrong(x, index):
        out = normal(x, index)
        return NormalEquations(out.cost, out.hess[:, :3, :3], out.grad)

    with pytest.raises(ValueError, match=r"NormalEquations.hess must have shape \(16, 4, 4\)"):
        solve(wrong, start.to(dtype))


def test_the_last_step_under_xtol_is_taken_unevaluated():
    """A problem whose next Gauss-Newton step passes the ``xtol`` test takes it without evaluating
    the point reached: one evaluation per step, the start's included (every Rosenbrock problem
    stops so; elsewhere the ``ftol`` test after an evaluated step may stop a problem first). The
    cost returned, the Gauss-Newton model's there, is the true cost at the returned parameters."""
    residual_fn = _rosenbrock(torch.linspace(0.5, 2.0, 16, dtype=F64))
    start = torch.tensor([-1.2, 1.0], dtype=F64).expand(16, 2)
    evaluations = torch.zeros(start.shape[0], dtype=torch.int64)

    def counted(x, index):
        evaluations.index_add_(0, index, torch.ones_like(index))
        return residual_fn(x, index)

    result = solve(counted, start, config=LMConfig(max_iterations=100))
    assert result.counts()["converged"] == start.shape[0]
    assert (evaluations == result.iterations.long()).all(), (evaluations, result.iterations)
    r, _ = residual_fn(result.params, torch.arange(start.shape[0]))
    torch.testing.assert_close(result.cost, 0.5 * (r * r).sum(-1), rtol=1e-6, atol=1e-24)
